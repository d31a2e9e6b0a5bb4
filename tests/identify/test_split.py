"""The held-out split of `identify.diagnose` when an experiment has a single log: a time
split, the held-out segment starting mid-swing with its state estimated from the data.

Oracle: the true state of the simulated pendulum at the split time (integrated at rtol
1e-11), against the guesses `split_logs` makes from the noisy samples alone.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from diagnose_cases import PENDULUM_NOISE, PENDULUM_T, pendulum  # tests/ is on sys.path

import flexdyn as fd
from identify._diagnose.split import split_logs
from identify._model.synthetic import simulate_log


@pytest.mark.parametrize("fraction", [0.5, 0.6, 0.7, 0.8])
def test_a_single_log_is_split_in_time_and_the_held_out_start_is_estimated(fraction):
    chain = pendulum()
    release = math.radians(-60.0)
    log = simulate_log(
        chain,
        PENDULUM_T,
        initial={"theta1": release},
        channels=("theta1",),
        noise={"theta1": PENDULUM_NOISE},
        rng=np.random.default_rng(3),
        fit_initial=("theta1",),
        offsets=("theta1",),
        name="drop",
    )
    fit, held, desc = split_logs([log], [], fraction)
    k = int(fraction * len(PENDULUM_T))
    assert desc.startswith("time split") and "drop" in desc
    (first,), (second,) = fit, held
    np.testing.assert_array_equal(first.t, PENDULUM_T[:k])
    np.testing.assert_array_equal(second.t, PENDULUM_T[k:])
    np.testing.assert_array_equal(
        np.concatenate([first.outputs["theta1"], second.outputs["theta1"]]), log.outputs["theta1"]
    )
    assert first.fit_initial == ("theta1",) and first.initial == log.initial
    assert set(second.fit_initial) == {"theta1", "theta1_rate"} and second.offsets == ("theta1",)

    y0 = jnp.array([release, 0.0])
    truth = fd.simulate(chain, y0, jnp.asarray(PENDULUM_T), rtol=1e-11, atol=1e-13).y[k]
    angle, rate = float(truth[0]), float(truth[1])
    # a quadratic through 9 samples with 1.75 mrad noise: RMS error 1.5 mrad on the angle and
    # 0.09 rad/s on the rate (measured over the swing; its peak rate is 3.4 rad/s); bounds at
    # 4 RMS. A mean of 3 samples would be off by rate x 10 ms (up to 34 mrad).
    assert abs(second.initial["theta1"] - angle) < 6e-3, (second.initial, angle)
    assert abs(second.initial["theta1_rate"] - rate) < 0.4, (second.initial, rate)
