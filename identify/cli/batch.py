"""Several experiments in one `identify` process: `identify fit a.toml b.toml`, or a folder.

A lab records many logs of one rig a day. Run in one process, the experiments after the
first reuse the programs JAX compiled for the first wherever the rig's structure and the
logs' shapes agree, instead of compiling them again in a new process each. Each experiment
is run as the command runs one (its own output folder, its own exit status); one that
fails does not stop the others, and the summary at the end lists every file's outcome.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

#: the exit status of an experiment the batch could not run to the end (Ctrl-C)
INTERRUPTED = 130


def experiment_files(paths: list[Path]) -> list[Path]:
    """The experiment files named by `paths`: a file as given, a folder as the `*.toml`
    files in it (sorted), or, where it has none, those one level down (`*/*.toml`: a
    folder of experiment folders, as `identify/examples`)."""
    out = []
    for path in paths:
        if path.is_dir():
            found = sorted(path.glob("*.toml")) or sorted(path.glob("*/*.toml"))
            out.extend(found or [path])  # (an empty folder: the command says what it expected)
        else:
            out.append(path)
    return out


def output_folders(files: list[Path], out: Path | None, suffix: str) -> list[Path | None]:
    """Each experiment's output folder: `<stem>-<suffix>` (in `out` when given, else the
    current folder, as for one experiment: None), or `<parent>-<stem>-<suffix>` for all of
    them where two stems agree (`a/experiment.toml` and `b/experiment.toml`)."""
    stems = [f.stem for f in files]
    if len(set(stems)) < len(stems):
        names = [f"{f.resolve().parent.name}-{f.stem}-{suffix}" for f in files]
    elif out is None:
        return [None] * len(files)
    else:
        names = [f"{stem}-{suffix}" for stem in stems]
    base = Path.cwd() if out is None else out
    return [base / name for name in names]


def run_batch(args: argparse.Namespace, run_one: Callable[[argparse.Namespace], int], suffix: str | None) -> int:
    """`run_one` on each experiment of `args.experiments` (`experiment_files`), with its
    own `experiment` and `out` (`output_folders`; `suffix` None: a command that writes
    nothing). Returns 0 when every run returned 0, else the largest status (130 after
    Ctrl-C, which stops the batch); the summary names each file's."""
    files = experiment_files(list(args.experiments))
    outs = output_folders(files, args.out, suffix) if suffix else [None] * len(files)
    outcomes: list[tuple[Path, int, float]] = []
    for k, (path, out) in enumerate(zip(files, outs, strict=True), start=1):
        print(f"identify {args.command} [{k}/{len(files)}]: {path}", flush=True)
        one = argparse.Namespace(**{**vars(args), "experiment": path, "out": out})
        start = time.perf_counter()
        try:
            code = run_one(one)
        except KeyboardInterrupt:
            outcomes.append((path, INTERRUPTED, time.perf_counter() - start))
            print(f"identify {args.command}: interrupted at {path}; the rest not run", file=sys.stderr, flush=True)
            break
        except Exception as e:  # noqa: BLE001 (one experiment's failure must not stop the others)
            print(f"identify {args.command}: {path}: failed: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
            code = 1
        outcomes.append((path, code, time.perf_counter() - start))
        print(flush=True)
    _summary(args.command, outcomes, files)
    return max((code for _, code, _ in outcomes), default=0)


def _summary(command: str, outcomes: list[tuple[Path, int, float]], files: list[Path]) -> None:
    """Each file's exit status and time, and the files not run."""
    failed = [(p, c) for p, c, _ in outcomes if c]
    print(f"identify {command}: {len(outcomes) - len(failed)} of {len(files)} experiment(s) done (exit status 0)")
    for path, code, seconds in outcomes:
        print(f"  {'ok' if code == 0 else f'exit {code}':>8}  {seconds:7.1f} s  {path}")
    for path in files[len(outcomes) :]:
        print(f"  {'not run':>8}  {'':9}  {path}")
    if failed:
        listed = ", ".join(f"{p} ({c})" for p, c in failed)
        print(f"identify {command}: not done: {listed}", file=sys.stderr, flush=True)
