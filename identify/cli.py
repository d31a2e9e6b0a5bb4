"""The `identify` command line (also `python -m identify`).

    identify fit EXPERIMENT.toml [--out DIR] [--stages N] [--no-frequency-init] [--max-restarts N]
                 [--no-restart-poor-fit] [--quiet] [--force] [--any-rate]
    identify diagnose EXPERIMENT.toml [--out DIR] [--only NAME,...] [--max-effects N] [--quiet] [--force]
                      [--any-rate]
    identify check EXPERIMENT.toml [--any-rate]

`check` reads the experiment file and its logs with every check a fit makes and prints
what a fit would start from, in seconds (nothing compiled or written): exit 0 if a fit
can start, 2 with the file, line and key if not.

`diagnose` fits the experiment's model, shows what it gets wrong, tries the catalogue of
model extensions (`identify.catalogue`), names the cause(s) whose gain is significant and
writes `diagnosis.json`, `report.md` and plots (default folder
`./<experiment file stem>-diagnosis/`; see `identify.diagnose`).

loads the experiment (see `identify/FORMAT.md`), fits its free parameters to its fit
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

import argparse
import json
import math
import platform
import sys
import time
import warnings
from pathlib import Path

MARKER = ".identify-output"
#: `identify diagnose` writes every progress line here as it goes (review: a diagnosis
#: stopped after 20 minutes left nothing on disk)
PROGRESS_FILE = "progress.log"
NOT_CONVERGED = 3  # exit status when the fit (`diagnose`: the baseline fit) did not converge
RESULT_FILE = "result.json"


class _Refused(Exception):
    """The output folder may not be used; the message says why."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="identify", description="System identification of flexdyn rigs from measured logs."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    fit = sub.add_parser(
        "fit",
        help="fit an experiment's free parameters to its logs",
        description="Fit the free parameters of an experiment file (identify/FORMAT.md) to its fit logs, check "
        "the fit on its validation logs, print the results and write result.json and plots.",
    )
    fit.add_argument("experiment", type=Path, help="the experiment file (TOML)")
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
        description="Load the experiment file (identify/FORMAT.md) and its logs with every check a fit makes, "
        "print the rig, the free parameters, the logs and the set-up checks, and exit: 0 if a fit could start, 2 "
        "(with the file, line and key) if not. Nothing is compiled or written (a few seconds).",
    )
    ck.add_argument("experiment", type=Path, help="the experiment file (TOML)")
    ck.add_argument("--any-rate", action="store_true", help="as for fit")
    dg = sub.add_parser(
        "diagnose",
        help="find what the model gets wrong, name the cause, extend the model, measure the gain",
        description="Fit the experiment's model holding data out, show the residual evidence, fit every "
        "applicable model extension of the catalogue, name the significant cause(s) and write diagnosis.json, "
        "report.md and plots.",
    )
    dg.add_argument("experiment", type=Path, help="the experiment file (TOML)")
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
    with warnings.catch_warnings():  # (restores `showwarning` on the way out)
        warnings.showwarning = _show_warning
        if args.command == "fit":
            return _fit_command(args)
        if args.command == "diagnose":
            return _diagnose_command(args)
        if args.command == "check":
            return _check_command(args)
    return 2  # pragma: no cover (argparse requires a command)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """A warning as the commands print it: `WARNING: message` on stderr, without Python's
    source location and line of code (found in review: a user of the command line read
    `.../identify/run.py:36: UserWarning:` and the library's source line)."""
    print(f"WARNING: {message}", file=sys.stderr if file is None else file, flush=True)


# ---------------------------------------------------------------------------
# Output folder
# ---------------------------------------------------------------------------


def output_files() -> tuple[str, ...]:
    """Every file name the commands write into their output folders."""
    from .diagnosis_report import FILES
    from .report import BY_LOG_PLOT, PLOT_FILES

    return (MARKER, RESULT_FILE, PROGRESS_FILE, *PLOT_FILES, BY_LOG_PLOT, *FILES)


def _same(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except OSError:
        return False


def check_output_folder(out: Path, inputs: list[Path], force: bool, suffix: str = "fit") -> None:
    """Raise `_Refused` unless we may write our files into `out`. `inputs`: the
    experiment file and its logs."""
    for p in inputs:
        if _same(out, p.parent):
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
    foreign = [p.name + ("/" if p.is_dir() else "") for p in entries if p.name not in ours or not p.is_file()]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f", ... ({len(foreign)} in all)" if len(foreign) > 5 else "")
        raise _Refused(
            f"refusing to write into {out}: it holds files this command did not write ({shown}). "
            "Choose another folder with --out, or pass --force to write our files there anyway "
            "(other files are left untouched)."
        )
    if not (out / MARKER).is_file():
        raise _Refused(
            f"refusing to write into {out}: it exists and is not the output of a previous `identify` command "
            f"(no {MARKER} file). Choose another folder with --out, or pass --force."
        )


# ---------------------------------------------------------------------------
# Computation helpers
# ---------------------------------------------------------------------------


def modal_configuration(chain):
    """The configuration to analyse the fitted chain about: hanging along gravity (first
    joint angle `atan2(g_y, g_x)`, i.e. -pi/2 for gravity pointing down, the others 0,
    rotor angles with their links, undeformed) under gravity, else all zero."""
    import numpy as np

    lay = chain.layout
    Q0 = np.zeros(lay.n_dof)
    g = np.asarray(chain.gravity, float) if getattr(chain, "gravity", None) is not None else np.zeros(2)
    if np.linalg.norm(g) > 0:
        angle = float(np.arctan2(g[1], g[0]))
        Q0[lay.theta[0]] = angle
        if lay.rotor[0] is not None:
            Q0[lay.rotor[0]] = angle
        where = f"hanging equilibrium, theta1 = {np.degrees(angle):.4g} deg"
    else:
        where = "zero configuration"
    return Q0, where


def natural_frequencies(chain):
    """Undamped natural frequencies (Hz) of `chain` about `modal_configuration(chain)`."""
    import numpy as np

    import flexdyn as fd

    Q0, where = modal_configuration(chain)
    modes = fd.modal_analysis(chain, Q0)
    return [float(f) for f in np.asarray(modes.natural_frequency)], where


def validate(exp, result, progress=None):
    """The fitted model on every validation log (`identify.evaluate_held_out`: physical
    parameters fixed, each log's own initial-state entries and offsets re-estimated).
    Returns `(outputs, report, nuisances)` in the layout of `identify.fitted_outputs`,
    `identify.residual_report` and `FitResult.initial_states/offsets`."""
    from .fit import fitted_outputs
    from .run import evaluate_held_out, residual_report

    held = evaluate_held_out(result, exp, progress=progress)
    nuisances = {
        name: {
            "initial_states": {k: v[0] for k, v in held.initial_states.get(name, {}).items()},
            "offsets": {k: v[0] for k, v in held.offsets.get(name, {}).items()},
            # (each held-out log's own value of a per-log parameter, `Parameter.per_log`)
            "parameters": {p: by_log[name] for p, by_log in held.per_log.items()},
        }
        for name in held.problem.log_names
    }
    return fitted_outputs(held), residual_report(held), nuisances


def _versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("flexdyn", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "numpy", "scipy", "matplotlib"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out


# ---------------------------------------------------------------------------
# Printing
# ---------------------------------------------------------------------------


def _set_up_checks(exp) -> list[str]:
    """What to check of the set-up before a long run: where the rig's gravity makes the
    first link hang (against the logs' angle zero), any log whose sampling rate
    questions its time column's unit, initial values held at a noisy first sample, and the
    columns each log leaves unused."""
    from .experiment import gravity_text

    lines = [gravity_text(exp.chain.gravity)]
    for spec in exp.logs:
        hint = spec.log.sampling.time_unit_hint
        if hint:
            lines.append(f"warning: log {spec.name!r}: {spec.log.sampling.rate:.6g} Hz, {hint}")
        lines.extend(f"warning: {w}" for w in spec.warnings())
        if spec.log.ignored:
            lines.append(f"log {spec.name!r}: columns not used: {', '.join(map(repr, spec.log.ignored))}")
    return lines


def _residual_lines(report: dict, outputs: dict, roles: dict) -> list[str]:
    """The residual table: per log and channel the residual's RMS, its ratio to the noise
    floor of the measured samples alone (`identify.noise_floor`: ~1 where the model
    explains the data; the fit's own noise estimate would read ~1 whatever the misfit),
    whiteness and correlation with the input. `outputs`: `fitted_outputs` of the logs."""
    from .noise_floor import series_floor
    from .report import display_unit

    lines = [
        f"{'log':<24} {'channel':<10} {'RMS':>14} {'RMS/floor':>9}  {'whiteness (Ljung-Box p)':<26} input correlation"
    ]
    for name, per_channel in report.items():
        label = name + (" [val]" if roles.get(name) == "validation" else "")
        for c, item in per_channel.items():
            scale, unit = display_unit(c)
            w = item["whiteness"]
            white = f"{'white' if w['white'] else 'NOT white'} (p = {w['p_value']:.2g})"
            ic = item["input_correlation"]
            if not ic:
                inp = "n/a (no input)"
            else:
                bad = [k for k, v in ic.items() if not v["independent"]]
                inp = "correlated with " + ", ".join(bad) if bad else "independent of " + ", ".join(ic)
            entry = outputs.get(name, {})
            floor = series_floor(entry["t"], entry["measured"][c]) if c in entry.get("measured", {}) else 0.0
            ratio = item["rms"] / floor if floor > 0 else float("nan")
            rms = f"{scale * item['rms']:.4g} {unit}"
            lines.append(f"{label:<24} {c:<10} {rms:>14} {ratio:>9.3g}  {white:<26} {inp}")
    lines.append(
        "(RMS/floor: the residual against the noise of the measured samples alone, identify.noise_floor; "
        "a model that explains the data reaches ~1)"
    )
    coloured = [
        f"{name} {c}"
        for name, per_channel in report.items()
        if roles.get(name) != "validation"
        for c, item in per_channel.items()
        if not item["whiteness"]["white"]
    ]
    if coloured:
        lines.append(
            f"note: the residuals of {', '.join(coloured)} (fit logs) are not white: the fitted intervals assume "
            "white residuals and are then too narrow; the cause may be an effect the model misses (identify "
            'diagnose), a filtered sensor, or an initial value held at a noisy first sample ("measured" without '
            "fit_initial)"
        )
    return lines


def _nuisance_lines(result, validation_nuisances: dict) -> list[str]:
    from .fit import parameter_unit
    from .report import display_unit, state_display_unit

    lines = []
    names = list(dict.fromkeys([*result.initial_states, *result.offsets, *validation_nuisances]))
    for name in names:
        parts = []
        for entry, (v, se) in result.initial_states.get(name, {}).items():
            scale, unit = state_display_unit(entry)
            parts.append(f"initial {entry} = {scale * v:.4g} +- {scale * se:.2g} {unit}")
        for c, (v, se) in result.offsets.get(name, {}).items():
            scale, unit = display_unit(c)
            parts.append(f"offset {c} = {scale * v:.4g} +- {scale * se:.2g} {unit}")
        val = validation_nuisances.get(name)
        if val is not None:
            for entry, v in val["initial_states"].items():
                scale, unit = state_display_unit(entry)
                parts.append(f"initial {entry} = {scale * v:.4g} {unit}")
            for c, v in val["offsets"].items():
                scale, unit = display_unit(c)
                parts.append(f"offset {c} = {scale * v:.4g} {unit}")
            for p, v in val.get("parameters", {}).items():
                parts.append(f"{p} = {v:.4g} {parameter_unit(result.problem, p)}")
            name = name + " [val]"
        if parts:
            lines.append(f"  {name}: " + "; ".join(parts))
    return lines


#: `identify fit` adds cluster-robust intervals (`identify.clustered_uncertainty`) from this
#: many fit logs on (fewer clusters give an interval too uncertain to be useful).
CLUSTER_MIN_LOGS = 5


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
    from .experiment import ExperimentError, load_experiment
    from .logs import LogError

    try:
        exp = load_experiment(args.experiment)
    except (ExperimentError, LogError) as e:
        raise _Refused(str(e)) from None
    from .logs import PLAUSIBLE_RATE_HZ

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


def _check_command(args) -> int:
    """`identify check`: load the experiment with every check a fit makes before it
    compiles anything (the file, the logs, the problem `make_problem` builds: its logs at
    rest, its sampling) and print what a fit would start from (review: the only way to
    validate a file was to start a fit and wait for its compilation)."""
    try:
        exp = _load_experiment(args)
    except _Refused as e:
        print(f"identify check: {e}", file=sys.stderr, flush=True)
        return 2
    from .run import problem_from_experiment

    print(f"identify check: {exp.summary()}")
    for line in _set_up_checks(exp)[1:]:  # (the summary gives the gravity)
        if not line.startswith("warning: ") or line not in exp.summary():
            print(f"  {line}")
    try:
        problem = problem_from_experiment(exp)
    except ValueError as e:
        print(f"identify check: {e}", file=sys.stderr, flush=True)
        return 2
    # the declared noise against the model-free floor of the fit logs (review: "0.05 m"
    # for a 0.05 mm strain gauge passed the check and was only flagged after the fit)
    import numpy as np

    from .fit import _floors
    from .noise_floor import declared_noise_warnings, pooled

    floor, count = _floors(problem)
    floors = np.sqrt(pooled(floor**2, count))
    quality = {c: {"noise_floor": float(f)} for c, f in zip(problem.channels, floors) if np.isfinite(f)}
    for line in declared_noise_warnings(exp.noise, quality):
        print(f"  warning: {line}")
    samples = int(problem.valid.sum())
    print(
        f"ok: a fit can start: {len(exp.free)} free parameter(s), {len(problem.log_names)} fit log(s) "
        f"({samples} samples), {len(exp.validation_logs)} validation log(s); run `identify fit {args.experiment}`"
    )
    return 0


def _failure_text(e: Exception) -> str:
    """What to print of a failed fit: a run-time check's own message without the JAX and
    Equinox stacks around it (`flexdyn._checks.runtime_check_message`), else the error's."""
    from flexdyn._checks import runtime_check_message

    return runtime_check_message(e) or str(e)


def _compile_estimate(exp) -> float:
    """A rough guess of the first fit's time (s), compilation included, on a 2-core
    machine, growing with the number of coordinates and channels. Measured 2026-12-03 (2-core
    Intel Xeon): 10.6 s for `examples/pendulum_drops` (1 coordinate, 1 channel), 49.5 s for
    a flexible link on an elastic joint (4 coordinates, 3 channels, frequency
    initialisation included); the guess is ~1.15x those. Doubled where the process may use
    one core only (review, a two-link arm under `taskset -c 0`: ~96 s guessed, 198 s to the
    end of the first stage)."""
    n = exp.chain.n_dof
    guess = 12.0 * (1.0 + 0.8 * (n - 1)) * (1.0 + 0.2 * (len(exp.output_channels) - 1))
    return guess * (2.0 if _cores() < 2 else 1.0)


def _cores() -> int:
    """The CPU cores this process may run on."""
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


# ---------------------------------------------------------------------------
# The fit command
# ---------------------------------------------------------------------------


def _fit_command(args) -> int:
    start = time.perf_counter()
    quiet = args.quiet

    def say(msg=""):
        if not quiet:
            print(msg, flush=True)

    def error(msg: str) -> int:
        print(f"identify fit: {msg}", file=sys.stderr, flush=True)
        return 2

    if args.stages < 1:
        return error(f"--stages expects an integer >= 1, got {args.stages}")
    if args.max_restarts < 0:
        return error(f"--max-restarts expects an integer >= 0, got {args.max_restarts}")

    try:
        exp, inputs, out = _experiment_and_folder(args, "fit")
    except _Refused as e:
        return error(str(e))

    import jax
    import numpy as np

    from . import channels as ch, evidence, report as plots
    from .fit import fitted_outputs, parameter_unit
    from .noise_floor import declared_noise_warnings
    from .run import fit_experiment, residual_report
    from .uncertainty import between_logs, clustered_uncertainty

    roles = {spec.name: spec.role for spec in exp.logs}
    n_fit = len(exp.fit_logs)
    n_samples = sum(len(spec.log) for spec in exp.fit_logs)
    say(f"identify fit: experiment {exp.name!r} ({exp.path})")
    say(
        f"  rig: {exp.chain.n_links} link(s), coordinates {', '.join(exp.chain.coordinate_names())}; "
        f"free: {', '.join(p.name + (' (per log)' if p.per_log else '') for p in exp.free)}"
    )
    for line in _set_up_checks(exp):
        say(f"  {line}")
    say(
        f"  {n_fit} fit log(s) ({n_samples} samples), {len(exp.validation_logs)} validation log(s); "
        f"{args.stages} horizon stage(s); JAX on {jax.default_backend()}"
    )
    say(
        f"compiling the simulation and Levenberg-Marquardt (first call, ~{_compile_estimate(exp):.0f} s in all on "
        f"{_cores()} core(s): the frequency initialisation's and the first stage's times include it) ..."
    )

    last = [time.perf_counter()]

    def progress(msg: str):
        now = time.perf_counter()
        say(f"[{now - start:6.1f} s, +{now - last[0]:5.1f} s] {msg.strip()}")
        last[0] = now

    if args.independent:
        return _independent_fits(args, exp, inputs, out, start, say, progress)
    try:
        result = fit_experiment(
            exp,
            n_stages=args.stages,
            frequency_init=not args.no_frequency_init,
            max_restarts=args.max_restarts,
            restart_poor_fit=not args.no_restart_poor_fit,
            progress=progress,
        )
    except (RuntimeError, ValueError) as e:
        print(f"identify fit: the fit failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    say(f"[{time.perf_counter() - start:6.1f} s] fit done ({result.wall_time:.1f} s incl. compilation and covariance)")

    t0 = time.perf_counter()
    outputs = fitted_outputs(result)
    resid = residual_report(result)
    fitted_chain = result.chain
    freqs, where = natural_frequencies(fitted_chain)
    robust, robust_note = None, None
    if n_fit >= CLUSTER_MIN_LOGS and result.problem.per_log:
        robust_note = (
            "cluster-robust intervals not computed: a per-log parameter is informed by one log (cluster) only, "
            "so they do not apply"
        )
    elif n_fit >= CLUSTER_MIN_LOGS and n_fit <= len(result.names):
        robust_note = (
            f"cluster-robust intervals not computed: {n_fit} fit logs for {len(result.names)} free parameters "
            "(they need more logs than parameters)"
        )
    elif n_fit >= CLUSTER_MIN_LOGS:
        say(f"cluster-robust intervals ({n_fit} fit logs as clusters) ...")
        robust = clustered_uncertainty(result)
    val_outputs, val_report, val_nuisances = {}, {}, {}
    if exp.validation_logs:
        own = "".join(f", {p.name}" for p in exp.free if p.per_log)
        say(f"checking the fit on the validation log(s) (their initial state, offsets{own} re-estimated) ...")
        val_outputs, val_report, val_nuisances = validate(exp, result, progress)
    t_post = time.perf_counter() - t0

    # ---- results -------------------------------------------------------------
    print()
    print(f"Fitted parameters ({exp.name}):")
    print(result.summary())
    for line in declared_noise_warnings(exp.noise, result.fit_quality):
        print(f"warning: {line}")
    if not result.identifiability:
        sv = np.asarray(result.singular_values)
        ratio = float(sv[-1] / sv[0]) if sv.size and sv[0] > 0 else float("nan")
        print(f"identifiability: no warnings (smallest/largest singular value of the Jacobian {ratio:.2g})")
    if not result.converged:
        last = result.stages[-1]["result"]
        if last != "successful":
            print(f"WARNING: the fit did not converge (last stage: {last}); try more --stages")
        else:  # the solver stopped at a bound: not an interior optimum
            print(
                f"WARNING: the fit ended with {', '.join(result.at_bounds)} on a bound, so it is not an optimum of "
                "the model: widen the bounds, or check the model (gravity, units: see the warnings above)"
            )
    if robust_note is not None:
        print()
        print(robust_note)
    agreement = None
    if result.problem.per_log and result.converged and n_fit >= 2:
        print()
        try:  # do the per-log values differ beyond their intervals?
            agreement = between_logs(result)
            print(agreement.summary())
        except ValueError as e:  # (a per-log value some log does not determine)
            print(f"per-log values not compared: {e}")
    if robust is not None:
        print()
        print(robust.summary())
        print(
            "(the intervals above assume white residuals; these assume only that the logs are independent: "
            "read these when the residual tests below fail, as on real rigs)"
        )
    nuisance = _nuisance_lines(result, val_nuisances)
    if nuisance:
        print()
        own = " (validation logs: also their own per-log parameters)" if result.problem.per_log else ""
        print(f"Per-log nuisances{own}:")
        print("\n".join(nuisance))
    print()
    nf = ", ".join(f"{f:.4g}" for f in freqs if f > 0) or "none (rigid-body modes only)"
    kept = ", ".join(n for n, _ in result.problem.per_log)
    kept = f"; {kept} at the rig's value, not a log's" if kept else ""
    print(f"Natural frequencies of the fitted model ({where}{kept}): {nf} Hz")
    unstable = [f for f in freqs if f < 0]
    if unstable:  # (`fd.Modes`: a negative frequency is an unstable mode)
        print(
            f"WARNING: the fitted model is not stable about that configuration: {len(unstable)} mode(s) diverge "
            f"(growth rate {', '.join(f'{-2 * math.pi * f:.4g}' for f in unstable)} 1/s); a slender link hanging "
            "under gravity needs `geometric_stiffening = true`"
        )
    all_outputs = {**outputs, **val_outputs}
    model_checks = evidence.stiffening_checks_of(fitted_chain, all_outputs, key="simulated")
    for check in model_checks:
        print(f"{'WARNING: ' if check['flagged'] else ''}model check: {check['message']}")
    print()
    print("Residuals (fitted - measured; [val] = validation log, not used by the fit):")
    combined_report = {**resid, **val_report}
    print("\n".join(_residual_lines(combined_report, all_outputs, roles)))

    # ---- files ---------------------------------------------------------------
    t0 = time.perf_counter()
    try:
        check_output_folder(out, inputs, args.force)  # again: the fit took a while
    except _Refused as e:
        return error(str(e))
    _write_marker(out)
    doc = result.to_dict()
    doc["experiment"] = _experiment_doc(exp)
    doc["residuals"] = resid
    doc["validation"] = {
        name: {
            "residuals": val_report[name],
            "initial_states": {
                e: {"value": v, "unit": ch.state_unit(e)} for e, v in val_nuisances[name]["initial_states"].items()
            },
            "offsets": {c: {"value": v, "unit": ch.channel_unit(c)} for c, v in val_nuisances[name]["offsets"].items()},
            "parameters": {
                p: {"value": v, "unit": parameter_unit(result.problem, p)}
                for p, v in val_nuisances[name]["parameters"].items()
            },
        }
        for name in val_outputs
    }
    doc["natural_frequencies_hz"] = freqs
    doc["model_checks"] = model_checks
    doc["clustered_uncertainty"] = None if robust is None else robust.to_dict()
    doc["per_log_agreement"] = None if agreement is None else agreement.to_dict()
    doc["modal_configuration"] = where
    doc["options"] = {"stages": args.stages}
    doc["command"] = ["identify", "fit", *map(str, _argv_tail(args))]
    doc["versions"] = _versions()
    (out / RESULT_FILE).write_text(json.dumps(plots.jsonable(doc), indent=1) + "\n")
    written = [out / MARKER, out / RESULT_FILE]
    written += plots.write_plots(
        result,
        {**outputs, **val_outputs},
        combined_report,
        out,
        natural_frequencies=freqs,
        where=where,
        roles=roles,
        title=exp.name,
    )
    if result.problem.per_log:  # each log's own values, and their common value when compared
        written += plots.plot_per_log(result, agreement, out)
    t_files = time.perf_counter() - t0

    print()
    say(
        f"timings: fit {result.wall_time:.1f} s (compilation included), residual tests, modal analysis and "
        f"validation {t_post:.1f} s, files {t_files:.1f} s; total {time.perf_counter() - start:.1f} s"
    )
    print(f"Results written to {out}/:")
    for p in written:
        if p.name != MARKER:
            print(f"  {p}")
    if not result.converged:  # a script must not read this as success (found in review: exit 0)
        print(
            f"identify fit: exit status {NOT_CONVERGED}: the fit did not converge"
            + (f" ({', '.join(result.at_bounds)} on a bound)" if result.at_bounds else "")
            + "; the results above are written but are not an optimum of the model",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _write_marker(out: Path) -> None:
    """Create `out` and mark it as `identify`'s (`check_output_folder`)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text(
        "Written by `identify` (flexdyn). This folder holds its outputs; a new run may overwrite these "
        f"files: {', '.join(output_files())}.\n"
    )


def _experiment_doc(exp) -> dict:
    """The experiment's part of result.json: name, description, path, logs."""
    return {
        "name": exp.name,
        "description": exp.description,
        "path": str(Path(exp.path).resolve()),
        "logs": [
            {"name": s.name, "file": str(Path(s.file).resolve()), "role": s.role, "samples": len(s.log), "set": s.set}
            for s in exp.logs
        ],
    }


def _independent_fits(args, exp, inputs, out, start, say, progress) -> int:
    """`identify fit --independent`: every fit log on its own, then `between_logs`."""
    from . import report as plots
    from .fit import fitted_outputs
    from .run import fit_experiment_independent, residual_report
    from .uncertainty import between_logs

    if len(exp.fit_logs) < 2:
        print("identify fit: --independent needs at least 2 fit logs; this experiment has 1", file=sys.stderr)
        return 2
    if exp.validation_logs:
        say(f"  --independent: the {len(exp.validation_logs)} validation log(s) are not used (each log is its own fit)")
    try:
        results = fit_experiment_independent(
            exp,
            n_stages=args.stages,
            frequency_init=not args.no_frequency_init,
            restart_poor_fit=not args.no_restart_poor_fit,
            progress=progress,
        )
    except (RuntimeError, ValueError) as e:
        print(f"identify fit: the fits failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    say(f"[{time.perf_counter() - start:6.1f} s] {len(results)} independent fits done")
    try:
        between = between_logs(results)
    except ValueError as e:  # fewer than 2 converged logs
        between, between_note = None, str(e)
    print()
    print(f"Independent fits ({exp.name}): each fit log on its own")
    for r in results:
        print()
        print(r.summary())
    print()
    print(between.summary() if between is not None else f"no comparison between the logs: {between_note}")

    try:
        check_output_folder(out, inputs, args.force)  # again: the fits took a while
    except _Refused as e:
        print(f"identify fit: {e}", file=sys.stderr, flush=True)
        return 2
    _write_marker(out)
    outputs, reports = {}, {}
    for r in results:
        outputs.update(fitted_outputs(r))
        reports.update(residual_report(r))
    doc = {
        "mode": "independent",
        "experiment": _experiment_doc(exp),
        "logs": {", ".join(r.problem.log_names): r.to_dict() for r in results},
        "between_logs": None if between is None else between.to_dict(),
        "residuals": reports,
        "options": {"stages": args.stages, "independent": True},
        "command": ["identify", "fit", *map(str, _argv_tail(args))],
        "versions": _versions(),
    }
    (out / RESULT_FILE).write_text(json.dumps(plots.jsonable(doc), indent=1) + "\n")
    roles = {name: "fit" for name in outputs}
    written = [out / RESULT_FILE]
    written += plots.plot_fit(outputs, out, title=f"{exp.name}: each log fitted on its own", roles=roles)
    written += plots.plot_residuals(outputs, out, roles=roles)
    written += plots.plot_by_log(results, between, out)
    print()
    say(f"total {time.perf_counter() - start:.1f} s")
    print(f"Results written to {out}/:")
    for p in written:
        print(f"  {p}")
    failed = [", ".join(r.problem.log_names) for r in results if not r.converged]
    if failed:
        print(
            f"identify fit: exit status {NOT_CONVERGED}: the fit of log(s) {', '.join(failed)} did not converge; "
            "the results above are written but those logs' values are not optima of the model",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _diagnose_command(args) -> int:
    start = time.perf_counter()

    def say(msg=""):
        if not args.quiet:
            print(msg, flush=True)

    def error(msg: str) -> int:
        print(f"identify diagnose: {msg}", file=sys.stderr, flush=True)
        return 2

    from .catalogue import NAMES

    catalogue = NAMES
    if args.only:
        catalogue = tuple(x.strip() for x in args.only.split(",") if x.strip())
        bad = [x for x in catalogue if x not in NAMES]
        if bad:
            return error(f"--only: unknown catalogue entries {bad}; expected some of {', '.join(NAMES)}")
    if args.max_effects < 1:
        return error(f"--max-effects expects an integer >= 1, got {args.max_effects}")
    try:
        exp, inputs, out = _experiment_and_folder(args, "diagnosis")
    except _Refused as e:
        return error(str(e))

    from .diagnose import diagnose
    from .diagnosis_report import write_report

    # The output folder is made now and every progress line goes to its progress.log as
    # it is said, so that a diagnosis stopped part way (Ctrl-C, a job's time limit) leaves
    # what it found so far: the baseline fit, the screening, each round's scores.
    out.mkdir(parents=True, exist_ok=True)
    _write_marker(out)
    log_path = out / PROGRESS_FILE
    log_file = log_path.open("w", encoding="utf-8")

    def record(msg: str):
        say(msg)
        log_file.write(msg + "\n")
        log_file.flush()

    record(f"identify diagnose: experiment {exp.name!r} ({exp.path})")
    for line in _set_up_checks(exp):
        record(f"  {line}")
    record(f"  catalogue: {', '.join(catalogue)}; compiling takes most of the first minutes")
    last = [time.perf_counter()]

    def progress(msg: str):
        now = time.perf_counter()
        record(f"[{now - start:6.1f} s, +{now - last[0]:5.1f} s] {msg.strip()}")
        last[0] = now

    try:
        diag = diagnose(
            exp,
            catalogue=catalogue,
            max_effects=args.max_effects,
            progress=progress,
            **({"n_fit": None} if args.fit_all else {}),
        )
    except (RuntimeError, ValueError) as e:
        record(f"identify diagnose: failed: {_failure_text(e)}")
        log_file.close()
        print(f"identify diagnose: failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        record(f"identify diagnose: interrupted after {time.perf_counter() - start:.1f} s")
        log_file.close()
        print(
            f"identify diagnose: interrupted; what it had found so far is in {log_path}",
            file=sys.stderr,
            flush=True,
        )
        return 130
    log_file.close()
    print()
    print(diag.summary())
    try:
        check_output_folder(out, inputs, args.force, "diagnosis")
    except _Refused as e:
        return error(str(e))
    _write_marker(out)
    extra = {
        "experiment": {"name": exp.name, "path": str(Path(exp.path).resolve())},
        "command": ["identify", "diagnose", str(args.experiment)],
        "versions": _versions(),
    }
    written = write_report(diag, out, title=exp.name, extra=extra)
    print()
    print(f"total {time.perf_counter() - start:.1f} s. Report: {out / 'report.md'} (open it; plots beside it)")
    for p in [*written, log_path]:
        print(f"  {p}")
    if not diag.baseline_converged:  # found in review: exit 0, and nothing said
        print(
            f"identify diagnose: exit status {NOT_CONVERGED}: the baseline fit did not converge "
            f"({diag.baseline.stages[-1]['result']}); the diagnosis is written, but its scores are measured "
            "against a model short of its optimum (see the baseline note in the summary)",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _argv_tail(args) -> list:
    tail = [args.experiment]
    if args.out is not None:
        tail += ["--out", args.out]
    tail += ["--stages", args.stages]
    if args.quiet:
        tail.append("--quiet")
    if args.force:
        tail.append("--force")
    return tail


if __name__ == "__main__":
    sys.exit(main())
