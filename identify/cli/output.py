"""The output folder of a command: what it may hold, the marker that claims it, the names of the
files the commands write, and the exit codes.
"""

from __future__ import annotations

import sys
from pathlib import Path

MARKER = ".identify-output"


#: held locked by the run writing into the folder (`folder.OutputFolder.claim`)
LOCK_FILE = ".identify-lock"


#: a run's files are written into a hidden folder of this prefix, then moved into place
STAGING_PREFIX = ".identify-staging-"


#: temporary files (written, then renamed into place) and probes of writability
TEMPORARY_PREFIX = ".identify-tmp-"


#: `identify diagnose` writes every progress line here as it goes, so that a diagnosis
#: stopped part-way leaves its progress on disk
PROGRESS_FILE = "progress.log"


NOT_CONVERGED = 3  # exit status when the fit (`diagnose`: the baseline fit) did not converge


INTERRUPTED = 130  # exit status after Ctrl-C (the shell's 128 + SIGINT)


RESULT_FILE = "result.json"


class _Refused(Exception):
    """The output folder may not be used; the message says why."""


def output_files() -> tuple[str, ...]:
    """Every file name the commands write into their output folders."""
    from .._report.diagnosis_report import FILES
    from .._report.fit_plots import BY_LOG_PLOT, PLOT_FILES

    return (MARKER, LOCK_FILE, RESULT_FILE, PROGRESS_FILE, *PLOT_FILES, BY_LOG_PLOT, *FILES)


def _ours(p: Path) -> bool:
    """Whether `p`, an entry of an output folder, is one of the commands' (files under our
    names, staging folders and temporary files of a run)."""
    if p.name.startswith((STAGING_PREFIX, TEMPORARY_PREFIX)):
        return True
    return p.name in output_files() and p.is_file()


def _same(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except (OSError, RuntimeError):  # (a symbolic link loop: Python 3.11's `resolve` raises RuntimeError)
        return False


def check_output_folder(out: Path, inputs: list[Path], force: bool, suffix: str = "fit") -> None:
    """Raise `_Refused` unless we may write our files into `out`. `inputs`: the
    experiment file and its logs."""
    for p in inputs:
        if _same(out, p.parent) or (p.is_dir() and _same(out, p)):  # (a ROS 2 bag is a folder)
            raise _Refused(
                f"refusing to write into {out}: it holds an input of the experiment ({p.name}). "
                f"Choose another folder with --out (by default the command writes ./<experiment stem>-{suffix} "
                "in the current folder)."
            )
    if out.exists() and not out.is_dir():
        raise _Refused(f"refusing to use --out {out}: it exists and is not a folder")
    if not out.exists():
        return
    ours = set(output_files())
    entries = sorted(out.iterdir(), key=lambda p: p.name)
    targets = [out / name for name in ours]
    for target in targets:  # e.g. a symbolic link from one of our names to a log
        if any(_same(target, p) for p in inputs if target.exists()):
            raise _Refused(f"refusing to write {target}: it is an input of the experiment")
    if force or not entries:
        return
    foreign = [p.name + ("/" if p.is_dir() else "") for p in entries if not _ours(p)]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f", ... ({len(foreign)} in all)" if len(foreign) > 5 else "")
        raise _Refused(
            f"refusing to write into {out}: it holds files this command did not write ({shown}). "
            "Choose another folder with --out, or pass --force to write our files there anyway "
            "(other files are left untouched)."
        )
    # (a run killed between claiming the folder, its lock file, and marking it leaves
    # only the lock: that folder is ours too)
    if not (out / MARKER).is_file() and not (out / LOCK_FILE).is_file():
        raise _Refused(
            f"refusing to write into {out}: it exists and is not the output of a previous `identify` command "
            f"(no {MARKER} file). Choose another folder with --out, or pass --force."
        )


def _experiment_and_folder(args, suffix: str):
    """The experiment of `args.experiment`, its input files, and the output folder
    (`--out`, default `<experiment stem>-<suffix>` here), checked (`check_output_folder`);
    raises `_Refused` with the message for the user."""
    exp = _load_experiment(args)
    inputs = [Path(exp.path)] + [Path(spec.file) for spec in exp.logs]
    out = args.out if args.out is not None else Path.cwd() / f"{Path(exp.path).stem}-{suffix}"
    check_output_folder(out, inputs, args.force, suffix)
    return exp, inputs, out


def _load_experiment(args):
    """The experiment of `args.experiment`, its logs' sampling rates checked (`--any-rate`);
    raises `_Refused` with the message for the user."""
    from .._data.columns import LogError
    from .._data.experiment_file import load_experiment
    from .._data.toml_reader import ExperimentError

    try:
        exp = load_experiment(args.experiment)
    except (ExperimentError, LogError) as e:
        raise _Refused(str(e)) from None
    from .._data.logs import PLAUSIBLE_RATE_HZ

    slow = [spec for spec in exp.logs if spec.log.sampling.rate < PLAUSIBLE_RATE_HZ[0]]
    if slow and not args.any_rate:
        spec = slow[0]
        raise _Refused(
            f"refusing to fit: log {spec.name!r} ({spec.file}) is sampled at {spec.log.sampling.rate:.3g} Hz over "
            f"{spec.log.sampling.duration:.4g} s, below any rig's log ({PLAUSIBLE_RATE_HZ[0]:g} Hz): is its time "
            "column in milliseconds but labelled [s]? (simulating such a span takes hours) Fix the unit in the "
            "header or the experiment's columns, or pass --any-rate to fit it as it is"
        )
    return exp


def printers(command: str, quiet: bool):
    """`(say, error)` of a command: `say` prints progress unless `quiet`; `error` prints
    `identify COMMAND: message` on stderr and returns exit status 2 (bad arguments)."""

    def say(msg=""):
        if not quiet:
            print(msg, flush=True)

    def error(msg: str) -> int:
        print(f"identify {command}: {msg}", file=sys.stderr, flush=True)
        return 2

    return say, error
