"""System identification (`identify.fit`) on synthetic logs from known parameters.

Issue requirements tested here:

- recovery: every parameter inside its reported 95 % CI (coverage >= 90 % over 50 seeded
  trials, slow) and to 1 % (EI, hub inertia) / 5 % (joint damping, payload) at 1 % noise;
- convergence from far-off guesses (-50 % / +100 % on each of EI, damping, hub inertia,
  payload) in >= 95 % of seeded trials (slow), with the iteration counts printed;
- a multi-log fit (three releases, shared EI and damping, per-log initial angle);
- paper 000's log-decrement damping estimate against a full fit of the exact model.

The CI-sized versions run by default (about 3 minutes on 2 cores); the statistical ones
are marked `slow` (`pytest -m slow -s tests/identify/test_fit.py` prints their tables).

**The 4-parameter scenario.** A single flexible link in the horizontal plane (paper
002's link: l = 0.5 m, rho = 0.2 kg/m, EI = 1 N m^2, hub 0.02 kg m^2, payload 0.05 kg,
joint damping 0.005 N m s, modal damping ratio 0.02), driven by two torque doublets of
0.05 N m, logged for 1.2 s at 4 ms (`theta1` and `tip1`), white noise of 1 % of each
channel's RMS. We use ONE assumed mode (`N_MODES`): measured on seeds 1-3, the estimates
and standard errors with one mode agree with those of the two-mode model to 3 digits
(e.g. seed 1: EI +0.127 % vs +0.128 %, damping +0.294 % vs +0.292 %) while a fit is ~4x
cheaper (about 12 s instead of 45 s per fit on the shared 2-core machine); the 1.2 s log
at 4 ms (instead of 2.0 s at 2 ms) recovers all four parameters within the issue's bars.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from fresh_jacobian import assert_standard_errors_match, fresh_covariance  # tests/ is on sys.path
from scipy.integrate import quad
from scipy.signal import find_peaks

import flexdyn as fd
import identify
import identify._fit.fit as fit_module
import identify._fit.jacobian as jacobian_module
import identify._fit.quality as quality_module
import identify._fit.starts as starts_module
import identify._fit.steps as steps_module
import identify._model.parameters as parameters_module
import identify._model.residuals as residuals_module
from identify._fit.stage import Stage
from identify._model.variables import Variables

# ---------------------------------------------------------------------------
# The 4-parameter scenario
# ---------------------------------------------------------------------------

N_MODES = 1
TRUTH = {"link1.EI": 1.0, "joint1.damping": 0.005, "hub1.inertia": 0.02, "payload.mass": 0.05}
#: The issue's accuracy bars at 1 % noise (relative error).
BARS = {"link1.EI": 0.01, "joint1.damping": 0.05, "hub1.inertia": 0.01, "payload.mass": 0.05}
T_END, DT = 1.2, 4e-3
CHANNELS = ("theta1", "tip1")


def arm_chain() -> fd.Chain:
    return fd.Chain(
        [fd.FlexibleLink(0.5, 0.2, TRUTH["link1.EI"], n_modes=N_MODES, damping_ratio=0.02)],
        joints=[fd.RigidJoint(damping=TRUTH["joint1.damping"])],
        hubs=[fd.Hub(inertia=TRUTH["hub1.inertia"])],
        payload=fd.Payload(mass=TRUTH["payload.mass"]),
    )


def doublets(t):
    """Two torque doublets of 0.05 N m: +/- on [0, 0.2)/[0.2, 0.4), then [0.8, 0.9)/[0.9, 1.0)."""
    tau = np.zeros_like(t)
    for a, b, v in ((0.0, 0.2, 0.05), (0.2, 0.4, -0.05), (0.8, 0.9, 0.05), (0.9, 1.0, -0.05)):
        tau[(t >= a) & (t < b)] = v
    return tau[:, None]


class Arm:
    """The scenario's chain, time grid, torque and noise levels (1 % of each channel's RMS
    on the noise-free log), built once per test session."""

    def __init__(self):
        self.chain = arm_chain()
        self.t = np.arange(0.0, T_END, DT)
        self.torque = doublets(self.t)
        clean = identify.simulate_log(self.chain, self.t, torque=self.torque, channels=CHANNELS)
        self.noise = {c: 0.01 * float(np.sqrt(np.mean(v**2))) for c, v in clean.outputs.items()}

    def log(self, seed: int) -> identify.LogData:
        return identify.simulate_log(
            self.chain,
            self.t,
            torque=self.torque,
            channels=CHANNELS,
            noise=self.noise,
            rng=np.random.default_rng(seed),
        )

    def fit(self, seed: int, factors, **options):
        """Fit all four parameters to the log of `seed` from guesses `truth * factors`,
        bounds truth * [1e-2, 1e2]. Returns (result, wall seconds)."""
        params = [
            identify.Parameter(name, value * f, value * 1e-2, value * 1e2)
            for (name, value), f in zip(TRUTH.items(), factors)
        ]
        start = time.perf_counter()
        problem = identify.make_problem(self.chain, params, [self.log(seed)], noise=self.noise)
        # (the problem keeps the guesses: `fit` needs no parameter list)
        result = identify.fit(problem, estimate_noise=False, **options)
        return result, time.perf_counter() - start


@pytest.fixture(scope="module")
def arm():
    return Arm()


def rel_errors(result) -> dict:
    return {n: result.value[n] / TRUTH[n] - 1.0 for n in TRUTH}


def within_bars(result) -> bool:
    return all(abs(e) <= BARS[n] for n, e in rel_errors(result).items())


def in_ci(result) -> dict:
    return {n: bool(result.ci_low[i] <= TRUTH[n] <= result.ci_high[i]) for i, n in enumerate(result.names)}


def iterations(result) -> int:
    return sum(s.iterations for s in result.stages)


def describe(result, seconds, label="") -> str:
    errs = rel_errors(result)
    se = {n: result.std_errors[i] / TRUTH[n] for i, n in enumerate(result.names)}
    cells = "  ".join(f"{n} {100 * errs[n]:+.3f}% (SE {100 * se[n]:.3f}%)" for n in TRUTH)
    its = "+".join(str(s.iterations) for s in result.stages)
    return f"{label} {cells}  iterations {its}={iterations(result)}  {seconds:.1f} s  converged={result.converged}"


# ---------------------------------------------------------------------------
# CI-sized: recovery and far-off guesses
# ---------------------------------------------------------------------------


def test_recovery_accuracy_and_ci(arm):
    """Three seeded noisy logs, moderate guesses (+-20 %): each fit converges, recovers EI
    and hub inertia to 1 % and damping and payload to 5 % (the issue's bars at 1 % noise),
    and the reported 95 % CIs cover the truth.

    CI containment is probabilistic: with 3 x 4 = 12 intervals each covering with
    probability 0.95, P(3 or more misses) = 2 %, so we allow at most 2 misses; and no
    estimate may be more than 4 standard errors from the truth (P = 6e-5 each), which
    catches error bars that are too small by a large factor."""
    misses = []
    for seed, factors in ((1, (1.2, 0.8, 1.2, 0.8)), (2, (0.8, 1.2, 0.8, 1.2)), (3, (1.2, 1.2, 0.8, 0.8))):
        result, seconds = arm.fit(seed, factors)
        print(describe(result, seconds, f"seed {seed}:"))
        if seed == 1:
            # the standard errors come from the Levenberg-Marquardt's last linearisation
            # (`identify.fit._solve`); a Jacobian computed afresh at the optimum agrees
            fresh = fresh_covariance(result)
            assert_standard_errors_match(result, fresh)
            # and the fallback without that linearisation (block Jacobian computed afresh)
            x = parameters_module.x_from_z(result.problem, result.z.phys)
            sigma = np.asarray([result.sigma[c] for c in result.problem.channels])
            fallback, _ = jacobian_module._covariance_at(result.problem, x, result.z, sigma, result.step)
            np.testing.assert_allclose(fallback.std_errors, fresh.std_errors, rtol=1e-8)
        assert result.converged, result.summary()
        for n, e in rel_errors(result).items():
            assert abs(e) <= BARS[n], f"seed {seed}: {n} off by {100 * e:+.3f}% (bar {100 * BARS[n]:.0f}%)"
        for i, n in enumerate(result.names):
            z = (result.values[i] - TRUTH[n]) / result.std_errors[i]
            assert abs(z) <= 4.0, f"seed {seed}: {n} is {z:+.1f} standard errors from the truth"
        misses += [(seed, n) for n, ok in in_ci(result).items() if not ok]
    assert len(misses) <= 2, f"truth outside the 95% CI in {misses}"


@pytest.mark.parametrize(
    "seed, factors",
    [
        (4, (0.5, 2.0, 0.5, 2.0)),  # EI -50 %, damping +100 %, hub -50 %, payload +100 %
        (5, (2.0, 0.5, 2.0, 0.5)),  # the opposite corner
    ],
    ids=["EI-50_damp+100_hub-50_payload+100", "EI+100_damp-50_hub+100_payload-50"],
)
def test_converges_from_far_off_corner(arm, seed, factors):
    """From guesses -50 % / +100 % off on every parameter the default fit (growing horizon)
    converges to the truth within the issue's accuracy bars."""
    result, seconds = arm.fit(seed, factors)
    print(describe(result, seconds, f"corner {factors}:"))
    assert result.converged, result.summary()
    errs = rel_errors(result)
    for n, e in errs.items():
        assert abs(e) <= BARS[n], f"{n} off by {100 * e:+.3f}% (bar {100 * BARS[n]:.0f}%)\n{result.summary()}"


def test_one_start_growing_horizon_needs_the_scaled_first_damping(arm):
    """A growing horizon from a single start (no frequency initialisation), guess EI +100 %,
    damping, hub and payload -50 % (`benchmarks/bench_fit_convergence.py`, trial 8): with
    optimistix's first damping (1, an undamped Gauss-Newton step here) the short first stage
    jumps to a spurious optimum, the joint damping on its lower bound; with the scaled first
    damping (`first_damping`, the default) the fit reaches the truth within the bars."""
    options = dict(n_starts=1, max_restarts=0, frequency_init=False)
    factors = (2.0, 0.5, 0.5, 0.5)
    result, seconds = arm.fit(3008, factors, **options)
    print(describe(result, seconds, "scaled first damping:"))
    assert result.converged and within_bars(result), result.summary()
    classical, seconds = arm.fit(3008, factors, first_damping=0.0, **options)
    print(describe(classical, seconds, "optimistix's first damping:"))
    assert not within_bars(classical)
    assert classical.value["joint1.damping"] < 0.05 * TRUTH["joint1.damping"]
    # the same start plus a caller's point 20-30 % off the truth (`extra_starts`): the
    # short first stage runs from both, and the better one, the caller's, continues
    near = {"link1.EI": 1.3, "joint1.damping": 0.0065, "hub1.inertia": 0.016, "payload.mass": 0.06}
    helped, seconds = arm.fit(3008, factors, first_damping=0.0, extra_starts=[near], **options)
    print(describe(helped, seconds, "with a start near the truth:"))
    first = helped.stages[0]
    assert first.starts == 2 and first.start_costs[1] < first.start_costs[0], first
    assert helped.converged and within_bars(helped), helped.summary()


# ---------------------------------------------------------------------------
# CI-sized: a log that rests before its input (horizons from the onset)
# ---------------------------------------------------------------------------

REST_S = 3.0


def test_a_log_that_rests_before_its_input_is_fitted_from_its_onset(arm):
    """The rig sits still for 3 s before the doublets start (the scenario's input, delayed):
    the growing horizon counts from the log's onset (`identify.log_onset`), so its short
    first stages see the start of the motion, not 0.5-2 s of rest, and the frequency
    initialisation reads the spectrum of the motion. The default fit from guesses 20 % off
    recovers the four parameters within the issue's bars, in one pass of the growing horizon.

    Counted from the log's start (the code before `log_onset`), this seed's fit ended with
    joint damping -98.6 %, payload +20 % and EI +7 % (cost 4,672 for 2,100 residuals), after
    the frequency initialisation had put EI's guess at 0.45 of the truth (the spectrum's Hann
    window over the rest weighed the motion down: a 2.7 Hz peak for a 4.2 Hz mode). Over
    seeds 1-8 (guesses alternating +-20 %): 7 of 8 fits within the bars before, 8 of 8 now,
    the other seven at the same optimum."""
    # (simulated, not the scenario's log delayed: the torque is linear between samples, so
    # a log that starts at 0.05 N m is not the same input as one that rises to it from 0 in
    # the sample before; that 4 ms ramp alone, fitted as the delayed log, costs ~3,000
    # instead of ~2,100 and biases the damping by +30 %)
    t = np.arange(0.0, REST_S + T_END, DT)
    torque = doublets(t - REST_S)
    torque[t < REST_S] = 0.0
    log = identify.simulate_log(
        arm.chain, t, torque=torque, channels=CHANNELS, noise=arm.noise, rng=np.random.default_rng(5)
    )
    factors = (1.2, 0.8, 1.2, 0.8)
    params = [
        identify.Parameter(name, value * f, value * 1e-2, value * 1e2)
        for (name, value), f in zip(TRUTH.items(), factors)
    ]
    problem = identify.make_problem(arm.chain, params, [log], noise=arm.noise)
    # the torque's first change is at REST_S; it is linear between samples, so it starts
    # to change one sample before
    assert float(problem.onset[0]) == pytest.approx(REST_S - DT, abs=1e-9)
    # An early stage simulates the log from its onset (the rest skipped): the arm rests at
    # its equilibrium until the input, so by time invariance the outputs up to the stage's
    # horizon are the whole log's solve's (both adaptive, rtol 1e-10)
    y0s = residuals_module.initial_states_of(problem, jnp.zeros(0))
    truth = jnp.asarray(list(TRUTH.values()))
    early, ok_early = residuals_module.predict(problem, truth, y0s, jnp.asarray(0.3))
    whole, ok_whole = residuals_module.predict(problem, truth, y0s)
    within = np.asarray(problem.t[0]) <= REST_S - DT + 0.3
    assert bool(ok_early[0]) and bool(ok_whole[0]) and within.sum() >= round(REST_S / DT) + 70  # 0.28 s of motion
    np.testing.assert_allclose(np.asarray(early[0])[within], np.asarray(whole[0])[within], rtol=0, atol=1e-9)
    x0 = starts_module._frequency_initialise(
        problem, parameters_module.x_from_theta(problem, [p.guess for p in params]), print
    )
    assert math.exp(x0[0]) == pytest.approx(TRUTH["link1.EI"], rel=0.15)
    start = time.perf_counter()
    result = identify.fit(problem, params, estimate_noise=False)
    print(describe(result, time.perf_counter() - start, "rest then doublets:"))
    assert result.converged, result.summary()
    # the first growing-horizon pass lands (the multi-start stage and four stages; no
    # restart from another start)
    assert len(result.stages) == 5, result.stages
    for n, e in rel_errors(result).items():
        assert abs(e) <= BARS[n], f"{n} off by {100 * e:+.3f}% (bar {100 * BARS[n]:.0f}%)\n{result.summary()}"


def _rest_then(t, k_input, rng, sigma=1e-3):
    """Two channels of white noise (`sigma`) at rest, a torque that steps at sample `k_input`."""
    measured = rng.normal(0.0, sigma, (len(t), 2))
    torque = np.zeros((len(t), 1))
    torque[k_input:] = 0.05
    return measured, torque, np.array([sigma, sigma])


def test_log_onset_is_where_the_input_or_the_motion_starts():
    """`log_onset` on logs built with a known onset: the sample before the torque first
    rises (noise at rest, 600 samples at 5 standard deviations' threshold, does not trigger
    it), the sample before the motion where the log moves before its input; the first
    sample for a log driven from its first sample, for one released at its start (no input),
    and for one in which nothing happens."""
    rng = np.random.default_rng(5)
    t = 0.25 + np.arange(1000) * 4e-3
    measured, torque, sigma = _rest_then(t, 600, rng)
    measured[:, 1] += np.where(t >= t[600], 0.02 * np.sin(2 * np.pi * 4.0 * (t - t[600])), 0.0)
    assert identify.log_onset(t, torque, measured, sigma) == t[599]
    # the arm is nudged at sample 300, before the input: its motion starts the log
    measured[300:, 0] += 0.01
    assert identify.log_onset(t, torque, measured, sigma) == t[299]
    # driven from the first sample on (a doublet: the torque changes later)
    torque = np.where(t < t[500], 0.05, -0.05)[:, None]
    assert identify.log_onset(t, torque, measured, sigma) == t[0]
    # the torque rises from zero after the first sample
    torque[0] = 0.0
    assert identify.log_onset(t, torque, measured, sigma) == t[0]
    # released at the first sample, no input: a decaying oscillation from t[0]
    released = 0.3 * np.exp(-t) * np.cos(2 * np.pi * 2.0 * (t - t[0]))
    assert identify.log_onset(t, np.zeros((len(t), 1)), released[:, None], sigma[:1]) == t[0]
    # no input and no motion: nothing to skip
    measured, _, sigma = _rest_then(t, 0, rng)
    assert identify.log_onset(t, np.zeros((len(t), 1)), measured, sigma) == t[0]
    # no channel recorded: the input alone
    assert identify.log_onset(t, _rest_then(t, 600, rng)[1], np.zeros((len(t), 0)), np.zeros(0)) == t[599]


def test_the_onset_of_a_channel_given_no_noise_level_is_judged_against_its_floor():
    """Review (two-link arm): logs driven from 0.1 s got onsets at 0.012-0.018 s, the strain
    gauges' noise (no level declared: make_problem's start is 1 % of the channel's RMS,
    under the noise here) read as motion. The rest is judged against at least the log's own
    model-free floor of such a channel; the oracle is the torque's known start."""
    t = np.arange(0.0, 1.0, 2e-3)
    tau = np.where((t >= 0.1) & (t < 0.3), 0.2, 0.0)[:, None]
    noise = {"theta1": math.radians(0.01), "curvature1": 2e-3}
    log = identify.simulate_log(
        _sweep_chain(), t, torque=tau, channels=("theta1", "curvature1"), noise=noise, rng=np.random.default_rng(0)
    )
    params = [identify.Parameter("link1.EI", 2.0, 0.1, 20.0)]
    problem = identify.make_problem(_sweep_chain(), params, [log], noise={"theta1": noise["theta1"]})
    assert float(problem.sigma[problem.channels.index("curvature1")]) < noise["curvature1"]  # 1 % of the RMS
    assert float(problem.onset[0]) == pytest.approx(0.1 - 2e-3, abs=1e-9)


# ---------------------------------------------------------------------------
# CI-sized: multi-log fit
# ---------------------------------------------------------------------------


@pytest.mark.slow  # 102 s in a 2-worker run; fits of several logs sharing parameters stay in CI (test_cli's two logs,
# test_real_pendulums: the real single pendulum's identification segments)
def test_multi_log_shared_parameters():
    """Paper 000's flexible pendulum (one mode, modal damping ratio 0.02), three drop logs
    released from 0, -45 and -97 deg: EI and joint damping shared, the release angle of each
    log fitted (the logs' nominal angles are 1.5 deg off, as a protractor reading might be).
    The fit recovers the shared parameters to the issue's bars and each log's release angle.

    Error bars: a single seeded trial is within its 95 % CI only with probability 0.95 per
    quantity (this seed, 7, happens to put EI 2.1 SE low: -0.15 % with SE 0.07 %; the same
    optimum is found with LM rtol 1e-8 and a 5x finer integration grid, and the noise-free
    logs give EI and damping exact to 1e-6 %, so it is the noise). Coverage is what
    `test_coverage_50_trials` measures; here every estimate must lie within 3 standard
    errors of the truth (P = 0.997 each), which catches error bars that are too small."""
    chain = fd.rigs.flexible_pendulum(n_modes=1, damping_ratio=0.02)
    ei, damping = float(fd.get_parameter(chain, "link1.EI")), float(fd.get_parameter(chain, "joint1.damping"))
    t = np.arange(0.0, 1.0, 2e-3)
    releases = {"drop_0": 0.0, "drop_m45": -45.0, "drop_m97": -97.0}
    logs, noise = [], {"theta1": 1e-3, "tip1": 2e-6}  # pot 0.06 deg, strain-gauge tip 2 um
    rng = np.random.default_rng(7)
    for name, deg in releases.items():
        log = identify.simulate_log(
            chain,
            t,
            initial={"theta1": math.radians(deg)},
            channels=("theta1", "tip1"),
            noise=noise,
            rng=rng,
            name=name,
        )
        nominal = {"theta1": math.radians(deg + 1.5)}
        logs.append(dataclasses.replace(log, initial=nominal, fit_initial=("theta1",)))
    params = [
        identify.Parameter("link1.EI", 1.5 * ei, ei / 100, ei * 100),
        identify.Parameter("joint1.damping", 0.5 * damping, damping / 100, damping * 100),
    ]
    start = time.perf_counter()
    problem = identify.make_problem(chain, params, logs, noise=noise)
    result = identify.fit(problem, params, estimate_noise=False)
    print(result.summary(), f"\n({time.perf_counter() - start:.1f} s)")
    assert result.converged, result.summary()
    truth = {"link1.EI": ei, "joint1.damping": damping}
    for i, n in enumerate(result.names):
        err = result.values[i] / truth[n] - 1
        assert abs(err) <= BARS[n], f"{n} off by {100 * err:+.3f}%"
        z = (result.values[i] - truth[n]) / result.std_errors[i]
        assert abs(z) <= 3.0, f"{n}: {z:+.1f} standard errors from the truth\n{result.summary()}"
    assert set(result.initial_states) == set(releases)
    for name, deg in releases.items():
        value, se = result.initial_states[name]["theta1"]
        assert abs(value - math.radians(deg)) <= 3.0 * se, (name, math.degrees(value), deg, se)
        assert abs(math.degrees(value) - deg) < 0.05, (name, math.degrees(value), deg)


# ---------------------------------------------------------------------------
# CI-sized: paper 000's log-decrement damping estimate vs a full fit
# ---------------------------------------------------------------------------

G = fd.rigs.STANDARD_GRAVITY
ROD_L, ROD_M, PAYLOAD_M, HUB_I, XI_TRUE = 0.30, 0.180, 0.020, 2e-5, 1.9e-3


def amplitude_factor(A: float) -> float:
    """r(A): the per-cycle log decrement of a viscously damped (lightly) pendulum swinging
    at amplitude A, relative to its small-amplitude value. Energy E = k (1 - cos A) and
    its loss per cycle c * oint theta_dot^2 dt give d(ln A) per cycle = c oint theta_dot^2 dt
    / (k A sin A), against c pi omega_0 / k for the linear oscillator, so
    r(A) = 4 sqrt(2) int_0^A sqrt(cos u - cos A) du / (pi A sin A)  (-> 1 as A -> 0)."""
    integral = quad(lambda u: math.sqrt(max(math.cos(u) - math.cos(A), 0.0)), 0.0, A)[0]
    return 4.0 * math.sqrt(2.0) * integral / (math.pi * A * math.sin(A))


def swing_peaks(t, theta):
    """Times and amplitudes (rad, from the hanging equilibrium) of the successive maxima,
    refined by a parabola through each sampled peak and its neighbours."""
    phi = theta + math.pi / 2
    idx, _ = find_peaks(phi)
    idx = idx[(idx > 0) & (idx < len(phi) - 1)]
    a, b, c = phi[idx - 1], phi[idx], phi[idx + 1]
    shift = 0.5 * (a - c) / (a - 2 * b + c)
    return t[idx] + shift * (t[1] - t[0]), b - 0.25 * (a - c) * shift


def test_paper000_damping_full_fit_vs_log_decrement():
    """Paper 000's joint-damping estimate against a full fit.

    **What "eta" must be.** Paper 000 (section 4) writes xi = eta * xi_c with xi_c =
    rho l^2 sqrt(2 l g / 3) and calls eta "the ratio of the successive amplitudes". Taken
    literally (eta = A_{n+1}/A_n ~ 0.85) xi would be 85 % of critical damping and the
    pendulum would not swing at all, so eta must be the *damping ratio* obtained from that
    ratio. For the linear oscillator J phi'' + xi phi' + k phi = 0 with xi < xi_c = 2 sqrt(k J):
    phi = A e^{-zeta w0 t} cos(w_d t), zeta = xi / xi_c, w_d = w0 sqrt(1 - zeta^2); successive
    maxima are one damped period T_d = 2 pi / w_d apart, so the log decrement is
        delta = ln(A_n / A_{n+1}) = zeta w0 T_d = 2 pi zeta / sqrt(1 - zeta^2),
    hence
        eta = zeta = delta / sqrt(4 pi^2 + delta^2)  (~ delta / 2 pi),   xi = eta * xi_c.
    The paper's xi_c is exactly 2 sqrt(k J) of the bare uniform rod: J = rho l^3 / 3,
    k = rho l g * l / 2 (gravity stiffness at the hanging equilibrium), 2 sqrt(k J) =
    rho l^2 sqrt(2 l g / 3).

    **Why it differs from the fit, quantified.** The rig (`fd.rigs.rigid_pendulum`) also has
    the 0.020 kg payload at the tip and the 2e-5 kg m^2 hub: J = 7.22e-3 instead of 5.40e-3
    kg m^2 and k = 0.324 instead of 0.265 N m, so its true critical damping is 0.0967 N m s,
    not xi_c = 0.0756. The decrement measures the damping ratio of the real system, so
    the paper's formula returns xi * (xi_c,rod / xi_c,true) = 0.782 xi at small amplitude: 22 %
    low. At large amplitude the pendulum is nonlinear and the decrement is larger by r(A)
    (`amplitude_factor`: 1.37 at 90 deg, 1.21 at 71 deg), which happens to offset part of the
    inertia error for a drop from horizontal (the first-cycle estimate is only ~5 % low,
    drifting to ~18 % low as the swing decays). The full fit uses the exact nonlinear model
    with payload and hub and recovers xi to << 1 %. We check all three statements on
    noise-free logs (the decrement's best case) and fit the noisy log."""
    chain = fd.rigs.rigid_pendulum(joint_damping=XI_TRUE, payload_mass=PAYLOAD_M, hub_inertia=HUB_I)
    rho, l = ROD_M / ROD_L, ROD_L
    xi_c_rod = rho * l**2 * math.sqrt(2 * l * G / 3)
    J = rho * l**3 / 3 + PAYLOAD_M * l**2 + HUB_I
    k = (rho * l**2 / 2 + PAYLOAD_M * l) * G
    xi_c_true = 2 * math.sqrt(k * J)
    assert xi_c_rod == pytest.approx(2 * math.sqrt(rho * l**2 * G / 2 * rho * l**3 / 3), rel=1e-12)
    inertia_ratio = xi_c_rod / xi_c_true
    assert inertia_ratio == pytest.approx(0.782, abs=1e-3)

    t = np.arange(0.0, 8.0, 5e-3)
    estimates = {}
    for deg in (-97.0, 0.0):  # paper's Fig. 6(b) and 6(a)
        clean = identify.simulate_log(chain, t, initial={"theta1": math.radians(deg)}, channels=("theta1",))
        _, A = swing_peaks(t, clean.outputs["theta1"])
        assert len(A) >= 6
        delta = np.log(A[:-1] / A[1:])
        eta = delta / np.sqrt(4 * math.pi**2 + delta**2)
        xi_paper = eta * xi_c_rod
        # The model behind the decrement: xi_paper = xi * (xi_c,rod / xi_c,true) * r(A_mean).
        r = np.array([amplitude_factor(math.sqrt(a0 * a1)) for a0, a1 in zip(A[:-1], A[1:])])
        predicted = XI_TRUE * inertia_ratio * r
        print(
            f"release {deg:+.0f} deg: amplitudes {np.round(np.degrees(A[:6]), 2)} deg\n"
            f"  paper's xi (per cycle) {np.array2string(xi_paper[:5], precision=4)} = "
            f"{np.array2string(xi_paper[:5] / XI_TRUE, precision=4)} x truth;"
            f" predicted {np.array2string(predicted[:5] / XI_TRUE, precision=4)} x truth"
        )
        np.testing.assert_allclose(xi_paper, predicted, rtol=5e-3)
        estimates[deg] = xi_paper

    small = estimates[-97.0]
    # Small amplitude: the decrement gives the true damping ratio; the paper's xi_c makes it 22 % low.
    np.testing.assert_allclose(small / xi_c_rod, XI_TRUE / xi_c_true, rtol=5e-3)
    np.testing.assert_allclose(small / XI_TRUE, inertia_ratio, rtol=5e-3)
    large = estimates[0.0]
    assert 0.93 < large[0] / XI_TRUE < 0.96  # first cycle from horizontal: errors partly cancel
    assert np.all(np.diff(large) < 0)  # and the estimate drifts down as the swing decays

    # The full fit of the exact model on a noisy drop from horizontal (pot noise 0.1 deg),
    # starting from the paper's own (small-amplitude) estimate.
    noise = {"theta1": math.radians(0.1)}
    log = identify.simulate_log(
        chain, t, initial={"theta1": 0.0}, channels=("theta1",), noise=noise, rng=np.random.default_rng(0)
    )
    guess = float(small.mean())
    params = [identify.Parameter("joint1.damping", guess, 1e-5, 1e-1)]
    start = time.perf_counter()
    problem = identify.make_problem(chain, params, [log], noise=noise)
    result = identify.fit(problem, params, estimate_noise=False)
    print(result.summary(), f"\n({time.perf_counter() - start:.1f} s)")
    assert result.converged, result.summary()
    xi_fit = result.values[0]
    assert abs(xi_fit / XI_TRUE - 1) < 2e-3, xi_fit
    assert result.ci_low[0] <= XI_TRUE <= result.ci_high[0], result.summary()
    assert abs(xi_fit - XI_TRUE) < 0.05 * abs(guess - XI_TRUE)


# ---------------------------------------------------------------------------
# CI-sized: EI of a spinning link, with and without geometric stiffening
# ---------------------------------------------------------------------------


@pytest.mark.slow  # 70 s in CI; stiffening's dynamics stay in CI (test_chain, the stiffening notebook)
def test_ei_of_a_spinning_link_is_biased_without_geometric_stiffening():
    """Paper 002's link (two modes) spinning at a constant Omega = 2 sqrt(EI / (rho l^4))
    (17.9 rad/s) on a heavy hub, released with a 1 mm first-mode deflection; 1 s of `tip1`
    at 2 ms with 1 % noise, simulated with geometric stiffening. Fitting EI alone (plain
    single shooting from one start: the guesses are 20 % off, the cost has one minimum here):
    - with the option, the truth (1 N m^2) is inside the 95 % CI (measured 0.99998 +- 5e-5);
    - with the papers' linear model, EI comes out 38 % high, the factor the rotating-beam
      tables predict: the linear model vibrates at `omega_0(EI')^2 - Omega^2`, the data at
      `omega_out^2 - Omega^2`, so `EI' / EI = (omega_out / omega_0)^2 = (4.1373 / 3.5160)^2 =
      1.3846` (Hodges & Rutkowski 1981, lam = 2; measured 1.38486). The biased model still
      fits the frequency; what gives it away is the cost (measured 740 against 447 for 500
      residuals: the shapes and the second mode are off)."""
    L, rho, EI = 0.5, 0.2, 1.0
    speed = 2.0 * math.sqrt(EI / (rho * L**4))

    def chain(stiffening):
        link = fd.FlexibleLink(L, rho, EI, n_modes=2, geometric_stiffening=stiffening)
        return fd.Chain([link], hubs=[fd.Hub(inertia=1e6)])  # kg m^2: the spin stays constant (1e-8)

    t = np.arange(0.0, 1.0, 2e-3)
    initial = {"theta1_rate": speed, "q1_1": 1e-3}
    clean = identify.simulate_log(chain(True), t, initial=initial, channels=("tip1",))
    noise = {"tip1": 0.01 * float(np.sqrt(np.mean(clean.outputs["tip1"] ** 2)))}
    log = identify.simulate_log(
        chain(True), t, initial=initial, channels=("tip1",), noise=noise, rng=np.random.default_rng(7)
    )
    results = {}
    for stiffening, guess in ((True, 0.8), (False, 1.2)):
        params = [identify.Parameter("link1.EI", guess, 0.1, 10.0)]
        problem = identify.make_problem(chain(stiffening), params, [log], noise=noise)
        results[stiffening] = identify.fit(
            problem, params, estimate_noise=False, n_stages=1, n_starts=1, max_restarts=0, frequency_init=False
        )
        assert results[stiffening].converged, results[stiffening].summary()
    right, linear = results[True], results[False]
    assert right.ci_low[0] <= EI <= right.ci_high[0], right.summary()
    assert linear.value["link1.EI"] == pytest.approx(EI * (4.1373 / 3.5160153) ** 2, rel=2e-3)
    # the model check `identify diagnose` reports (identify.evidence) flags the fitted linear
    # model at this spin and predicts its bias from first-order perturbation theory (Southwell's
    # coefficient): 1.3861 against the 1.38486 fitted here
    (check,) = identify.evidence.stiffening_checks(linear.chain, {"link1": speed})
    assert check["flagged"], check
    assert check["ei_bias_factor"] == pytest.approx(linear.value["link1.EI"] / EI, rel=3e-3), check
    assert identify.evidence.stiffening_checks(right.chain, {"link1": speed}) == []  # it has the option
    n = right.n_residuals
    assert right.cost < n + 4 * math.sqrt(2 * n) and linear.cost > right.cost + 100, (right.cost, linear.cost)


# ---------------------------------------------------------------------------
# Slow: the statistical versions
# ---------------------------------------------------------------------------


def _table(rows) -> str:
    head = f"{'trial':>5} {'seed':>4} {'guess factors':>24} " + " ".join(f"{n:>16}" for n in TRUTH)
    head += f" {'iters':>11} {'s':>6} {'ok':>3}"
    lines = [head]
    for r in rows:
        f = " ".join(f"{x:.2f}" for x in r["factors"])
        errs = " ".join(f"{100 * r['err'][n]:+8.3f}%{'' if r['in_ci'][n] else '*':1}{'':6}" for n in TRUTH)
        lines.append(
            f"{r['trial']:>5} {r['seed']:>4} {f:>24} {errs} {r['iters_str']:>11} {r['seconds']:6.1f} "
            f"{'yes' if r['ok'] else 'NO':>3}"
        )
    return "\n".join(lines)


def _trial_row(trial, seed, factors, result, seconds):
    return {
        "trial": trial,
        "seed": seed,
        "factors": factors,
        "err": rel_errors(result),
        "in_ci": in_ci(result),
        "iters": iterations(result),
        "iters_str": "+".join(str(s.iterations) for s in result.stages),
        "seconds": seconds,
        "converged": result.converged,
        "ok": result.converged and within_bars(result),
    }


@pytest.mark.slow
def test_coverage_50_trials(arm):
    """50 seeded noisy logs, guesses within +-20 % (log-uniform): each parameter's 95 % CI
    covers the truth in >= 90 % of the trials, and >= 95 % of the trials recover every
    parameter within the issue's bars (1 % EI/hub, 5 % damping/payload). The table marks
    CI misses with '*'."""
    rng = np.random.default_rng(20261123)
    rows = []
    for trial in range(50):
        seed = 1000 + trial
        factors = tuple(float(f) for f in np.exp(rng.uniform(math.log(0.8), math.log(1.25), size=4)))
        result, seconds = arm.fit(seed, factors)
        rows.append(_trial_row(trial, seed, factors, result, seconds))
        print(describe(result, seconds, f"trial {trial:2d} seed {seed}:"), flush=True)
    print(_table(rows))
    coverage = {n: np.mean([r["in_ci"][n] for r in rows]) for n in TRUTH}
    accurate = np.mean([r["ok"] for r in rows])
    print("coverage of the 95% CI:", {n: f"{100 * c:.0f}%" for n, c in coverage.items()})
    print(f"within the accuracy bars: {100 * accurate:.0f}%; converged: {sum(r['converged'] for r in rows)}/50")
    print("iterations: median", np.median([r["iters"] for r in rows]), "max", max(r["iters"] for r in rows))
    for n, c in coverage.items():
        assert c >= 0.90, f"{n}: 95% CI covered the truth in only {100 * c:.0f}% of 50 trials"
    assert accurate >= 0.95, f"only {100 * accurate:.0f}% of trials within the accuracy bars"


@pytest.mark.slow
def test_coverage_on_the_elastic_two_link_arm():
    """Paper 004's arm (two flexible links of two modes, elastic joints of 100 N m/rad, joint
    damping 0.05 / 0.02 N m s), six parameters (both stiffnesses, both EIs, both dampings)
    fitted to hub angles and tip deflections of two 2 s logs at 500 Hz, 20 seeds, guesses
    20 % high. Each 95 % interval is a white-noise one: over the 120 intervals the misses
    follow Binomial(120, 0.05) (mean 6; 15 or more has P = 0.001), and the z-scores of each
    parameter scatter with a standard deviation near 1. Review (2026-12-05, one seed): 3 of
    6 intervals missed on a layout like this one; over 30 seeds of this one 9 of 180 missed
    (5.0 %), z standard deviations 0.86-1.01, the same z at a 5x finer step."""
    truth = fd.with_parameters(
        fd.rigs.flexible_link_joint_arm(joint_stiffness=100.0, n_modes=2),
        {"joint1.damping": 0.05, "joint2.damping": 0.02},
    )
    values = {
        "joint1.stiffness": 100.0,
        "joint2.stiffness": 100.0,
        "link1.EI": 1.0,
        "link2.EI": 1.0,
        "joint1.damping": 0.05,
        "joint2.damping": 0.02,
    }
    params = [identify.Parameter(n, v * 1.2, v / 10, v * 10) for n, v in values.items()]
    noise = {"theta1": 1e-3, "theta2": 1e-3, "tip1": 1e-4, "tip2": 1e-4}
    t = np.arange(1001) / 500.0
    zs = []
    for seed in range(100, 120):
        rng = np.random.default_rng(seed)
        logs = []
        for k, (a1, a2, w) in enumerate(((0.3, 0.1, 0.4), (-0.2, 0.15, 0.3))):
            tq1 = np.where(t < w, a1, np.where(t < 2 * w, -a1, 0.0))
            tq2 = np.where(t < 1.5 * w, a2, np.where(t < 3 * w, -a2, 0.0))
            logs.append(
                identify.simulate_log(
                    truth,
                    t,
                    torque=np.stack([tq1, tq2], axis=1),
                    channels=tuple(noise),
                    noise=noise,
                    rng=rng,
                    name=f"log{k}",
                )
            )
        problem = identify.make_problem(truth, params, logs, noise)
        result = identify.fit(problem, estimate_noise=False, n_starts=1, frequency_init=False)
        assert result.converged, result.summary()
        zs.append([(v - values[n]) / s for n, v, s in zip(result.names, result.values, result.std_errors)])
        print(f"seed {seed}: z", np.round(zs[-1], 2), flush=True)
    zs = np.asarray(zs)
    misses = int(np.sum(np.abs(zs) > 1.96))
    print(f"misses {misses} of {zs.size}; z sd per parameter {np.round(zs.std(axis=0, ddof=1), 2)}")
    assert misses < 15, f"{misses} of {zs.size} 95 % intervals missed the truth"
    # the standard deviation of 20 N(0, 1) z-scores is outside [0.55, 1.55] with P = 0.002
    # (chi-square, 19 degrees of freedom): ~1 % for any of the six
    for n, sd in zip(result.names, zs.std(axis=0, ddof=1)):
        assert 0.55 <= sd <= 1.55, f"{n}: z-scores scatter with sd {sd:.2f}"


@pytest.mark.slow
def test_far_off_guess_convergence(arm):
    """24 seeded trials from far-off guesses: the 16 corners of [-50 %, +100 %]^4 (every
    parameter at -50 % or +100 %) and 8 guesses drawn log-uniformly in [0.5, 2] x truth.
    >= 95 % must converge to within the accuracy bars; iteration counts are printed."""
    rng = np.random.default_rng(99)
    guesses = [tuple(2.0 if (c >> j) & 1 else 0.5 for j in range(4)) for c in range(16)]
    guesses += [tuple(float(f) for f in 2.0 ** rng.uniform(-1, 1, size=4)) for _ in range(8)]
    rows = []
    for trial, factors in enumerate(guesses):
        seed = 2000 + trial
        result, seconds = arm.fit(seed, factors)
        rows.append(_trial_row(trial, seed, factors, result, seconds))
        print(describe(result, seconds, f"trial {trial:2d} guess {factors}:"), flush=True)
    print(_table(rows))
    rate = np.mean([r["ok"] for r in rows])
    its = [r["iters"] for r in rows]
    print(f"converged within the bars: {sum(r['ok'] for r in rows)}/{len(rows)} ({100 * rate:.0f}%)")
    print(f"iterations: min {min(its)}, median {np.median(its):.0f}, max {max(its)}")
    assert rate >= 0.95, f"only {100 * rate:.0f}% of far-off guesses converged"


@pytest.mark.slow  # 64 s in a 2-worker run: a check of compile reuse, not of a result
def test_problems_differing_only_in_their_log_names_share_compiled_programs():
    """The logs' names are labels (`_LogLabels`): two problems that differ only in them
    trace a jitted function once; a different number of logs traces again. A fit of the
    second problem reports its own names (nothing built from names is cached)."""
    import equinox as eqx
    import jax.numpy as jnp

    from identify._model.synthetic import simulate_log

    chain = fd.rigs.rigid_pendulum()
    t = np.arange(101) / 100.0
    truth = fd.with_parameters(chain, {"joint1.damping": 2e-3})
    log = simulate_log(truth, t, initial={"theta1": 0.3}, channels=("theta1",), fit_initial=("theta1",))

    def logs(*names):
        return [dataclasses.replace(log, name=n) for n in names]

    params = [identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1)]
    pa = identify.make_problem(chain, params, logs("drop_a"), {"theta1": 1e-3})
    pb = identify.make_problem(chain, params, logs("drop_b"), {"theta1": 1e-3})
    assert pa.log_names == ("drop_a",) and pb.log_names == ("drop_b",)
    traced = []
    f = eqx.filter_jit(lambda p: (traced.append(1), jnp.sum(p.t))[1])
    f(pa), f(pb)
    assert len(traced) == 1
    f(identify.make_problem(chain, params, logs("a", "b"), {"theta1": 1e-3}))
    assert len(traced) == 2
    ra = identify.fit(pa, params, n_stages=1, estimate_noise=False)
    rb = identify.fit(pb, params, n_stages=1, estimate_noise=False)
    assert list(ra.initial_states) == ["drop_a"] and list(rb.initial_states) == ["drop_b"]
    assert list(identify.fitted_outputs(rb)) == ["drop_b"]
    assert rb.values[0] == pytest.approx(2e-3, rel=1e-4)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("fit_initial", ("theta1", "theta1_rate", "theta1"), "fit_initial lists 'theta1' more than once"),
        ("offsets", ("theta1", "theta1"), "offsets lists 'theta1' more than once"),
        ("fit_initial", ("q1_1",), "fit_initial entry 'q1_1' is not one of"),
    ],
)
def test_make_problem_rejects_bad_nuisances_naming_the_log(field, value, message):
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="drop_7", **{field: value})
    with pytest.raises(ValueError, match=f"log 'drop_7': {message}"):
        identify.make_problem(chain, [identify.Parameter("joint1.damping", 1e-3)], [log], {"theta1": 1e-3})


def _nan_at(values, i):
    values = np.array(values, dtype=float)
    values[i] = np.nan
    return values


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"t": np.r_[0.0, 0.01, 0.01, np.arange(3, 11) / 100.0]}, r"t must be strictly increasing; t\[2\] = 0.01 s"),
        ({"t": _nan_at(np.arange(11) / 100.0, 4)}, r"t\[4\] is nan"),
        (
            {"outputs": {"theta1": _nan_at(np.zeros(11), 3)}},
            r"outputs\['theta1'\] is not finite at sample 3 \(t = 0.03 s\)",
        ),
        ({"outputs": {"theta1": np.zeros(9)}}, r"outputs\['theta1'\] has shape \(9,\); expected \(11,\)"),
        ({"torque": _nan_at(np.zeros(11), 5)}, r"torque is not finite at sample 5"),
        ({"torque": np.zeros(10)}, r"torque has shape \(10,\)"),
        ({"outputs": {}}, r"no output channels"),
    ],
)
def test_make_problem_checks_log_data_naming_the_log(change, message):
    """Found in review: a LogData built in Python skipped the CSV loader's checks, and the
    fit failed far from the cause ("SVD did not converge" for a NaN output)."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    log = identify.LogData(**{"t": t, "outputs": {"theta1": 0.01 * t}, "name": "drop_7", **change})
    with pytest.raises(ValueError, match=f"log 'drop_7': {message}"):
        identify.make_problem(chain, [identify.Parameter("joint1.damping", 1e-3)], [log], {"theta1": 1e-3})


def test_make_problem_warns_of_a_log_sampled_below_one_hertz():
    """Review: a log whose times were in ms, read as s (0.2 Hz over 4,000 s), stalled a
    Python fit for minutes without a word (the command line refuses it)."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) * 5.0
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="drop_7")
    with pytest.warns(UserWarning, match=r"log 'drop_7': sampled at 0.2 Hz over 50 s.*in milliseconds"):
        identify.make_problem(chain, [identify.Parameter("joint1.damping", 1e-3)], [log], {"theta1": 1e-3})


def test_make_problem_warns_of_a_log_that_shows_no_motion():
    """Review: a pendulum hanging still for 5 s was fitted without a word, "converged",
    and gave its hub inertia a 95 % interval from the noise alone. A log is at rest when
    every channel's spread about its mean is within `AT_REST` noise floors (white noise
    alone: 1); a swing of 100 noise standard deviations is not."""
    chain = fd.rigs.rigid_pendulum()
    rng = np.random.default_rng(3)
    t = np.arange(500) / 100.0
    noise = 1e-3 * rng.standard_normal(t.size)
    still = identify.LogData(t=t, outputs={"theta1": -np.pi / 2 + noise}, name="hanging")
    swing = identify.LogData(t=t, outputs={"theta1": -np.pi / 2 + 0.1 * np.sin(6.5 * t) + noise}, name="swing")
    params = [identify.Parameter("hub1.inertia", 4e-5)]
    identify.make_problem(chain, params, [swing], {"theta1": 1e-3})  # (pytest turns a warning into an error)
    with pytest.warns(UserWarning, match=r"log 'hanging' shows no motion above its noise \(theta1 0.05\d+ deg RMS"):
        identify.make_problem(chain, params, [swing, still], {"theta1": 1e-3})
    # a dead sensor reading exactly zero under a torque: at rest, and the static-test hint
    dead = identify.LogData(t=t, outputs={"theta1": np.zeros_like(t)}, torque=np.full(t.size, 0.01), name="dead")
    with pytest.warns(UserWarning, match=r"log 'dead' shows no motion.*a static test under load determines only"):
        identify.make_problem(chain, params, [dead], {"theta1": 1e-3})


def test_a_declared_resolution_puts_a_quantised_logs_fit_quality_at_one():
    """The finding on a geared servo rig, simulated: a pendulum's slow swing (0.1 rad,
    about 16 counts) read by a 1024-count encoder at 1 kHz, moving at most 0.1 count per
    sample, and rounded to the count q. The fitted model follows the swing, so its residual
    is the rounding error, RMS q / sqrt(12) (the oracle: uniform quantisation noise,
    Widrow & Kollar 2008, measured here on the simulated samples). Without the declared
    resolution the floor is the staircase's (2.3x below that) and the fit is called poor;
    with `Sensor.resolution = q` the floor is q / sqrt(12) and the ratio is 1 within 2 %.
    The damping is recovered either way (the truth, 1.9e-3 N m s/rad, within 1 %)."""
    from identify._data import measurement as meas

    rig = fd.rigs.rigid_pendulum()
    q = 2 * math.pi / 1024
    t = np.arange(0.0, 3.0, 1e-3)
    start = {"theta1": -math.pi / 2 + 0.1}
    log = identify.simulate_log(rig, t, initial=start, name="swing")
    exact = np.asarray(log.outputs["theta1"])
    counts = q * np.round(exact / q)
    quantisation = float(np.std(counts - exact))
    assert quantisation == pytest.approx(q / math.sqrt(12), rel=0.01)
    assert np.max(np.abs(np.diff(exact))) < 0.11 * q
    log = dataclasses.replace(log, outputs={"theta1": counts})
    params = [identify.Parameter("joint1.damping", 3e-3, 1e-6, 1.0)]
    quality = {}
    for declared in (None, meas.Measurement({"theta1": meas.Sensor(resolution=q)})):
        problem = identify.make_problem(rig, params, [log], {"theta1": q / math.sqrt(12)}, measurement=declared)
        result = identify.fit(problem, params, estimate_noise=False, frequency_init=False)
        assert result.values[0] == pytest.approx(float(rig.joints[0].damping), rel=0.01)
        assert result.fit_quality["theta1"]["residual_rms"] == pytest.approx(quantisation, rel=0.01)
        quality[declared is not None] = result.fit_quality["theta1"]
    assert quality[False]["ratio"] > 2.0 and quality[False]["poor"]  # measured 2.26
    assert quality[True]["noise_floor"] == pytest.approx(q / math.sqrt(12), rel=1e-12)
    assert quality[True]["ratio"] == pytest.approx(1.0, abs=0.02) and not quality[True]["poor"]


def test_a_log_that_moves_by_a_count_is_at_rest_against_its_declared_resolution():
    """A hanging pendulum whose encoder (4096 counts) flickers between neighbouring counts
    (0.7 count of slow sway): its spread, 0.67 count, is far above the staircase's floor,
    so it reads as motion; against the declared step's noise, q / sqrt(12) = 0.29 count
    (3 floors: 0.87 count), it is at rest."""
    from identify._data import measurement as meas

    chain, q = fd.rigs.rigid_pendulum(), 2 * np.pi / 4096
    t = np.arange(500) / 100.0
    counts = q * np.round((-np.pi / 2 + 0.7 * q * np.sin(2.0 * t)) / q)
    log = identify.LogData(t=t, outputs={"theta1": counts}, name="flicker")
    params = [identify.Parameter("hub1.inertia", 4e-5)]
    identify.make_problem(chain, params, [log], {"theta1": 1e-3})  # (a warning would be an error)
    encoder = meas.Measurement({"theta1": meas.Sensor(resolution=q)})
    with pytest.warns(UserWarning, match=r"log 'flicker' shows no motion .* noise floor 0.0254 deg"):
        identify.make_problem(chain, params, [log], {"theta1": 1e-3}, measurement=encoder)


def test_make_problem_refuses_two_logs_of_one_name_and_a_bad_noise():
    """Found in review: two logs named alike were accepted and one's fitted initial state
    was lost from `result.initial_states` (a dict by name)."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="drop_7")
    params = [identify.Parameter("joint1.damping", 1e-3)]
    with pytest.raises(ValueError, match="two logs are named 'drop_7'"):
        identify.make_problem(chain, params, [log, log], {"theta1": 1e-3})
    with pytest.raises(ValueError, match=r"noise\['theta1'\] expected a standard deviation > 0"):
        identify.make_problem(chain, params, [log], {"theta1": -1e-3})


def test_parameter_lists_noise_channels_and_fit_arguments_checked():
    """Review (Python fit API): a parameter listed twice was fitted twice and `value` kept
    one; lower > upper read "guess not inside bounds"; noise for a channel name that does
    not exist was dropped in silence; `fit` with other parameters than the problem's read
    their guesses by position; a torque of the wrong shape was said to need (T, T)."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="drop_7")
    P = identify.Parameter
    with pytest.raises(ValueError, match=r"free parameter\(s\) 'joint1.damping' listed more than once"):
        identify.make_problem(chain, [P("joint1.damping", 1e-3), P("joint1.damping", 2e-3)], [log], {"theta1": 1e-3})
    with pytest.raises(ValueError, match=r"'joint1.damping': lower bound 2.0 is not below the upper bound 0.5"):
        identify.make_problem(chain, [P("joint1.damping", 1.0, 2.0, 0.5)], [log], {"theta1": 1e-3})
    with pytest.raises(ValueError, match=r"make_problem: noise: output channel 'theta'.*the logs record \['theta1'\]"):
        identify.make_problem(chain, [P("joint1.damping", 1e-3)], [log], {"theta1": 1e-3, "theta": 1.0})
    problem = identify.make_problem(chain, [P("joint1.damping", 1e-3)], [log], {"theta1": 1e-3})
    # the problem keeps its parameters (guesses and bounds, SI) for `fit(problem)`
    given = [P("joint1.damping", 1e-3, 1e-6, 0.1), P("hub1.inertia", 2e-5), P("gravity[0]", 0.1, -1.0)]
    kept = identify.make_problem(chain, given, [log], {"theta1": 1e-3}).parameters
    assert [(p.name, p.guess) for p in kept] == [(p.name, p.guess) for p in given]
    for p, q in zip(kept, given):  # (a positive one's bounds pass through its log: exact to rounding)
        for a, b in ((p.lower, q.lower), (p.upper, q.upper)):
            assert (a is None and b is None) or a == pytest.approx(b, rel=1e-14), (p, q)
    for call in (identify.fit, identify.fit_independent):
        with pytest.raises(
            ValueError, match=r"parameters \['hub1.inertia'\] are not the problem's \['joint1.damping'\]"
        ):
            call(problem, [P("hub1.inertia", 1e-4)])
    bad = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, torque=np.zeros((1, 11)), name="drop_8")
    with pytest.raises(ValueError, match=r"torque has shape \(1, 11\); expected \(11,\) or \(11, n_joints\)"):
        identify.make_problem(chain, [P("joint1.damping", 1e-3)], [bad], {"theta1": 1e-3})
    with pytest.raises(
        ValueError, match=r"simulate_log: noise: output channel 'theta'.*this log records \('theta1',\)"
    ):
        identify.simulate_log(chain, t, channels=("theta1",), noise={"theta": 1e-3})


def test_fit_independent_names_the_logs_whose_nuisances_differ():
    """Found in review: "every log must estimate the same initial-state entries and
    offsets", naming neither the logs nor the entries."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    logs = [
        identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="a", fit_initial=("theta1",)),
        identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="b", fit_initial=("theta1", "theta1_rate")),
    ]
    params = [identify.Parameter("joint1.damping", 1e-3)]
    problem = identify.make_problem(chain, params, logs, {"theta1": 1e-3})
    with pytest.raises(
        ValueError, match=r"log 'a' has fit_initial \['theta1'\], log 'b' has \['theta1', 'theta1_rate'\]"
    ):
        identify.fit_independent(problem, params)


def _tiny_problem():
    """A rigid pendulum's 11-sample log and its joint damping free: for argument checks."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(11) / 100.0
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, name="drop_7")
    params = [identify.Parameter("joint1.damping", 1e-3)]
    problem = identify.make_problem(chain, params, [log], {"theta1": 1e-3})
    return problem, params


@pytest.mark.parametrize("value", [-1e-3, float("nan"), float("inf")])
def test_fit_rejects_a_bad_first_damping(value):
    problem, params = _tiny_problem()
    with pytest.raises(ValueError, match="first_damping must be a finite number >= 0"):
        identify.fit(problem, params, first_damping=value)
    with pytest.raises(ValueError, match="first_damping must be a finite number >= 0"):
        identify.fit_independent(problem, params, first_damping=value)


@pytest.mark.parametrize(
    ("start", "message"),
    [
        ({"joint1.stiffness": 10.0}, r"extra_starts\[0\] names \['joint1.stiffness'\], which are not free"),
        ({"joint1.damping": -1e-3}, r"extra_starts\[0\]: joint1.damping = -0.001 is not a finite value inside"),
        ({"joint1.damping": float("nan")}, r"extra_starts\[0\]: joint1.damping = nan is not a finite value"),
    ],
)
def test_fit_rejects_a_bad_extra_start_by_name(start, message):
    problem, params = _tiny_problem()
    with pytest.raises(ValueError, match=message):
        identify.fit(problem, params, extra_starts=[start])


def test_dx_dz_is_the_derivative_of_the_bound_transform():
    """`dx_dz` (host-side, for the standard errors) against `jax.jacfwd` of `x_from_z`,
    for each kind of bound: both finite, lower only, upper only, none."""
    import types

    import jax
    import jax.numpy as jnp

    problem = types.SimpleNamespace(
        lower=jnp.asarray([-1.0, 0.5, -np.inf, -np.inf]), upper=jnp.asarray([3.0, np.inf, 2.0, np.inf])
    )
    for z in (np.array([0.3, -1.2, 0.7, 5.0]), np.array([-30.0, 40.0, -40.0, -2.0])):
        exact = np.diag(np.asarray(jax.jacfwd(lambda z_: parameters_module.x_from_z(problem, z_))(jnp.asarray(z))))
        np.testing.assert_allclose(parameters_module.dx_dz(problem, z), exact, rtol=1e-12, atol=0.0)


def test_standard_errors_fall_back_to_a_fresh_jacobian_when_the_last_solve_saw_part_of_the_log(arm):
    """The last linearisation stands for the full Jacobian only when its horizon covers every
    sample and no parameter is pressed against a bound; otherwise `_natural_blocks` declines
    it. It reports a log whose simulation
    failed at the optimum (its residuals all `FAILED_RESIDUAL`) instead of using it."""
    params = [identify.Parameter(n, v, v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    problem = identify.make_problem(arm.chain, params, [arm.log(1)], noise=arm.noise)
    n = problem.t.shape[1] * len(problem.channels)
    z = Variables(offset=np.zeros(0), phys=np.zeros(len(params)), y0=np.zeros(0))
    lin = (np.ones((1, n)), np.ones((1, n, len(params))), np.zeros((1, n, 0)))
    full = float(problem.t[0, -1] - problem.t[0, 0])
    assert jacobian_module._natural_blocks(problem, z, lin, full) is not None
    assert jacobian_module._natural_blocks(problem, z, lin, 0.5 * full) is None
    # a parameter pressed against a bound: d x / d z from the logistic has lost digits
    near_bound = dataclasses.replace(z, phys=np.array([0.0, 16.0, 0.0, 0.0]))
    assert jacobian_module._natural_blocks(problem, near_bound, lin, full) is None
    failed = (np.full((1, n), residuals_module.FAILED_RESIDUAL), *lin[1:])
    with pytest.raises(RuntimeError, match="the simulation at the fitted parameters failed"):
        jacobian_module._natural_blocks(problem, z, failed, full)


@pytest.mark.parametrize("budget", [{"max_steps": 0}, {"early_max_steps": 0}, {"max_steps": 2.5}])
def test_fit_rejects_an_iteration_budget_below_one(budget):
    problem, params = _tiny_problem()
    (name,) = budget
    with pytest.raises(ValueError, match=f"fit: {name} expected a whole number of Levenberg-Marquardt steps >= 1"):
        identify.fit(problem, params, **budget)


def test_a_stage_step_is_at_most_the_torque_sample_interval():
    """`aligned_step` caps a stage's constant step at the torque's sample interval: the mean
    adaptive step of a log that rests before its input (0.10-0.33 s measured on a 4 ms log,
    8-27x the stiffest mode's stability limit) must not become the grid; a shorter step
    is shortened to divide the interval."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(101) * 4e-3
    torque = np.where(t >= 0.3, 0.01, 0.0)[:, None]
    log = identify.LogData(t=t, outputs={"theta1": 0.01 * t}, torque=torque, name="rest_then_step")
    params = [identify.Parameter("joint1.damping", 1e-3)]
    problem = identify.make_problem(chain, params, [log], {"theta1": 1e-3})
    assert float(steps_module.aligned_step(problem, 0.33)) == pytest.approx(4e-3, rel=1e-12)
    assert float(steps_module.aligned_step(problem, 1.5e-3)) == pytest.approx(4e-3 / 3, rel=1e-12)


def test_a_simulation_that_runs_out_of_steps_is_named_with_the_values_where_it_failed():
    """Review: a fit whose simulation failed said only "the simulation at the current
    parameters failed". A solver budget of 3 steps cannot cover a 0.4 s swing of the
    pendulum (its adaptive solver takes ~20): `SimulationFailed` names the log, the step
    limit, the horizon and the parameter values."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 0.4, 1e-2)
    log = identify.simulate_log(chain, t, initial={"theta1": 0.3}, channels=("theta1",), name="swing")
    params = [identify.Parameter("joint1.damping", 2e-3, 1e-6, 1e-1)]
    problem = identify.make_problem(chain, params, [log], {"theta1": 1e-3}, max_steps=3)
    with pytest.raises(identify.SimulationFailed) as info:
        identify.fit(problem, params, n_stages=1, frequency_init=False)
    e = info.value
    assert e.values == {"joint1.damping": pytest.approx(2e-3, rel=1e-12)}
    assert list(e.logs) == ["swing"] and "limit of 3 steps" in e.logs["swing"]
    assert "log 'swing'" in str(e) and "joint1.damping = 0.002" in str(e)
    assert e.horizon_s == pytest.approx(float(t[-1] - problem.onset[0]), rel=1e-12)  # one stage: the whole log


# A local optimum of the 3 s, 1.5 Hz sine-driven log below (seed 1): where `fit_independent`
# ended, 'converged', from guesses EI x6 and the others 20 % off without the frequency
# initialisation (tests/identify/test_frequency_init.py). Its residual is 3.3 (theta1) and
# 8.5 (tip1) times the model-free noise floor; the right basin's are 0.99 and 0.98.
WRONG_BASIN = {"link1.EI": 1.68, "joint1.damping": 0.00526, "hub1.inertia": 0.00279, "payload.mass": 0.118}


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
@pytest.mark.parametrize("restart", [True, False, "fails"])
def test_a_fit_that_ends_in_a_wrong_basin_restarts_from_the_next_start(arm, monkeypatch, restart):
    """The growing horizon from the best start is sent to a wrong basin (its first attempt
    starts at `WRONG_BASIN` and fits the full log, where it stays): the residuals are
    several times the noise floor, so `fit` grows the horizon again from the next-best
    start and ends within the issue's bars with residuals at the floor. With
    `restart_poor_fit=False` it keeps the wrong basin and reports it: `poor_fit` names
    both channels and the summary warns. A restart whose simulation fails (walked into a
    stiff region, found on a real log: the whole fit exited 1) leaves the first attempt as
    the result, with a note naming the failure."""
    t = np.arange(0.0, 3.0, DT)
    log = identify.simulate_log(
        arm.chain,
        t,
        torque=(0.05 * np.sin(2 * np.pi * 1.5 * t))[:, None],
        channels=CHANNELS,
        noise=arm.noise,
        rng=np.random.default_rng(1),
    )
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), (1.2, 0.8, 1.2, 0.8))]
    problem = identify.make_problem(arm.chain, params, [log], noise=arm.noise)
    grow, attempts = fit_module._grow, []

    def first_attempt_in_the_wrong_basin(problem, z, sigma, horizons, *rest):
        if not attempts:
            x = parameters_module.x_from_theta(problem, [WRONG_BASIN[n] for n in problem.names])
            z, horizons = (
                dataclasses.replace(z, phys=jnp.asarray(parameters_module.z_from_x(problem, x))),
                horizons[-1:],
            )
        attempts.append(1)
        if restart == "fails" and len(attempts) == 2:
            raise steps_module.SimulationFailed("stand-in: step limit at t = 1.2 s", horizon_s=3.0, values={}, logs={})
        return grow(problem, z, sigma, horizons, *rest)

    monkeypatch.setattr(fit_module, "_grow", first_attempt_in_the_wrong_basin)
    said = []
    result = identify.fit(
        problem,
        params,
        estimate_noise=False,
        frequency_init=False,
        restart_poor_fit=bool(restart),
        progress=said.append,
    )
    print(result.summary())
    ratios = {c: q["ratio"] for c, q in result.fit_quality.items()}
    if restart == "fails":
        failed = "the restart from the first stage's optimum #2 failed (stand-in: step limit at t = 1.2 s)"
        assert len(attempts) == 2 and result.failed_restarts == [failed], result.failed_restarts
        assert result.value["payload.mass"] == pytest.approx(WRONG_BASIN["payload.mass"], rel=0.05)
        assert f"note: {failed}; the result is the best attempt that finished" in result.summary()
        assert result.to_dict()["failed_restarts"] == [failed]
    elif restart:
        assert len(attempts) == 2 and any("times the noise floor: growing the horizon again" in m for m in said), said
        assert within_bars(result), result.summary()
        assert result.poor_fit == [] and all(0.8 < r < 1.2 for r in ratios.values()), ratios
    else:
        assert len(attempts) == 1
        assert result.value["payload.mass"] == pytest.approx(WRONG_BASIN["payload.mass"], rel=0.05)
        assert result.poor_fit == ["theta1", "tip1"] and all(r > 3 for r in ratios.values()), ratios
        assert "estimated from the data alone" in result.summary()


def test_restarts_skip_the_multi_start_stages_repeated_optima():
    """`bench_fit_convergence.py`'s trial 14 (noise seed 3014, guesses EI, damping, hub x2,
    payload x0.5), multi-start without the frequency initialisation: 7 of the 8 starts end at
    one short-horizon optimum (cost 76.7302), which grows into a wrong basin (joint damping
    on its lower bound, EI +7 %, payload +20 %). The restarts used to take the next-best
    starts, i.e. the same optimum twice more, and the fit ended there; they now take the
    next distinct optima (`_distinct`: cost 76.88), and the fit ends within the bars."""
    costs = np.array([76.7302, 76.7302001, 76.88, 2688.0, np.inf])
    zs = [{"phys": np.full(2, float(k))} for k in range(5)]
    assert [float(z["phys"][0]) for z in starts_module._distinct(zs, costs)] == [0.0, 2.0, 3.0]
    chain = arm_chain()
    t = np.arange(0.0, T_END, DT)
    clean = identify.simulate_log(chain, t, torque=doublets(t), channels=CHANNELS)
    noise = {c: 0.01 * float(np.sqrt(np.mean(v**2))) for c, v in clean.outputs.items()}
    log = identify.simulate_log(
        chain, t, torque=doublets(t), channels=CHANNELS, noise=noise, rng=np.random.default_rng(3014)
    )
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), (2, 2, 2, 0.5))]
    problem = identify.make_problem(chain, params, [log], noise=noise)
    said = []
    result = identify.fit(problem, params, estimate_noise=False, frequency_init=False, progress=said.append)
    print("\n".join(said), result.summary(), sep="\n")
    assert any("optimum #2" in m for m in said), said
    assert result.converged and within_bars(result), result.summary()


def test_a_poor_fit_says_why_it_was_not_restarted():
    """Review: a poor fit (residual 16-180x the floor) whose starts all ended at one cost
    left no trace of whether the documented restart had run. A pendulum log with an
    unfitted 0.02 rad sensor offset (20x its noise) stays poor from any start."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 1.0, 1e-2)
    log = identify.simulate_log(
        chain, t, initial={"theta1": 0.3}, channels=("theta1",), noise={"theta1": 1e-3},
        rng=np.random.default_rng(2), true_offsets={"theta1": 0.02}, name="offset",
    )  # fmt: skip
    params = [identify.Parameter("joint1.damping", 2e-3, 1e-6, 1e-1)]
    problem = identify.make_problem(chain, params, [log], {"theta1": 1e-3})
    said = []
    result = identify.fit(problem, params, n_starts=1, n_stages=1, frequency_init=False, progress=said.append)
    assert result.poor_fit == ["theta1"], result.summary()
    (line,) = [m for m in said if "not restarted" in m]
    assert "times the noise floor; not restarted: no other start (n_starts=1 and no extra starts)" in line, line


def test_parameters_the_data_see_only_in_combination_have_no_interval():
    """A pendulum's free swing shows its rotary inertia about the pivot `J = I + m c^2` only
    through `m g c / J` (the frequency) and `d / J` (the decay). With the mass known and
    `c`, `I`, `d` all free, one combination of the three is invisible: each is undetermined
    (infinite standard error, "not determined" interval, a warning saying so), where the
    pseudo-inverse alone gave each a small finite error (seen on the real pendulum: two
    fits of the same data 1000 of those errors apart). Oracle: the two combinations the
    data do see, recovered at their true values (closed form above)."""
    m, g = 0.15, 9.81
    chain = fd.Chain([fd.RigidLink(0.3, m, com=0.15, inertia=1e-4)], gravity=(0.0, -g))
    truth = {"link1.com": 0.14, "link1.inertia": 1.3e-4, "joint1.damping": 3e-4}
    t = np.arange(0.0, 4.0, 0.01)
    log = identify.simulate_log(
        fd.with_parameters(chain, truth), t, initial={"theta1": 0.4}, channels=("theta1",), fit_initial=("theta1",)
    )
    params = [
        identify.Parameter("link1.com", 0.15, 0.01, 0.3),
        identify.Parameter("link1.inertia", 1e-4, 1e-6, 1e-2),
        identify.Parameter("joint1.damping", 2e-4, 1e-7, 1e-1),
    ]
    problem = identify.make_problem(chain, params, [log], {"theta1": 1e-4})
    result = identify.fit(problem, params, n_stages=1, n_starts=1, estimate_noise=False, max_steps=40)
    c, inertia, d = (result.value[n] for n in truth)

    def seen(c, inertia, d):
        J = inertia + m * c**2
        return np.array([m * g * c / J, d / J])

    np.testing.assert_allclose(seen(c, inertia, d), seen(*truth.values()), rtol=1e-5)
    assert np.isinf(result.std_errors).all(), result.summary()
    summary = result.summary()
    assert "not determined" in summary and "link1.com, link1.inertia, joint1.damping not determined" in summary
    assert result.identifiability, summary
    from identify._report.json import jsonable  # what result.json holds: no interval, not a number

    assert all(p["ci95"][1] is None for p in jsonable(result.to_dict())["parameters"])


def test_a_gross_misfit_points_at_the_set_up_first():
    """`FitResult.summary`: a residual hundreds of times its noise floor (a log in degrees
    read as radians, gravity the wrong way for the logs' angle zero: measured 2.5e4x and
    3.5e4x on the real pendulum) adds a hint to check gravity and units; a poor fit of a
    right set-up (the real pendulum's missing drag and dry friction, 46x) does not."""
    from identify._fit.quality import GROSS_MISFIT
    from identify._fit.result import FitResult

    def summary(ratio):
        quality = {"theta1": {"residual_rms": ratio * 1e-3, "noise_floor": 1e-3, "ratio": ratio, "poor": True}}
        one = np.ones(1)
        return FitResult(
            names=["joint1.damping"], values=one, guesses=one, std_errors=0.1 * one, ci_low=0.8 * one,
            ci_high=1.2 * one, correlation=np.eye(1), initial_states={}, offsets={}, sigma={"theta1": 1e-3},
            residual_variance=ratio**2, cost=1.0, n_residuals=100, stages=[Stage(1.0, 3, 1.0, optx.RESULTS.successful)],
            converged=True, at_bounds=[], identifiability=[], singular_values=one, wall_time=1.0, problem=None,
            z={}, fit_quality=quality,
        ).summary()  # fmt: skip

    assert "check the set-up first" in summary(2.5e4) and "gravity" in summary(2.5e4)
    assert "check the set-up first" not in summary(46.0) and "times its noise floor" in summary(46.0)
    # in the table's units (found in review: "RMS 9.91" in rad beside a table in deg)
    assert "(RMS 2.64 deg) is 46 times its noise floor (0.0573 deg," in summary(46.0)
    assert 46.0 < GROSS_MISFIT < 2.5e4


def test_the_noise_printout_has_units_and_says_declared_or_estimated():
    """Review: `noise re-estimated: theta1=0.000524, tip1=4.97e-05` showed a declared
    0.03 deg in rad beside an estimated tip noise, unlabelled."""
    from identify._fit.quality import _noise_text

    text = _noise_text(("theta1", "tip1"), [math.radians(0.03), 4.97e-5], ("tip1",))
    assert text == "theta1 0.03 deg (declared), tip1 0.0497 mm (estimated)"


def test_restarts_stop_at_the_same_misfit_on_a_bound_too():
    from identify._fit.quality import _same_misfit

    assert _same_misfit(True, 1.05e9, [(True, 1.0e9)])  # review: restarts on bounds, same cost
    assert _same_misfit(False, 10.5, [(False, 10.0)])
    assert not _same_misfit(False, 10.5, [(True, 10.0)])  # off the bound now: a different outcome
    assert not _same_misfit(True, 2.0e9, [(True, 1.0e9)])


def test_a_channel_whose_sign_is_reversed_is_named(arm):
    """Review: an encoder counting the other way than the torque put every parameter on a
    bound with a residual 861x the floor, and the fit gave only generic advice. The log's
    theta1 negated: the fit is poor (it makes theta1 barely move: a 4 kg payload, so the
    whole traces do not correlate), and over the torque's first push the measured theta1
    moves against the simulated one (cosine near -1): named, with the convention."""
    log = arm.log(5)
    flipped = dataclasses.replace(log, outputs={**log.outputs, "theta1": -np.asarray(log.outputs["theta1"])})
    params = [identify.Parameter(n, v, v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    problem = identify.make_problem(arm.chain, params, [flipped], noise=arm.noise)
    options = dict(estimate_noise=False, n_starts=1, max_restarts=0, frequency_init=False, n_stages=1)
    result = identify.fit(problem, params, **options)
    assert "theta1" in result.poor_fit, result.summary()
    # measured: theta1 -0.907 (tip1 +0.996; on the true log +0.9995 / +0.9999)
    assert result.reversed_channels.get("theta1", 0.0) < -0.8 and "tip1" not in result.reversed_channels
    assert "theta1 first moves against the simulation" in result.summary()
    # the fix it names: the log's calibration key that negates the column when it is read
    assert "calibration = { theta1 = { sign = -1 } }" in result.summary()
    assert result.to_dict()["reversed_channels"] == result.reversed_channels


@pytest.mark.slow
def test_the_noise_is_re_estimated_until_it_agrees_with_the_residuals():
    """Review (Python API, no `noise=` given): make_problem's default weights (1 % of each
    channel's RMS: 0.9 deg for the angle, 0.003 mm for the tip) overweight the tip 60x; one
    re-estimation left the angle's weight at ~0.33 deg while its residual after the refit
    was 0.05 deg, the intervals 3.5x too wide. Oracle: the injected noise (0.05 deg, 0.05
    mm): the weights the fit ends with are within 10 % of it (~150 s on one loaded core)."""
    chain = fd.rigs.flexible_pendulum()
    t = np.arange(0.0, 2.0, 4e-3)
    rng = np.random.default_rng(7)
    noise = {"theta1": np.radians(0.05), "tip1": 0.05e-3}
    logs = []
    for k, f in enumerate((1.5, 2.5)):
        tau = (0.05 * np.sin(2 * np.pi * f * t) * (t > 0.1))[:, None]
        logs.append(
            identify.simulate_log(
                chain, t, initial={"theta1": -np.pi / 2}, torque=tau, channels=("theta1", "tip1"),
                noise=noise, rng=rng, fit_initial=("theta1",), name=f"log{k}",
            )
        )  # fmt: skip
    EI = float(fd.get_parameter(chain, "link1.EI"))
    params = [identify.Parameter("link1.EI", 1.3 * EI), identify.Parameter("joint1.damping", 2e-3, 1e-6, 1.0)]
    said = []
    res = identify.fit(
        identify.make_problem(chain, params, logs), params, n_starts=1, frequency_init=False, progress=said.append
    )
    for c, s in noise.items():
        assert res.sigma[c] == pytest.approx(s, rel=0.1), (c, res.sigma, said)
    assert sum("noise re-estimated:" in m for m in said) >= 2 and any("within 10 %" in m for m in said), said
    assert res.value["link1.EI"] == pytest.approx(EI, rel=0.01)


def test_a_poor_channel_weighted_far_off_its_floor_names_the_weights():
    """Review: fit_independent on make_problem's default weights (1 % of each channel's
    RMS) left every log 5-9x its floor and the summary blamed the basin or the model."""
    import types

    hint = identify.FitResult._weight_hint
    two = types.SimpleNamespace(sigma={"theta1": math.radians(0.9), "tip1": 3e-6}, sigma_estimated=())
    text = hint(two, "theta1", {"noise_floor": math.radians(0.05)})
    assert "its weight assumed a noise of 0.9 deg, 18 times its floor" in text and "declare" in text
    assert hint(two, "theta1", {"noise_floor": math.radians(0.5)}) == ""  # within 3x
    assert hint(types.SimpleNamespace(sigma={"theta1": 1.0}, sigma_estimated=()), "theta1", {"noise_floor": 0.01}) == ""
    # a weight the fit re-estimated itself is said to be, with the floor to declare instead
    # (the effect it names: `test_a_re_estimated_weight_inflated_by_a_missing_effect_is_named`)
    own = types.SimpleNamespace(sigma=two.sigma, sigma_estimated=("theta1",))
    text = hint(own, "theta1", {"noise_floor": math.radians(0.05)})
    assert "re-estimated from the residuals as a noise of 0.9 deg, 18 times its floor" in text, text
    assert "declare its noise, about 0.05 deg" in text, text


@pytest.mark.slow
def test_a_re_estimated_weight_inflated_by_a_missing_effect_is_named():
    """Review: on a flexible link whose joint has dry friction the model lacks, with the
    encoder's noise declared and the strain gauge's re-estimated, the gauge's weight fell
    round by round (its re-estimated noise grew to 42x its floor), the fit traded the gauge
    away and EI came out 2.8x low. Here (one doublet log, 1.5 s, 0.02 N m of hidden
    friction; measured 2026-12-05): re-estimated, the gauge's noise ends ~9x its floor and EI
    2.06 (interval 1.98-2.15, truth 2.3); with the gauge's noise declared, EI 2.280 (2.257-
    2.303). The summary names the re-estimated weight and gives the floor to declare; the
    oracle for the advice is the truth the log was made with."""
    t = np.arange(0.0, 1.5, 2e-3)
    tau = (np.where((t >= 0.2) & (t < 0.5), 0.2, 0.0) - np.where((t >= 0.5) & (t < 0.8), 0.2, 0.0))[:, None]
    noise = {"theta1": math.radians(0.05), "curvature1": 2e-3}
    rig = fd.Chain(
        [fd.FlexibleLink(0.6, 0.3, 2.3, n_modes=2, damping_ratio=0.01)],
        [fd.RigidJoint(damping=5e-3, coulomb=0.02)],
        [fd.Hub(inertia=4e-3)],
        payload=fd.Payload(mass=0.0),
    )
    log = identify.simulate_log(
        rig, t, torque=tau, channels=("theta1", "curvature1"), noise=noise, rng=np.random.default_rng(4), name="l0"
    )
    params = [identify.Parameter("link1.EI", 1.8, 0.1, 20.0), identify.Parameter("joint1.damping", 3e-3, 1e-6, 0.1)]
    fits = {
        which: identify.fit(
            identify.make_problem(_sweep_chain(), params, [log], noise=declared), params, n_stages=2, n_starts=1
        )
        for which, declared in (("re-estimated", {"theta1": noise["theta1"]}), ("declared", noise))
    }
    own = fits["re-estimated"]
    assert own.sigma_estimated == ("curvature1",) and own.to_dict()["noise_sigma_estimated"] == ["curvature1"]
    floor = own.fit_quality["curvature1"]["noise_floor"]
    assert own.sigma["curvature1"] > quality_module.WEIGHT_MISMATCH * floor, (own.sigma, floor)
    assert "its weight was re-estimated from the residuals" in own.summary(), own.summary()
    ei = {k: (r.values[0], r.ci_low[0], r.ci_high[0]) for k, r in fits.items()}
    assert not ei["re-estimated"][1] <= 2.3 <= ei["re-estimated"][2], ei
    assert ei["declared"][1] <= 2.3 <= ei["declared"][2], ei
    assert fits["declared"].sigma_estimated == ()


def test_declared_noise_is_kept_unless_asked_to_re_estimate():
    """make_problem's docstring: channels given a noise level keep it and only the others
    are re-estimated by `fit` (review: the default re-estimated declared levels too, so a
    declared 0.05 deg encoder noise became the residual RMS). `estimate_noise=True`
    re-estimates every channel: then the weight is the residual RMS, which a right model
    brings to the injected noise (oracle, within 10 %)."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 3.0, 1e-2)
    injected = 2e-3
    log = identify.simulate_log(
        chain, t, initial={"theta1": 0.5}, channels=("theta1",), noise={"theta1": injected},
        rng=np.random.default_rng(2), fit_initial=("theta1",),
    )  # fmt: skip
    params = [identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1)]
    declared = 5e-4  # 4x below the truth: kept as given
    problem = identify.make_problem(chain, params, [log], noise={"theta1": declared})
    options = dict(n_stages=1, n_starts=1, frequency_init=False)
    kept = identify.fit(problem, params, **options)
    assert kept.sigma["theta1"] == declared
    re_estimated = identify.fit(problem, params, estimate_noise=True, **options)
    assert re_estimated.sigma["theta1"] == pytest.approx(injected, rel=0.1)


def _sweep_chain(payload_mass=0.0):
    """A flexible link on a light hub in a horizontal plane (review: a payload sweep)."""
    return fd.Chain(
        [fd.FlexibleLink(0.6, 0.3, 2.3, n_modes=2, damping_ratio=0.01)],
        [fd.RigidJoint(damping=5e-3)],
        [fd.Hub(inertia=4e-3)],
        payload=fd.Payload(mass=payload_mass),
    )


@pytest.mark.slow  # ~90 s on 2 cores (CI budget); known per-log values stay in CI: test_batch's known payloads
def test_logs_at_known_different_payloads_are_fitted_together():
    """Review: logs of one link at three known tip masses (0, 20, 50 g) could only be
    fitted with one payload for all, which biased EI by +3 % with a 0.2 % interval. With
    each log's payload given (`LogData.set`), EI and the joint damping shared by the logs
    are recovered within their 95 % intervals and the residuals are at the noise floor;
    the oracle is the values the logs were simulated with (each log from its own chain)."""
    t = np.arange(0.0, 1.5, 2e-3)
    tau = (np.where((t >= 0.2) & (t < 0.5), 0.2, 0.0) - np.where((t >= 0.5) & (t < 0.8), 0.2, 0.0))[:, None]
    noise = {"theta1": math.radians(0.05), "curvature1": 2e-3}
    rng = np.random.default_rng(4)
    logs = [
        dataclasses.replace(
            identify.simulate_log(
                _sweep_chain(m), t, torque=tau, channels=("theta1", "curvature1"), noise=noise, rng=rng, name=f"m{k}"
            ),
            set={"payload.mass": m},
        )
        for k, m in enumerate((0.0, 0.02, 0.05))
    ]
    params = [identify.Parameter("link1.EI", 1.8, 0.1, 20.0), identify.Parameter("joint1.damping", 3e-3, 1e-6, 0.1)]
    problem = identify.make_problem(_sweep_chain(), params, logs, noise=noise)
    assert problem.log_set_names == ("payload.mass",)
    res = identify.fit(problem, params, n_stages=2, n_starts=1)
    print(res.summary())
    for name, truth in {"link1.EI": 2.3, "joint1.damping": 5e-3}.items():
        i = res.names.index(name)
        assert res.ci_low[i] <= truth <= res.ci_high[i], (name, res.values[i], res.ci_low[i], res.ci_high[i])
    assert res.poor_fit == [], res.summary()


@pytest.mark.slow  # CI time: the experiment file's per-log fit (test_run) checks the same in CI
def test_unknown_payloads_are_fitted_per_log_beside_the_shared_parameters():
    """Logs of one link at three tip masses nobody weighed (10, 20, 50 g): the mass is a
    per-log parameter (`Parameter.per_log`), EI and the joint damping are shared. The
    oracle is the values the logs were simulated with (each log from its own chain): all
    five lie in their 95 % intervals, the residuals are at the noise floor, and each log's
    chain (`log_chain`) carries its own fitted mass while the rig's (`chain`) keeps its."""
    t = np.arange(0.0, 1.5, 2e-3)
    tau = (np.where((t >= 0.2) & (t < 0.5), 0.2, 0.0) - np.where((t >= 0.5) & (t < 0.8), 0.2, 0.0))[:, None]
    noise = {"theta1": math.radians(0.05), "curvature1": 2e-3}
    rng = np.random.default_rng(4)
    masses = (0.01, 0.02, 0.05)
    logs = [
        identify.simulate_log(
            _sweep_chain(m), t, torque=tau, channels=("theta1", "curvature1"), noise=noise, rng=rng, name=f"m{k}"
        )
        for k, m in enumerate(masses)
    ]
    params = [
        identify.Parameter("link1.EI", 1.8, 0.1, 20.0),
        identify.Parameter("payload.mass", 0.03, 1e-4, 1.0, per_log=True),
        identify.Parameter("joint1.damping", 3e-3, 1e-6, 0.1),
    ]
    problem = identify.make_problem(_sweep_chain(), params, logs, noise=noise)
    assert problem.names == ("link1.EI", "payload.mass[m0]", "payload.mass[m1]", "payload.mass[m2]", "joint1.damping")
    # (the round trip: one entry per per-log parameter; the bounds pass through log and exp)
    assert [(q.name, q.per_log, q.guess) for q in problem.parameters] == [(q.name, q.per_log, q.guess) for q in params]
    res = identify.fit(problem, n_stages=2, n_starts=1)
    print(res.summary())
    truth = {"link1.EI": 2.3, "joint1.damping": 5e-3, **{f"payload.mass[m{k}]": m for k, m in enumerate(masses)}}
    for name, value in truth.items():
        i = res.names.index(name)
        assert res.ci_low[i] <= value <= res.ci_high[i], (name, res.values[i], res.ci_low[i], res.ci_high[i])
    assert res.poor_fit == [], res.summary()
    assert set(res.shared_value) == {"link1.EI", "joint1.damping"}
    assert res.per_log["payload.mass"] == {f"m{k}": res.value[f"payload.mass[m{k}]"] for k in range(3)}
    assert res.log_chain("m2").payload.mass == res.value["payload.mass[m2]"]
    assert res.log_chain("m2").links[0].EI == res.value["link1.EI"]
    assert res.chain.payload.mass == 0.0  # the rig's
    assert "payload.mass[m1]" in res.summary() and " kg" in res.summary().split("payload.mass[m1]")[1].split("\n")[0]
    with pytest.raises(ValueError, match=r"no log named 'm3'"):
        res.log_chain("m3")
    with pytest.raises(ValueError, match=r"'payload.mass' is fitted per log .*white-noise intervals"):
        identify.clustered_uncertainty(res)


@pytest.mark.slow  # ~10 s a seed on one core
def test_coverage_of_per_log_payloads():
    """The intervals of a fit with per-log parameters cover: three 1 s logs of the sweep's
    link at 10, 20 and 50 g, EI shared, each log's mass its own, 20 seeds. Over the 80
    intervals the misses follow Binomial(80, 0.05) (mean 4; 11 or more has P = 0.003),
    and each parameter's z-scores scatter with a standard deviation near 1. Measured over
    seeds 7-34 of this layout: 5 of 112 missed, z standard deviations 0.79-0.98."""
    t = np.arange(0.0, 1.0, 2e-3)
    tau = (np.where((t >= 0.1) & (t < 0.3), 0.2, 0.0) - np.where((t >= 0.3) & (t < 0.5), 0.2, 0.0))[:, None]
    noise = {"theta1": math.radians(0.05), "curvature1": 2e-3}
    masses = {"m10": 0.01, "m20": 0.02, "m50": 0.05}
    params = [
        identify.Parameter("link1.EI", 1.8, 0.1, 20.0),
        identify.Parameter("payload.mass", 0.03, 1e-4, 1.0, per_log=True),
    ]
    truth = {"link1.EI": 2.3, **{f"payload.mass[{n}]": m for n, m in masses.items()}}
    zs = []
    for seed in range(200, 220):
        rng = np.random.default_rng(seed)
        logs = [
            identify.simulate_log(
                _sweep_chain(m), t, torque=tau, channels=("theta1", "curvature1"), noise=noise, rng=rng, name=n
            )
            for n, m in masses.items()
        ]
        result = identify.fit(identify.make_problem(_sweep_chain(), params, logs, noise), n_stages=2, n_starts=1)
        assert result.converged, result.summary()
        zs.append([(result.value[n] - v) / result.std_errors[result.names.index(n)] for n, v in truth.items()])
        print(f"seed {seed}: z", np.round(zs[-1], 2), flush=True)
    zs = np.asarray(zs)
    misses = int(np.sum(np.abs(zs) > 1.96))
    print(f"misses {misses} of {zs.size}; z sd per parameter {np.round(zs.std(axis=0, ddof=1), 2)}")
    assert misses < 11, f"{misses} of {zs.size} 95 % intervals missed the truth"
    for n, sd in zip(truth, zs.std(axis=0, ddof=1)):  # (P = 0.002 each outside, as above)
        assert 0.55 <= sd <= 1.55, f"{n}: z-scores scatter with sd {sd:.2f}"


def test_a_per_log_parameter_is_checked():
    """A per-log parameter cannot also be known in a log, is refused by `fit_independent`
    (every parameter is per log there), and must be passed to `fit` as it was made; an
    extra start may name it plainly (every log's value) or per log. (`diagnose_logs` takes
    it: tests/identify/test_diagnose.py.)"""
    t = np.arange(0.0, 0.2, 1e-2)
    log = identify.simulate_log(_sweep_chain(), t, torque=np.full((len(t), 1), 0.1), channels=("theta1",), name="a")
    logs = [log, dataclasses.replace(log, name="b")]
    own = identify.Parameter("payload.mass", 0.02, 1e-4, 1.0, per_log=True)
    with pytest.raises(ValueError, match=r"log 'a': set 'payload.mass' is also a free parameter.*per_log=True"):
        identify.make_problem(_sweep_chain(), [own], [dataclasses.replace(log, set={"payload.mass": 0.01}), logs[1]])
    problem = identify.make_problem(_sweep_chain(), [own], logs)
    with pytest.raises(ValueError, match=r"fit_independent: 'payload.mass' is fitted per log"):
        identify.fit_independent(problem)
    mismatch = r"parameters \['payload.mass'\] are not the problem's \['payload.mass \(per log\)'\]"
    with pytest.raises(ValueError, match=mismatch):
        identify.fit(problem, [dataclasses.replace(own, per_log=False)])
    starts = starts_module._extra_starts(problem, [own], [{"payload.mass": 0.04}, {"payload.mass[b]": 0.03}])
    np.testing.assert_allclose(np.exp(starts[0]), [0.04, 0.04])
    np.testing.assert_allclose(np.exp(starts[1]), [0.02, 0.03])


def test_an_early_stage_that_uses_its_budget_says_the_next_one_goes_on():
    """Review: "horizon 0.617 s: 60 iterations ... (max_steps_reached)" passed without a
    word, and a user could not tell whether it mattered. An early stage's budget is
    `early_max_steps`, and the next stage continues from where it stopped."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 2.0, 1e-2)
    log = identify.simulate_log(chain, t, initial={"theta1": 0.5}, channels=("theta1",), name="a")
    params = [identify.Parameter("joint1.damping", 1e-4, 1e-6, 1e-1)]
    problem = identify.make_problem(chain, params, [log], noise={"theta1": 1e-3})
    said = []
    identify.fit(problem, params, n_stages=2, n_starts=1, early_max_steps=1, frequency_init=False, progress=said.append)
    early = [m for m in said if "horizon" in m and "iterations" in m][0]
    assert early.endswith(
        "(max_steps_reached: an early stage's budget, early_max_steps=1; the next stage goes on from here)"
    ), said


def test_a_residual_well_below_a_floor_raised_by_fast_motion_gets_a_note():
    """Review (two-link arm, elastic joints, 500 Hz): motor encoders at 0.46-0.51 of their
    floor with the residual equal to the true noise. Oracle: the floor's closed-form signal
    leakage (`identify.noise_floor`): white noise `sigma` plus a 150 Hz ringing of amplitude
    `A` at 500 Hz reads `sqrt(sigma^2 + (A (2 sin(pi f dt))^4 / sqrt(140))^2)`; a model that
    explains the ringing leaves `sigma`, well under that floor."""
    from identify._data import noise_floor as nf

    rng = np.random.default_rng(3)
    t = np.arange(0.0, 4.0, 2e-3)
    sigma, amplitude, f = 1e-3, 0.05, 150.0
    noise = sigma * rng.standard_normal(t.size)
    y = amplitude * np.sin(2 * np.pi * f * t) + noise
    floor, count = nf.channel_floors(t[None], y[None, :, None], np.ones((1, t.size), bool), np.ones((1, 1), bool))
    leak = amplitude * (2 * np.sin(np.pi * f * 2e-3)) ** 4 / math.sqrt(140)
    assert floor[0, 0] == pytest.approx(math.sqrt(sigma**2 + leak**2), rel=0.05)
    quality = nf.goodness(("alpha2",), np.asarray([[np.mean(noise**2)]]), floor, count)
    assert quality["alpha2"]["ratio"] < quality_module.FLOOR_ABOVE_RESIDUAL
    (note,) = quality_module._floor_above_residual_notes(quality)
    assert note.startswith("note: the residual of alpha2 is 0.") and "near the Nyquist frequency" in note
    at_floor = nf.goodness(("alpha2",), np.asarray([[np.mean(noise**2)]]), np.asarray([[sigma]]), count)
    assert quality_module._floor_above_residual_notes(at_floor) == []


def test_a_free_optional_term_the_chain_lacks_says_how_to_add_it():
    """Review: `Parameter("joint2.coulomb", ...)` on a chain without dry friction listed the
    chain's 30 parameter names and not `fd.with_optional_terms`; with the term added, the
    same problem is built."""
    t = np.arange(0.0, 0.2, 1e-2)
    log = identify.simulate_log(_sweep_chain(), t, torque=np.full((len(t), 1), 0.1), channels=("theta1",), name="a")
    params = [identify.Parameter("joint1.coulomb", 1e-3, 1e-6, 1.0)]
    with pytest.raises(ValueError, match=r"'joint1.coulomb' is an optional term .*fd.with_optional_terms\(chain"):
        identify.make_problem(_sweep_chain(), params, [log])
    problem = identify.make_problem(fd.with_optional_terms(_sweep_chain(), ["joint1.coulomb"]), params, [log])
    assert problem.names == ("joint1.coulomb",)


def test_a_log_setting_is_checked_against_the_rig_and_the_free_parameters():
    t = np.arange(0.0, 0.2, 1e-2)
    log = identify.simulate_log(_sweep_chain(), t, torque=np.full((len(t), 1), 0.1), channels=("theta1",), name="a")
    params = [identify.Parameter("link1.EI", 2.0, 0.1, 20.0)]
    for bad, expected in (
        ({"payload.mas": 0.02}, r"log 'a': set 'payload.mas' is not a parameter.*did you mean 'payload.mass'"),
        ({"link1.EI": 2.0}, r"log 'a': set 'link1.EI' is also a free parameter"),
        ({"payload.mass": -0.01}, r"log 'a': set: Payload.mass: expected a value >= 0"),
        ({"payload.mass": "20 g"}, r"log 'a': set 'payload.mass' expected a number \(SI\)"),
    ):
        with pytest.raises(ValueError, match=expected):
            identify.make_problem(_sweep_chain(), params, [dataclasses.replace(log, set=bad)])


@pytest.mark.parametrize("flipped", [False, True])
def test_the_reversed_sign_check_survives_a_noisy_torque_column(arm, flipped):
    """Review: a logged torque with noise (2 mN m on a 0.25 N m drive) started the "first
    push" at the first nonzero sample, the noise's, so the push was two samples of encoder
    noise, and a correct encoder on a poorly fitting model was called reversed (cosine
    -0.67). The arm's doublets after 0.2 s at rest, the torque column with 2 mN m of noise
    (4 % of the 0.05 N m drive), a sign-correct model far off (EI x0.35, hub x0.1, damping
    x6): seeds 2 and 6 were named reversed before (-0.96, -0.67), none now; with theta1
    negated, every seed is named (10 of 10 over seeds 0-9 measured; 7 of 10 with the push
    starting at 10 % of the drive's peak, which noise spikes reached)."""
    tau = np.where(arm.t[:, None] < 0.2, 0.0, doublets(arm.t - 0.2))
    params = [identify.Parameter(n, v, v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    wrong = {"link1.EI": 0.35, "joint1.damping": 0.03, "hub1.inertia": 0.002, "payload.mass": 0.05}
    named = []
    for seed in (2, 6, 7, 8):
        log = identify.simulate_log(
            arm.chain, arm.t, torque=tau, channels=CHANNELS, noise=arm.noise, rng=np.random.default_rng(seed)
        )
        outputs = {**log.outputs, "theta1": -np.asarray(log.outputs["theta1"])} if flipped else log.outputs
        noisy = dataclasses.replace(
            log, outputs=outputs, torque=log.torque + np.random.default_rng(100 + seed).normal(0, 0.002, tau.shape)
        )
        problem = identify.make_problem(arm.chain, params, [noisy], noise=arm.noise)
        x = parameters_module.x_from_theta(problem, [wrong[n] for n in problem.names])
        z = Variables(offset=jnp.zeros(0), phys=jnp.asarray(parameters_module.z_from_x(problem, x)), y0=jnp.zeros(0))
        named.append(quality_module._reversed_channels(problem, z, problem.sigma, None, ["theta1", "tip1"]))
    if flipped:
        assert all(list(n) == ["theta1"] for n in named), named
    else:
        assert not any(named), named


def test_a_fitted_start_far_from_the_first_sample_is_flagged():
    """A fit that moves a log's start far from its first sample says so (review: a model
    without the rig's dry friction put fitted initial angles 5-15 deg from encoders reading
    12.3 deg at rest, without a word). Oracle: a pendulum drop whose first sample is a
    0.05 rad glitch (50x the noise): the fitted start follows the swing, not the glitch,
    and is flagged; the intact log is not."""
    chain = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 2.0, 1e-2)
    log = identify.simulate_log(
        chain, t, initial={"theta1": 0.3}, channels=("theta1",), noise={"theta1": 1e-3},
        rng=np.random.default_rng(3), fit_initial=("theta1",),
    )  # fmt: skip
    glitch = np.asarray(log.outputs["theta1"]).copy()
    glitch[0] += 0.05
    params = [identify.Parameter("joint1.damping", 1e-3, 1e-6, 1e-1)]
    options = dict(n_stages=1, n_starts=1, frequency_init=False)
    for outputs, flagged in ((log.outputs, False), ({"theta1": glitch}, True)):
        data = dataclasses.replace(log, outputs=outputs, initial={"theta1": float(outputs["theta1"][0])})
        res = identify.fit(identify.make_problem(chain, params, [data], noise={"theta1": 1e-3}), params, **options)
        assert bool(res.initial_far) == flagged, res.summary()
        assert ("from the log's first sample" in res.summary()) == flagged
    start, first, noise = res.initial_far["synthetic"]["theta1"]
    assert start == pytest.approx(0.3, abs=5e-3) and first == pytest.approx(0.35, abs=5e-3) and noise == 1e-3
