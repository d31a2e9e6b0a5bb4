"""Held-out scoring: each held-out log's nuisances refitted with the model held, the headroom above
the noise floor, and detection limits.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._data import measurement as meas, noise_floor as nf
from .._data.channels import state_names
from .._fit.quality import noise_floors
from .._fit.result import FitResult
from .._model.parameters import exp_natural, x_from_z, z_from_x
from .._model.problem import Problem, make_problem, parameter_unit
from .._model.residuals import (
    log_blocked,
    residuals as _residuals_from,
)
from .._model.variables import AbstractVariables
from .joint_model import SLOTS, Superset, _bounds, _jacobian, _Joint, _pad, _pad_used, _used


@dataclasses.dataclass(frozen=True)
class _HeldOut:
    """`detection_limits`: the held-out logs at the model of the search's end."""

    joint: _Joint  # the joint model on the held-out problem
    y0: jax.Array  # their initial-state entries and offsets, refitted at that model
    offset: jax.Array
    used: np.ndarray
    cost: float  # their weighted cost at that model
    xb: jax.Array  # the held-out problem's baseline entries there (natural coordinates)
    # for each of them, its entry among the fit's baseline entries; -1: a held-out log's own
    # value of a per-log parameter (`Parameter.per_log`), refitted there like a nuisance
    source: tuple[int, ...]


def detection_limits(
    j: _Joint, current, candidates, ext_names, used, sigma, step, bic_threshold: float, held: _HeldOut, min_gain
):
    """The smallest value of each parameter of each continuous candidate that would have
    been named had it been in the logs, linearised at the model `current` (the search's
    final one, a `state.CurrentModel`): `{label: {parameter: (limit,
    criterion)}}` (the limit in the parameter's SI unit, an offset from its neutral value;
    the criterion that sets it, "BIC" or "held-out gain"; inf where the logs cannot tell
    the parameter from the model's own to first order).

    An effect of size `a` in a parameter whose weighted-residual Jacobian column (at its
    neutral value) is `j` adds `a^2 |P j|^2` to the cost of a model without it, `P` the
    projector onto what the other columns cannot reproduce (the Gauss-Newton prediction
    the screening uses). On the fit logs the other columns are every free parameter of the
    model and of the candidate, initial state and offset; the BIC test, `N ln(1 - drop /
    C) + k ln N < -bic_threshold`, asks `|a| >= sqrt(C (1 - exp(-(bic_threshold + k ln
    N) / N))) / |P j|`, C the model's cost, k the candidate's parameters. A model without
    the effect fitted to such logs moves its own parameters to absorb part of it (`-a c`,
    `c` the coefficients of that projection), and on the held-out logs, where only their
    own initial states and offsets (and own values of per-log parameters) are refitted, it
    misses `a h`, `h = P_h (j_h - J_h c)` (`J_h`, `c`: the parameters they share);
    the held-out gain `sqrt((C_h + a^2 |h|^2) / C_h) >= min_gain` asks `|a| >=
    sqrt((min_gain^2 - 1) C_h) / |h|`, C_h the model's held-out cost. The limit is the
    larger. Noise moves the realised drop and gain about these values: an effect at its
    limit is named about half the time. The linearisation holds while the effect is small
    against the motion (a dead band or a delay comparable with the motion's time scale is
    not). Checked against the search itself (tests/identify/test_diagnose.py)."""
    nb = j.nb
    n_layout = len(current.layout)
    v = current.v
    xb = x_from_z(_bounds(j), v.zb)
    N = int(np.sum(used))
    out = {}

    def seen(column, others):
        """|P column|, P the projector onto what `others` cannot reproduce; the coefficients."""
        coef, *_ = np.linalg.lstsq(others, column, rcond=None)
        norm = float(np.linalg.norm(column - others @ coef))
        # (below round-off of the column: the other parameters reproduce it)
        return (norm if norm > 1e-9 * float(np.linalg.norm(column)) else 0.0), coef

    for c in candidates:
        if n_layout + len(c.params) > SLOTS:
            continue
        idx = np.asarray(current.idx).copy()
        logf = np.asarray(current.logf).copy()
        xe = np.asarray(v.xe, float).copy()
        for s, n in enumerate(c.params, start=n_layout):
            idx[s] = ext_names.index(n)
            logf[s] = False
            xe[s] = float(j.neutral[ext_names.index(n)])
        idx, logf, xe = jnp.asarray(idx), jnp.asarray(logf), jnp.asarray(xe)
        J = np.asarray(_jacobian(j, xb, xe, v.y0, v.offset, idx, logf, sigma, step)[1])[used]
        Jh = np.asarray(_jacobian(held.joint, held.xb, xe, held.y0, held.offset, idx, logf, sigma, step)[1])
        Jh = Jh[held.used]
        nh = held.joint.nb
        # held-out columns: the shared ones, paired with the fit's; a held-out log's own
        # values (`_HeldOut.source` -1) are refitted there, with its nuisances
        shared_h = [i for i, src in enumerate(held.source) if src >= 0]
        nuisance_h = [i for i, src in enumerate(held.source) if src < 0] + list(range(nh + SLOTS, Jh.shape[1]))
        k = len(c.params)
        drop = current.cost * -math.expm1(-(bic_threshold + k * math.log(N)) / N)
        excess = (min_gain**2 - 1.0) * held.cost
        per = {}
        for s, n in enumerate(c.params, start=n_layout):
            col = nb + s
            model = [i for i in range(nb + SLOTS) if i != col]  # the model's parameters
            fit_seen, coef = seen(J[:, col], J[:, model + list(range(nb + SLOTS, J.shape[1]))])
            # held out: the effect less what the model's parameters absorbed of it on the
            # fit logs (those the held-out logs share), less what the held-out logs' own
            # unknowns absorb
            of_model = dict(zip(model, coef[: len(model)]))
            cols_h = shared_h + [nh + t for t in range(SLOTS) if t != s]
            coef_h = np.asarray(
                [of_model[held.source[i]] for i in shared_h] + [of_model[nb + t] for t in range(SLOTS) if t != s]
            )
            ho_seen, _ = seen(Jh[:, nh + s] - Jh[:, cols_h] @ coef_h, Jh[:, nuisance_h])
            a_bic = math.sqrt(drop) / fit_seen if fit_seen > 0 else math.inf
            a_gain = math.sqrt(excess) / ho_seen if ho_seen > 0 else math.inf
            per[n] = (a_bic, "BIC") if a_bic >= a_gain else (a_gain, "held-out gain")
        out[c.label] = per
    return out


class _Own(eqx.Module):
    """The held-out logs' own values of the per-log parameters (`Parameter.per_log`),
    re-estimated with their nuisances as `identify.evaluate_held_out` does: their entries
    `pos` of the held-out problem's parameter vector, the bounds of their natural
    coordinates (`lower`, `upper`; `identify.fit`'s transform) and which are log-scale."""

    pos: jax.Array  # (n_own,) int
    lower: jax.Array
    upper: jax.Array
    log_scale: tuple[bool, ...] = eqx.field(static=True)

    @staticmethod
    def of(problem: Problem) -> _Own:
        pos = sorted(i for _, index in problem.per_log for i in index)
        return _Own(
            jnp.asarray(pos, dtype=int),
            jnp.asarray(np.asarray(problem.lower)[pos], dtype=float),
            jnp.asarray(np.asarray(problem.upper)[pos], dtype=float),
            tuple(problem.log_scale[i] for i in pos),
        )

    def theta(self, theta, z):
        """`theta` with the own entries at the transformed coordinates `z`."""
        if not self.log_scale:
            return theta
        x = x_from_z(self, z)
        values = jnp.stack([exp_natural(x[i]) if lg else x[i] for i, lg in enumerate(self.log_scale)])
        return theta.at[self.pos].set(values)

    def z_of(self, values) -> jax.Array:
        """The transformed coordinates of own values (SI)."""
        values = np.asarray(values, float)
        x = np.where(np.asarray(self.log_scale, bool), np.log(np.maximum(values, 1e-300)), values)
        return jnp.asarray(z_from_x(self, x), dtype=float)


class HeldVariables(AbstractVariables):
    """The held-out logs' unknowns at one model: their own values of the per-log parameters
    (`own`, transformed coordinates of `_Own`), shared by nothing but fitted with the logs'
    nuisances `y0`, `offset`."""

    offset: jax.Array
    own: jax.Array
    y0: jax.Array

    @property
    def shared(self):
        return self.own

    def with_parts(self, shared, y0, offset) -> HeldVariables:
        return HeldVariables(offset=offset, own=shared, y0=y0)


def _held_unpack(args):
    problem, theta, own, sigma, step = args
    return problem, lambda z_own: own.theta(theta, z_own), sigma, None, step


def _held_residual(v: HeldVariables, args):
    problem, theta, own, sigma, step = args
    return _residuals_from(problem, own.theta(theta, v.own), v.y0, v.offset, sigma, None, step)[0]


_held_residual_lm = log_blocked(_held_unpack)


@eqx.filter_jit
def _held_out_batch(problem: Problem, thetas, v0, own: _Own, sigma, step, max_steps: int):
    """Weighted held-out residuals for a batch of parameter vectors (the held-out
    problem's), each held-out log's own unknowns re-estimated from `v0`: its nuisances
    (`v0.y0` initial state entries, `v0.offset` offsets) and its own values of the per-log
    parameters (`v0.own`, at `own`'s entries). Returns the residuals, the re-estimated
    unknowns and the parameter vectors with the own values in."""
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-10, norm=optx.rms_norm)

    def one(theta):
        args = (problem, theta, own, sigma, step)
        if v0.y0.size + v0.offset.size + v0.own.size:
            v = optx.least_squares(_held_residual_lm, solver, v0, args=args, max_steps=max_steps, throw=False).value
        else:
            v = v0
        return _held_residual(v, args), v, own.theta(theta, v.own)

    return jax.vmap(one)(thetas)


def _held_out_start(problem: Problem, own: _Own, base) -> HeldVariables:
    """The held-out unknowns' start: the logs' own initial-state values, zero offsets and,
    for each own value of a per-log parameter, the median of the fit logs' values
    (`base`: the baseline `FitResult`)."""
    names = [name for name, index in problem.per_log for _ in index]
    order = np.argsort([i for _, index in problem.per_log for i in index]).astype(int)
    medians = [float(np.median(list(base.per_log[n].values()))) for n in names]
    return HeldVariables(
        offset=jnp.zeros(len(problem.offset_free)),
        own=own.z_of(np.asarray(medians, float)[order]) if names else jnp.zeros(0),
        y0=jnp.asarray([problem.y0_known[l, s] for l, s in problem.y0_free], dtype=float),
    )


@dataclasses.dataclass(frozen=True)
class HeldOutUnknowns:
    """The held-out logs' unknowns refitted at a batch of models (`HeldOutSet.refit`), batch-first."""

    y0: jax.Array  # free initial-state entries
    offset: jax.Array  # free sensor offsets
    theta: jax.Array  # the held-out problem's parameter vectors, each log's own per-log values in


@dataclasses.dataclass(frozen=True)
class HeldOutSet:
    """The held-out logs of one search on the joint model (`joint_model.Superset`): their
    `problem`, each entry's source among the fit problem's (`source`; a held-out log's own
    value of a per-log parameter, at `own_set`, is re-estimated there, `own`), the start of
    their unknowns (`start`), the residual entries that count (`used`) and the batch size
    every held-out call is padded to (one compiled program for the whole search)."""

    problem: Problem
    own: _Own
    own_set: frozenset[int]
    source: np.ndarray
    start: HeldVariables
    used: np.ndarray
    batch: int
    sigma: jax.Array
    max_steps: int

    def _batch(self, thetas, step):
        thetas_ho = jnp.asarray(thetas)[:, self.source]
        return _held_out_batch(
            self.problem, _pad(thetas_ho, self.batch), self.start, self.own, self.sigma, step, self.max_steps
        )

    def residuals(self, thetas, step) -> np.ndarray:
        """Weighted held-out residuals (used entries) at a batch of the fit problem's parameter vectors."""
        n = thetas.shape[0]
        r, _, _ = self._batch(thetas, step)
        return np.asarray(r)[:n][:, self.used]

    def refit(self, thetas, step) -> tuple[np.ndarray, HeldOutUnknowns]:
        """`residuals`, and the held-out unknowns re-estimated there."""
        n = thetas.shape[0]
        r, w, th = self._batch(thetas, step)
        return np.asarray(r)[:n][:, self.used], HeldOutUnknowns(w.y0[:n], w.offset[:n], th[:n])


def held_out_set(superset: Superset, held_out_logs, channels, base, batch: int, max_steps: int) -> HeldOutSet:
    """The held-out logs on the joint model `superset` (recording its `channels`), their
    unknowns started from the baseline fit `base` (`_held_out_start`)."""
    problem = make_problem(
        superset.chain,
        superset.parameters,
        held_out_logs,
        dict(zip(channels, superset.sigma)),
        measurement=superset.measurement,
        controller=superset.controller,
    )
    if problem.channels != channels:
        raise ValueError(f"diagnose: held-out logs record channels {problem.channels}, the fit logs {channels}")
    own = _Own.of(problem)
    own_set = frozenset(np.asarray(own.pos).tolist())
    names = superset.problem.names
    source = np.asarray([0 if i in own_set else names.index(n) for i, n in enumerate(problem.names)], dtype=int)
    start = _held_out_start(problem, own, base)
    return HeldOutSet(problem, own, own_set, source, start, _used(problem), batch, superset.sigma_j, max_steps)


def limits_at_end(
    superset: Superset, held: HeldOutSet, current, unknowns: HeldOutUnknowns, candidates, step, bic_threshold, min_gain
) -> dict:
    """`Diagnosis.detection_limits`: `detection_limits` of the continuous `candidates` at the
    search's final model `current` (a `state.CurrentModel`), whose held-out unknowns are
    `unknowns` (`HeldOutSet.refit`), with each parameter's unit and neutral value."""
    problem = held.problem
    nb_ho = len(problem.names) - len(superset.ext_names)
    theta_ho = np.asarray(unknowns.theta[0])[:nb_ho]
    at_end = _HeldOut(
        _Joint(problem, superset.joint.neutral, nb_ho),
        unknowns.y0[0],
        unknowns.offset[0],
        held.used,
        float(current.ho @ current.ho),
        jnp.asarray(np.where(np.asarray(problem.log_scale[:nb_ho]), np.log(np.abs(theta_ho)), theta_ho)),
        tuple(-1 if i in held.own_set else int(held.source[i]) for i in range(nb_ho)),
    )
    limits = detection_limits(
        superset.joint,
        current,
        candidates,
        superset.ext_names,
        superset.used,
        superset.sigma_j,
        step,
        bic_threshold,
        at_end,
        min_gain,
    )
    return {
        lab: {
            n: {
                "value": a,
                "criterion": why,
                "unit": parameter_unit(superset.problem, n),
                "neutral": superset.neutral[superset.ext_names.index(n)],
            }
            for n, (a, why) in per.items()
        }
        for lab, per in limits.items()
    }


#: `held_out_headroom`: the relative standard error of the order-4 noise floor of `n` white
#: samples is `FLOOR_SE / sqrt(n)` (`held_out_headroom`'s docstring)
FLOOR_SE = 1.146


#: `held_out_headroom`: the lags (samples) of the residual's autocorrelation checked
WHITE_LAGS = 4


@dataclasses.dataclass(frozen=True)
class Headroom:
    """`held_out_headroom`: a held-out residual against its own noise floor."""

    ratio: float  # its RMS over its model-free noise floor
    floor_se: float  # the floor's relative standard error
    autocorrelation: tuple  # at lags 1..WHITE_LAGS samples, pooled over logs and channels
    n: int  # the samples behind the autocorrelation

    def at_the_noise(self, min_gain: float, margin_se: float) -> bool:
        """Whether no model can take `min_gain` off this residual's RMS: the ratio below
        `min_gain` less `margin_se` standard errors of the floor, and the residual white
        (every autocorrelation within `margin_se + 1` of its white-noise standard error
        `1 / sqrt(n)`)."""
        white = all(abs(a) * math.sqrt(self.n) < margin_se + 1.0 for a in self.autocorrelation)
        return white and self.ratio < min_gain * (1.0 - margin_se * self.floor_se)


def held_out_headroom(problem: Problem, r_used: np.ndarray) -> Headroom:
    """How far a model's held-out weighted residual `r_used` (the residuals of `problem`'s
    logs that count, `_used`) is above the noise: the ratio of its RMS to its own
    model-free noise floor (`identify.noise_floor`, the floor of the residual traces,
    pooled over logs and channels by their samples), that floor's relative standard
    error, and the residual's autocorrelation at the first `WHITE_LAGS` lags.

    A better model's held-out RMS cannot fall below the noise, so when the ratio is below
    `min_gain` (less a margin for the floor's error) no candidate can reach the held-out
    gain `min_gain`. The floor is taken of the residual, not of the measured traces: the
    measured floor carries the signal's leakage (`A (2 sin(pi f dt))^4 / sqrt(140)` for a
    sine, 8e-4 A at 20 samples per period, which on the spinning link's tip is 40 % of
    the noise), the residual's only the misfit's. A slow misfit leaks next to nothing, but
    one near the Nyquist frequency passes the 4th difference almost whole (above a third
    of the sampling rate, more than its RMS): the floor cannot tell it from noise, its
    autocorrelation can (a misfit of a fraction `w` of the residual's variance at
    frequency `f` adds `w cos(2 pi f k dt)` at lag `k`, and no `f` is small at all four
    lags). Noise that is not white gives a smaller floor and a non-zero autocorrelation:
    refits are then kept.

    Standard error: the normalised 4th differences of white noise have the lag
    correlations `(-1)^m C(8, 4 + m) / C(8, 4)` (-0.8, 0.4, -0.114, 0.014), so the mean of
    their squares has variance `(2 / n) (1 + 2 sum rho^2) = 5.25 / n` relative to
    `sigma^4`, and the floor a relative error of `1.146 / sqrt(n)` (`FLOOR_SE`; `n` the
    differences, `ORDER` fewer than the samples per log and channel)."""
    L, T, C = problem.measured.shape
    used = _used(problem)
    r = _pad_used(np.asarray(r_used, float), used).reshape(L, T, C)
    # (the residual carries the measured samples' quantisation: its floor is at least it too)
    floor, count = nf.channel_floors(
        problem.t, r, problem.valid, problem.present, meas.resolutions(problem.measurement, problem.channels)
    )
    n = float(np.sum(count))
    n_pseudo = float(np.sum(np.clip(count - nf.ORDER, 0, None)))  # the floor's differences
    if n_pseudo == 0:
        return Headroom(float("inf"), float("inf"), (), 0)
    f2 = float(np.sum(count * np.square(floor)) / n)
    ms = float(np.mean(np.square(r_used)))
    ratio = math.sqrt(ms / f2) if f2 > 0 else float("inf")
    # autocorrelation of each log's channel over its valid samples, pooled
    lagged, total = np.zeros(WHITE_LAGS), 0.0
    valid, present = np.asarray(problem.valid, bool), np.asarray(problem.present, bool)
    for l in range(L):
        for c in range(C):
            if present[l, c]:
                x = r[l, valid[l], c]
                total += float(x @ x)
                lagged += [float(x[:-k] @ x[k:]) if x.size > k else 0.0 for k in range(1, WHITE_LAGS + 1)]
    auto = tuple(float(v) for v in lagged / total) if total > 0 else (0.0,) * WHITE_LAGS
    return Headroom(ratio, FLOOR_SE / math.sqrt(n_pseudo), auto, int(n))


#: `held_out_headroom`: the margin, in standard errors, by which a held-out residual must be
#: below `min_gain` floors (and its autocorrelations near 0) before later rounds stop
#: refitting candidates
FLOOR_MARGIN_SE = 3.0


def _no_headroom(problem: Problem, r_used, min_gain: float) -> tuple[bool, str]:
    """Whether a model's held-out residual `r_used` leaves no room for a held-out gain of
    `min_gain` (`held_out_headroom`), and the reason in words."""
    h = held_out_headroom(problem, r_used)
    limit = min_gain * (1.0 - FLOOR_MARGIN_SE * h.floor_se)
    text = (
        f"its held-out residual is {h.ratio:.3f} times its own noise floor (SE {100 * h.floor_se:.1f} %), "
        f"below {limit:.3f}, and white (autocorrelation at most {max(map(abs, h.autocorrelation), default=0):.3f} "
        f"at lags 1-{WHITE_LAGS}): no candidate can reach the held-out gain of {min_gain:g}"
    )
    return h.at_the_noise(min_gain, FLOOR_MARGIN_SE), text


def _held_out_summary(rms_base: dict, rms_ext: dict, cost_base: float, cost_ext: float, floor: dict) -> dict:
    """`floor`: each channel's model-free noise floor on the held-out logs (`_floor_per_channel`),
    what the best model could reach."""
    return {
        "baseline": rms_base,
        "extended": rms_ext,
        "gain": {c: rms_base[c] / rms_ext[c] if rms_ext[c] > 0 else float("inf") for c in rms_base},
        "gain_total": math.sqrt(cost_base / cost_ext) if cost_ext > 0 else float("inf"),
        "noise_floor": floor,
    }


def _floor_per_channel(problem: Problem) -> dict:
    """Per channel, the model-free noise floor of the problem's logs (SI; `identify.noise_floor`,
    the sample-weighted RMS over the logs)."""
    floor, count = noise_floors(problem)
    f2 = nf.pooled(np.square(floor), count)
    return {c: float(np.sqrt(v)) for c, v in zip(problem.channels, f2) if not np.isnan(v)}


def _own_starts(result: FitResult) -> tuple:
    """`fit`'s `extra_starts` that start each log's own value of a per-log parameter at its
    value in `result` (none without per-log parameters): a `Parameter`'s guess is one value
    for all logs, their median in a refit (`_value_of`), which may be far from a log's own.
    A structural candidate's multi-start gets this warm start beside its design (one start
    more)."""
    own = {f"{name}[{log}]": v for name, by_log in result.per_log.items() for log, v in by_log.items()}
    return (own,) if own else ()


def _with_extra_state(logs, chain):
    """Logs whose initial-state names exist in `chain` (a structural change may add
    coordinates; their initial values default to 0)."""
    names = set(state_names(chain))
    out = []
    for log in logs:
        out.append(
            dataclasses.replace(
                log,
                initial={k: v for k, v in log.initial.items() if k in names},
                fit_initial=tuple(k for k in log.fit_initial if k in names),
            )
        )
    return out
