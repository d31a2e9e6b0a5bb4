"""Multiple shooting: `fit`'s way into the basin of a long log that cannot be simulated open loop
over its whole length.

**What.** Each log is cut into segments of at most `segment` s. Every segment after a log's
first starts from its own estimated state `s_i` (all `2n` entries); the first starts from
the log's initial state (its known entries and its `fit_initial` ones). The residual vector
is the noise-weighted output residuals of every segment,

    r[i, k, c] = (y_c(t_ik; theta, s_i) + o_lc - m_ikc) / sigma_c,

followed by the continuity defects between a segment's end state and the next one's start,

    d[i, j] = mu * w_j * (x_j(t_end,i; theta, s_i) - s_{i+1, j}),

solved by Levenberg-Marquardt for `theta`, the start states and the logs' nuisances
together. `w_j` is the norm of the output residuals' sensitivity to start entry `j` (the
median over segments, at the starting values): a defect of `1 / w_j` moves a segment's
outputs by one noise level in the RMS sense, so the weights carry no units and need no
per-state scale from the user. The penalty `mu` grows over `CONTINUITY` (1, 10, 100):
continuity is weak while the parameters are far off (a segment may end where the data
says, not where a wrong model says) and nearly exact at the end.

**Why this shape.** A drifting or lightly damped arm simulated over seconds from a wrong
guess ends far from its log, and single shooting's cost then has many local minima (a
wrong frequency matched a whole period off). A segment is short, starts near the measured
state, and its cost is close to quadratic in the parameters (Bock 1984; Voss, Timmer &
Kurths 2004). Initial start states come from the measurements where a channel is a state:
a joint angle `theta<j>` from its encoder column (a local cubic fit over a few
samples), its rate from that fit's slope; other entries (elastic coordinates, rates not
measured) start at 0.

**The answer is single shooting's.** A penalty leaves a small bias, and the
segmented problem's covariance is not the logs'. So multiple shooting only reaches the
basin: `fit` then solves the ordinary (single-shooting) problem over whole logs from its
optimum, and the reported optimum, noise estimate and intervals are that fit's. Where both
converge they reach the same optimum by construction; where single shooting from the guess
does not, this gives it a start inside the basin.

**Approximations inside a segment** (gone in the final single-shooting fit): a sensor's
high-pass filter and delay restart at each segment's start (an actuator lag does not: the
input is built over the whole log). Closed-loop problems are refused: a segment of a
closed-loop log needs the controller's internal state too. The segments integrate at one
constant step, chosen as a growing-horizon stage's is but over whole logs at the starting
values (`fit`): a guess whose whole-log simulation fails stops the fit there, as it stops
single shooting's last stage.

Each segment's Jacobian is taken w.r.t. its own inputs only (the physical parameters, its
start state, its log's offsets: `P + 2n + C` tangents per solve, `vmap` over segments) and
placed in the dense Jacobian of all variables; Levenberg-Marquardt linearises through it
(as `residuals.log_blocked` does for logs).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import flexdyn as fd
from flexdyn.held_steps import clipped_constant_steps

from .._data import channels as ch, measurement as meas
from .._model.parameters import theta_from_x, x_from_z
from .._model.problem import Problem
from .._model.residuals import (
    FAILED_RESIDUAL,
    _admissible,
    _measurement,
    _strictly_increasing,
    chain_at,
    open_loop_outputs,
)
from .._model.variables import Variables
from .stage import Stage

#: the continuity penalties `mu` of the successive Levenberg-Marquardt solves (see the
#: module docstring); the last makes a defect cost 1e4 times the output misfit it would cause
CONTINUITY = (1.0, 10.0, 100.0)

#: a segment spans at least this many sample intervals
MIN_SEGMENT_SAMPLES = 4

#: the degree of the local polynomial through the encoder samples around a segment's start
#: (a quadratic's slope is biased by the third derivative: 1.5 % of a swinging pendulum's rate)
START_FIT_DEGREE = 3

#: the local polynomial fit that reads a start angle and rate from the encoder column spans
#: this many samples either side of the segment's start (fewer at a log's ends)
START_FIT_HALF_WIDTH = 5


class Segments(NamedTuple):
    """Where each segment of `segment_logs` lies: `log[i]` its log, samples `first[i]` to
    `last[i]` (inclusive) of that log; `last[i] == first[i + 1]` within a log (the end of a
    segment is the next one's start: its sample's residual counts in the later segment).
    `opens[i]`: whether segment i is its log's first (it starts from the log's initial
    state); `width`: the most samples of any segment."""

    log: np.ndarray
    first: np.ndarray
    last: np.ndarray
    opens: np.ndarray
    width: int


def check_segment(problem: Problem, segment) -> float:
    """`segment` (s) checked against `problem`: an open-loop problem, a finite positive
    length shorter than its longest log and at least `MIN_SEGMENT_SAMPLES` sample intervals."""
    if problem.loop is not None:
        raise ValueError(
            "fit: shooting='multiple' supports open-loop problems only; this problem is closed loop (a "
            "controller): fit it with shooting='single'"
        )
    if isinstance(segment, bool) or not isinstance(segment, int | float | np.floating | np.integer):
        raise ValueError(f"fit: segment expected a length in seconds (a number > 0), got {segment!r}")
    segment = float(segment)
    t, valid = np.asarray(problem.t), np.asarray(problem.valid)
    ends = np.array([t[l][valid[l]][-1] - t[l, 0] for l in range(t.shape[0])])
    dt = float(np.median(np.diff(t[0][valid[0]])))
    if not (math.isfinite(segment) and segment > 0):
        raise ValueError(f"fit: segment expected a length in seconds > 0, got {segment!r}")
    if segment >= float(ends.max()):
        raise ValueError(
            f"fit: segment = {segment:.6g} s is not shorter than the longest log ({float(ends.max()):.6g} s): "
            "one segment per log is single shooting (shooting='single')"
        )
    if segment < MIN_SEGMENT_SAMPLES * dt:
        raise ValueError(
            f"fit: segment = {segment:.6g} s spans fewer than {MIN_SEGMENT_SAMPLES} sample intervals "
            f"({dt:.3g} s each): choose at least {MIN_SEGMENT_SAMPLES * dt:.3g} s"
        )
    return segment


def segment_logs(problem: Problem, segment: float) -> Segments:
    """Each log cut into `ceil(duration / segment)` segments of equal length (at most
    `segment` s), their boundaries at the nearest samples."""
    t, valid = np.asarray(problem.t), np.asarray(problem.valid)
    log, first, last, opens = [], [], [], []
    for l in range(t.shape[0]):
        tl = t[l][valid[l]]
        n = max(1, math.ceil((tl[-1] - tl[0]) / segment - 1e-9))
        cuts = np.searchsorted(tl, tl[0] + (tl[-1] - tl[0]) * np.arange(n + 1) / n)
        cuts = np.unique(np.clip(cuts, 0, len(tl) - 1))
        for i in range(len(cuts) - 1):
            log.append(l), first.append(int(cuts[i])), last.append(int(cuts[i + 1])), opens.append(i == 0)
    first, last = np.asarray(first), np.asarray(last)
    return Segments(np.asarray(log), first, last, np.asarray(opens), int(np.max(last - first)) + 1)


def measured_starts(problem: Problem, segments: Segments) -> np.ndarray:
    """Start states `(S, 2n)` read from the measurements: a joint angle (`theta<j>`, when
    its log records that channel) and its rate from a cubic fitted to the
    `START_FIT_HALF_WIDTH` samples either side of the segment's start; every other entry 0."""
    names = ch.state_names(problem.chain)
    t, measured, present, valid = (np.asarray(a) for a in (problem.t, problem.measured, problem.present, problem.valid))
    starts = np.zeros((len(segments.log), len(names)))
    for i, (l, a) in enumerate(zip(segments.log, segments.first)):
        n = int(valid[l].sum())
        window = slice(max(a - START_FIT_HALF_WIDTH, 0), min(a + START_FIT_HALF_WIDTH + 1, n))
        for c, channel in enumerate(problem.channels):
            if channel in names and present[l, c] and f"{channel}_rate" in names:
                rate, value = np.polyfit(t[l, window] - t[l, a], measured[l, window, c], START_FIT_DEGREE)[-2:]
                starts[i, names.index(channel)] = value
                starts[i, names.index(f"{channel}_rate")] = rate
    return starts


class Shooting(eqx.Module):
    """A multiple-shooting problem: `problem`'s logs cut into segments (`Segments`), and
    where each segment's inputs `(phys, start state, its log's offsets)` sit in the flat
    vector of all variables `v = [phys, y0, offset, starts]` (`index` `(S, K)`, -1: the
    fixed value `base`)."""

    problem: Problem
    index: np.ndarray = eqx.field(static=True, converter=lambda a: tuple(map(tuple, np.asarray(a).tolist())))
    base: jax.Array  # (S, K)
    first: jax.Array  # (S,) sample index of each segment's start in its log
    last: jax.Array  # (S,)
    log: jax.Array  # (S,)
    follows: jax.Array  # (S,) the next segment of the same log (itself for a log's last)
    closes: jax.Array  # (S,) bool: the segment is its log's last (no defect)
    opens: jax.Array  # (S,) bool: the segment is its log's first (starts from its initial state)
    width: int = eqx.field(static=True)
    n_phys: int = eqx.field(static=True)
    n_vars: int = eqx.field(static=True)

    @property
    def index_array(self) -> np.ndarray:
        return np.asarray(self.index, int).reshape(len(self.index), -1)


def make_shooting(problem: Problem, segments: Segments, n_phys: int) -> Shooting:
    """The `Shooting` of `problem` cut into `segments`; `n_phys` physical variables."""
    S, n2, C = len(segments.log), problem.y0_known.shape[1], problem.present.shape[1]
    n_y0, n_off = len(problem.y0_free), len(problem.offset_free)
    later = np.cumsum(~segments.opens) - 1  # each later segment's row among the estimated starts
    index = -np.ones((S, n_phys + n2 + C), int)
    base = np.zeros((S, n_phys + n2 + C))
    index[:, :n_phys] = np.arange(n_phys)
    y0_known = np.asarray(problem.y0_known)
    for i, l in enumerate(segments.log):
        if segments.opens[i]:
            base[i, n_phys : n_phys + n2] = y0_known[l]
            for p, (ll, s) in enumerate(problem.y0_free):
                if ll == l:
                    index[i, n_phys + s] = n_phys + p
        else:
            index[i, n_phys : n_phys + n2] = n_phys + n_y0 + n_off + n2 * later[i] + np.arange(n2)
        for p, (ll, c) in enumerate(problem.offset_free):
            if ll == l:
                index[i, n_phys + n2 + c] = n_phys + n_y0 + p
    closes = np.append(segments.log[1:] != segments.log[:-1], True)
    follows = np.where(closes, np.arange(S), np.arange(S) + 1)
    return Shooting(
        problem=problem,
        index=index,
        base=jnp.asarray(base),
        first=jnp.asarray(segments.first),
        last=jnp.asarray(segments.last),
        log=jnp.asarray(segments.log),
        follows=jnp.asarray(follows),
        closes=jnp.asarray(closes),
        opens=jnp.asarray(segments.opens),
        width=segments.width,
        n_phys=n_phys,
        n_vars=n_phys + n_y0 + n_off + n2 * int((~segments.opens).sum()),
    )


def _inputs(shooting: Shooting, v):
    """Each segment's inputs `(S, K)` gathered from the flat variables `v`."""
    index = shooting.index_array
    return jnp.where(index >= 0, v[np.maximum(index, 0)], shooting.base)


def _segment(shooting: Shooting, i, u, sigma, step):
    """Segment `i`'s weighted output residuals `(W C,)`, its end state `(2n,)` and whether
    its solve succeeded, at its inputs `u` (`phys`, start state, offsets)."""
    problem = shooting.problem
    P, n2 = shooting.n_phys, problem.y0_known.shape[1]
    l, a, b = shooting.log[i], shooting.first[i], shooting.last[i]
    k = jnp.minimum(a + jnp.arange(shooting.width), b)
    ts = problem.t[l][k]
    theta = theta_from_x(problem, x_from_z(problem, u[:P]))
    theta, y0, admissible = _admissible(problem, theta, u[P : P + n2])
    values = problem.log_set[l]
    asm = fd.assemble(chain_at(problem, theta, values, l))
    sensors = _measurement(problem, theta, values, l)
    # the input over the whole log: an actuator lag carries over from segment to segment
    torque = meas.actuated_torque(sensors, _strictly_increasing(problem.t[l]), problem.torque_v[l], problem.hold)
    field = fd.ChainVectorField(asm, torque)
    solver, dt0 = (diffrax.Tsit5(), step) if step is not None else (fd.RK4(), problem.dt)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        t0=ts[0],
        t1=ts[-1],
        dt0=dt0,
        y0=y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=clipped_constant_steps(torque.jump_times()),
        max_steps=problem.max_steps,
        adjoint=diffrax.ForwardMode(),
        throw=False,
    )
    ok = admissible & (sol.result == diffrax.RESULTS.successful) & jnp.all(jnp.isfinite(sol.ys))
    ys = jnp.where(ok, sol.ys, 0.0)
    out = open_loop_outputs(asm, problem.channels, sensors, field, ts, ys)
    r = (out + u[P + n2 :] - problem.measured[l][k]) / sigma
    # a segment's last sample is the next one's first: it counts there (but in a log's last)
    counted = (a + jnp.arange(shooting.width) < b) | ((a + jnp.arange(shooting.width) == b) & shooting.closes[i])
    used = (counted & problem.valid[l][k])[:, None] & problem.present[l][None, :]
    r = jnp.where(used, jnp.where(ok, r, FAILED_RESIDUAL), 0.0)
    return r.reshape(-1), ys[-1], ok


def _blocks(shooting: Shooting, v, sigma, step):
    """Every segment's residuals, end state, success and Jacobian w.r.t. its own inputs."""
    u = _inputs(shooting, v)

    def one(i, u_i):
        def f(u_):
            r, end, ok = _segment(shooting, i, u_, sigma, step)
            return (r, end), (r, end, ok)

        (J_r, J_end), (r, end, ok) = jax.jacfwd(f, has_aux=True)(u_i)
        return r, end, ok, J_r, J_end

    return u, jax.vmap(one)(jnp.arange(u.shape[0]), u)


def _defects(shooting: Shooting, u, end, weight):
    """Continuity defects `(S, 2n)`: `weight * (end state - next segment's start)`; 0 at a
    log's last segment."""
    P, n2 = shooting.n_phys, shooting.problem.y0_known.shape[1]
    gap = end - u[shooting.follows, P : P + n2]
    return jnp.where(shooting.closes[:, None], 0.0, weight * gap)


def shooting_residuals(v, args):
    """The residual vector: every segment's output residuals then its continuity defects."""
    shooting, sigma, step, weight = args
    u, (r, end, ok, _, _) = _blocks(shooting, v, sigma, step)
    return jnp.concatenate([r.reshape(-1), _defects(shooting, u, end, weight).reshape(-1)])


@eqx.filter_custom_jvp
def _residuals_blocked(v, args):
    return shooting_residuals(v, args)


@_residuals_blocked.def_jvp
def _residuals_blocked_jvp(primals, tangents):
    v, args = primals
    tv, _ = tangents
    shooting, sigma, step, weight = args
    u, (r, end, ok, J_r, J_end) = _blocks(shooting, v, sigma, step)
    value = jnp.concatenate([r.reshape(-1), _defects(shooting, u, end, weight).reshape(-1)])
    if tv is None:
        return value, jnp.zeros_like(value)
    index = shooting.index_array
    du = jnp.where(index >= 0, tv[np.maximum(index, 0)], 0.0)  # (S, K) each segment's input tangent
    dr = jnp.einsum("snk,sk->sn", J_r, du)
    P, n2 = shooting.n_phys, shooting.problem.y0_known.shape[1]
    dgap = jnp.einsum("sjk,sk->sj", J_end, du) - du[shooting.follows, P : P + n2]
    dd = jnp.where(shooting.closes[:, None], 0.0, weight * dgap)
    return value, jnp.concatenate([dr.reshape(-1), dd.reshape(-1)])


@eqx.filter_jit
def _continuity_weights(shooting: Shooting, v, sigma, step):
    """`w_j` (module docstring): the median over later segments of the norm of their
    output residuals' derivative w.r.t. start entry j; a floor of 1e-6 of the largest keeps
    an unobservable entry's defect from vanishing."""
    P, n2 = shooting.n_phys, shooting.problem.y0_known.shape[1]
    _, (_, _, _, J_r, _) = _blocks(shooting, v, sigma, step)
    norms = jnp.sqrt(jnp.sum(J_r[:, :, P : P + n2] ** 2, axis=1))  # (S, 2n)
    w = jnp.nanmedian(jnp.where(shooting.opens[:, None], jnp.nan, norms), axis=0)
    return jnp.maximum(w, 1e-6 * jnp.max(w))


@eqx.filter_jit
def _solve_shooting(shooting: Shooting, v0, sigma, step, weight, max_steps: int, rtol: float, atol: float):
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm)
    args = (shooting, sigma, step, weight)
    sol = optx.least_squares(_residuals_blocked, solver, v0, args=args, max_steps=max_steps, throw=False)
    r = shooting_residuals(sol.value, args)
    n_out = shooting.log.shape[0] * shooting.width * shooting.problem.present.shape[1]
    u, (_, end, _, _, _) = _blocks(shooting, sol.value, sigma, step)
    gap = _defects(shooting, u, end, 1.0)
    return sol.value, sol.result, sol.stats["num_steps"], jnp.sum(r[:n_out] ** 2), jnp.sum(r[n_out:] ** 2), gap


class ShootingOutcome(NamedTuple):
    """`multiple_shooting`'s result: the variables `z` (the logs' own: physical parameters,
    free initial-state entries, offsets) for the single-shooting fit that follows, the
    stages' records, and the largest continuity gap left per state entry (SI)."""

    z: Variables
    stages: list
    gap: np.ndarray


def multiple_shooting(
    problem: Problem,
    z: Variables,
    segment: float,
    step,
    *,
    max_steps: int,
    rtol: float,
    atol: float,
    say: Callable,
) -> ShootingOutcome:
    """Multiple shooting from `z` (module docstring): segments of at most `segment` s
    (`check_segment`), integrated at the constant `step` (s; None: the problem's `dt`),
    one Levenberg-Marquardt solve per penalty of `CONTINUITY` (each at most `max_steps`
    steps, `rtol`/`atol` as `fit`'s). Returns the logs' variables at its optimum."""
    segments = segment_logs(problem, segment)
    shooting = make_shooting(problem, segments, int(jnp.size(z.phys)))
    starts = measured_starts(problem, segments)[~segments.opens]
    v = jnp.concatenate([jnp.ravel(z.phys), jnp.ravel(z.y0), jnp.ravel(z.offset), jnp.ravel(jnp.asarray(starts))])
    v = v.astype(float)
    sigma = problem.sigma
    weight = _continuity_weights(shooting, v, sigma, step)
    say(
        f"  multiple shooting: {len(segments.log)} segments of at most {segment:.4g} s "
        f"({int((~segments.opens).sum())} estimated start states of {problem.y0_known.shape[1]} entries)"
    )
    stages = []
    duration = float(np.max(np.asarray(problem.t[:, -1] - problem.onset)))
    for mu in CONTINUITY:
        v, result, steps, cost, penalty, gap = _solve_shooting(
            shooting, v, sigma, step, mu * weight, max_steps, rtol, atol
        )
        stages.append(Stage(duration, int(steps), float(cost), result, segments=len(segments.log)))
        say(
            f"  continuity weight {mu:g}: {int(steps):3d} iterations, output cost {float(cost):.6g}, "
            f"defect cost {float(penalty):.3g} ({stages[-1].outcome})"
        )
    P, n_y0, n_off = shooting.n_phys, len(problem.y0_free), len(problem.offset_free)
    z = Variables(
        offset=v[P + n_y0 : P + n_y0 + n_off],
        phys=jnp.reshape(v[:P], jnp.shape(z.phys)),
        y0=v[P : P + n_y0],
    )
    return ShootingOutcome(z, stages, np.max(np.abs(np.asarray(gap)), axis=0))
