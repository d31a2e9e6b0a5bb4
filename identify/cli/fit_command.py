"""`identify fit`: print and write what the library's fit returns."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from .._report.json import package_versions
from .check_command import _set_up_checks
from .output import (
    MARKER,
    NOT_CONVERGED,
    RESULT_FILE,
    _experiment_and_folder,
    _Refused,
    _write_marker,
    check_output_folder,
    printers,
)


def _residual_lines(report: dict, outputs: dict, roles: dict) -> list[str]:
    """The residual table: per log and channel the residual's RMS, its ratio to the noise
    floor of the measured samples alone (`identify.noise_floor`: ~1 where the model
    explains the data; the fit's own noise estimate would read ~1 whatever the misfit),
    whiteness and correlation with the input. `outputs`: `fitted_outputs` of the logs."""
    from .._data.noise_floor import series_floor
    from .._data.units import display_unit

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
    from .._data.units import display_unit, state_display_unit
    from .._model.problem import parameter_unit

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
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def run_fit(args) -> int:
    """`identify fit EXPERIMENT`: fit, print the results, write `result.json` and plots.
    Exit status 0, 1 (the fit failed), 2 (bad arguments or folder), `NOT_CONVERGED`."""
    start = time.perf_counter()

    say, error = printers("fit", args.quiet)

    if args.stages < 1:
        return error(f"--stages expects an integer >= 1, got {args.stages}")
    if args.max_restarts < 0:
        return error(f"--max-restarts expects an integer >= 0, got {args.max_restarts}")
    try:
        exp, inputs, out = _experiment_and_folder(args, "fit")
    except _Refused as e:
        return error(str(e))

    from .._workflow import fit_experiment, fit_report

    _say_set_up(exp, args, say)
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
    report = fit_report(exp, result, progress=progress, say=say)
    t_post = time.perf_counter() - t0
    _print_results(report)
    t0 = time.perf_counter()
    try:
        check_output_folder(out, inputs, args.force)  # again: the fit took a while
    except _Refused as e:
        return error(str(e))
    written = _write_files(report, out, args)
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


def _print_results(report) -> None:
    """The fitted parameters, warnings, intervals, nuisances, natural frequencies, model
    checks and the residual table."""
    import numpy as np

    from .._data.noise_floor import declared_noise_warnings

    exp, result = report.experiment, report.result
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
        last = result.stages[-1].outcome
        if last != "successful":
            print(f"WARNING: the fit did not converge (last stage: {last}); try more --stages")
        else:  # the solver stopped at a bound: not an interior optimum
            print(
                f"WARNING: the fit ended with {', '.join(result.at_bounds)} on a bound, so it is not an optimum of "
                "the model: widen the bounds, or check the model (gravity, units: see the warnings above)"
            )
    if report.robust_note is not None:
        print()
        print(report.robust_note)
    if report.agreement is not None or report.agreement_note is not None:
        print()
        print(report.agreement.summary() if report.agreement is not None else report.agreement_note)
    if report.robust is not None:
        print()
        print(report.robust.summary())
        print(
            "(the intervals above assume white residuals; these assume only that the logs are independent: "
            "read these when the residual tests below fail, as on real rigs)"
        )
    _print_model(report)


def _print_model(report) -> None:
    """Per-log nuisances, natural frequencies, model checks and the residual table."""
    result = report.result
    nuisance = _nuisance_lines(result, report.validation_nuisances)
    if nuisance:
        print()
        own = " (validation logs: also their own per-log parameters)" if result.problem.per_log else ""
        print(f"Per-log nuisances{own}:")
        print("\n".join(nuisance))
    print()
    freqs = report.natural_frequencies
    nf = ", ".join(f"{f:.4g}" for f in freqs if f > 0) or "none (rigid-body modes only)"
    kept = ", ".join(n for n, _ in result.problem.per_log)
    kept = f"; {kept} at the rig's value, not a log's" if kept else ""
    print(f"Natural frequencies of the fitted model ({report.modal_configuration}{kept}): {nf} Hz")
    unstable = [f for f in freqs if f < 0]
    if unstable:  # (`fd.Modes`: a negative frequency is an unstable mode)
        print(
            f"WARNING: the fitted model is not stable about that configuration: {len(unstable)} mode(s) diverge "
            f"(growth rate {', '.join(f'{-2 * math.pi * f:.4g}' for f in unstable)} 1/s); a slender link hanging "
            "under gravity needs `geometric_stiffening = true`"
        )
    for check in report.model_checks:
        print(f"{'WARNING: ' if check['flagged'] else ''}model check: {check['message']}")
    print()
    print("Residuals (fitted - measured; [val] = validation log, not used by the fit):")
    roles = {spec.name: spec.role for spec in report.experiment.logs}
    combined = {**report.residuals, **report.validation_residuals}
    print("\n".join(_residual_lines(combined, {**report.outputs, **report.validation_outputs}, roles)))


def _write_files(report, out: Path, args) -> list[Path]:
    """`result.json` and the plots into `out`, with the folder's marker; the paths written."""
    from .._report import fit_plots as plots
    from .._report.json import jsonable

    result, exp = report.result, report.experiment
    _write_marker(out)
    doc = report.to_dict(options={"stages": args.stages}, command=["identify", "fit", *map(str, _argv_tail(args))])
    (out / RESULT_FILE).write_text(json.dumps(jsonable(doc), indent=1) + "\n")
    written = [out / MARKER, out / RESULT_FILE]
    written += plots.write_plots(
        result,
        {**report.outputs, **report.validation_outputs},
        {**report.residuals, **report.validation_residuals},
        out,
        natural_frequencies=report.natural_frequencies,
        where=report.modal_configuration,
        roles={spec.name: spec.role for spec in exp.logs},
        title=exp.name,
    )
    if result.problem.per_log:  # each log's own values, and their common value when compared
        written += plots.plot_per_log(result, report.agreement, out)
    return written


def _independent_fits(args, exp, inputs, out, start, say, progress) -> int:
    """`identify fit --independent`: every fit log on its own, then `between_logs`."""
    from .._fit.result import fitted_outputs
    from .._fit.uncertainty import between_logs
    from .._report import fit_plots as plots
    from .._report.json import jsonable
    from .._workflow import experiment_document, fit_experiment_independent, residual_report

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
        "experiment": experiment_document(exp),
        "logs": {", ".join(r.problem.log_names): r.to_dict() for r in results},
        "between_logs": None if between is None else between.to_dict(),
        "residuals": reports,
        "options": {"stages": args.stages, "independent": True},
        "command": ["identify", "fit", *map(str, _argv_tail(args))],
        "versions": package_versions(),
    }
    (out / RESULT_FILE).write_text(json.dumps(jsonable(doc), indent=1) + "\n")
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
