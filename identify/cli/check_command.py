"""`identify check`: read an experiment and its logs and report the set-up, without fitting."""

from __future__ import annotations

import sys

from .output import _load_experiment, _Refused


def _set_up_checks(exp) -> list[str]:
    """What to check of the set-up before a long run: where the rig's gravity makes the
    first link hang (against the logs' angle zero), any log whose sampling rate
    questions its time column's unit, initial values held at a noisy first sample, and the
    columns each log leaves unused."""
    from .._data.bag_log import is_bag
    from .._data.experiment import gravity_text

    lines = [gravity_text(exp.chain.gravity)]
    for spec in exp.logs:
        hint = spec.log.sampling.time_unit_hint
        if hint:
            lines.append(f"warning: log {spec.name!r}: {spec.log.sampling.rate:.6g} Hz, {hint}")
        lines.extend(f"warning: {w}" for w in spec.warnings())
        if spec.log.ignored:
            unused = "topics" if is_bag(spec.file) else "columns"
            lines.append(f"log {spec.name!r}: {unused} not used: {', '.join(map(repr, spec.log.ignored))}")
    return lines


def run_check(args) -> int:
    """`identify check`: load the experiment with every check a fit makes before it
    compiles anything (the file, the logs, the problem `make_problem` builds: its logs at
    rest, its sampling) and print what a fit would start from: a file is validated without
    waiting for a fit's compilation."""
    try:
        exp = _load_experiment(args)
    except _Refused as e:
        print(f"identify check: {e}", file=sys.stderr, flush=True)
        return 2
    from .._workflow import problem_from_experiment

    print(f"identify check: {exp.summary()}")
    for line in _set_up_checks(exp)[1:]:  # (the summary gives the gravity)
        if not line.startswith("warning: ") or line not in exp.summary():
            print(f"  {line}")
    try:
        problem = problem_from_experiment(exp)
    except ValueError as e:
        print(f"identify check: {e}", file=sys.stderr, flush=True)
        return 2
    # the declared noise against the model-free floor of the fit logs, so that a noise in
    # the wrong unit ("0.05 m" for a 0.05 mm strain gauge) is flagged before any fit
    import numpy as np

    from .._data.noise_floor import declared_noise_warnings, pooled

    floor, count = _fit_log_floors(exp, problem.channels)
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


def _fit_log_floors(exp, channels):
    """`identify.noise_floor.channel_floors` of the experiment's fit logs, from the logs'
    own arrays: `(floor, count)`, both `(logs, channels)`. (From the problem's, each
    array would be copied off the device first: 0.6 GB more for a 1 GB log.)"""
    import numpy as np

    from .._data.measurement import resolutions
    from .._data.noise_floor import series_floors

    step = resolutions(exp.measurement, channels)
    floor, count = np.zeros((len(exp.fit_logs), len(channels))), np.zeros((len(exp.fit_logs), len(channels)), int)
    for l, spec in enumerate(exp.fit_logs):
        recorded = [j for j, c in enumerate(channels) if c in spec.log.outputs]
        ys = [spec.log.outputs[channels[j]] for j in recorded]
        floor[l, recorded] = series_floors(spec.log.t_relative, ys, step[recorded])
        count[l, recorded] = len(spec.log.t)
    return floor, count
