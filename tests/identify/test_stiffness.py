"""Issue 61: a structural candidate too stiff for the solver is detected up front, not after
10-16 minutes on the step limit (`identify._fit.stiff_start`, `identify._diagnose.stiffness`).

Oracles: the two-inertia torsional system's closed form `omega^2 = k (1/J_rotor + 1/J_link)`,
and the adaptive solver's own step count (`identify.residuals.predict`'s statistics)."""

from __future__ import annotations

import math
import time
import types

import numpy as np
import pytest

import flexdyn as fd
import identify
from identify._diagnose import catalogue as cat, stiffness, structural
from identify._diagnose.scores import Score, not_fitted_of
from identify._fit import stiff_start
from identify._model.residuals import predict_jit

LENGTH, LINK_MASS, HUB_INERTIA = 0.3, 0.01, 2e-4
J_LINK = HUB_INERTIA + LINK_MASS * LENGTH**2 / 3  # the link side about the joint, kg m^2
J_ROTOR = 0.05  # a geared rotor, reflected: 100x the link side


def two_inertia(k: float, damping: float = 0.0) -> fd.Chain:
    """A rotor `J_ROTOR` on a torsional spring `k` (N m/rad) driving a rigid link (`J_LINK`),
    horizontal."""
    return fd.Chain(
        [fd.RigidLink(LENGTH, LINK_MASS)],
        [fd.ElasticJoint(k, J_ROTOR, damping=damping)],
        [fd.Hub(inertia=HUB_INERTIA)],
        fd.Payload(0.0),
        gravity=(0.0, 0.0),
    )


def closed_form_hz(k: float) -> float:
    return math.sqrt(k * (1 / J_ROTOR + 1 / J_LINK)) / (2 * math.pi)


def problem_of(chain, torque, t, *, max_steps=100_000, rtol=1e-8):
    """A problem with the joint's stiffness and damping free, on one log (its measurement a
    stand-in: the estimate and the step count do not read it)."""
    log = identify.LogData(t=t, outputs={"theta1": np.sin(2 * np.pi * t)}, torque=np.asarray(torque)[:, None])
    params = [identify.Parameter("joint1.stiffness", 1e3), identify.Parameter("joint1.damping", 0.01, 1e-6, 10.0)]
    return identify.make_problem(
        chain, params, [log], {"theta1": 1e-3}, rtol=rtol, atol=1e-2 * rtol, max_steps=max_steps
    )


def test_the_highest_frequency_is_the_two_inertia_closed_form():
    """The estimate's frequency at the parameters given (not the chain's own), undamped:
    `sqrt(k (1/J_rotor + 1/J_link)) / (2 pi)`; and the joint mode the elastic joint's start
    is aimed with (`stiffness.joint_mode`), all of whose energy is in the spring."""
    t = np.linspace(0.0, 2.0, 401)
    problem = problem_of(two_inertia(1.0), np.zeros_like(t), t)
    for k in (1e2, 1e5):
        est = stiff_start.estimate_steps(problem, [k, 0.0], grid_safety=1.0)
        assert est.frequency_hz == pytest.approx(closed_form_hz(k), rel=1e-9)
        assert est.span_s == pytest.approx(2.0) and est.log == "log" and est.budget == 100_000
        # the stage's steps: the span over `ADAPTIVE_OVER_STABLE` stable steps, at `grid_safety`
        assert est.steps == pytest.approx(2.0 / (stiff_start.ADAPTIVE_OVER_STABLE * est.stable_step_s))
        assert stiff_start.estimate_steps(problem, [k, 0.0], grid_safety=0.5).steps == pytest.approx(2 * est.steps)
        f, share = stiffness.joint_mode(two_inertia(k), 1)
        assert f == pytest.approx(closed_form_hz(k), rel=1e-9) and share == pytest.approx(1.0, rel=1e-9)
    # a stiffer model needs proportionally more steps (the stable step ~ 1 / omega)
    soft, stiff = (stiff_start.estimate_steps(problem, [k, 0.0]) for k in (1e3, 1e5))
    assert stiff.steps / soft.steps == pytest.approx(10.0, rel=1e-3)


@pytest.mark.parametrize("damping", [0.01, 1.0])
def test_the_step_estimate_errs_low_against_the_adaptive_solver(damping):
    """Oracle: the adaptive Tsit5 solve of the fit's problems (rtol 1e-8, `predict`'s step
    count) on a 2 kHz joint mode, under a sine and under a square wave of torque: it takes at
    least the estimate's steps (`ADAPTIVE_OVER_STABLE`: a model called too stiff is), and at
    most 4x as many (the estimate is not vacuous; measured: 1.3-2.5x)."""
    t = np.linspace(0.0, 0.5, 251)
    k = (2 * math.pi * 2000.0) ** 2 / (1 / J_ROTOR + 1 / J_LINK)
    for torque in (0.05 * np.sin(2 * np.pi * 3.0 * t), 0.05 * np.sign(np.sin(2 * np.pi * 3.0 * t))):
        problem = problem_of(two_inertia(k), torque, t)
        theta = np.asarray([k, damping])
        est = stiff_start.estimate_steps(problem, theta, grid_safety=1.0)  # (the adaptive solve's own steps)
        _, ok, steps = predict_jit(problem, theta, problem.y0_known, None, None, stats=True)
        assert bool(ok[0])
        assert est.steps <= int(steps[0]) <= 4 * est.steps, (est, int(steps[0]))


def test_a_fit_from_a_too_stiff_start_is_refused_at_once():
    """`fit(stop_when_stiff=True)` from a start whose solves would end on the step limit
    raises `TooStiff` before any simulation (in well under the seconds one solve to the
    limit takes), naming the frequency and the budget; the same start fits without the
    option's refusal when the budget allows it."""
    t = np.linspace(0.0, 2.0, 401)
    k = 1e5  # a 2.26 kHz joint mode: ~57 000 steps of a stage over the 2 s log
    problem = problem_of(two_inertia(k), 0.05 * np.sin(2 * np.pi * t), t, max_steps=5_000)
    params = [identify.Parameter("joint1.stiffness", k), identify.Parameter("joint1.damping", 0.01, 1e-6, 10.0)]
    start = time.perf_counter()
    with pytest.raises(stiff_start.TooStiff) as e:
        identify.fit(problem, params, stop_when_stiff=True, frequency_init=False, estimate_noise=False, n_starts=1)
    took = time.perf_counter() - start
    est = e.value.estimate
    assert est.too_stiff and est.budget == 5_000 and est.frequency_hz == pytest.approx(closed_form_hz(k), rel=1e-6)
    message = str(e.value)
    assert f"{closed_form_hz(k):.3g} Hz" in message and "limit of 5000 steps" in message, message
    assert isinstance(e.value, identify.SimulationFailed) and e.value.logs == {"log": est.reason()}
    assert took < 20.0, took  # (a linearisation: compiled once, no simulation)
    roomy = problem_of(two_inertia(k), 0.05 * np.sin(2 * np.pi * t), t)
    assert stiff_start.stiff_at(roomy, _start_variables(roomy, params), None, 0.5) is None


def _start_variables(problem, params):
    from identify._fit.starts import initial_variables
    from identify._model.parameters import x_from_theta
    from identify._model.problem import guesses_of

    return initial_variables(problem, x_from_theta(problem, guesses_of(problem, params)))


def test_a_geared_joints_elastic_start_is_aimed_below_nyquist():
    """Issue 61: behind a gear the rotor's reflected inertia is 100x the link's, so the spring
    the catalogue sized against a locked link rings 10x higher with the link free: 200 Hz,
    above the logs' 50 Hz Nyquist. With the logs' Nyquist frequency the start is moved down
    to `max_frequency_hz` (the closed form's `k` for 20 Hz); a start the logs can show is
    kept as sized."""
    rotor, gear = J_ROTOR / 100.0, 10.0  # reflected: J_ROTOR
    rigid = fd.Chain(
        [fd.RigidLink(LENGTH, LINK_MASS)],
        [fd.RigidJoint(damping=0.01, rotor_inertia=rotor, gear_ratio=gear)],
        [fd.Hub(inertia=HUB_INERTIA)],
        fd.Payload(0.0),
        gravity=(0.0, 0.0),
    )
    cand = cat.Candidate(
        "joint_elasticity", "joint1", ("joint1.stiffness", "joint1.rotor_inertia"), (True, True), ((),), True
    )
    locked_k = J_ROTOR * (2 * math.pi * 20.0) ** 2
    _, sized = cat.structural_model(rigid, cand, max_frequency_hz=20.0)
    assert sized["joint1.stiffness"] == pytest.approx(locked_k) and sized["joint1.rotor_inertia"] == pytest.approx(
        J_ROTOR
    )
    assert closed_form_hz(locked_k) > 150.0  # the link free: ~10x the 20 Hz aimed at
    elastic, aimed = cat.structural_model(rigid, cand, max_frequency_hz=20.0, nyquist_hz=50.0)
    k = aimed["joint1.stiffness"]
    assert k == pytest.approx((2 * math.pi * 20.0) ** 2 / (1 / J_ROTOR + 1 / J_LINK), rel=3e-2)
    assert float(elastic.joints[0].stiffness) == k and stiffness.joint_mode(elastic, 1)[0] == pytest.approx(
        20.0, rel=3e-2
    )
    # a start at or below Nyquist is the logs' to show: kept
    _, kept = cat.structural_model(rigid, cand, max_frequency_hz=20.0, nyquist_hz=closed_form_hz(locked_k) * 1.01)
    assert kept["joint1.stiffness"] == pytest.approx(locked_k)
    with pytest.raises(ValueError, match="target_hz expected"):
        stiffness.aim_joint_mode(elastic, 1, target_hz=60.0, nyquist_hz=50.0)


def test_a_structural_candidate_too_stiff_for_the_solver_is_not_fitted():
    """A structural candidate whose start is too stiff (`TooStiff`) is a `Score` that is not
    fitted: in the round's scores and notes with its reason, in `Diagnosis.not_fitted`, no
    cost drop recorded for a later round, and never evidence of a rigid joint (its fit made
    nothing rigid)."""
    est = stiff_start.StepEstimate(5070.0, 1e-5, 4e5, 100_000, "log0", 8.0)
    cand = types.SimpleNamespace(name="joint_elasticity", where="joint1", label="joint_elasticity:joint1")
    values = {"joint1.stiffness": 86.93, "joint1.rotor_inertia": 8.564e-8}
    error = stiff_start.TooStiff(est, where="at its starting values", horizon_s=None, values=values)
    assert structural._rigid_limit(cand, error, 100.0) is None
    said = []
    score = structural._not_fitted(cand, 2, f"at its starting values its model is {est.reason()}", said.append)
    assert isinstance(score, Score) and not score.accepted and math.isnan(score.delta_bic)
    assert "5.07e+03 Hz" in score.not_fitted and "limit of 100000 steps" in score.not_fitted
    assert not_fitted_of([[score]]) == {"joint_elasticity:joint1": f"round 1: {score.not_fitted}"}
    # the round: the candidate's score is kept and noted, no drop recorded for it
    state = types.SimpleNamespace(
        round=1,  # (a later round: the first checks the baseline's headroom first)
        done=set(),
        notes=[],
        struct_promising={cand.label},
        current=types.SimpleNamespace(ho=np.ones(4), cost=10.0),
        struct_models={},
        struct_drop={},
    )
    c = types.SimpleNamespace(**vars(cand), structural=True)
    setting = types.SimpleNamespace(say=said.append, min_gain=1.1, score=lambda *a: score)
    scores = []
    structural.fit_structural_round(setting, state, [c], scores, None, None)
    assert scores == [score] and state.struct_models == {}
    text = f"{cand.label}: not fitted: {score.not_fitted}; it has no detection limit"
    assert state.notes == [{"round": 2, "text": text}]
    structural.record_drops(state, scores, [c])
    assert state.struct_drop == {}


@pytest.mark.slow  # (~1-2 min: a fit's programs compile)
def test_a_fit_that_walks_into_a_stiff_model_stops_keeping_the_finished_stage(monkeypatch):
    """`fit(stop_when_stiff=True)`: when the second stage's start is too stiff for the solver
    (a stand-in estimate there: `StepEstimate` itself is tested above), or its adaptive
    solve ends on the step limit (a stand-in failure), the fit stops before that stage and
    keeps the first: the result is the first stage's, marked (`FitResult.stopped`, the
    summary, the JSON), not converged. Without the option the failure raises, as before."""
    from identify._fit import fit as fit_module

    t = np.linspace(0.0, 2.0, 401)
    k = 1e2
    problem = problem_of(two_inertia(k), 0.05 * np.sin(2 * np.pi * t), t)
    params = [identify.Parameter("joint1.stiffness", k), identify.Parameter("joint1.damping", 0.01, 1e-6, 10.0)]
    options = dict(n_stages=2, n_starts=1, frequency_init=False, estimate_noise=False, max_restarts=0)
    estimate = stiff_start.StepEstimate(7000.0, 1e-5, 1.3e5, 100_000, "log", 2.0)
    stage_step, stiff_at = fit_module._stage_step, fit_module.stiff_at
    limit = identify.SimulationFailed(
        "stand-in: the adaptive solver reached its limit of 100000 steps", horizon_s=2.0, values={}, logs={}
    )

    def second(real, stand_in):
        calls = []

        def call(problem, z, horizon, *rest):
            calls.append(horizon)
            if horizon is not None and float(horizon) > 1.5:
                return stand_in()
            return real(problem, z, horizon, *rest)

        return call

    def fail():
        raise limit

    for caught_by in ("estimate", "solve", "not asked"):
        monkeypatch.setattr(fit_module, "stiff_at", second(stiff_at, lambda: estimate))
        monkeypatch.setattr(fit_module, "_stage_step", second(stage_step, fail))
        if caught_by == "solve":
            monkeypatch.setattr(fit_module, "stiff_at", second(stiff_at, lambda: None))
        if caught_by == "not asked":
            with pytest.raises(identify.SimulationFailed, match="stand-in"):
                identify.fit(problem, params, **options)
            continue
        said = []
        result = identify.fit(problem, params, stop_when_stiff=True, progress=said.append, **options)
        assert [s.horizon_s for s in result.stages] == [pytest.approx(1.0)], result.stages
        assert result.stopped.startswith("stopped before the 2 s stage, keeping the 1 s one: "), result.stopped
        why = (
            "the model is too stiff for the solver: its highest natural frequency"
            if caught_by == "estimate"
            else "stand-in"
        )
        assert why in result.stopped and any(result.stopped in m for m in said), (result.stopped, said)
        assert not result.converged and result.to_dict()["stopped"] == result.stopped
        assert f"note: the fit {result.stopped}; the result is that stage's, over its horizon only" in result.summary()
