"""Independent fits of many logs in one vmapped call (identify.fit_independent).

Oracle: each synthetic log is generated with its own known joint damping; every log's
fit must recover its own value within its reported 95 % interval (and to 1 %); its standard
errors (read from the vmapped Levenberg-Marquardt's last linearisation) equal those of a
Jacobian computed afresh at its optimum."""

import numpy as np
import pytest
from fresh_jacobian import assert_standard_errors_match, fresh_covariance  # tests/ is on sys.path

import flexdyn as fd
import identify


def test_independent_vmapped_fits_recover_each_logs_own_damping():
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 3.0, 1e-2)
    rng = np.random.default_rng(11)
    truth = [(1.5e-3, 0.0), (2.0e-3, -30.0), (2.5e-3, -60.0)]
    logs = [
        identify.simulate_log(
            fd.with_parameters(chain, {"joint1.damping": d}),
            t,
            initial={"theta1": np.radians(deg)},
            channels=("theta1",),
            noise={"theta1": 1e-3},
            rng=rng,
            fit_initial=("theta1",),
            name=f"log{k}",
        )
        for k, (d, deg) in enumerate(truth)
    ]
    params = [identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1)]
    problem = identify.make_problem(chain, params, logs, noise={"theta1": 1e-3})
    results = identify.fit_independent(problem, params, n_stages=2)
    assert len(results) == 3
    for res, (d, deg) in zip(results, truth):
        assert res.converged
        assert res.ci_low[0] <= d <= res.ci_high[0], (res.values[0], res.ci_low[0], res.ci_high[0], d)
        assert res.values[0] == pytest.approx(d, rel=0.01)
        (name,) = res.initial_states
        assert res.initial_states[name]["theta1"][0] == pytest.approx(np.radians(deg), abs=5e-4)
    # Review: a per-log summary did not say which log it was, and its time was the batch's
    # divided among the logs without saying so.
    for k, res in enumerate(results):
        head, *rest = res.summary().splitlines()
        assert head == f"fit to 1 log: log{k}"
        assert res.batch_size == 3 and "(its share of 3 logs fitted in one batch)" in res.summary()
    # log 1 (not 0: each log's own linearisation is picked out of the batch)
    assert_standard_errors_match(results[1], fresh_covariance(results[1]))


def test_a_failed_simulation_names_its_log(monkeypatch):
    """Review: the error said "a simulation at the current parameters failed" without
    naming the log. Here the stage's simulation is made to fail for every log."""
    import sys

    F = sys.modules["identify.fit"]
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 0.5, 1e-2)
    logs = [
        identify.simulate_log(chain, t, initial={"theta1": a}, channels=("theta1",), name=f"drop{k}")
        for k, a in enumerate((0.1, 0.2))
    ]
    params = [identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1)]
    problem = identify.make_problem(chain, params, logs, noise={"theta1": 1e-3})
    grid_step = F._grid_step

    def failing(problem, z, horizon, safety):
        step, ok, out = grid_step(problem, z, horizon, safety)
        return step, ok & False, out

    monkeypatch.setattr(F, "_grid_step", failing)
    with pytest.raises(RuntimeError, match=r"the simulation of log\(s\) \['drop0', 'drop1'\] .*failed \(stage 1"):
        identify.fit_independent(problem, params, n_stages=1, frequency_init=False)
