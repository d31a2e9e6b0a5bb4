"""A command's output folder for one run: claimed before the work, written through a staging
folder, committed by renames.

A fit or a diagnosis takes minutes; nothing about the folder may fail after that. So the
folder is claimed first (`OutputFolder.claim`): checked (`output.check_output_folder`),
created, shown to be writable, and locked, so that a second run into it is refused while
the first holds it. The lock is an advisory `flock` held for the life of the process: the
system releases it when the process ends, even by SIGKILL, so no stale lock survives.

The files of a run are written into a hidden staging folder inside it and moved into place
by `os.replace` (atomic on one file system) when the run is done (`OutputFolder.commit`),
the result file (`result.json`, `diagnosis.json`) last and the previous run's result file
first removed. So at every instant the folder holds the previous complete result, or the
new complete one, or (for the milliseconds of the renames) no result file at all: never a
result file beside another run's plots. The marker file says what the last run did
(`running`, `complete`, `interrupted`, `failed`); a marker that says `running` while no
process holds the lock is a run that was killed.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

from .output import LOCK_FILE, MARKER, STAGING_PREFIX, TEMPORARY_PREFIX, _Refused, check_output_folder, output_files

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None


#: how a marker says that its folder's files are an earlier run's than the one it describes
EARLIER = "; the files here are an earlier run's ("


def _now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomic(path: Path, text: str) -> None:
    """Write `text` (UTF-8) to `path` through a temporary file beside it and a rename:
    `path` holds its old content or the new one, never part of it."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f"{TEMPORARY_PREFIX}{path.name}.")
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # (mkstemp's 0o600: the permissions of a plain write)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def deferred_interrupt():
    """Hold Ctrl-C (SIGINT) back for the duration of the block, then raise it
    (`KeyboardInterrupt`): for the renames of a commit, which take milliseconds."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def _lock(path: Path):
    """An open file holding an exclusive lock on `path`, or None if another process holds it."""
    f = open(path, "a+", encoding="utf-8")  # noqa: SIM115 (held open: the lock lives with it)
    try:
        if fcntl is not None:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        else:  # pragma: no cover - Windows
            import msvcrt

            msvcrt.locking(f.fileno(), msvcrt.LK_NBLCK, 1)
    except OSError:
        f.close()
        return None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()}, since {_now()}\n")
    f.flush()
    return f


def _holder(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8").strip() or "unknown"
    except OSError:
        return "unknown"


def _make(out: Path) -> bool:
    """Create `out` (and its parents); whether it was created now. Raises `_Refused`."""
    if out.is_dir():
        return False
    try:
        out.mkdir(parents=True)
    except FileExistsError:
        raise _Refused(f"cannot use --out {out}: it exists and is not a folder") from None
    except NotADirectoryError:
        above = next((p for p in out.parents if p.exists() and not p.is_dir()), out.parent)
        raise _Refused(f"cannot create --out {out}: {above} is a file, not a folder") from None
    except OSError as e:
        raise _Refused(f"cannot create --out {out}: {e.strerror or e}") from None
    return True


def _probe(out: Path) -> None:
    """Raise `_Refused` unless a file can be created, written and renamed in `out`."""
    try:
        fd, tmp = tempfile.mkstemp(dir=out, prefix=TEMPORARY_PREFIX + "probe-")
        os.close(fd)
        os.replace(tmp, tmp + "-renamed")
        os.unlink(tmp + "-renamed")
    except OSError as e:
        raise _Refused(f"cannot write into {out}: {e.strerror or e}. Choose another folder with --out") from None


def _blocked(out: Path) -> None:
    """Raise `_Refused` if one of our file names in `out` is taken by something that is not a file."""
    for name in output_files():
        p = out / name
        if (p.exists() or p.is_symlink()) and not p.is_file():
            what = "a folder" if p.is_dir() else "not a regular file"
            raise _Refused(f"cannot write {p}: it is {what}. Remove or rename it, or choose another folder with --out")


class OutputFolder:
    """One run's claim on its output folder (module docstring). Use `claim`, then
    `staging` for the files, `commit` them, and `release` (or use it as a context manager)."""

    def __init__(self, path: Path, lock, created: bool, previous: str | None):
        self.path = path
        self._lock_file = lock
        self.created = created
        #: what the marker said before this run claimed the folder (e.g. a killed run's "running")
        self.previous = previous
        self._staging: Path | None = None
        self._ended = False  # committed or abandoned

    @classmethod
    def claim(cls, out: Path, inputs: list[Path], force: bool, suffix: str = "fit") -> OutputFolder:
        """Check `out` for this run (`check_output_folder`), create it, prove it writable,
        lock it and mark it `running`. Raises `_Refused` with the message for the user."""
        out = Path(out)
        check_output_folder(out, inputs, force, suffix)
        created = _make(out)
        try:
            _probe(out)
        except _Refused:
            if created:
                out.rmdir()
            raise
        lock = _lock(out / LOCK_FILE)
        if lock is None:
            raise _Refused(
                f"refusing to write into {out}: another identify run is writing there "
                f"({_holder(out / LOCK_FILE)}). Wait for it to finish, or choose another folder with --out"
            )
        try:
            _blocked(out)
            previous = cls._status(out)
            for old in out.glob(STAGING_PREFIX + "*"):  # a killed run's (we hold the lock)
                shutil.rmtree(old, ignore_errors=True)
            folder = cls(out, lock, created, previous)
            folder.mark(f"running (pid {os.getpid()}, since {_now()})")
        except BaseException:
            lock.close()
            raise
        return folder

    @staticmethod
    def _status(out: Path) -> str | None:
        try:
            lines = (out / MARKER).read_text(encoding="utf-8").splitlines()
        except OSError:
            return None
        return next((line[len("status: ") :] for line in lines if line.startswith("status: ")), None)

    @property
    def killed_before(self) -> bool:
        """Whether the previous run into this folder was killed (its marker still says running)."""
        return bool(self.previous and self.previous.startswith("running"))

    def mark(self, status: str) -> None:
        """Rewrite the marker with `status` (atomically)."""
        write_atomic(
            self.path / MARKER,
            "Written by `identify` (flexdyn). This folder holds its outputs; a new run may overwrite these "
            f"files: {', '.join(output_files())}.\nstatus: {status}\n",
        )

    def staging(self) -> Path:
        """The hidden folder this run writes its files into before `commit`."""
        if self._staging is None:
            self._staging = Path(tempfile.mkdtemp(dir=self.path, prefix=STAGING_PREFIX))
        return self._staging

    def commit(self, result_file: str, status: str = "complete", keep: tuple[str, ...] = ()) -> list[Path]:
        """Move every staged file into the folder, `result_file` last, after removing the
        previous run's result file and those of its files this run did not write (but
        `keep`); mark the folder `status`. Returns the paths moved. Ctrl-C waits for the
        renames."""
        staged = sorted(p for p in self.staging().iterdir() if p.is_file())
        names = {p.name for p in staged}
        ours = [n for n in output_files() if n not in (MARKER, LOCK_FILE, *keep)]
        with deferred_interrupt():
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path / result_file)
            for name in ours:
                if name not in names and name != result_file:
                    with contextlib.suppress(FileNotFoundError):
                        if (self.path / name).is_file():
                            os.unlink(self.path / name)
            moved = []
            for p in sorted(staged, key=lambda p: p.name == result_file):
                os.replace(p, self.path / p.name)
                moved.append(self.path / p.name)
            self.mark(f"{status} ({_now()})")
            shutil.rmtree(self.staging(), ignore_errors=True)
            self._staging = None
            self._ended = True
        return moved

    def abandon(self, status: str) -> None:
        """End a run that wrote nothing: remove the folder if this run created it and it
        holds nothing else, otherwise mark it with `status` (the previous result stays)."""
        self._ended = True
        if self._staging is not None:
            shutil.rmtree(self._staging, ignore_errors=True)
            self._staging = None
        leftover = {p.name for p in self.path.iterdir()} - {MARKER, LOCK_FILE}
        if self.created and not leftover:
            for name in (MARKER, LOCK_FILE):
                with contextlib.suppress(OSError):
                    os.unlink(self.path / name)
            self.release()
            with contextlib.suppress(OSError):
                self.path.rmdir()
            return
        earlier = (self.previous or "").rsplit(EARLIER, 1)[-1].removesuffix(")")  # (not nested)
        kept = f"{EARLIER}{earlier})" if earlier and leftover else ""
        self.mark(f"{status} ({_now()}){kept}")

    def release(self) -> None:
        """Give up the lock (the process ending does the same)."""
        if self._lock_file is not None:
            self._lock_file.close()
            self._lock_file = None

    def __enter__(self) -> OutputFolder:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        """A run that ends by an exception before committing is abandoned (`abandon`)."""
        try:
            if kind is not None and not self._ended:
                how = "interrupted" if issubclass(kind, KeyboardInterrupt) else f"failed ({kind.__name__})"
                self.abandon(f"{how}, nothing written")
        finally:
            self.release()
