"""Real measured data: Kaheman et al.'s single and double compound pendulum
(`identify/examples/real_single_pendulum`, `real_double_pendulum`; arXiv:2205.06231).

The oracle is the authors' own estimate from the same recordings (published with the data)
and the held-out validation segments; the fits start far from the authors' values (their
guesses are 4-10x off). The free swing identifies only ratios of the inertial, gravity and
damping terms; the experiment files fix the scale (see their comments), so the comparisons
below are of identifiable combinations.

Each rig has two experiment files: `experiment.toml`, the authors' viscous model, and
`experiment_drag_friction.toml`, the dissipation law `identify diagnose` names on it (air
drag and dry friction). The single pendulum's two fits run in CI (about 30 s each); the
double pendulum's fits (1-2 min each, with 26 logs) and the two diagnoses are `slow`.
"""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import flexdyn as fd
from identify import clustered_uncertainty, fit, fitted_outputs, load_experiment, make_problem, predict
from identify._workflow import log_data, parameters, problem_from_experiment

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


def test_single_pendulum_viscous_law_validates_worse_than_the_authors(single_validation):
    """The viscous law fitted accurately to the identification segments predicts the smaller
    held-out swings worse than the authors' viscous parameters (measured 12.36 vs 10.30 mrad,
    1.20x; from the measured start 24.1 vs 17.9 mrad). Why: the dissipation depends on the
    amplitude (the drag + friction law below), so the best viscous coefficient depends on
    which swings it is fitted to, and the authors' estimate is tuned to a loose integrator's
    numerical error (the test above): their larger `k1` happens to suit the small swings.
    Issue 8's "no worse than the authors'" is met by the law `diagnose` names
    (`test_single_pendulum_drag_friction_beats_the_authors_on_validation`); this pins the
    viscous law's shortfall so that a change in it shows."""
    ours, authors = single_validation
    assert 1.05 < ours / authors < 1.4


# ---------------------------------------------------------------------------
# single pendulum with the diagnosed dissipation law (CI: about 30 s)
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def single_drag_friction():
    exp = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment_drag_friction.toml")
    return exp, _fit(exp)


def test_single_pendulum_drag_friction_file_is_the_viscous_file_with_the_law_changed():
    base = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    ext = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment_drag_friction.toml")
    assert [(s.name, s.role, s.file) for s in ext.logs] == [(s.name, s.role, s.file) for s in base.logs]
    assert float(ext.chain.joints[0].damping) == 0.0 and base.chain.joints[0].coulomb is None
    assert [p.name for p in ext.free] == ["link1.inertia", "joint1.coulomb", "link1.drag"]


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_single_pendulum_drag_friction_beats_the_authors_on_validation(single_drag_friction, single_validation):
    """Issue 8's requirement, on the model the toolkit ends with: the viscous term replaced
    by dry joint friction plus air drag on the link (`experiment_drag_friction.toml`, the
    pair `identify diagnose` names), fitted on the same four identification segments,
    predicts the smaller held-out swings better than the authors' parameters. Large swings
    lose energy faster than viscous (drag, ~v|v|) and small ones too (dry friction, a
    constant torque). Measured 2026-11-26: I1 = 1.1809e-4 kg m^2 (J1 unchanged), Coulomb
    4.9555e-4 N m [4.947e-4, 4.964e-4], drag 7.7193e-3 kg/m^2 [7.712e-3, 7.727e-3]; held-out
    RMS 6.30 mrad (initial state and offset re-estimated) vs the authors' 10.30 and our
    viscous fit's 12.36; from the measured start 13.56 mrad vs 17.9 and 24.1.
    The independent check of the two values is `diagnose`'s own fit (viscous term left
    free, slow pin below: drag 7.711e-3 [7.629e-3, 7.795e-3], Coulomb 4.953e-4 [4.886e-4,
    5.021e-4]): this fit must land inside those intervals."""
    exp, res = single_drag_friction
    assert res.converged and not res.at_bounds
    v = res.value
    assert 4.886e-4 <= v["joint1.coulomb"] <= 5.021e-4
    assert 7.629e-3 <= v["link1.drag"] <= 7.795e-3
    # J1 is set by the swing frequency whatever the dissipation law: the authors' within 1 %
    assert M1 * A1**2 + v["link1.inertia"] == pytest.approx(M1 * A1**2 + AUTHORS_SINGLE["link1.inertia"], rel=0.01)
    base = load_experiment(EXAMPLES / "real_single_pendulum" / "experiment.toml")
    ours = _rms_reestimated(exp, v, res.sigma)["theta1"]
    viscous, authors = single_validation
    assert ours < 0.75 * authors  # measured 0.61x
    assert ours < 0.6 * viscous  # measured 0.51x
    assert _rms_measured_start(exp, v)["theta1"] < 0.85 * _rms_measured_start(base, AUTHORS_SINGLE)["theta1"]


def test_single_pendulum_fits_are_flagged_above_the_encoders_noise_floor(single, single_drag_friction):
    """Neither model explains the recordings down to the encoder's noise, and the fits say
    so (`FitResult.poor_fit`, `identify.noise_floor`). The floor of these logs (5 ms
    samples) is 4.2e-5 rad at the 4th order (4.3e-5 at the 3rd and 6th: the swing's leakage
    is gone from order 3 on; the 1 kHz recordings they were cut from give 4.8e-5 at the 2nd
    order), while the fits leave ~1e-3 rad of model error. Measured: the viscous fit's
    residual 101 floors, drag and dry friction's 30, in the order of their held-out errors
    (previous test)."""
    ratios = {}
    for label, (_, res) in (("viscous", single), ("drag_friction", single_drag_friction)):
        q = res.fit_quality["theta1"]
        assert 3e-5 < q["noise_floor"] < 6e-5, q
        assert res.poor_fit == ["theta1"] and "estimated from the data alone" in res.summary()
        ratios[label] = q["ratio"]
    assert ratios["drag_friction"] < 0.5 * ratios["viscous"] and ratios["drag_friction"] > 10, ratios


# ---------------------------------------------------------------------------
# double pendulum (slow: 1-2 min per fit on two cores; loading and the model oracle in CI)
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def double():
    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    return exp, _fit(exp)


@pytest.fixture(scope="module")
def double_validation(double):
    """Held-out RMS per channel, ours and the authors' viscous parameters in our model, two
    ways: `reestimated` (initial state and encoder offsets re-estimated per log, parameters
    fixed: the toolkit's validation) and `measured_start` (the authors' procedure)."""
    exp, res = double
    return {
        who: {
            "reestimated": _rms_reestimated(exp, v, res.sigma),
            "measured_start": _rms_measured_start(exp, v),
        }
        for who, v in (("ours", res.value), ("authors", AUTHORS_DOUBLE))
    }


def _double_combinations(w):
    """The identifiable combinations at the authors' `m1`, `m2`, `a2` (see experiment.toml)."""
    w = {"link1.mass": DM1, "link2.mass": DM2, "link2.com": DA2, **w}
    return {
        "J1": w["link1.inertia"] + DM1 * w["link1.com"] ** 2 + DM2 * w["link1.length"] ** 2,
        "J2": w["link2.inertia"] + DM2 * DA2**2,
        "c": DM2 * w["link1.length"] * DA2,
        "G1": DM1 * w["link1.com"] + DM2 * w["link1.length"],
    }


def test_double_pendulum_files_load_as_documented():
    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    assert exp.output_channels == ("phi1", "phi2")
    assert [s.name for s in exp.fit_logs] == [f"id{k}" for k in range(26)]
    assert [s.name for s in exp.validation_logs] == [f"vad{k}" for k in range(4)]
    for s in exp.fit_logs + exp.validation_logs:
        assert s.log.sampling.median_dt == pytest.approx(0.005)


def _authors_double_ode(w, g):
    """The authors' model (`DoublePendulumODE_Mounted.m`, as the data README states it),
    written here independently of flexdyn: absolute angles from upright, kinetic energy
    `J1 p1'^2/2 + J2 p2'^2/2 + c cos(p1 - p2) p1' p2'`, potential `g (G1 cos p1 + G2 cos p2)`,
    viscous `k1` on `p1'` and `k2` on `p1' - p2'`."""
    comb = _double_combinations(w)
    J1, J2, c, G1 = comb["J1"], comb["J2"], comb["c"], comb["G1"]
    G2, k1, k2 = DM2 * DA2, w["joint1.damping"], w["joint2.damping"]

    def f(t, y):
        p1, p2, w1, w2 = y
        d = p1 - p2
        M = np.array([[J1, c * np.cos(d)], [c * np.cos(d), J2]])
        b = np.array(
            [
                -c * np.sin(d) * w2**2 + g * G1 * np.sin(p1) - k1 * w1 - k2 * (w1 - w2),
                c * np.sin(d) * w1**2 + g * G2 * np.sin(p2) - k2 * (w2 - w1),
            ]
        )
        return [w1, w2, *np.linalg.solve(M, b)]

    return f


def test_double_pendulum_model_is_the_authors_ode():
    """Oracle for the two-link chain: the authors' ODE in NumPy (SciPy DOP853) and flexdyn's
    explicit chain, both with the authors' parameters, from a validation segment's measured
    start: the same trajectory to 1e-7 rad over its 2.67 s."""
    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    s = exp.validation_logs[0]
    t = s.log.t_relative
    i = s.initial
    y0 = [i["theta1"], i["theta1"] + i["theta2"], i["theta1_rate"], i["theta1_rate"] + i["theta2_rate"]]
    ref = solve_ivp(
        _authors_double_ode(AUTHORS_DOUBLE, 9.80858), (0, t[-1]), y0, "DOP853", t_eval=t, rtol=1e-12, atol=1e-12
    )
    chain = fd.with_parameters(exp.chain, AUTHORS_DOUBLE)
    y0_ours = jnp.asarray([i["theta1"], i["theta2"], i["theta1_rate"], i["theta2_rate"]])
    Q = np.asarray(fd.simulate(chain, y0_ours, jnp.asarray(t), rtol=1e-12, atol=1e-12).Q)
    np.testing.assert_allclose(Q[:, 0], ref.y[0], atol=1e-7)
    np.testing.assert_allclose(Q[:, 0] + Q[:, 1], ref.y[1], atol=1e-7)


@pytest.mark.slow
def test_double_pendulum_combinations_and_damping_agree(double):
    """All 26 identification segments, as the authors fitted. The two viscous coefficients
    agree within our 95 % intervals, white-noise and cluster-robust (measured k1 2.4046e-4
    [2.346e-4, 2.464e-4] vs 2.3714e-4; k2 1.081e-5 [9.61e-6, 1.216e-5] vs 1.0e-5). The
    inertial and gravity combinations agree within 0.3 % (measured +0.16 to +0.28 %). The
    white-noise intervals are far narrower than that (they assume white residuals; the
    residual is model error); the cluster-robust ones (`identify.clustered_uncertainty`, 26
    logs) have half-widths 0.05-0.26 % and hold the authors' G1, not J1 (by 0.002 %), J2 or
    c: explained in the slow test below (the combinations move by up to 0.18 % with the
    estimator: run the authors' procedure in our model and J2 becomes theirs)."""
    exp, res = double
    assert res.converged and not res.at_bounds
    ours, auth = _double_combinations(res.value), _double_combinations(AUTHORS_DOUBLE)
    for key in ours:
        assert ours[key] == pytest.approx(auth[key], rel=0.003), key
    robust = clustered_uncertainty(res)
    for name in ("joint1.damping", "joint2.damping"):
        i = res.names.index(name)
        assert res.ci_low[i] <= AUTHORS_DOUBLE[name] <= res.ci_high[i], (name, res.value[name])
        assert robust.ci_low[i] <= AUTHORS_DOUBLE[name] <= robust.ci_high[i], (name, res.value[name])
    _, lo, hi = robust.interval(lambda w: _double_combinations(w)["G1"])
    assert lo <= auth["G1"] <= hi
    # the robust intervals are wider than the white-noise ones by an order of magnitude
    i = res.names.index("link1.length")
    assert robust.std_errors[i] > 3 * res.std_errors[i]


@pytest.mark.slow
def test_double_pendulum_validation_no_worse_than_the_authors(double_validation):
    """Issue 8's requirement on the viscous model: on the four held-out segments, with each
    log's initial state and encoder offsets re-estimated, our fit predicts no worse than the
    authors' parameters (measured 1.561 / 2.405 mrad vs 1.617 / 2.454, phi1 / phi2). From the
    measured start (first sample, denoised rate, no offsets) both are 4x worse, 6.19 / 8.91 vs
    5.87 / 8.39 mrad: that error is mostly the start (one angle sample and the authors'
    denoised rate; the fitted encoder offsets are 0-2 mrad), not the model (see the drag +
    friction test: a 3x better model changes it by at most 10 %)."""
    ours, authors = double_validation["ours"], double_validation["authors"]
    for c in ("phi1", "phi2"):
        assert ours["reestimated"][c] <= authors["reestimated"][c], (c, ours, authors)
        assert ours["measured_start"][c] <= 1.1 * authors["measured_start"][c], (c, ours, authors)
    assert ours["reestimated"]["phi2"] < 0.003


@pytest.mark.slow
def test_double_pendulum_combinations_move_with_the_estimator_toward_the_authors(double):
    """Why J1, J2 and c differ from the authors' by 0.2-0.3 %, more than our cluster-robust
    intervals: on a model that is not exact (the viscous law, see the diagnosis) these
    combinations depend on the estimator at that level. The authors simulated every segment
    from its measured start (first sample and denoised rate, no encoder offsets); the same
    procedure in our model (accurate integrator), on the same 26 segments, moves J2 to
    within 0.05 % of theirs and J1 and c toward theirs (measured: J1 +0.261 -> +0.174 %, J2
    +0.188 -> +0.007 %, c +0.278 -> +0.116 %; G1 +0.163 -> +0.217 %, and k1 halves). The
    authors' ODE, written independently in NumPy, reproduces our measured-start simulation
    (notebook), so this is the estimator, not the model."""
    exp, res = double
    data = [dataclasses.replace(log_data(s, exp.chain.n_links), fit_initial=(), offsets=()) for s in exp.fit_logs]
    problem = make_problem(exp.chain, parameters(exp), data, dict(res.sigma), rtol=RTOL, atol=1e-2 * RTOL)
    start = fit(problem, parameters(exp), estimate_noise=list(problem.channels), n_starts=1)
    assert start.converged
    auth = _double_combinations(AUTHORS_DOUBLE)
    ours, theirs_way = _double_combinations(res.value), _double_combinations(start.value)
    assert theirs_way["J2"] == pytest.approx(auth["J2"], rel=5e-4)
    for key in ("J1", "J2", "c"):
        assert abs(theirs_way[key] / auth[key] - 1) < abs(ours[key] / auth[key] - 1), key


@pytest.mark.slow
def test_double_pendulum_drag_friction_beats_the_authors_on_validation(double, double_validation):
    """The law `diagnose` names on the double pendulum (`experiment_drag_friction.toml`: air
    drag on link 2, dry friction in both joints, viscous damping in joint 1 only), fitted on
    the same 26 segments: held-out RMS about 3x below the authors' parameters."""
    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment_drag_friction.toml")
    res = _fit(exp)
    assert res.converged and not res.at_bounds
    ours, auth = _double_combinations(res.value), _double_combinations(AUTHORS_DOUBLE)
    for key in ours:
        assert ours[key] == pytest.approx(auth[key], rel=0.01), key
    held = _rms_reestimated(exp, res.value, res.sigma)
    start = _rms_measured_start(exp, res.value)
    authors = double_validation["authors"]
    for c in ("phi1", "phi2"):
        assert held[c] < 0.5 * authors["reestimated"][c], (c, held, authors)
        assert start[c] <= 1.1 * authors["measured_start"][c], (c, start, authors)


# ---------------------------------------------------------------------------
# diagnosis (slow: about 20 min for the single pendulum, 45-70 min for the double, on
# two cores)
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
    """`identify diagnose` on the real double pendulum (all 26 identification segments), as
    measured (identify/diagnose.py of 2026-11-26; 4055 s on two cores shared with other
    runs, so about 45-70 min): three effects stacked, in this order, **air drag on link 2**
    (`quadratic_damping:link2`, dBIC -23586, held-out gain 1.17x), **dry friction in joint
    2** (-51561, 1.34x) and **dry friction in joint 1** (-15488, 2.11x); the search stops at
    the default `max_effects = 3`. Held-out RMS on vad0..vad3 (initial state and offsets
    re-estimated per log) falls from 1.561 / 2.405 mrad (phi1 / phi2, our viscous fit) to
    0.482 / 0.716 mrad: 3.24x / 3.36x, and 3.3x / 3.4x below the authors' viscous
    parameters in our model (1.606 / 2.468, the validation test above). Fitted: drag 1.7883e-2
    kg/m^2 [1.7832e-2, 1.7934e-2], Coulomb 1.9744e-4 N m [1.9636e-4, 1.9853e-4] (joint 2)
    and 2.2490e-4 [2.2171e-4, 2.2813e-4] (joint 1): within 0.2 % of the independent fit of
    `experiment_drag_friction.toml` (viscous damping in joint 2 dropped there). The same law
    as the single pendulum's (drag + dry friction), found here one term at a time; on the 6
    segments the file listed until 2026-11-26 it named the same three in the same order.
    The fit is deterministic; tolerances allow for a different BLAS/XLA build, not for a
    different answer."""
    from identify import diagnose

    exp = load_experiment(EXAMPLES / "real_double_pendulum" / "experiment.toml")
    d = diagnose(exp)
    labels = [f"{c.name}:{c.where}" for c in d.causes]
    assert labels == ["quadratic_damping:link2", "coulomb_friction:joint2", "coulomb_friction:joint1"], d.summary()
    held = d.to_dict()["held_out"]
    for c, before, after in (("phi1", 1.561e-3, 0.482e-3), ("phi2", 2.405e-3, 0.716e-3)):
        assert held["baseline"][c] == pytest.approx(before, rel=0.02), held
        assert held["extended"][c] == pytest.approx(after, rel=0.05), held
    # the extended model beats the authors' parameters on the held-out swings (test above:
    # 1.606 / 2.468 mrad in our model, initial state and offsets re-estimated the same way)
    assert held["extended"]["phi1"] < 1.606e-3 / 2 and held["extended"]["phi2"] < 2.468e-3 / 2
    params = {k: v for c in d.causes for k, v in c.parameters.items()}
    for name, value in (("link2.drag", 1.7883e-2), ("joint2.coulomb", 1.9744e-4), ("joint1.coulomb", 2.2490e-4)):
        assert params[name]["value"] == pytest.approx(value, rel=0.03), (name, params[name])
        lo, hi = params[name]["ci95"]  # measured widths 0.6 % (drag) to 2.9 % (joint 1)
        assert 0 < lo < hi and hi - lo < 0.1 * value, (name, params[name])
