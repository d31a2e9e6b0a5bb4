"""The held-out split: which logs (or which part of one log) fit the model and which validate it."""

from __future__ import annotations

import dataclasses

import numpy as np


def split_logs(fit_logs, validation_logs, fraction: float = 0.7):
    """`(fit_logs, held_out_logs, description)`: the validation logs if any; else the last
    of several logs; else a time split of the single log at `fraction` of its length."""
    fit_logs, validation_logs = list(fit_logs), list(validation_logs)
    if validation_logs:
        names = ", ".join(v.name for v in validation_logs)
        return fit_logs, validation_logs, f"whole logs held out (the experiment's validation logs: {names})"
    if len(fit_logs) >= 2:
        return fit_logs[:-1], fit_logs[-1:], f"whole log held out (the last log, {fit_logs[-1].name})"
    (log,) = fit_logs
    k = int(fraction * len(log.t))
    t = np.asarray(log.t, float)
    first = dataclasses.replace(
        log,
        t=t[:k],
        outputs={c: np.asarray(v)[:k] for c, v in log.outputs.items()},
        torque=None if log.torque is None else np.asarray(log.torque)[:k],
        reference={c: np.asarray(v)[:k] for c, v in log.reference.items()},
        name=f"{log.name}[:{k}]",
    )
    rest_initial = _segment_initial(t[k:], {c: np.asarray(v)[k:] for c, v in log.outputs.items()})
    # the held-out segment starts mid-motion: its link angles and rates are estimated (from
    # the guesses above), with whatever else the log already estimated at its start
    rest_fit = tuple(dict.fromkeys((*log.fit_initial, *rest_initial)))
    second = dataclasses.replace(
        log,
        t=t[k:],
        outputs={c: np.asarray(v)[k:] for c, v in log.outputs.items()},
        torque=None if log.torque is None else np.asarray(log.torque)[k:],
        reference={c: np.asarray(v)[k:] for c, v in log.reference.items()},
        initial=rest_initial,
        fit_initial=rest_fit,
        name=f"{log.name}[{k}:]",
    )
    desc = (
        f"time split: the first {100 * fraction:.0f} % of {log.name} fits, the last {100 * (1 - fraction):.0f} % "
        f"(t >= {t[k]:.3g} s) is held out, its initial state estimated"
    )
    return [first], [second], desc


def _segment_initial(t, outputs, n: int = 9) -> dict:
    """Initial-state guesses of a segment from its measured link angles: angle and rate at
    `t[0]` from a least-squares quadratic through the first `n` samples (a mean or a line
    would be biased by the rate and the acceleration of a swinging link)."""
    init = {}
    n = min(len(t), n)
    for c, v in outputs.items():
        if c.startswith("theta") or c.startswith("alpha"):
            deg = min(2, n - 1)
            coef = np.polyfit(np.asarray(t[:n]) - t[0], np.asarray(v[:n], float), deg)
            init[c] = float(coef[-1])
            init[f"{c}_rate"] = float(coef[-2]) if deg >= 1 else 0.0
    return init
