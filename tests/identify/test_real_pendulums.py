"""Real measured data: Kaheman et al.'s single and double compound pendulum
(`identify/examples/real_single_pendulum`, `real_double_pendulum`; arXiv:2205.06231).

The oracle is the authors' own estimate from the same recordings (published with the data)
and the held-out validation segments; the fits start far from the authors' values (their
guesses are 4-10x off). The free swing identifies only ratios of the inertial, gravity and
damping terms; the experiment files fix the scale (see their comments), so the comparisons
below are of identifiable combinations.

The single pendulum fit runs in CI (about a minute); the double pendulum fit and the two
diagnoses are `slow` (several minutes each on two cores).
"""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import flexdyn as fd
from identify import fit, fitted_outputs, load_experiment, make_problem, predict
from identify.run import log_data, parameters, problem_from_experiment

EXAMPLES = Path(__file__).resolve().parents[2] / "identify" / "examples"
RTOL = 1e-7  # fit solver tolerance; the model error is ~1e-3 rad

# The authors' estimates (EstimatedParameters_*.mat of dynamicslab/MultiArm-Pendulum).
M1, A1 = 0.14758, 0.14775
AUTHORS_SINGLE = {"link1.mass": M1, "link1.com": A1, "link1.inertia": 1.0912e-4, "joint1.damping": 2.2394e-4}
DM1, DM2, DA2 = 0.093844, 0.137596, 0.116779
AUTHORS_DOUBLE = {
    "link1.mass": DM1,
    "link2.mass": DM2,
    "link1.com": 0.108565,
    "link2.com": DA2,
    "link1.length": 0.172719,
    "link1.inertia": 4.3753e-4,
    "link2.inertia": 1.26883e-3,
    "joint1.damping": 2.3714e-4,
    "joint2.damping": 1.0e-5,
    "gravity[0]": -9.80858,
}


def _fit(exp):
    problem = problem_from_experiment(exp, rtol=RTOL, atol=1e-2 * RTOL)
    return fit(problem, parameters(exp), estimate_noise=list(problem.channels), n_starts=1)


def _rms_reestimated(exp, values, sigma):
    """Validation RMS per channel with the parameters fixed and each log's initial state and
    encoder offsets re-estimated."""
    chain = fd.with_parameters(exp.chain, values)
    data = [log_data(s, chain.n_links) for s in exp.validation_logs]
    problem = make_problem(chain, [], data, dict(sigma), rtol=RTOL, atol=1e-2 * RTOL)
    res = fit(problem, [], n_stages=1, estimate_noise=False)
    outs = fitted_outputs(res).values()
    return {c: float(np.sqrt(np.mean(np.concatenate([e["residual"][c] for e in outs]) ** 2))) for c in problem.channels}


def _rms_measured_start(exp, values):
    """Validation RMS per channel of a pure simulation from the measured initial state (the
    authors' procedure: first sample, their denoised rate), no offsets."""
    chain = fd.with_parameters(exp.chain, values)
    data = [dataclasses.replace(log_data(s, chain.n_links), fit_initial=(), offsets=()) for s in exp.validation_logs]
    problem = make_problem(chain, [], data, {c: 1.0 for c in exp.output_channels}, rtol=1e-10, atol=1e-12)
    pred, ok = predict(problem, jnp.zeros(0), problem.y0_known)
    assert bool(jnp.all(ok))
    err = (np.asarray(pred) - np.asarray(problem.measured))[np.asarray(problem.valid)]
    return {c: float(np.sqrt(np.mean(err[:, j] ** 2))) for j, c in enumerate(problem.channels)}


# ---------------------------------------------------------------------------
# single pendulum (CI)
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def single():
    exp = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    return exp, _fit(exp)


def test_single_pendulum_files_load_as_documented():
    exp = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    assert [s.name for s in exp.fit_logs] == ["id0", "id1", "id2", "id3"]
    assert [s.name for s in exp.validation_logs] == ["vad0", "vad1"]
    for s in exp.fit_logs + exp.validation_logs:
        assert s.log.sampling.median_dt == pytest.approx(0.005)
        # upright = 0: the recordings swing about pi
        assert abs(np.median(s.log.outputs["theta1"]) - np.pi) < 0.1
    assert np.asarray(exp.chain.gravity).tolist() == [-9.81, 0.0]


def test_single_pendulum_inertia_agrees_damping_differs_as_explained(single):
    exp, res = single
    assert res.converged
    J_ours = M1 * A1**2 + res.value["link1.inertia"]
    J_auth = M1 * A1**2 + AUTHORS_SINGLE["link1.inertia"]
    # inertia about the pivot at the authors' m1*a1: measured +0.27 % (our 95 % interval is
    # +-0.003 %: it assumes white residuals, and the residual is mostly model error)
    assert abs(J_ours / J_auth - 1) < 0.01
    # damping: ours is lower (measured 0.84x); see the next two tests
    assert 0.6 < res.value["joint1.damping"] / AUTHORS_SINGLE["joint1.damping"] < 0.95


def _single_rms(values, specs, method, rtol):
    J, k = M1 * A1**2 + values["link1.inertia"], values["joint1.damping"]
    err = []
    for s in specs:
        t = s.log.t_relative
        y0 = [s.log.outputs["theta1"][0], s.initial["theta1_rate"]]
        sol = solve_ivp(
            lambda t, y: [y[1], (M1 * A1 * 9.81 * np.sin(y[0]) - k * y[1]) / J],
            (0.0, t[-1]),
            y0,
            method=method,
            t_eval=t,
            rtol=rtol,
            atol=1e-6 if rtol >= 1e-6 else 1e-12,
        )
        err.append(sol.y[0] - s.log.outputs["theta1"])
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


def test_single_pendulum_authors_estimate_fits_a_loose_integrator(single):
    """The difference explained: the authors simulated with MATLAB ode15s at its default
    RelTol 1e-3. Simulated accurately (SciPy DOP853), our parameters reproduce the
    identification segments far better than theirs; with a loose variable-order BDF
    integrator (rtol 1e-3) theirs are the better ones: their estimate absorbs the integrator's
    numerical error. Measured (RMS over id0-id3): accurate, ours 17.9 mrad vs authors' 141.8;
    BDF 1e-3, ours 127.5 vs authors' 41.9."""
    exp, res = single
    ours_accurate = _single_rms(res.value, exp.fit_logs, "DOP853", 1e-11)
    auth_accurate = _single_rms(AUTHORS_SINGLE, exp.fit_logs, "DOP853", 1e-11)
    ours_loose = _single_rms(res.value, exp.fit_logs, "BDF", 1e-3)
    auth_loose = _single_rms(AUTHORS_SINGLE, exp.fit_logs, "BDF", 1e-3)
    assert ours_accurate < 0.3 * auth_accurate
    assert auth_loose < 0.5 * ours_loose


@pytest.fixture(scope="module")
def single_validation(single):
    exp, res = single
    return _rms_reestimated(exp, res.value, res.sigma)["theta1"], _rms_reestimated(exp, AUTHORS_SINGLE, res.sigma)[
        "theta1"
    ]


def test_single_pendulum_validation_error(single_validation):
    ours, authors = single_validation
    # measured: ours 12.36 mrad, the authors' parameters in our model 10.30 mrad
    assert ours < 0.0130
    assert ours < 1.25 * authors


@pytest.mark.xfail(
    strict=True,
    reason="issue 8's requirement fails on the single pendulum: the held-out segments are the "
    "smallest swings, which decay faster than a viscous law fitted to the larger ones predicts "
    "(amplitude-dependent dissipation the viscous model lacks); the authors' larger k1 suits them "
    "better. Measured: ours 12.36 mrad vs the authors' 10.30 mrad (initial state and offset "
    "re-estimated); from the measured start 24.1 vs 17.9 mrad.",
)
def test_single_pendulum_validation_no_worse_than_the_authors(single_validation):
    ours, authors = single_validation
    assert ours <= authors


# ---------------------------------------------------------------------------
# double pendulum (slow: about 3 min on two cores)
# ---------------------------------------------------------------------------


@pytest.mark.slow
def test_double_pendulum_combinations_and_validation():
    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    assert exp.output_channels == ("phi1", "phi2")
    res = _fit(exp)
    assert res.converged
    v = {"link1.mass": DM1, "link2.mass": DM2, "link2.com": DA2, **res.value}

    def combos(w):
        return {
            "J1": w["link1.inertia"] + DM1 * w["link1.com"] ** 2 + DM2 * w["link1.length"] ** 2,
            "J2": w["link2.inertia"] + DM2 * DA2**2,
            "c": DM2 * w["link1.length"] * DA2,
            "G1": DM1 * w["link1.com"] + DM2 * w["link1.length"],
        }

    ours, auth = combos(v), combos(AUTHORS_DOUBLE)
    # the inertial and gravity combinations agree within 1 % (measured: 0.1-0.4 %)
    for key in ours:
        assert ours[key] == pytest.approx(auth[key], rel=0.01), key
    # validation against the authors' parameters in our model. Measured (mrad, phi1/phi2):
    # measured start, ours 6.25/9.14 vs authors' 5.87/8.39; initial state and offsets
    # re-estimated, ours 1.584/2.581 vs authors' 1.563/2.531. Ours is 1-9 % WORSE: issue 8's
    # "no worse" fails here too (the held-out segments are the smallest swings, where the
    # authors' larger k1, fitted to all 26 segments, does better); it is pinned, not hidden.
    for how, worst in ((_rms_measured_start, 1.15), (lambda e, w: _rms_reestimated(e, w, res.sigma), 1.05)):
        a, b = how(exp, res.value), how(exp, AUTHORS_DOUBLE)
        for c in ("phi1", "phi2"):
            assert a[c] <= worst * b[c], (c, a, b)
    assert _rms_reestimated(exp, res.value, res.sigma)["phi2"] < 0.003


# ---------------------------------------------------------------------------
# diagnosis (slow: about 20 min for the single pendulum, 40 min for the double, on two
# loaded cores)
# ---------------------------------------------------------------------------


@pytest.mark.slow
def test_single_pendulum_diagnosis_is_pinned():
    """`identify diagnose` on the real single pendulum, as measured (identify/diagnose.py of
    2026-11-24, with the pair search; 1338 s on two loaded cores): **air drag on the link and
    dry friction in the joint, together** (`quadratic_damping:link1 + coulomb_friction:joint1`,
    dBIC -17637, held-out gain 1.965x: 12.36 -> 6.29 mrad on vad0 + vad1). Neither passes
    alone: drag halves the fit cost (dBIC -4884) but is worse on the held-out smaller swings
    (0.867x); Coulomb friction alone ends at its neutral value (gain 1.000x). Fitted: drag
    7.711e-3 kg/m^2 [7.629e-3, 7.795e-3], Coulomb 4.953e-4 N m [4.886e-4, 5.021e-4]; the
    independent hand-built fit below (viscous damping removed instead of left free) gives
    7.720e-3 and 4.957e-4. Round 2 names nothing more (a sensor delay fits, dBIC -640, but
    gains 1.003x on the held-out data).
    The fit is deterministic; tolerances allow for a different BLAS/XLA build, not for a
    different answer."""
    from identify import diagnose

    exp = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    d = diagnose(exp)
    assert sorted(d.named) == ["coulomb_friction", "quadratic_damping"], d.summary()
    causes = {c.name: c for c in d.causes}
    assert causes["coulomb_friction"].together_with == ["quadratic_damping:link1"]
    assert causes["quadratic_damping"].together_with == ["coulomb_friction:joint1"]
    held = d.to_dict()["held_out"]
    assert held["baseline"]["theta1"] == pytest.approx(0.01236, rel=0.02)
    assert held["extended"]["theta1"] == pytest.approx(0.00629, rel=0.03)
    assert held["gain_total"] == pytest.approx(1.965, rel=0.03)
    # the two parameters agree with the independent hand-built fit (slow test below)
    drag = causes["quadratic_damping"].parameters["link1.drag"]
    dry = causes["coulomb_friction"].parameters["joint1.coulomb"]
    assert drag["ci95"][0] <= 7.720e-3 <= drag["ci95"][1], drag
    assert dry["ci95"][0] <= 4.957e-4 <= dry["ci95"][1], dry
    # each alone fails on the held-out data: this is what the pair search is for
    singles = {s["members"] or (s["name"], s["where"]): s for s in d.to_dict()["rounds"][0]}
    drag_alone = singles[("quadratic_damping", "link1")]
    assert drag_alone["delta_bic"] < -1000 and not drag_alone["accepted"]
    assert drag_alone["held_out_gain"] == pytest.approx(0.867, abs=0.03)
    assert singles[("coulomb_friction", "joint1")]["held_out_gain"] == pytest.approx(1.0, abs=0.02)


@pytest.mark.slow
def test_double_pendulum_diagnosis_is_pinned():
    """`identify diagnose` on the real double pendulum, as measured (identify/diagnose.py of
    2026-11-24; 2345 s on two loaded cores): three effects stacked, in this order,
    **air drag on link 2** (`quadratic_damping:link2`, dBIC -6433, held-out gain 1.23x),
    **dry friction in joint 2** (-12049, 1.33x) and **dry friction in joint 1** (-3251,
    2.03x); the search stops at the default `max_effects = 3`. Held-out RMS on vad0..vad3
    (initial state and offsets re-estimated per log) falls from 1.584 / 2.581 mrad (phi1 /
    phi2, our viscous fit) to 0.494 / 0.760 mrad: 3.2x / 3.4x, and 3.2x / 3.3x below the
    authors' viscous parameters in our model (1.563 / 2.531, the test above). Fitted: drag
    1.860e-2 kg/m^2 [1.850e-2, 1.871e-2], Coulomb 2.080e-4 N m [2.057e-4, 2.102e-4] (joint
    2) and 2.102e-4 [2.038e-4, 2.169e-4] (joint 1). The same law as the single pendulum's
    (drag + dry friction, test above), found here one term at a time.
    The fit is deterministic; tolerances allow for a different BLAS/XLA build, not for a
    different answer."""
    from identify import diagnose

    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    d = diagnose(exp)
    labels = [f"{c.name}:{c.where}" for c in d.causes]
    assert labels == ["quadratic_damping:link2", "coulomb_friction:joint2", "coulomb_friction:joint1"], d.summary()
    held = d.to_dict()["held_out"]
    for c, before, after in (("phi1", 1.584e-3, 0.494e-3), ("phi2", 2.581e-3, 0.760e-3)):
        assert held["baseline"][c] == pytest.approx(before, rel=0.02), held
        assert held["extended"][c] == pytest.approx(after, rel=0.05), held
    # the extended model beats the authors' parameters on the held-out swings (test above:
    # 1.563 / 2.531 mrad in our model, initial state and offsets re-estimated the same way)
    assert held["extended"]["phi1"] < 1.563e-3 / 2 and held["extended"]["phi2"] < 2.531e-3 / 2
    params = {k: v for c in d.causes for k, v in c.parameters.items()}
    for name, value in (("link2.drag", 1.860e-2), ("joint2.coulomb", 2.080e-4), ("joint1.coulomb", 2.102e-4)):
        assert params[name]["value"] == pytest.approx(value, rel=0.03), (name, params[name])
        lo, hi = params[name]["ci95"]  # measured widths 1.1 % (drag) to 6.3 % (joint 1)
        assert 0 < lo < hi and hi - lo < 0.1 * value, (name, params[name])


# ---------------------------------------------------------------------------
# single pendulum: a dissipation law that generalises (slow: ~4 min on two cores)
# ---------------------------------------------------------------------------


@pytest.mark.slow
def test_single_pendulum_dry_friction_and_air_drag_beat_the_authors_on_validation():
    """The viscous law is what fails on the held-out swings (the xfail above). Replacing it
    by dry joint friction plus air drag on the link (`joint1.coulomb`, `link1.drag`, the
    catalogue's `coulomb_friction` and `quadratic_damping` together), fitted on the same
    identification segments, predicts the smaller held-out swings better than the authors'
    parameters. Neither term alone does (the diagnosis pin above: drag alone 0.867x, Coulomb
    alone ends at zero; `diagnose` finds the two by its pair search): large swings decay
    faster than viscous (drag, ~v|v|) and small ones too (dry friction, a constant torque).
    Measured 2026-11-24: J1 unchanged (I1 = 1.1810e-4 kg m^2); coulomb 4.957e-4 N m
    [4.949e-4, 4.966e-4]; drag 7.720e-3 kg/m^2 [7.712e-3, 7.727e-3]; held-out RMS (initial state and
    offset re-estimated) 6.31 mrad vs the authors' 10.30
    and our viscous fit's 12.36; from the measured start 13.56 mrad vs 17.9 and 24.1. With a
    free viscous coefficient as well, it goes to its lower bound (1e-7 N m s/rad)."""
    import equinox as eqx

    from identify.fit import Parameter

    exp = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    absent = lambda x: x is None  # noqa: E731 - optional part fields are None when absent
    chain = eqx.tree_at(lambda c: c.joints[0].damping, exp.chain, 0.0)
    chain = eqx.tree_at(lambda c: c.joints[0].coulomb, chain, 1e-4, is_leaf=absent)
    chain = eqx.tree_at(lambda c: c.links[0].drag, chain, 1e-3, is_leaf=absent)
    ext = dataclasses.replace(exp, chain=chain)
    params = [
        Parameter("link1.inertia", 1e-3, 1e-6, 1e-1),
        Parameter("joint1.coulomb", 1e-4, 1e-8, 1e-1),  # N m, start 5x below the fitted value
        Parameter("link1.drag", 1e-3, 1e-7, 1.0),  # kg/m^2, start 8x below
    ]
    data = [log_data(s, chain.n_links) for s in ext.fit_logs]
    res = fit(make_problem(chain, params, data, {}, rtol=RTOL, atol=1e-2 * RTOL), params, estimate_noise=["theta1"])
    assert res.converged and not res.at_bounds
    v = res.value
    assert 3e-4 < v["joint1.coulomb"] < 8e-4 and 4e-3 < v["link1.drag"] < 1.5e-2
    # J1 is set by the swing frequency whatever the dissipation law: the authors' within 1 %
    assert M1 * A1**2 + v["link1.inertia"] == pytest.approx(M1 * A1**2 + AUTHORS_SINGLE["link1.inertia"], rel=0.01)
    ours = _rms_reestimated(ext, v, res.sigma)["theta1"]
    authors = _rms_reestimated(exp, AUTHORS_SINGLE, res.sigma)["theta1"]
    assert ours < 0.75 * authors  # measured 0.61x
    assert _rms_measured_start(ext, v)["theta1"] < 0.85 * _rms_measured_start(exp, AUTHORS_SINGLE)["theta1"]
