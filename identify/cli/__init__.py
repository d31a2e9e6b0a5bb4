"""The `identify` command line (also `python -m identify`).

    identify fit EXPERIMENT.toml [--out DIR] [--stages N] [--segment SECONDS] [--no-frequency-init] [--max-restarts N]
                 [--no-restart-poor-fit] [--closed-loop-only] [--quiet] [--force] [--any-rate]
    identify diagnose EXPERIMENT.toml [--out DIR] [--only NAME,...] [--max-effects N] [--quiet] [--force]
                      [--any-rate]
    identify check EXPERIMENT.toml [--any-rate]

Each command takes several experiment files, or a folder of them, too: they run one after
the other in this process (`identify.cli.batch`), each into its own output folder, and a
summary lists each file's exit status; the command's own is the largest of them.

`check` reads the experiment file and its logs with every check a fit makes and prints
what a fit would start from, in seconds (nothing compiled or written): exit 0 if a fit
can start, 2 with the file, line and key if not.

`diagnose` fits the experiment's model, shows what it gets wrong, tries the catalogue of
model extensions (`identify.catalogue`), names the cause(s) whose gain is significant and
writes `diagnosis.json`, `report.md` and plots (default folder
`./<experiment file stem>-diagnosis/`; see `identify.diagnose`).

`fit` loads the experiment (see `docs/experiment-format.md`), fits its free parameters to its fit
logs, checks the fit on its validation logs, prints the parameter table, the
identifiability warnings and a residual summary, and writes into the output folder
(default `./<experiment file stem>-fit/`):

- `result.json`: `FitResult.to_dict()`, the residual report, the validation results,
  the model's natural frequencies, the experiment's name and path, versions;
- `measured_vs_fitted.png`, `residuals.png`, `residual_spectrum.png`,
  `residual_autocorrelation.png`, `parameter_correlation.png` (`identify.report`);
- `.identify-output`: marks the folder as written by this command.

The output folder policy never risks an input: the command refuses (exit code 2) to
write into a folder that holds an input of the experiment (the experiment file or a log),
and, unless `--force`, into an existing folder that holds files other than ours or that a
previous run did not mark. `--force` only lets it write its own file names next to other
files; it never deletes anything and never writes over an input.

A log sampled below 1 Hz is refused (exit code 2) unless `--any-rate`: on a rig it is
almost always a time column in milliseconds labelled [s], and simulating its 1000-fold
span would take hours.

Exit codes: 0 done, the fit converged; 1 the fit failed; 2 a usage error, an unreadable
experiment or log, a refused output folder or sampling rate; 3 (`fit`) the fit finished and
its results are written, but it did not converge or a parameter ended on its bound
(`converged: false` in `result.json`, the WARNING printed says which); 3 (`diagnose`) the
diagnosis is written, but the baseline fit's solver did not converge
(`baseline_converged: false` in `diagnosis.json`; a baseline parameter on its bound is
only noted: there it is often the missing effect's symptom).
"""

from __future__ import annotations

import _thread
import argparse
import contextlib
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

EXPERIMENTS_HELP = (
    "the experiment file (TOML); several, or a folder of them, run one after the other in this process "
    "(each in its own output folder: <stem>-fit, in --out if given; the programs compiled for the first are "
    "reused by the others of the same rig), with a summary of each file's outcome"
)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="identify", description="System identification of flexdyn rigs from measured logs."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    fit = sub.add_parser(
        "fit",
        help="fit an experiment's free parameters to its logs",
        description="Fit the free parameters of an experiment file (docs/experiment-format.md) to its fit logs, check "
        "the fit on its validation logs, print the results and write result.json and plots.",
    )
    fit.add_argument("experiments", type=Path, nargs="+", metavar="EXPERIMENT", help=EXPERIMENTS_HELP)
    fit.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder, created if needed (default: ./<experiment stem>-fit in the current folder)",
    )
    fit.add_argument(
        "--stages",
        type=int,
        default=4,
        metavar="N",
        help="horizon stages of the fit: the horizon (from each log's onset, where its input or motion starts) "
        "doubles N-1 times up to the logs' length (default 4; 1 is plain single shooting)",
    )
    fit.add_argument(
        "--segment",
        type=float,
        default=None,
        metavar="SECONDS",
        help="multiple shooting (for long, drifting logs that cannot be simulated open loop over their whole "
        "length): cut each log into segments of at most SECONDS, each with its own estimated start state, "
        "continuity enforced; the result is then the ordinary fit over whole logs from its optimum "
        "(default: single shooting with the growing horizon of --stages)",
    )
    fit.add_argument(
        "--no-frequency-init",
        action="store_true",
        help="keep the guesses of the links' EI as given (default: each free link<i>.EI with a recorded tip or "
        "curvature channel starts where the model's simulated spectrum best matches the log's)",
    )
    fit.add_argument(
        "--max-restarts",
        type=int,
        default=2,
        metavar="N",
        help="if the fit ends with a parameter on a bound, or a channel's residual above twice its noise floor "
        "estimated from the log alone, run the growing horizon again from up to N other optima of the first stage "
        "(default 2; 0: never)",
    )
    fit.add_argument(
        "--no-restart-poor-fit",
        action="store_true",
        help="restart only when a parameter ends on a bound, not on a poor fit (a model that misses an effect "
        "is poor from every start: the restart costs one more fit and the fit reports the misfit either way)",
    )
    fit.add_argument(
        "--closed-loop-only",
        action="store_true",
        help="with a [controller]: report the closed-loop fit (default: refit from its optimum by the direct "
        "method, the logged command replayed open loop, whose intervals hold where the closed loop's are too "
        "narrow; kept only if it does not drift: docs/identification.md)",
    )
    fit.add_argument(
        "--independent",
        action="store_true",
        help="fit every fit log on its own (each log its own parameter values, all logs in one batch: "
        "identify.fit_independent) and test whether they agree (weighted mean and a chi-square test per "
        "parameter); the logs must estimate the same initial-state entries and offsets",
    )
    fit.add_argument("--quiet", action="store_true", help="print no progress, only the results")
    fit.add_argument(
        "--any-rate",
        action="store_true",
        help="fit logs sampled below 1 Hz too (refused by default: most often a time column in ms labelled [s])",
    )
    fit.add_argument(
        "--force",
        action="store_true",
        help="write our files into --out even if it holds other files (they are never deleted or overwritten)",
    )
    ck = sub.add_parser(
        "check",
        help="read an experiment file and its logs and say what a fit would start from, without fitting",
        description="Load the experiment file (docs/experiment-format.md) and its logs with every check a fit makes, "
        "print the rig, the free parameters, the logs and the set-up checks, and exit: 0 if a fit could start, 2 "
        "(with the file, line and key) if not. Nothing is compiled or written (a few seconds).",
    )
    ck.add_argument("experiments", type=Path, nargs="+", metavar="EXPERIMENT", help=EXPERIMENTS_HELP)
    ck.add_argument("--any-rate", action="store_true", help="as for fit")
    dg = sub.add_parser(
        "diagnose",
        help="find what the model gets wrong, name the cause, extend the model, measure the gain",
        description="Fit the experiment's model holding data out, show the residual evidence, fit every "
        "applicable model extension of the catalogue, name the significant cause(s) and write diagnosis.json, "
        "report.md and plots.",
    )
    dg.add_argument("experiments", type=Path, nargs="+", metavar="EXPERIMENT", help=EXPERIMENTS_HELP)
    dg.add_argument("--out", type=Path, default=None, help="output folder (default: ./<experiment stem>-diagnosis)")
    dg.add_argument(
        "--only",
        default=None,
        metavar="NAMES",
        # (written out: importing the catalogue would import JAX before --help;
        # tests/identify/test_cli.py checks it against catalogue.NAMES)
        help="comma-separated catalogue entries to try (default: all that apply): "
        "coulomb_friction, quadratic_damping, missing_mode, joint_elasticity, sensor_delay, sensor_gain_offset, "
        "sensor_highpass, actuator_lag, backlash, base_tilt, geometric_stiffening",
    )
    dg.add_argument("--max-effects", type=int, default=3, metavar="N", help="effects to stack at most (default 3)")
    dg.add_argument(
        "--fit-all",
        action="store_true",
        help="fit every candidate in full (default: one Gauss-Newton step screens them and the 3 most "
        "promising are fitted; slower)",
    )
    dg.add_argument("--quiet", action="store_true", help="print no progress, only the results")
    dg.add_argument("--force", action="store_true", help="as for fit")
    dg.add_argument("--any-rate", action="store_true", help="as for fit")
    return parser


def main(argv=None) -> int:
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed)
        return int(e.code or 0) if not isinstance(e.code, str) else 2
    with warnings.catch_warnings(), _terminate_as_interrupt(), _interrupts_not_swallowed():  # (all restored after)
        warnings.showwarning = _show_warning
        # (the commands import the library, and with it JAX, only once parsed: `--help` stays fast)
        try:
            return _run(args)
        except KeyboardInterrupt:  # (outside the commands' own handling: loading, compiling)
            print(f"identify {args.command}: interrupted; nothing was written", file=sys.stderr, flush=True)
            return 130


def console_main() -> None:
    """The `identify` console script and `python -m identify`: `main`, then exit with its
    status, Ctrl-C and SIGTERM ignored from then on. After an interruption the process
    ends at once (`os._exit`, output flushed): the interpreter's teardown while XLA's
    threads may still be compiling could otherwise crash (a segmentation fault seen after
    Ctrl-C), and everything the command writes is closed and renamed into place by then."""
    code = main()
    # the command is done and its files are closed: a signal now would only interrupt
    # Python's and JAX's clean-up with a traceback (seen in the kill test)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def _run(args) -> int:
    """The command of `args`, on each of its experiments (`batch.run_batch`) or on its one."""
    from .batch import experiment_files, run_batch

    files = experiment_files(list(args.experiments))
    if len(files) > 1:
        suffix = {"fit": "fit", "diagnose": "diagnosis"}.get(args.command)
        return run_batch(args, _run_one, suffix)
    args.experiment = files[0]
    return _run_one(args)


def _run_one(args) -> int:
    """The command of `args` on its experiment (`args.experiment`)."""
    if args.command == "fit":
        from .fit_command import run_fit

        return run_fit(args)
    if args.command == "diagnose":
        from .diagnose_command import run_diagnose

        return run_diagnose(args)
    if args.command == "check":
        from .check_command import run_check

        return run_check(args)
    return 2  # pragma: no cover (argparse requires a command)


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM (a batch job's time limit, `kill`) handled as Ctrl-C: the commands then keep
    and write what they finished, as they do after Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _interrupts_not_swallowed():
    """A Ctrl-C that lands in a callback Python cannot raise from (JAX's garbage-collection
    callback, run at any allocation, often while the libraries import) would be printed
    as "Exception ignored" and lost, the command going on as if never interrupted: such a
    KeyboardInterrupt is re-delivered to the main thread instead (a moment later, again
    until it lands outside a callback), where it stops the command as any Ctrl-C does."""
    previous = sys.unraisablehook

    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            # from another thread, a moment later: the main thread raises it once out of
            # the callback (raised here, it would be lost again in the hook)
            threading.Timer(0.01, _thread.interrupt_main).start()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """A warning as the commands print it: `WARNING: message` on stderr, without Python's
    source location and line of code, which mean nothing to a user of the command line."""
    print(f"WARNING: {message}", file=sys.stderr if file is None else file, flush=True)


if __name__ == "__main__":
    console_main()
