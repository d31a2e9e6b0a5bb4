"""Closed-loop logs fitted by the direct method (`identify/_fit/direct.py`): the logged
command replayed open loop from the loop fit's optimum, kept only where it does not drift.

The coverage the method is for is measured on the servo example over seeded sensor count
phases (`test_servo_flexible_link_coverage.py`, slow); here, the plumbing: which fit is kept
and why, the experiment path, and recovery on the servo pendulum of `closed_loop_case.py`
(its independent SciPy loop writes the log)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from closed_loop_case import (
    CONTROLLER_TOML,
    ENCODER,
    KD,
    KP,
    LIMIT,
    PERIOD,
    RIG_TOML,
    TRUTH,
    V_FF,
    reference,
    reference_loop,
)

import identify
from identify._fit.direct import DRIFT_TOLERANCE, drift_reason, start_parameters


def _quality(**ratios):
    return {c: {"ratio": r} for c, r in ratios.items()}


def test_a_direct_fit_that_fits_as_well_as_the_loop_is_kept():
    loop = SimpleNamespace(fit_quality=_quality(theta1=1.1, voltage1=1.0))
    direct = SimpleNamespace(converged=True, at_bounds=[], fit_quality=_quality(theta1=1.0))
    assert drift_reason(loop, direct) == ""


def test_a_direct_fit_that_drifts_or_stops_short_is_not_kept_and_says_why():
    loop = SimpleNamespace(fit_quality=_quality(theta1=1.1, tip1=1.0))
    worse = 1.01 * DRIFT_TOLERANCE * 1.1
    drifted = SimpleNamespace(converged=True, at_bounds=[], fit_quality=_quality(theta1=worse, tip1=1.0))
    why = drift_reason(loop, drifted)
    assert why.startswith("the direct fit (logged command replayed) was not kept: it drifts, theta1")
    assert "tip1" not in why
    on_bounds = SimpleNamespace(converged=False, at_bounds=["hub1.inertia"], fit_quality=_quality(theta1=1.0))
    assert "on bounds ['hub1.inertia']" in drift_reason(loop, on_bounds)
    stopped = SimpleNamespace(converged=False, at_bounds=[], fit_quality=_quality(theta1=1.0))
    assert drift_reason(loop, stopped).endswith("it did not converge")


def test_the_direct_fit_starts_at_the_loop_fits_values_within_the_bounds():
    shared = identify.Parameter("hub1.inertia", 1e-3, 1e-4, 1e-2)
    own = identify.Parameter("joint1.damping", 1e-3, 1e-5, 1e-1, per_log=True)
    loop = SimpleNamespace(
        problem=SimpleNamespace(parameters=[shared, own]),
        value={"hub1.inertia": 2e-3},
        per_log={"joint1.damping": {"a": 1e-3, "b": 3e-3, "c": 2e-2}},
    )
    start = start_parameters(loop)
    assert [(p.name, p.guess, p.lower, p.upper, p.per_log) for p in start] == [
        ("hub1.inertia", 2e-3, 1e-4, 1e-2, False),
        ("joint1.damping", 3e-3, 1e-5, 1e-1, True),
    ]


_EXPERIMENT = (
    RIG_TOML.format(resolution=ENCODER).replace("inertia = 1e-3", "inertia = 1.5e-3")
    + '\n[parameters]\n"hub1.inertia" = { guess = 1.5e-3, lower = 1e-4, upper = 1e-2 }\n'
    + CONTROLLER_TOML.format(kp=KP, kd=KD, ff=V_FF, limit=LIMIT)
    + '\n[[logs]]\nfile = "run.csv"\n'
    + 'columns = { time = "time [s]", theta1 = "enc [deg]", theta1_ref = "ref [deg]", voltage1 = "u [V]" }\n'
    + 'hold = "zoh"\ninitial = { theta1 = -0.3 }\n'
)


def test_an_experiment_with_a_controller_is_fitted_closed_loop_then_by_the_direct_method(tmp_path):
    """The servo pendulum's log from the independent loop (quantised encoder, 0.4 s): the
    loop fit, then the replay of its logged command from there; the result is the replay's
    (open loop, no caveat), the loop fit kept beside it, and the hub inertia's interval
    holds the truth."""
    t = np.arange(400) * PERIOD
    ref = reference(t)
    _, _, volts, recorded = reference_loop(t, -0.3, ref)
    rows = ["time [s],enc [deg],ref [deg],u [V]"] + [
        f"{a:.17g},{np.degrees(b):.17g},{np.degrees(c):.17g},{d:.17g}" for a, b, c, d in zip(t, recorded, ref, volts)
    ]
    (tmp_path / "run.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "exp.toml").write_text(_EXPERIMENT)
    exp = identify.load_experiment(tmp_path / "exp.toml")

    result = identify.fit_experiment(exp, n_starts=1)
    assert result.problem.loop is None and result.problem.channels == ("theta1",)
    assert result.loop_fit is not None and result.loop_fit.problem.loop is not None
    assert result.converged and result.direct_note.startswith("values and intervals by the direct method")
    assert not result.closed_loop_caveat and "note: values and intervals by the direct method" in result.summary()
    assert result.to_dict()["loop_fit"]["cost"] == pytest.approx(result.loop_fit.cost)
    (k,) = [i for i, n in enumerate(result.names) if n == "hub1.inertia"]
    assert result.ci_low[k] <= TRUTH["hub1.inertia"] <= result.ci_high[k], (result.value, result.std_errors)

    assert result.loop_fit.closed_loop_caveat and not result.loop_fit.direct_note


def test_direct_false_returns_the_loop_fit(tmp_path, monkeypatch):
    from identify import _workflow

    rows = [f"{k / 1000},0,0,0" for k in range(20)]
    (tmp_path / "run.csv").write_text("\n".join(["time [s],enc [deg],ref [deg],u [V]", *rows]) + "\n")
    (tmp_path / "exp.toml").write_text(_EXPERIMENT)
    exp = identify.load_experiment(tmp_path / "exp.toml")
    loop_fit = object()
    monkeypatch.setattr(_workflow, "problem_from_experiment", lambda exp, **kw: SimpleNamespace(channels=()))
    monkeypatch.setattr(_workflow, "fit", lambda *a, **kw: loop_fit)
    monkeypatch.setattr(_workflow, "direct_fit", lambda *a, **kw: pytest.fail("direct fit with direct=False"))
    assert _workflow.fit_experiment(exp, direct=False) is loop_fit


def test_the_replay_holds_the_command_and_drops_the_references(tmp_path):
    """A closed-loop log read with `hold = "linear"` is still replayed held: the command
    was held over each controller period whatever the file says of its inputs."""
    rows = [f"{k / 1000},{3.0 * k},{1.0},{0.1 * k}" for k in range(20)]
    (tmp_path / "run.csv").write_text("\n".join(["time [s],enc [deg],ref [deg],u [V]", *rows]) + "\n")
    (tmp_path / "exp.toml").write_text(_EXPERIMENT.replace('hold = "zoh"', 'hold = "linear"'))
    exp = identify.load_experiment(tmp_path / "exp.toml")
    loop = identify.problem_from_experiment(exp)
    replay = identify.problem_from_experiment(exp, replay=True)
    assert loop.loop is not None and loop.channels == ("theta1", "voltage1") and loop.hold == "linear"
    assert replay.loop is None and replay.reference is None and replay.channels == ("theta1",)
    assert replay.hold == "zoh"
    np.testing.assert_array_equal(np.asarray(replay.torque_v[0, :20, 0]), 0.1 * np.arange(20))
