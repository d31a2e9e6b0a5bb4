"""Goodness of fit against the model-free noise floor, and re-estimation of the noise weights."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._data import measurement as meas, noise_floor as nf
from .._data.units import display_unit
from .._model.parameters import theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import (
    residuals as _residuals_from,
    used_mask,
)

#: `FitResult.summary`: a residual this many times its noise floor is more likely a set-up
#: error (a log in degrees read as radians, gravity pointing the wrong way for the logs'
#: angle zero: ~1e4x) than a missing effect (tens of times; docs/performance.md)
GROSS_MISFIT = 300.0


#: `FitResult.summary`: a channel weighted by a noise level this many times off its
#: noise floor (either way) is named as a possible cause of its poor fit
WEIGHT_MISMATCH = 3.0


#: `fit`: a restart whose `identify.noise_floor.score` is within this fraction of an earlier
#: attempt's ended with the same misfit (the same basin, or a model that misses an effect)
SAME_SCORE = 0.1


def _same_misfit(bounded: bool, score: float, earlier) -> bool:
    """Whether an attempt of `fit`'s growing horizon (on a bound or not, its score) ends
    with the misfit of an earlier one (`earlier`: `(bounded, score)` pairs): both on a
    bound or both off, scores within `SAME_SCORE`. Among attempts on a bound too: a misfit
    that puts every parameter on a bound (an encoder counting against the torque) ends
    every restart at the same cost, so a restart is not worth its time."""
    return any(b == bounded and abs(score - s) <= SAME_SCORE * s for b, s in earlier)


def _residual_ms(problem: Problem, z, sigma, step, lin=None) -> np.ndarray:
    """Each log's mean squared residual per channel (SI), `(L, C)`, at `z` over every
    sample: from `lin = ((r, S, U), horizon)`, the last Levenberg-Marquardt solve's
    linearisation at `z` (`_grow`), when its horizon covered every sample, else from one
    simulation."""
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    r = None
    if lin is not None:
        (r_lin, *_), horizon = lin
        if horizon is None or np.array_equal(np.asarray(used_mask(problem, float(horizon))), mask):
            r = r_lin
    if r is None:
        theta = theta_from_x(problem, x_from_z(problem, z.phys))
        r, _ = _residuals_from(problem, theta, z.y0, z.offset, sigma, None, step)
    res = np.asarray(r).reshape(mask.shape) * np.asarray(sigma)
    return np.sum(np.where(mask, res, 0.0) ** 2, axis=1) / np.maximum(mask.sum(axis=1), 1)


#: `_reversed_channels`: a channel whose first response to the torque and the simulation's
#: have a cosine below this moves against the model
REVERSED_CORRELATION = -0.5


#: ... over the first push: where the drive first exceeds this fraction of its peak, until it
#: falls below it or reverses
PUSH_LEVEL = 0.3


#: ... a log's push counts only if it moves the measured channel by this many noise floors
PUSH_MOTION = 10.0


def _reversed_channels(problem: Problem, z, sigma, step, channels) -> dict:
    """Of `channels` (those fitted poorly: `FitResult.poor_fit`), the ones whose first
    response to the input moves against the simulation's: channel -> the cosine of the
    two traces over each driven log's first push (from its onset to the first sign change
    of its largest torque, at most a quarter of the log), each taken from its value at the
    onset and pooled over the logs; named below `REVERSED_CORRELATION`. Any model with
    positive inertias first moves the way the torque pushes, whatever its parameters, so
    a measured channel that moves the other way has its sign (or the torque's) reversed.
    Such a fit ends with parameters on their bounds and a simulation that barely moves (a
    payload of kilograms), so the whole traces do not correlate and the first push is what
    tells. One simulation, only on a poor fit."""
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    r, _ = _residuals_from(problem, theta, z.y0, z.offset, sigma, None, step)
    meas_ = np.asarray(problem.measured)
    pred = np.asarray(r).reshape(meas_.shape) * np.asarray(sigma) + meas_
    t, valid, present = np.asarray(problem.t), np.asarray(problem.valid), np.asarray(problem.present)
    tau = np.asarray(problem.torque_v)
    pushes = []
    for l in range(meas_.shape[0]):
        k = valid[l] & (t[l] >= float(problem.onset[l]))
        if k.sum() < 4 or not np.any(tau[l][k] != 0):
            continue
        idx = np.flatnonzero(k)
        j = int(np.argmax(np.max(np.abs(tau[l][idx]), axis=0)))
        drive = tau[l][idx, j]
        # the push: from the first sample above PUSH_LEVEL of the drive's peak to where it
        # falls below that level or reverses; not from the first nonzero sample, which in a
        # logged torque is the noise's (a push of a few samples of encoder noise, that could
        # call a correct encoder reversed)
        level = PUSH_LEVEL * float(np.max(np.abs(drive)))
        first = int(np.flatnonzero(np.abs(drive) > level)[0])
        ends = np.flatnonzero(drive[first:] * np.sign(drive[first]) <= level)
        stop = first + (int(ends[0]) if ends.size else len(idx))
        stop = min(stop, first + max(len(idx) // 4, 4))
        pushes.append((l, idx[: stop + 1]))
    floors = noise_floors(problem)[0]
    out = {}
    for jc, c in enumerate(problem.channels):
        if c not in channels:
            continue
        ps, ms = [], []
        for l, w in pushes:
            if present[l, jc] and w.size >= 4:
                m = meas_[l, w, jc] - meas_[l, w[0], jc]
                if np.max(np.abs(m)) < PUSH_MOTION * floors[l, jc]:  # the push moved it less than its noise
                    continue
                ps.append(pred[l, w, jc] - pred[l, w[0], jc])
                ms.append(m)
        if not ps:
            continue
        p_all, m_all = np.concatenate(ps), np.concatenate(ms)
        denom = np.sqrt(np.sum(p_all**2) * np.sum(m_all**2))
        cosine = float(np.sum(p_all * m_all) / denom) if denom > 0 else 0.0
        if cosine < REVERSED_CORRELATION:
            out[c] = cosine
    return out


#: `_initial_far`: a fitted initial angle this many noise levels from its first sample
INITIAL_FAR = 20.0


def _initial_far(problem: Problem, init: dict, offs: dict, sigma) -> dict:
    """Fitted initial-state entries that a log also measures (`theta<i>`, `alpha<i>`, ...:
    a coordinate whose name is a channel), more than `INITIAL_FAR` times the channel's
    noise from the log's first sample (fitted value plus the log's fitted offset of that
    channel, if any): log -> {entry: (fitted + offset, first sample, noise)}. A fit that
    cannot explain a log moves its start to absorb what it can (a model without the rig's
    dry friction can start degrees away from encoders at rest); this names it."""
    measured, valid = np.asarray(problem.measured), np.asarray(problem.valid)
    sig = np.asarray(sigma, float)
    # (a channel with a sensor model, gain, high-pass, delay, does not read the state itself)
    sensed = {
        n.split(".")[1] for n in [*meas.parameter_names(problem.measurement), *problem.names] if n.startswith("sensor.")
    }
    out = {}
    for l, name in enumerate(problem.log_names):
        for entry, (value, _) in init.get(name, {}).items():
            if entry not in problem.channels or entry in sensed:
                continue
            j = problem.channels.index(entry)
            if not np.asarray(problem.present)[l, j]:
                continue
            first = float(measured[l, np.flatnonzero(valid[l])[0], j])
            start = value + offs.get(name, {}).get(entry, (0.0, 0.0))[0]
            if abs(start - first) > INITIAL_FAR * sig[j]:
                out.setdefault(name, {})[entry] = (start, first, float(sig[j]))
    return out


def noise_floors(problem: Problem):
    """`identify.noise_floor.channel_floors` of the problem's logs, each channel's at least
    the quantisation noise of its sensor's declared resolution (`Sensor.resolution`)."""
    resolution = meas.resolutions(problem.measurement, problem.channels)
    return nf.channel_floors(problem.t, problem.measured, problem.valid, problem.present, resolution)


#: `FitResult.summary`: a channel whose residual RMS is below this fraction of its noise
#: floor gets a note (the floor is an upper bound of the white noise)
FLOOR_ABOVE_RESIDUAL = 0.7


def _floor_above_residual_notes(quality: dict) -> list[str]:
    """Notes for the channels whose residual is well below their model-free noise floor
    (`FLOOR_ABOVE_RESIDUAL`): a right fit whose residual is the true noise can read well
    below 1 (docs/performance.md), which looks like a fit "better than the noise". The
    floor counts fast motion as noise: a component of amplitude `A` at frequency `f` adds
    `A (2 sin(pi f dt))^4 / sqrt(140)` in quadrature (`identify.noise_floor`), large for a
    mode near the Nyquist frequency."""
    return [
        f"note: the residual of {c} is {q['ratio']:.2g} of its noise floor: the floor (from the samples' 4th "
        "differences) counts the channel's fast motion as noise (a mode near the Nyquist frequency), so it reads "
        "above the sensor noise; the residual, not the floor, is then the better noise estimate"
        for c, q in quality.items()
        if 0 < q["ratio"] < FLOOR_ABOVE_RESIDUAL
    ]


def _noise_text(channels, sigma, estimated) -> str:
    """`theta1 0.03 deg (declared), tip1 0.0497 mm (estimated)`: the noise weights in
    display units, each said to be declared or re-estimated from the residuals."""
    parts = []
    for c, s in zip(channels, np.asarray(sigma)):
        scale, unit = display_unit(c)
        parts.append(f"{c} {float(s) * scale:.3g} {unit} ({'estimated' if c in estimated else 'declared'})")
    return ", ".join(parts)


#: `fit`'s noise re-estimation: at most this many passes (the first with the given weights)
NOISE_ROUNDS = 4


#: ... and it stops when every re-estimated level is within this fraction of the one used
NOISE_AGREEMENT = 0.1


def _noise_to_estimate(problem: Problem, estimate_noise) -> list[str]:
    """`fit`'s `estimate_noise` as a list of channels: None, the channels make_problem was
    given no noise for; True, all; False, none."""
    if estimate_noise is None:
        return [c for c in problem.channels if c not in problem.declared]
    if estimate_noise is True:
        return list(problem.channels)
    return list(estimate_noise or ())


def _reestimate_sigma_per_log(ms, sigma, estimated) -> np.ndarray:
    """`fit_independent`'s noise levels `(L', C)` with those of channel indices `estimated`
    replaced, for each of the `len(ms)` logs, by the RMS of its residuals (`ms[k]`, its
    `_residual_ms` `(1, C)`; a channel a log does not record keeps its level). Padding rows
    (`flexdyn.batch`) repeat the last log's."""
    new = np.array(sigma, float)
    L = len(ms)
    for k in range(L):
        for j in estimated:
            if ms[k][0, j] > 0:
                new[k, j] = max(math.sqrt(float(ms[k][0, j])), 1e-12)
    new[L:] = new[L - 1]
    return new


def _noise_range_text(channels, sigma, estimated) -> str:
    """`theta1 0.0497-0.0521 deg`: each re-estimated channel's range over the logs `sigma`
    `(L, C)`, in display units."""
    parts = []
    for j in estimated:
        scale, unit = display_unit(channels[j])
        lo, hi = float(np.min(sigma[:, j])) * scale, float(np.max(sigma[:, j])) * scale
        parts.append(f"{channels[j]} {lo:.3g}{'' if f'{lo:.3g}' == f'{hi:.3g}' else f'-{hi:.3g}'} {unit}")
    return ", ".join(parts)


def _reestimate_sigma(problem: Problem, z, sigma, channels, step):
    theta = theta_from_x(problem, x_from_z(problem, z.phys))
    r, _ = _residuals_from(problem, theta, z.y0, z.offset, sigma, None, step)
    r = np.asarray(r).reshape(problem.measured.shape) * np.asarray(sigma)
    mask = np.asarray(problem.valid[:, :, None] & problem.present[:, None, :])
    new = np.asarray(sigma).copy()
    for j, c in enumerate(problem.channels):
        if c in channels:
            rms = math.sqrt(float(np.mean(r[:, :, j][mask[:, :, j]] ** 2)))
            new[j] = max(rms, 1e-12)
    return jnp.asarray(new)
