"""The frequency-domain initialisation of flexural stiffness (`identify.frequency_init`).

Oracles: closed forms of the windowed spectrum of a sine and of white noise; the known
EI of synthetic logs (the 4-parameter flexible arm of `test_fit`, flexural mode 4.2 Hz
at the truth) under inputs whose spectra are not the free vibration's, where picking the
largest peak (what `identify.fit` did before) is shown to be far off first.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time

import jax.numpy as jnp
import numpy as np
import pytest
from test_fit import BARS, CHANNELS, DT, TRUTH, Arm, doublets, rel_errors  # tests/identify/ is on sys.path

import flexdyn as fd
import identify
import identify._fit.fit_independent as fit_independent_module
import identify._fit.starts as starts_module
import identify._model.parameters as parameters_module
import identify._model.residuals as residuals_module
from identify._fit import frequency_init


def test_amplitude_spectrum_of_a_sine_and_of_white_noise():
    """A sine of amplitude A on a frequency bin peaks there at A sum(w) / 2 (Hann window w);
    white noise of standard deviation s has mean power s^2 sum(w^2) in every bin, the
    noise floor `spectral_similarity` adds to the model's spectrum."""
    dt, n = 1e-3, 4000
    t = np.arange(n) * dt
    f0, amplitude = 25.0, 0.3  # 100 cycles in the n samples: on a bin
    f, a, white = frequency_init.amplitude_spectrum(t, 0.7 + amplitude * np.sin(2 * np.pi * f0 * t))
    w = np.hanning(n)
    assert white == pytest.approx(float(w @ w), rel=1e-12)
    k = int(np.argmax(a))
    assert f[k] == pytest.approx(f0, abs=1e-9)
    assert a[k] == pytest.approx(amplitude * w.sum() / 2, rel=1e-3)
    sigma = 0.02
    f, a, white = frequency_init.amplitude_spectrum(t, np.random.default_rng(0).normal(0.0, sigma, n))
    band = (f > 5.0) & (f < 450.0)
    assert np.mean(a[band] ** 2) == pytest.approx(sigma**2 * white, rel=0.05)


def test_expected_amplitude_is_the_rice_mean():
    """`expected_amplitude(s, N)` against a Monte Carlo mean of `|s + n|`, `n` circular
    complex Gaussian with `E|n|^2 = N` (200,000 draws: the mean to ~0.1 %), and its two
    limits: noise alone, the Rayleigh mean `sqrt(pi N) / 2`; no noise, `s`."""
    rng = np.random.default_rng(0)
    noise_power = 2.5
    n = (rng.normal(size=200_000) + 1j * rng.normal(size=200_000)) * math.sqrt(noise_power / 2)
    for s in (0.0, 0.3, 1.0, 2.0, 5.0, 40.0):
        expected = frequency_init.expected_amplitude(np.asarray([s]), noise_power)[0]
        assert expected == pytest.approx(np.mean(np.abs(s + n)), rel=3e-3), s
    assert frequency_init.expected_amplitude(np.asarray([0.0]), 4.0)[0] == pytest.approx(math.sqrt(math.pi), rel=1e-12)
    np.testing.assert_allclose(frequency_init.expected_amplitude(np.asarray([0.0, 3.0]), 0.0), [0.0, 3.0])


@pytest.fixture(scope="module")
def arm():
    return Arm()


def _problem(arm, t, torque, factor_ei, seed=1):
    """The arm's log under `torque` and the problem from guesses EI x `factor_ei`, the other
    three parameters 20 % off (bounds 1e-2 to 1e2 times the truth)."""
    log = identify.simulate_log(
        arm.chain, t, torque=torque, channels=CHANNELS, noise=arm.noise, rng=np.random.default_rng(seed)
    )
    factors = (factor_ei, 0.8, 1.2, 0.8)
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
    return identify.make_problem(arm.chain, params, [log], noise=arm.noise), params


def _peak_picking(problem, params) -> float:
    """The EI guess scaled by (f_peak / f_model)^2: f_peak the largest peak of the tip's
    measured spectrum from the onset in the band, f_model the model's flexural frequency
    at the guess (the estimate `identify.fit` used before matched spectra)."""
    chain = residuals_module.chain_at(problem, np.asarray([p.guess for p in params]))
    f_model = frequency_init.flexural_frequency(chain, 0)
    t, y = np.asarray(problem.t[0]), np.asarray(problem.measured[0, :, problem.channels.index("tip1")])
    keep = t >= float(problem.onset[0])
    f, a, _ = frequency_init.amplitude_spectrum(t[keep], y[keep])
    band = (f >= frequency_init.BAND[0] * f_model) & (f <= frequency_init.BAND[1] * f_model)
    f_peak = f[band][np.argmax(a[band])]
    return params[0].guess * (f_peak / f_model) ** 2


def _square(t):
    return np.where(t < 1.5, 0.05 * np.sign(np.sin(2 * np.pi * 1.0 * t)), 0.0)


INPUTS = {
    # a drive below the flexural mode: the response's line is the drive's
    "sine 1.5 Hz": (2.0, lambda t: 0.05 * np.sin(2 * np.pi * 1.5 * t)),
    # above it
    "sine 7 Hz": (2.0, lambda t: 0.05 * np.sin(2 * np.pi * 7.0 * t)),
    # harmonics at 1, 3, 5 Hz, then 0.5 s free
    "square 1 Hz": (2.0, _square),
    # a doublet and a record that ends 0.2 s after it (the free vibration is half a period)
    "short record": (0.6, lambda t: np.where(t < 0.2, 0.05, np.where(t < 0.4, -0.05, 0.0))),
}


@pytest.mark.parametrize(
    "name, factor_ei",
    [("sine 1.5 Hz", 0.5), ("sine 1.5 Hz", 2.0), ("sine 7 Hz", 2.0), ("square 1 Hz", 0.5), ("short record", 2.0)],
)
def test_matched_spectra_find_the_stiffness_where_peak_picking_fails(arm, name, factor_ei):
    """From a guess of EI x0.5 or x2 (flexural frequency x0.71 or x1.41), the initialisation
    puts EI within 12 % of the truth (the factor grid's step is 41 % in EI before the
    golden-section refinement), where the largest peak of the measured spectrum, taken as
    the flexural frequency, puts it more than 40 % off (measured: 0.14, 3.0, 0.05 and 0.52
    of the truth). The other three parameters are 20 % off, and the match's maximum moves
    with them: under the 1.5 Hz sine from x0.5 it lies at 0.894 of the truth (a search of
    20 simulations), at 1.0007 with them at the truth (next test). The bar was 10 % while a
    parabola through three grid points refined the estimate: its vertex missed that maximum
    (and landed nearer the truth here)."""
    duration, drive = INPUTS[name]
    t = np.arange(0.0, duration, DT)
    problem, params = _problem(arm, t, drive(t)[:, None], factor_ei)
    assert abs(math.log(_peak_picking(problem, params) / TRUTH["link1.EI"])) > math.log(1.4)
    said = []
    start = time.perf_counter()
    x0 = starts_module._frequency_initialise(
        problem, parameters_module.x_from_theta(problem, [p.guess for p in params]), said.append
    )
    print(name, f"x{factor_ei}:", said, f"{time.perf_counter() - start:.1f} s")
    assert math.exp(x0[0]) == pytest.approx(TRUTH["link1.EI"], rel=0.12), said
    # the other parameters are not touched
    np.testing.assert_array_equal(x0[1:], parameters_module.x_from_theta(problem, [p.guess for p in params])[1:])


def test_with_the_other_parameters_right_the_match_peaks_at_the_truth(arm):
    """The 1.5 Hz sine from EI x0.5 with the other three parameters at the truth: the grid
    and its golden-section refinement put EI within 1 % of the truth (measured 1.0000)."""
    duration, drive = INPUTS["sine 1.5 Hz"]
    t = np.arange(0.0, duration, DT)
    log = identify.simulate_log(
        arm.chain, t, torque=drive(t)[:, None], channels=CHANNELS, noise=arm.noise, rng=np.random.default_rng(1)
    )
    params = [identify.Parameter(n, v * (0.5 if n == "link1.EI" else 1.0), v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    problem = identify.make_problem(arm.chain, params, [log], noise=arm.noise)
    said = []
    x0 = starts_module._frequency_initialise(
        problem, parameters_module.x_from_theta(problem, [p.guess for p in params]), said.append
    )
    assert math.exp(x0[0]) == pytest.approx(TRUTH["link1.EI"], rel=0.01), said


def test_a_log_without_flexural_motion_keeps_the_guess(arm):
    """The arm at rest, no input: the tip channel is white noise and every tried EI
    simulates no deflection, so every factor's expected spectrum is the noise floor alone
    and no factor beats the guess: the guess is kept, and the progress message says why."""
    t = np.arange(0.0, 1.0, DT)
    with pytest.warns(UserWarning, match=r"log 'synthetic' shows no motion above its noise"):  # (make_problem)
        problem, params = _problem(arm, t, np.zeros((len(t), 1)), 2.0)
    said = []
    x = parameters_module.x_from_theta(problem, [p.guess for p in params])
    x0 = starts_module._frequency_initialise(problem, x, said.append)
    np.testing.assert_array_equal(x0, x)
    assert len(said) == 1 and "guess kept" in said[0], said


@pytest.mark.slow  # ~60 s on 2 cores
def test_the_default_fit_of_a_sine_driven_log_converges(arm):
    """A 3 s log driven by a 1.5 Hz sine, guesses EI x2 and the others 20 % off: the default
    fit recovers the four parameters within the issue's bars. With the peak-picking
    initialisation (EI's guess put at 0.14 of the truth, out of every multi-start point's
    reach) this fit ended with damping on its bound (-99 %), payload +46 %, EI +15 %, after
    restarts from the next-best starts (103 s); without any initialisation it converged.
    (The 2 s version of the log was fitted either way.)"""
    t = np.arange(0.0, 3.0, DT)
    problem, params = _problem(arm, t, (0.05 * np.sin(2 * np.pi * 1.5 * t))[:, None], 2.0)
    start = time.perf_counter()
    result = identify.fit(problem, params, estimate_noise=False)
    print(result.summary(), f"\n{time.perf_counter() - start:.1f} s")
    assert result.converged, result.summary()
    for n, e in rel_errors(result).items():
        assert abs(e) <= BARS[n], f"{n} off by {100 * e:+.3f}% (bar {100 * BARS[n]:.0f}%)\n{result.summary()}"


def _own_ei_logs(arm, t, torque, eis):
    """One log per EI in `eis` (the arm's other parameters at the truth), seeds 0, 1, ..."""
    return [
        identify.simulate_log(
            fd.with_parameters(arm.chain, {"link1.EI": e}),
            t,
            torque=torque,
            channels=CHANNELS,
            noise=arm.noise,
            rng=np.random.default_rng(k),
            name=f"log{k}",
        )
        for k, e in enumerate(eis)
    ]


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_independent_fits_initialise_each_logs_own_stiffness(arm):
    """`fit_independent`: every log gets its own EI guess from its own spectrum (all logs'
    simulations batched). Two doublet logs of links with EI 0.8 and 1.25 N m^2, EI the one
    free parameter, guess 2: the initialisation moves the guesses by x0.4 and x0.625 (to
    within 10 %), and each fit lands on its own log's EI."""
    eis = (0.8, 1.25)
    logs = _own_ei_logs(arm, arm.t, arm.torque, eis)
    params = [identify.Parameter("link1.EI", 2.0, 0.01, 100.0)]
    problem = identify.make_problem(arm.chain, params, logs, noise=arm.noise)
    said = []
    results = identify.fit_independent(problem, params, n_stages=1, progress=said.append)
    (line,) = [m for m in said if "frequency initialisation" in m]
    print(line)
    low, high = (float(v) for v in re.search(r"moved in 2 \(x([\d.]+) to x([\d.]+)", line).groups())
    assert low == pytest.approx(eis[0] / 2.0, rel=0.10) and high == pytest.approx(eis[1] / 2.0, rel=0.10), line
    for result, e in zip(results, eis):
        assert result.converged
        assert result.value["link1.EI"] == pytest.approx(e, rel=BARS["link1.EI"])
        # each log's residuals against its own model-free noise floor (`identify.noise_floor`)
        assert all(0.8 < q["ratio"] < 1.2 for q in result.fit_quality.values()), result.fit_quality


@pytest.mark.slow  # ~70 s on 2 cores
def test_independent_fits_of_sine_driven_logs_from_a_far_guess(arm):
    """Three 3 s logs driven by a 1.5 Hz sine, links with EI 0.7, 1.0 and 1.4 N m^2, the four
    parameters free, guesses EI 6 N m^2 and the others 20 % off: every log's fit lands within
    the issue's bars of its own truth. Without the initialisation (`frequency_init=False`)
    the fit of the EI = 1.0 log ended, 'converged', at EI +68 %, hub inertia -86 %, payload
    +135 % (the other two within the bars), in 95 s against 66 s with it."""
    eis = (0.7, 1.0, 1.4)
    t = np.arange(0.0, 3.0, DT)
    logs = _own_ei_logs(arm, t, (0.05 * np.sin(2 * np.pi * 1.5 * t))[:, None], eis)
    factors = (6.0, 0.8, 1.2, 0.8)
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
    problem = identify.make_problem(arm.chain, params, logs, noise=arm.noise)
    results = identify.fit_independent(problem, params, progress=print)
    for result, e in zip(results, eis):
        assert result.poor_fit == [], result.summary()
        truth = {**TRUTH, "link1.EI": e}
        for n, v in truth.items():
            assert result.value[n] == pytest.approx(v, rel=BARS[n]), f"log with EI {e}: {n}\n{result.summary()}"


@pytest.mark.slow  # ~3 min on 2 cores
def test_independent_fits_retry_a_log_left_in_a_wrong_basin(arm):
    """The logs of the previous test with EI 0.7 and 1.0 N m^2, the same far guesses, without
    the initialisation: the EI = 1.0 log ends in a wrong basin (its residuals 3.3 and 8.5
    times the noise floor), the other fits its data. `fit_independent` grows that log's
    horizon again from the other's parameters and both end within the bars, at the floor.
    With `restart_poor_fit=False` the wrong basin stays and is reported (`poor_fit`). The noise
    is declared exactly (`arm.noise`) and not re-estimated: with it re-estimated (the
    default), the refit with the wrong basin's residual weights left that basin before any
    retry (measured 2026-12-05), and there would be nothing to retry."""
    eis = (0.7, 1.0)
    t = np.arange(0.0, 3.0, DT)
    logs = _own_ei_logs(arm, t, (0.05 * np.sin(2 * np.pi * 1.5 * t))[:, None], eis)
    factors = (6.0, 0.8, 1.2, 0.8)
    params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
    problem = identify.make_problem(arm.chain, params, logs, noise=arm.noise)
    for restart in (False, True):
        said = []
        results = identify.fit_independent(
            problem, params, frequency_init=False, restart_poor_fit=restart, estimate_noise=False, progress=said.append
        )
        print("\n".join(said), *(r.summary() for r in results), sep="\n")
        assert results[0].poor_fit == [] and results[0].value["link1.EI"] == pytest.approx(0.7, rel=BARS["link1.EI"])
        if not restart:
            assert results[1].poor_fit == ["theta1", "tip1"], results[1].summary()
            continue
        assert any("log1 left far above the noise floor" in m for m in said), said
        assert results[1].poor_fit == [], results[1].summary()
        for n, v in {**TRUTH, "link1.EI": 1.0}.items():
            assert results[1].value[n] == pytest.approx(v, rel=BARS[n]), f"{n}\n{results[1].summary()}"


def test_a_long_log_is_compared_over_its_first_flexural_periods(arm, monkeypatch):
    """The spectra compare at most `PERIODS` flexural periods of the model at the guess from
    the onset, and the simulations stop there. With 8 periods (EI guess x2: the model at
    5.9 Hz, 1.36 s) of a 3 s log (the doublets, then free vibration), every simulation asks
    for that span and the estimate is still within 10 % of the truth."""
    monkeypatch.setattr(frequency_init, "PERIODS", 8.0)
    t = np.arange(0.0, 3.0, DT)
    problem, params = _problem(arm, t, doublets(t), 2.0)
    guesses = np.asarray([p.guess for p in params])
    f_model = frequency_init.flexural_frequency(residuals_module.chain_at(problem, jnp.asarray(guesses)), 0)
    y0s = residuals_module.initial_states_of(problem, jnp.zeros(0))
    spans = []

    def simulate(thetas, span):
        spans.append(span)
        outputs, ok = residuals_module.predict_jit(problem, jnp.asarray(thetas[0]), y0s, jnp.asarray(span))
        return np.asarray(outputs)[None], np.asarray([bool(np.all(ok))])

    limits = (guesses * 1e-3, guesses * 1e3)
    said = []
    theta = frequency_init.initialise_stiffness([problem], guesses[None], limits, simulate, said.append)
    print(said, f"model {f_model:.3g} Hz")
    n_sims = len(frequency_init.FACTORS) + frequency_init.REFINE_EVALS
    assert len(spans) in (17, n_sims) and all(s == pytest.approx(8.0 / f_model, rel=1e-12) for s in spans), spans
    assert 8.0 / f_model < 0.5 * t[-1]
    assert theta[0, 0] == pytest.approx(TRUTH["link1.EI"], rel=0.10), said


def test_a_tip_channel_of_noise_only_is_flagged_as_a_poor_match(arm):
    """The doublet log with its tip channel replaced by white noise at the channel's noise
    level (a strain gauge that was not connected): no EI makes the model's spectrum match
    (a noise spectrum is flat), and the progress line warns so; on the intact log it does
    not (similarity >= 0.99)."""
    said = {}
    for kind in ("intact", "noise only"):
        log = arm.log(1)
        if kind == "noise only":
            log.outputs["tip1"] = np.random.default_rng(7).normal(0.0, arm.noise["tip1"], len(arm.t))
        factors = (2.0, 0.8, 1.2, 0.8)
        params = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
        problem = identify.make_problem(arm.chain, params, [log], noise=arm.noise)
        said[kind] = []
        x = parameters_module.x_from_theta(problem, [p.guess for p in params])
        starts_module._frequency_initialise(problem, x, said[kind].append)
    print(said)
    assert not any("WARNING" in m for m in said["intact"]), said
    assert any("WARNING" in m and "no link1.EI tried" in m for m in said["noise only"]), said


def test_a_tip_channel_dominated_by_noise_keeps_a_right_guess(arm):
    """The doublet log with its tip noise 300x the usual 1 % of RMS (3x the deflection's
    RMS), EI guessed 3.5 % off. Noise makes the measured spectrum's amplitudes random, so
    the best shape similarity any model reaches is ~0.87 (the true model's expected
    similarity, the `ceiling`, 0.887; noise alone gives sqrt(pi)/2 = 0.886), and some
    factor beats the guess by chance (measured: x2.25, match 0.864 against 0.842). Before
    the bootstrap (`spurious_gain`), EI moved to 2.3x the truth and the progress line warned
    that no EI matches (similarity < 0.9); now the gain is within what noise alone gives,
    the guess is kept and nothing is flagged."""
    noise = dict(arm.noise)
    noise["tip1"] *= 300
    log = identify.simulate_log(
        arm.chain, arm.t, torque=arm.torque, channels=CHANNELS, noise=noise, rng=np.random.default_rng(3)
    )
    params = [identify.Parameter(n, v * 1.035, v * 1e-2, v * 1e2) for n, v in TRUTH.items()]
    problem = identify.make_problem(arm.chain, params, [log], noise=noise)
    said = []
    x = parameters_module.x_from_theta(problem, [p.guess for p in params])
    x0 = starts_module._frequency_initialise(problem, x, said.append)
    print(said)
    np.testing.assert_array_equal(x0, x)
    assert len(said) == 1 and "no more than noise alone does" in said[0] and "guess kept" in said[0], said


def test_a_flexural_mode_over_4x_nyquist_is_not_initialised(arm):
    """The arm with a 400x stiffer link (flexural mode ~81 Hz) sampled at 20 Hz: no bin of
    the band (1/4 to 4 times the model's flexural frequency) is in the spectrum, so the
    guess is kept without a simulation and the line says why (before, the band was quoted up
    to 4x the mode, above the Nyquist frequency)."""
    chain = fd.with_parameters(arm.chain, {"link1.EI": 400.0})
    t = np.arange(0.0, 10.0, 0.05)
    log = identify.simulate_log(chain, t, torque=doublets(t), channels=CHANNELS)
    params = [identify.Parameter("link1.EI", 400.0 * 1.2, 1.0, 1e5)]
    problem = identify.make_problem(chain, params, [log], noise={"theta1": 1e-4, "tip1": 1e-6})

    def simulate(thetas, span):
        raise AssertionError("no simulation expected")

    said = []
    theta = frequency_init.initialise_stiffness([problem], np.asarray([[480.0]]), ([1.0], [1e5]), simulate, said.append)
    assert theta[0, 0] == 480.0
    assert len(said) == 1 and "over 4x the Nyquist frequency of tip1 (10 Hz)" in said[0], said


def _two_link_problem(guess_ei1, guess_ei2):
    """Paper 004's two-link arm (`fd.rigs.flexible_link_joint_arm`, EI = 1 N m^2 on both
    links) driven by 1.0 Hz and 1.7 Hz sines (0.05 and 0.03 N m) for 2 s, joint angles
    and both tips recorded with 1 % noise, and the problem from guesses of the two EIs."""
    chain = fd.rigs.flexible_link_joint_arm()
    t = np.arange(0.0, 2.0, 4e-3)
    torque = np.stack([0.05 * np.sin(2 * np.pi * 1.0 * t), 0.03 * np.sin(2 * np.pi * 1.7 * t)], axis=1)
    channels = ("theta1", "theta2", "tip1", "tip2")
    clean = identify.simulate_log(chain, t, torque=torque, channels=channels)
    noise = {c: 0.01 * float(np.sqrt(np.mean(clean.outputs[c] ** 2))) for c in channels}
    log = identify.simulate_log(chain, t, torque=torque, channels=channels, noise=noise, rng=np.random.default_rng(1))
    params = [
        identify.Parameter("link1.EI", guess_ei1, 1e-2, 1e2),
        identify.Parameter("link2.EI", guess_ei2, 1e-2, 1e2),
    ]
    return identify.make_problem(chain, params, [log], noise=noise), params


@pytest.mark.parametrize(
    "guesses",
    [(0.5, 2.0), pytest.param((2.0, 0.5), marks=pytest.mark.slow), pytest.param((1.4, 1.4), marks=pytest.mark.slow)],
)
@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_both_links_of_a_sine_driven_two_link_arm(guesses):
    """Under sine drives well below the second link's flexural mode, the second tip's
    spectrum is the drives' lines whatever EI2 is (shape similarity 0.99-1.00 at every
    factor tried); only its scale, the quasi-static deflection ~ load / EI2, tells EI2.
    Matching the spectrum's level as well as its shape puts both EIs within 10 % of the
    truth (measured 0.913/1.035, 1.000/1.000, 0.990/0.990); matching the shape alone left EI2
    at 2.0, 0.58 and 1.4 (guesses (0.5, 2), (2, 0.5), (1.4, 1.4))."""
    problem, params = _two_link_problem(*guesses)
    said = []
    x0 = starts_module._frequency_initialise(
        problem, parameters_module.x_from_theta(problem, [p.guess for p in params]), said.append
    )
    print(guesses, np.exp(x0), said)
    assert math.exp(x0[0]) == pytest.approx(1.0, rel=0.10), said
    assert math.exp(x0[1]) == pytest.approx(1.0, rel=0.10), said


def test_a_channel_with_a_free_gain_is_matched_in_shape_only(arm):
    """The doublet log with its tip channel recorded twice too large (a strain-gauge bridge
    calibrated wrong). With the channel's gain free (`sensor.tip1.gain`), the gain absorbs
    the scale and the spectra are compared in shape only: EI within 10 % of the truth from
    the guess x2. With the gain fixed at 1, the fit's own loss sees the scale, and so does
    the initialisation: it matches a softer link (a larger deflection under the same load),
    as the fit itself would."""
    from identify._data import measurement as meas

    log = arm.log(1)
    log.outputs["tip1"] = 2.0 * log.outputs["tip1"]
    noise = {**arm.noise, "tip1": 2.0 * arm.noise["tip1"]}
    factors = (2.0, 0.8, 1.2, 0.8)
    physical = [identify.Parameter(n, v * f, v * 1e-2, v * 1e2) for (n, v), f in zip(TRUTH.items(), factors)]
    found, said = {}, {}
    for free_gain in (True, False):
        params = physical + ([identify.Parameter("sensor.tip1.gain", 1.0, 0.2, 5.0)] if free_gain else [])
        measurement = meas.with_effect(meas.Measurement(), "sensor.tip1.gain") if free_gain else None
        problem = identify.make_problem(arm.chain, params, [log], noise=noise, measurement=measurement)
        said[free_gain] = []
        x = parameters_module.x_from_theta(problem, [p.guess for p in params])
        found[free_gain] = math.exp(starts_module._frequency_initialise(problem, x, said[free_gain].append)[0])
    print(found, said)
    assert found[True] == pytest.approx(TRUTH["link1.EI"], rel=0.10), said
    assert "shape only: its gain is free" in said[True][-1]
    assert found[False] < 0.9 * TRUTH["link1.EI"], said


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_a_lightly_damped_curvature_peak_is_matched_by_the_refinement():
    """Review case: a flexible link on a light hub (0.6 m, 0.3 kg/m, EI 2.3 N m^2, two
    modes at damping ratio 0.01, hub 4e-3 kg m^2), torque pulses, 3 s at 1 kHz, its root
    curvature (a strain gauge, 2 microstrain of noise on a 2 mm strip) dominated by a
    29 Hz mode whose peak (~0.6 Hz wide) is narrower than the factor grid's 9 % steps in
    frequency. From EI 1.5 (and the damping 5x low), the parabola through the grid's best
    put EI 6 % low, matching in shape 0.83, with a warning that no EI matches; the
    golden-section search puts it within 1 % (measured 2.302), without a warning."""
    chain = fd.Chain(
        [fd.FlexibleLink(0.6, 0.3, 2.3, n_modes=2, damping_ratio=0.01)],
        [fd.RigidJoint(damping=5e-3)],
        [fd.Hub(inertia=4e-3)],
    )
    t = np.arange(3001) / 1000.0
    tau = np.where((t >= 0.2) & (t < 0.5), 0.2, 0.0) - np.where((t >= 0.5) & (t < 0.8), 0.2, 0.0)
    noise = {"theta1": math.radians(0.05), "curvature1": 2e-6 / 1e-3}
    log = identify.simulate_log(
        chain, t, torque=tau[:, None], channels=("theta1", "curvature1"), noise=noise, rng=np.random.default_rng(1)
    )
    params = [identify.Parameter("link1.EI", 1.5, 0.1, 20.0), identify.Parameter("joint1.damping", 1e-3, 1e-6, 0.1)]
    problem = identify.make_problem(chain, params, [log], noise=noise)
    said = []
    x0 = starts_module._frequency_initialise(problem, parameters_module.x_from_theta(problem, [1.5, 1e-3]), said.append)
    print(said)
    assert math.exp(x0[0]) == pytest.approx(2.3, rel=0.01), said
    assert not any("WARNING" in m for m in said), said


def test_each_independent_log_is_banded_at_its_own_payload(arm):
    """`fit_independent` starts every log at the same guess, but a log's known payload
    (`LogData.set`) moves its flexural frequency: the band searched for each log is centred
    on its own rig's frequency (oracle: `flexural_frequency` of the chain built with that
    payload). Before, the frequencies were cached by parameter vector alone, so every log
    got the first log's."""
    t = np.arange(0.0, 0.5, DT)
    masses = (0.0, 0.05, 0.2)
    logs = [
        dataclasses.replace(
            identify.simulate_log(arm.chain, t, torque=doublets(t), channels=CHANNELS),
            set={"payload.mass": m},
            name=f"m{k}",
        )
        for k, m in enumerate(masses)
    ]
    params = [identify.Parameter("link1.EI", 2.0, 0.1, 20.0)]
    problem = identify.make_problem(arm.chain, params, logs, noise={"theta1": 1e-4, "tip1": 1e-6})
    _, singles = fit_independent_module._split(problem)
    got = frequency_init._flexural_frequencies(singles, [np.asarray([2.0])] * 3, 0)
    expected = [
        frequency_init.flexural_frequency(fd.with_parameters(arm.chain, {"link1.EI": 2.0, "payload.mass": m}), 0)
        for m in masses
    ]
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    assert expected[0] > 1.2 * expected[2], expected  # the check can fail
