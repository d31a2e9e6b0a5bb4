"""`identify fit`: print and write what the library's fit returns."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from .._report.json import package_versions
from .check_command import _set_up_checks
from .fit_text import print_results
from .folder import OutputFolder, write_atomic
from .output import INTERRUPTED, NOT_CONVERGED, RESULT_FILE, _experiment_and_folder, _Refused, printers


def _failure_text(e: Exception) -> str:
    """What to print of a failed fit: a run-time check's own message without the JAX and
    Equinox stacks around it (`flexdyn._checks.runtime_check_message`), else the error's."""
    from flexdyn._checks import runtime_check_message

    return runtime_check_message(e) or str(e)


def _compile_estimate(exp) -> float:
    """A rough guess of the first fit's time (s), compilation included, on a 2-core
    machine, growing with the number of coordinates and channels: ~1.15x the measured times
    (docs/performance.md). Doubled where the process may use one core only."""
    n = exp.chain.n_dof
    guess = 12.0 * (1.0 + 0.8 * (n - 1)) * (1.0 + 0.2 * (len(exp.output_channels) - 1))
    return guess * (2.0 if _cores() < 2 else 1.0)


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def run_fit(args) -> int:
    """`identify fit EXPERIMENT`: fit, write `result.json` and plots, print the results.
    Exit status 0, 1 (the fit failed), 2 (bad arguments or folder), `NOT_CONVERGED`, 130
    (interrupted). The output folder is claimed before the fit (`OutputFolder`); once the
    fit is done its result is written whatever fails or is interrupted after it."""
    start = time.perf_counter()
    say, error = printers("fit", args.quiet)
    if args.stages < 1:
        return error(f"--stages expects an integer >= 1, got {args.stages}")
    if args.max_restarts < 0:
        return error(f"--max-restarts expects an integer >= 0, got {args.max_restarts}")
    if args.segment is not None and args.independent:
        return error("--segment (multiple shooting) is an option of the joint fit, not of --independent")
    try:
        exp, inputs, out = _experiment_and_folder(args, "fit")
        folder = OutputFolder.claim(out, inputs, args.force)
    except _Refused as e:
        return error(str(e))
    with folder:
        if folder.killed_before:
            say(f"note: the previous run into {out} was killed ({folder.previous}); its files are replaced")
        return _fit_into(args, exp, folder, start, say)


def _fit_into(args, exp, folder: OutputFolder, start: float, say) -> int:
    """`run_fit` once its output `folder` is claimed."""
    from .._workflow import FitReport, fit_experiment

    _say_set_up(exp, args, say)
    progress = _progress(start, say)
    if args.independent:
        return _independent_fits(args, exp, folder, start, say, progress)
    options = dict(
        n_stages=args.stages,
        frequency_init=not args.no_frequency_init,
        max_restarts=args.max_restarts,
        restart_poor_fit=not args.no_restart_poor_fit,
        shooting="single" if args.segment is None else "multiple",
        segment=args.segment,
        progress=progress,
    )
    try:
        result = fit_experiment(exp, direct=False, **options)
    except (RuntimeError, ValueError) as e:
        folder.abandon("failed: the fit failed, nothing written")
        print(f"identify fit: the fit failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        folder.abandon("interrupted during the fit, nothing written")
        print("identify fit: interrupted during the fit; nothing was written", file=sys.stderr, flush=True)
        return INTERRUPTED
    say(f"[{time.perf_counter() - start:6.1f} s] fit done ({result.wall_time:.1f} s incl. compilation and covariance)")
    result, interrupted = (result, False) if args.closed_loop_only else _direct_step(exp, result, options, say)
    t0 = time.perf_counter()
    if interrupted:
        report = FitReport.of_fit(exp, result, "interrupted (Ctrl-C) during the direct fit: the closed-loop fit")
    else:
        report, interrupted = _follow_ups(exp, result, progress, say)
    t_post = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        written, interrupted = _write_fit(report, folder, args, interrupted)
    except OSError as e:  # the folder went away or the disk filled during the fit
        written = [_rescue(report, args, folder.path, e)]
    t_files = time.perf_counter() - t0
    _print_safely(lambda: print_results(report))
    print()
    say(
        f"timings: fit {result.wall_time:.1f} s (compilation included), residual tests, modal analysis and "
        f"validation {t_post:.1f} s, files {t_files:.1f} s; total {time.perf_counter() - start:.1f} s"
    )
    _say_written(folder.path, written)
    return _exit_status(result, report, interrupted)


def _progress(start: float, say):
    """The progress printer: each line with the time since `start` and since the last line."""
    last = [time.perf_counter()]

    def progress(msg: str):
        now = time.perf_counter()
        say(f"[{now - start:6.1f} s, +{now - last[0]:5.1f} s] {msg.strip()}")
        last[0] = now

    return progress


def _follow_ups(exp, result, progress, say):
    """`(report, interrupted)`: `fit_report` of the finished fit; after Ctrl-C, the fit alone."""
    from .._workflow import FitReport, fit_report

    try:
        return fit_report(exp, result, progress=progress, say=say), False
    except KeyboardInterrupt:
        print("identify fit: interrupted after the fit; writing the fit alone", file=sys.stderr, flush=True)
        return FitReport.of_fit(exp, result, "interrupted (Ctrl-C) before the fit's follow-ups were computed"), True


def _print_safely(show) -> None:
    """Run `show` (printing); a failure is a warning, never the end of the run."""
    try:
        show()
    except Exception as e:  # noqa: BLE001 (formatting must not cost the written result)
        print(
            f"identify fit: warning: the summary could not be printed ({type(e).__name__}: {e}); "
            "the results are in result.json",
            file=sys.stderr,
            flush=True,
        )


def _say_written(out: Path, written: list[Path]) -> None:
    print(f"Results written to {out}/:")
    for p in written:
        print(f"  {p}")


def _direct_step(exp, result, options: dict, say):
    """`(result, interrupted)`: a closed-loop experiment's direct-method fit from the
    loop fit `result` (`identify/_fit/direct.py`); after Ctrl-C, the loop fit."""
    if exp.controller is None:
        return result, False
    from .._workflow import refit_direct

    say("direct fit: the logged command replayed open loop from the closed-loop optimum ...")
    try:
        return refit_direct(exp, result, **options), False
    except KeyboardInterrupt:
        print("identify fit: interrupted in the direct fit; writing the closed-loop fit", file=sys.stderr, flush=True)
        return result, True


def _exit_status(result, report, interrupted: bool) -> int:
    if interrupted:
        print(f"identify fit: exit status {INTERRUPTED}: interrupted; what was done is written", file=sys.stderr)
        return INTERRUPTED
    if not result.converged:  # a script must not read this as success
        print(
            f"identify fit: exit status {NOT_CONVERGED}: the fit did not converge"
            + (f" ({', '.join(result.at_bounds)} on a bound)" if result.at_bounds else "")
            + "; the results above are written but are not an optimum of the model",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _say_set_up(exp, args, say) -> None:
    """The experiment, its rig, logs and set-up checks, and the compile-time guess."""
    import jax

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


def _write_fit(report, folder: OutputFolder, args, interrupted: bool) -> tuple[list[Path], bool]:
    """`result.json` first, then the plots, staged and committed into `folder`
    (`OutputFolder.commit`). A plot that fails is a warning (in `result.json`'s
    `problems`); Ctrl-C while plotting skips the remaining plots. Returns the paths
    written and whether the run was interrupted."""
    from .._report import fit_plots as plots

    result, exp = report.result, report.experiment
    stage = folder.staging()
    doc = report.to_dict(options=_options(args), command=["identify", "fit", *map(str, _argv_tail(args))])
    _write_json(stage / RESULT_FILE, doc)  # first: whatever happens next, the fit is on disk
    outputs = {**report.outputs, **report.validation_outputs}
    tasks = []
    if outputs:
        tasks.append(
            lambda: plots.write_plots(
                result,
                outputs,
                {**report.residuals, **report.validation_residuals},
                stage,
                natural_frequencies=report.natural_frequencies,
                where=report.modal_configuration,
                roles={spec.name: spec.role for spec in exp.logs},
                title=exp.name,
            )
        )
    if result.problem.per_log:  # each log's own values, and their common value when compared
        tasks.append(lambda: plots.plot_per_log(result, report.agreement, stage))
    problems, interrupted = _run_plots(tasks, stage, interrupted)
    return _commit_json(folder, doc, problems, interrupted), interrupted


def _run_plots(tasks, stage: Path, interrupted: bool) -> tuple[list[str], bool]:
    """Run the plotting `tasks` (writing into `stage`); each failure becomes a problem line
    and its files are removed; Ctrl-C stops them."""
    problems = []
    for task in tasks:
        if interrupted:
            problems.append("plots not written: interrupted (Ctrl-C)")
            break
        before = set(stage.iterdir())
        try:
            task()
        except (Exception, KeyboardInterrupt) as e:  # a plot must not cost the written result
            for p in set(stage.iterdir()) - before:  # (this task's files: one may be partial)
                p.unlink()
            interrupted |= isinstance(e, KeyboardInterrupt)
            why = "interrupted (Ctrl-C)" if isinstance(e, KeyboardInterrupt) else f"{type(e).__name__}: {e}"
            problems.append(f"plots not written: {why}")
            print(f"identify fit: warning: {problems[-1]}", file=sys.stderr, flush=True)
    return problems, interrupted


def _commit_json(folder: OutputFolder, doc: dict, problems: list[str], interrupted: bool) -> list[Path]:
    """The staged result file rewritten with the plots' `problems`, the list of the run's
    `files` and whether it was `interrupted`, then everything committed into `folder`."""
    stage = folder.staging()
    doc["problems"] = [*doc.get("problems", []), *problems]
    doc["interrupted"] = interrupted
    doc["files"] = sorted({p.name for p in stage.iterdir() if p.is_file()} | {RESULT_FILE})
    _write_json(stage / RESULT_FILE, doc)
    return folder.commit(RESULT_FILE, "interrupted, partly written" if interrupted else "complete")


def _rescue(report, args, out: Path, error: OSError) -> Path:
    """`result.json` written to the system's temporary folder when `out` cannot take it."""
    import tempfile

    doc = report.to_dict(options=_options(args), command=["identify", "fit", *map(str, _argv_tail(args))])
    doc["problems"] = [*doc["problems"], f"not written into {out}: {error}"]
    fd, name = tempfile.mkstemp(prefix=f"identify-{Path(report.experiment.path).stem}-", suffix=".json")
    os.close(fd)
    _write_json(Path(name), doc)
    print(
        f"identify fit: could not write into {out} ({error}); the result is saved as {name}",
        file=sys.stderr,
        flush=True,
    )
    return Path(name)


def _write_json(path: Path, doc: dict) -> None:
    from .._report.json import jsonable

    write_atomic(path, json.dumps(jsonable(doc), indent=1) + "\n")


def _independent_fits(args, exp, folder: OutputFolder, start, say, progress) -> int:
    """`identify fit --independent`: every fit log on its own, then `between_logs`."""
    from .._workflow import fit_experiment_independent

    if len(exp.fit_logs) < 2:
        folder.abandon("failed: --independent needs at least 2 fit logs")
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
        folder.abandon("failed: the fits failed, nothing written")
        print(f"identify fit: the fits failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        folder.abandon("interrupted during the fits, nothing written")
        print("identify fit: interrupted during the fits; nothing was written", file=sys.stderr, flush=True)
        return INTERRUPTED
    say(f"[{time.perf_counter() - start:6.1f} s] {len(results)} independent fits done")
    written, between, interrupted = _write_independent(args, exp, folder, results)
    print()
    print(f"Independent fits ({exp.name}): each fit log on its own")
    for r in results:
        print()
        _print_safely(lambda r=r: print(r.summary()))
    print()
    _print_safely(lambda: print(between.summary() if hasattr(between, "summary") else between))
    print()
    say(f"total {time.perf_counter() - start:.1f} s")
    _say_written(folder.path, written)
    if interrupted:
        return INTERRUPTED
    failed = [", ".join(r.problem.log_names) for r in results if not r.converged]
    if failed:
        print(
            f"identify fit: exit status {NOT_CONVERGED}: the fit of log(s) {', '.join(failed)} did not converge; "
            "the results above are written but those logs' values are not optima of the model",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _write_independent(args, exp, folder: OutputFolder, results):
    """`result.json` of the independent fits first, then their plots, into `folder`
    (`_write_fit`'s rules). Returns the paths, the comparison between the logs (or the
    text saying why there is none) and whether the run was interrupted."""
    from .._fit.result import fitted_outputs
    from .._fit.uncertainty import between_logs
    from .._report import fit_plots as plots
    from .._workflow import experiment_document, residual_report

    problems, outputs, reports = [], {}, {}
    try:
        between = between_logs(results)
    except ValueError as e:  # fewer than 2 converged logs
        between = f"no comparison between the logs: {e}"
    try:
        for r in results:
            outputs.update(fitted_outputs(r))
            reports.update(residual_report(r))
    except Exception as e:  # noqa: BLE001 (the fits are kept)
        problems.append(f"fitted outputs and residual tests not computed: {type(e).__name__}: {e}")
    doc = {
        "mode": "independent",
        "experiment": experiment_document(exp),
        "logs": {", ".join(r.problem.log_names): r.to_dict() for r in results},
        "between_logs": between.to_dict() if hasattr(between, "to_dict") else None,
        "residuals": reports,
        "problems": problems,
        "options": {"stages": args.stages, "independent": True},
        "command": ["identify", "fit", *map(str, _argv_tail(args))],
        "versions": package_versions(),
    }
    stage = folder.staging()
    _write_json(stage / RESULT_FILE, doc)
    roles = {name: "fit" for name in outputs}
    tasks = [lambda: plots.plot_by_log(results, between if hasattr(between, "to_dict") else None, stage)]
    if outputs:
        title = f"{exp.name}: each log fitted on its own"
        tasks[:0] = [
            lambda: plots.plot_fit(outputs, stage, title=title, roles=roles),
            lambda: plots.plot_residuals(outputs, stage, roles=roles),
        ]
    more, interrupted = _run_plots(tasks, stage, False)
    return _commit_json(folder, doc, more, interrupted), between, interrupted


def _options(args) -> dict:
    """The fit's options as `result.json` records them."""
    segment = getattr(args, "segment", None)
    return {"stages": args.stages} if segment is None else {"stages": args.stages, "segment": segment}


def _argv_tail(args) -> list:
    tail = [args.experiment]
    if args.out is not None:
        tail += ["--out", args.out]
    tail += ["--stages", args.stages]
    if getattr(args, "segment", None) is not None:
        tail += ["--segment", args.segment]
    if args.quiet:
        tail.append("--quiet")
    if args.force:
        tail.append("--force")
    return tail
