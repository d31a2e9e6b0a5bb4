"""What `identify fit` prints of a fit: parameters, warnings, intervals, nuisances, natural
frequencies, model checks and the residual table."""

from __future__ import annotations

import math


def _residual_lines(report: dict, outputs: dict, roles: dict, resolution: dict | None = None) -> list[str]:
    """The residual table: per log and channel the residual's RMS, its ratio to the noise
    floor of the measured samples alone (`identify.noise_floor`: ~1 where the model
    explains the data; the fit's own noise estimate would read ~1 whatever the misfit),
    whiteness and correlation with the input. `outputs`: `fitted_outputs` of the logs;
    `resolution`: channel -> its sensor's declared quantisation step (SI), which keeps
    the floor at least at its noise, as in the fit's `fit_quality`."""
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
            measured = entry.get("measured", {})
            step = (resolution or {}).get(c, 0.0)
            floor = series_floor(entry["t"], measured[c], step) if c in measured else 0.0
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


def print_results(report) -> None:
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
    steps = {c: s.resolution for c, s in result.problem.measurement.sensors.items() if s.resolution is not None}
    print("\n".join(_residual_lines(combined, {**report.outputs, **report.validation_outputs}, roles, steps)))
