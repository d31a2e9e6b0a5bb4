"""`identify.fit(..., shooting="multiple")`: multiple shooting (`identify/_fit/multiple_shooting.py`).

- on a long open-loop log of a lightly damped flexible link (`tests/multiple_shooting_case.py`)
  from EI a quarter of the truth, the growing horizon ends far from the data (a cost
  thousands of times the noise's) while multiple shooting reaches the optimum of single
  shooting started at the truth (slow);
- on a short pendulum log where both converge, both reach the same optimum;
- the pieces against independent evidence: the segments tile each log, the start states
  read from the encoder match the simulated states, the block Jacobian equals `jax.jacfwd`;
- bad input names the option.
"""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from closed_loop_case import closed_loop_log, controller, measurement, pendulum  # tests/ is on sys.path
from multiple_shooting_case import TRUTH as FLEX_TRUTH, long_log, problem_of

import flexdyn as fd
import identify
import identify._fit.multiple_shooting as ms
from identify._fit.starts import initial_variables
from identify._model.parameters import x_from_theta
from identify._model.problem import guesses_of

# a rigid pendulum in a vertical plane, swung by a sum of sines (`pendulum_log`)
TRUTH = {"payload.mass": 0.1, "joint1.damping": 2e-3, "hub1.inertia": 1e-3}
NOISE = {"theta1": math.radians(0.05)}
DT = 0.01


def swing_chain() -> fd.Chain:
    return fd.Chain(
        [fd.RigidLink(0.3, 0.2)],
        [fd.RigidJoint(damping=TRUTH["joint1.damping"])],
        [fd.Hub(inertia=TRUTH["hub1.inertia"])],
        payload=fd.Payload(TRUTH["payload.mass"]),
        gravity=(0.0, -9.81),
    )


def pendulum_log(duration: float, seed: int = 3) -> tuple[identify.LogData, np.ndarray]:
    """A log of `theta1` (noise 0.05 deg) from hanging at rest, under four sines of 0.15 N m
    (0.3-2.1 Hz), and the true states `(T, 2)` at its samples."""
    t = np.arange(0.0, duration, DT)
    rng = np.random.default_rng(seed)
    tau = sum(0.15 * np.sin(2 * np.pi * f * t + p) for f, p in zip((0.3, 0.7, 1.3, 2.1), rng.uniform(0, 6.3, 4)))
    y0 = jnp.asarray([-math.pi / 2, 0.0])
    inp = fd.SampledTorque(jnp.asarray(t), jnp.asarray(tau[:, None]))
    states = np.asarray(fd.simulate(swing_chain(), y0, jnp.asarray(t), inp, rtol=1e-11, atol=1e-13).y)
    log = identify.simulate_log(
        swing_chain(), t, torque=tau[:, None], noise=NOISE, rng=rng, initial={"theta1": -math.pi / 2}
    )
    return log, states


def pendulum_problem(log, factors=(1.0, 1.0, 1.0)) -> identify.Problem:
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
    return identify.make_problem(swing_chain(), params, [log], noise=NOISE)


def quiet_fit(problem, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return identify.fit(problem, estimate_noise=False, n_starts=1, frequency_init=False, **options)


@pytest.fixture(scope="module")
def short():
    return pendulum_log(2.0)


# ---------------------------------------------------------------------------
# The pieces
# ---------------------------------------------------------------------------


def test_segments_tile_each_log(short):
    log, _ = short
    problem = pendulum_problem(log)
    segments = ms.segment_logs(problem, 0.3)
    n = len(log.t)
    assert len(segments.log) == math.ceil((log.t[-1] - log.t[0]) / 0.3)
    assert segments.first[0] == 0 and segments.last[-1] == n - 1
    np.testing.assert_array_equal(segments.last[:-1], segments.first[1:])  # end of one = start of the next
    spans = log.t[segments.last] - log.t[segments.first]
    assert np.all(spans <= 0.3 + DT / 2) and np.all(spans > 0.3 - 2 * DT)
    assert segments.opens.tolist() == [True] + [False] * (len(segments.log) - 1)


def test_start_states_read_from_the_encoder_match_the_true_states(short):
    """The angle and rate at each estimated segment start (all but the log's first), from a
    local cubic through the noisy encoder samples, against the noise-free simulated state
    there: the angle within a noise level, the rate within 0.5 % of the rate's range."""
    log, states = short
    problem = pendulum_problem(log)
    segments = ms.segment_logs(problem, 0.25)
    starts = ms.measured_starts(problem, segments)[1:]
    truth = states[segments.first[1:]]
    np.testing.assert_allclose(starts[:, 0], truth[:, 0], atol=NOISE["theta1"])
    rate_range = np.ptp(states[:, 1])
    np.testing.assert_allclose(starts[:, 1], truth[:, 1], atol=0.005 * rate_range)


def test_block_jacobian_equals_jacfwd(short):
    """The Jacobian Levenberg-Marquardt linearises (each segment w.r.t. its own inputs,
    placed among all variables) against `jax.jacfwd` of the plain residual function."""
    jax.config.update("jax_enable_x64", True)
    log, _ = short
    log = identify.LogData(t=log.t[:60], outputs={"theta1": log.outputs["theta1"][:60]}, torque=log.torque[:60])
    params = [identify.Parameter(n, v * 1.3, v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    problem = identify.make_problem(swing_chain(), params, [log], noise=NOISE)
    segments = ms.segment_logs(problem, 0.15)
    z = initial_variables(problem, x_from_theta(problem, guesses_of(problem, params)))
    shooting = ms.make_shooting(problem, segments, 3)
    starts = ms.measured_starts(problem, segments)[~segments.opens]
    v = jnp.concatenate([z.phys, z.y0, z.offset, jnp.ravel(jnp.asarray(starts))]) + 1e-3
    args = (shooting, problem.sigma, jnp.asarray(2e-3), jnp.asarray([3.0, 0.5]))
    blocked = jax.jacfwd(ms._residuals_blocked)(v, args)
    plain = jax.jacfwd(ms.shooting_residuals)(v, args)
    assert blocked.shape == (segments.width * len(segments.log) + 2 * len(segments.log), v.shape[0])
    np.testing.assert_allclose(blocked, plain, rtol=1e-9, atol=1e-9 * float(jnp.max(jnp.abs(plain))))
    assert float(jnp.max(jnp.abs(plain[:, 3:]))) > 0  # (the start states do enter)


# ---------------------------------------------------------------------------
# Where both converge: the same optimum
# ---------------------------------------------------------------------------


def test_both_converge_to_the_same_optimum_on_a_short_log(short):
    """A 2 s log from guesses 1.5-3 times the truth: the growing horizon and multiple
    shooting (0.25 s segments) both converge, to the same parameters within 1 % of a
    standard error, the same cost and standard errors, and the truth within 3 standard
    errors."""
    log, _ = short
    problem = pendulum_problem(log, factors=(1.5, 3.0, 2.0))
    single = quiet_fit(problem)
    multiple = quiet_fit(problem, shooting="multiple", segment=0.25)
    assert single.converged and multiple.converged
    assert [s.segments for s in multiple.stages[:3]] == [8, 8, 8] and multiple.stages[3].segments is None
    assert multiple.stages[0].to_dict()["segments"] == 8 and "segments" not in multiple.stages[3].to_dict()
    se = np.asarray(single.std_errors)
    for i, n in enumerate(single.names):
        assert abs(multiple.value[n] - single.value[n]) < 0.01 * se[i], (n, multiple.value[n], single.value[n])
        assert abs(single.value[n] - TRUTH[n]) < 3 * se[i], (n, single.value[n], se[i])
    np.testing.assert_allclose(multiple.std_errors, se, rtol=1e-3)
    assert multiple.stages[-1].cost == pytest.approx(single.stages[-1].cost, rel=1e-6)


# ---------------------------------------------------------------------------
# Where the growing horizon does not converge
# ---------------------------------------------------------------------------


@pytest.mark.slow
def test_multiple_shooting_converges_where_the_growing_horizon_does_not():
    """6 s of a lightly damped flexible link (`tests/multiple_shooting_case.py`), guess EI
    0.25 of the truth, one start each: the growing horizon (4 stages) ends with a cost
    over 1000 times the noise's (about the number of residuals, 3000); multiple shooting
    (0.2 s segments) ends at the noise's level and at the optimum of single shooting
    started at the truth (within 5 % of a standard error), the truth within 4 standard
    errors. (Measured: `benchmarks/results/multiple_shooting_2026-12-07.txt`.)"""
    log, noise = long_log(6.0)
    n_residuals = 2 * len(log.t)
    far = problem_of(log, noise, {"link1.EI": 0.25})
    growing = quiet_fit(far, max_restarts=0)
    assert growing.stages[-1].cost > 1000 * n_residuals
    multiple = quiet_fit(far, max_restarts=0, shooting="multiple", segment=0.2)
    assert multiple.converged
    assert multiple.stages[-1].cost < n_residuals + 5 * math.sqrt(2 * n_residuals)  # chi-square: noise alone
    reference = quiet_fit(problem_of(log, noise, {}), n_stages=1, max_restarts=0)
    se = np.asarray(reference.std_errors)
    for i, n in enumerate(reference.names):
        assert abs(multiple.value[n] - reference.value[n]) < 0.05 * se[i], (n, multiple.value[n], reference.value[n])
        assert abs(multiple.value[n] - FLEX_TRUTH[n]) < 4 * se[i], (n, multiple.value[n], se[i])
        # the growing horizon's optimum is not the reference one
    assert max(abs(growing.value[n] / FLEX_TRUTH[n] - 1) for n in FLEX_TRUTH) > 0.05


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "options, match",
    [
        (dict(shooting="multiple", segment=0.0), r"segment expected a length in seconds > 0"),
        (dict(shooting="multiple", segment=-1.0), r"segment expected a length in seconds > 0"),
        (dict(shooting="multiple", segment=float("nan")), r"segment expected a length in seconds > 0"),
        (dict(shooting="multiple", segment="0.5"), r"segment expected a length in seconds"),
        (dict(shooting="multiple", segment=5.0), r"segment = 5 s is not shorter than the longest log"),
        (dict(shooting="multiple", segment=0.02), r"segment = 0.02 s spans fewer than 4 sample intervals"),
        (dict(shooting="several"), r"shooting expected 'single' or 'multiple', got 'several'"),
        (dict(segment=0.5), r"segment is multiple shooting's segment length: pass shooting='multiple'"),
    ],
)
def test_bad_options_name_the_parameter(short, options, match):
    problem = pendulum_problem(short[0])
    with pytest.raises(ValueError, match=match):
        identify.fit(problem, **options)


def test_a_closed_loop_problem_is_refused():
    t = np.arange(0.0, 0.5, 1e-3)
    log = closed_loop_log(t, -0.3, "steps")
    problem = identify.make_problem(pendulum(), [], [log], measurement=measurement(), controller=controller())
    with pytest.raises(ValueError, match=r"shooting='multiple' supports open-loop problems only.*closed loop"):
        identify.fit(problem, shooting="multiple", segment=0.1)
