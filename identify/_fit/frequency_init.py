"""Frequency-domain initial guesses of flexural stiffness (`link<i>.EI`) before a fit.

A 2x error in EI puts a simulated oscillation out of phase after a few periods, and the
time-domain loss has a local minimum per period slip; the amplitude spectrum of a recorded
flexural channel (tip deflection or root curvature) carries no phase, so matching it is a
nearly convex one-dimensional problem in EI.

**Matched spectra.** For each free `link<i>.EI` whose link has modes and whose `tip<i>` or
`curvature<i>` channel is recorded, the model is simulated with the logs' own inputs and
initial states at the guesses, with EI scaled by each factor of `FACTORS` (1/16 to 16),
and the factor is kept whose simulated amplitude spectrum, with the channel's noise floor,
matches the measured one best (then refined by a golden-section search between its
neighbours, `REFINE_EVALS` simulations):

    match(s) = 2 <A_meas, A_model(s)> / (|A_meas|^2 + |A_model(s)|^2),
    A_meas = |FFT(w (y - mean y))|,   A_model(s) = sqrt(|FFT(w (y_sim(s) - mean))|^2 + sigma^2 sum w^2)

(`w` the Hann window, `sigma` the channel's noise level), each log from its onset, the
inner products summed over the logs, over the band from 1/4 to 4 times the model's
flexural frequency at the guess. `match` is the cosine similarity (shape) times
`2r / (1 + r^2)`, `r = |A_model| / |A_meas|` (level): the level tells EI when the drive is
well below the flexural mode (quasi-static deflection ~ load / EI). When the channel's
sensor gain is free (`sensor.<channel>.gain`), the shape alone is compared. Both spectra
see the same input, window and record length, so the drive's lines and leakage are in
both (picking the largest measured peak instead mistakes a drive line for the mode). At
most `PERIODS` flexural periods are compared and simulated.

The guess is kept when the best match beats it by less than `MIN_GAIN`, or by no more than
noise alone does (`spurious_gain`, a parametric bootstrap of `ROUNDS` noisy copies of the
model's output at the guess), or when the mode lies over 4x the Nyquist frequency. A
progress line warns when no EI reaches `POOR_MATCH` times the shape similarity the model
would reach on its own output plus noise (`spectral_match`'s `ceiling`). Links are
initialised one at a time; `identify.fit_independent` does every log on its own, batched.
The measurements behind these choices are in `docs/identification.md`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from scipy.special import i0e, i1e

import flexdyn as fd

from .._model.residuals import chain_at
from .quality import noise_floors

#: EI factors tried around the guess (flexural frequency ~ sqrt(EI): 1/4 to 4 times the
#: guess's, in steps of 2^(1/4), 19 %)
FACTORS = 2.0 ** (np.arange(-8, 9) / 2)
#: the band of the spectra compared, in multiples of the model's flexural frequency at
#: the guess (it contains the flexural frequency of every factor in `FACTORS`)
BAND = (0.25, 4.0)
#: simulations of the golden-section search between the best factor's neighbours (the
#: bracket, a factor 2 in EI, shrinks to 2^(0.618^6) = 1.04 around the best, 2 % in frequency)
REFINE_EVALS = 8
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
#: the best factor replaces the guess only if its match exceeds the guess's by this
MIN_GAIN = 1e-3
#: below this fraction of the model's own expected shape similarity (`spectral_match`'s
#: `ceiling`) at the best shape of any EI tried, the progress line warns that no EI matches
#: the spectrum well (a model on its own output reaches ~1 of it; a noise-only channel
#: or a model missing an effect falls below: docs/identification.md)
POOR_MATCH = 0.9
#: noise realisations of `spurious_gain`'s parametric bootstrap (the largest of 16: a
#: spurious move from a right guess in ~1 in 17 logs where noise alone decides)
ROUNDS = 16
#: zero padding of the FFT (a finer frequency grid)
PAD = 4
#: the spectra compare at most this many flexural periods of the model at the guess from
#: each log's onset (the simulations stop there): a long log costs no more than a short one
PERIODS = 60.0


#: a free parameter this module initialises: link i's flexural stiffness
STIFFNESS = re.compile(r"link(\d+)\.EI")


def amplitude_spectrum(t, y) -> tuple[np.ndarray, np.ndarray, float]:
    """Frequencies (Hz) and amplitude spectrum `|FFT(w * (y - mean))|` of samples `y` at
    times `t` (s), interpolated onto a uniform grid at the median interval (gaps and
    non-uniform sampling), `w` the Hann window, zero-padded `PAD` times; and `sum(w^2)`,
    the expected power `E|FFT(w n)|^2` in every bin of unit-variance white noise `n`."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    dt = float(np.median(np.diff(t)))
    grid = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)  # t[-1] included
    y = np.interp(grid, t, y)
    w = np.hanning(len(y))
    n = PAD * len(y)
    return np.fft.rfftfreq(n, dt), np.abs(np.fft.rfft((y - y.mean()) * w, n)), float(w @ w)


class Match(NamedTuple):
    """`spectral_match`'s result (see there)."""

    shape: float
    level: float
    ceiling: float
    f_top: float


def expected_amplitude(signal, noise_power):
    """`E|s + n|` of a spectrum bin whose noise-free value has modulus `signal` and whose
    noise `n` is circular complex Gaussian with `E|n|^2 = noise_power`: the mean of the Rice
    distribution, `sqrt(pi N) / 2 * ((1 + 2z) I0e(z) + 2z I1e(z))`, `z = s^2 / (2N)`
    (`I0e`, `I1e` the exponentially scaled modified Bessel functions); `sqrt(pi N) / 2` for
    noise alone (the Rayleigh mean), `-> s` as `N -> 0`."""
    signal = np.asarray(signal, float)
    if noise_power <= 0:
        return signal
    z = signal**2 / (2.0 * noise_power)
    return 0.5 * np.sqrt(np.pi * noise_power) * ((1.0 + 2.0 * z) * i0e(z) + 2.0 * z * i1e(z))


class _Spectra:
    """Amplitude spectra (`amplitude_spectrum`) of channel index `j` of one problem's logs
    in `band` (Hz), each log from its onset up to `span` s after it: the measured one once,
    any simulated series on demand (logs with fewer than 16 such samples are left out)."""

    def __init__(self, problem, j: int, band: tuple[float, float], span: float = np.inf):
        valid, present = np.asarray(problem.valid), np.asarray(problem.present)
        self.parts, self.measured, self.noise_power = [], [], []
        self.f_top = 0.0
        sigma = float(problem.sigma[j])
        for l in range(valid.shape[0]):
            if not present[l, j]:
                continue
            t = np.asarray(problem.t[l])
            keep = valid[l] & (t >= float(problem.onset[l])) & (t <= float(problem.onset[l]) + span)
            if keep.sum() < 16:
                continue
            f, a, white = amplitude_spectrum(t[keep], np.asarray(problem.measured[l, :, j])[keep])
            inside = (f >= band[0]) & (f <= band[1])
            self.parts.append((l, t[keep], keep, inside))
            self.measured.append(a[inside])
            self.noise_power.append(sigma**2 * white)
            self.f_top = max(self.f_top, min(band[1], float(f[-1])))

    def amplitudes(self, series) -> list[np.ndarray]:
        """`|FFT(w (y - mean))|` in the band of each log's series `y` (`series` `(L, T)`)."""
        series = np.asarray(series)
        return [amplitude_spectrum(t, series[l][keep])[1][inside] for l, t, keep, inside in self.parts]

    def match(self, measured, signal, ceiling: bool = True) -> Match:
        """`spectral_match` of measured amplitudes against noise-free simulated ones (both
        from `amplitudes`, or `self.measured`); `ceiling=False` skips the ceiling (0), whose
        Bessel functions the bootstrap's rounds do not need."""
        dot = meas_sq = sim_sq = expected_dot = 0.0
        for a_meas, a_signal, noise_power in zip(measured, signal, self.noise_power):
            a_sim = np.sqrt(a_signal**2 + noise_power)
            dot += float(a_meas @ a_sim)
            meas_sq += float(a_meas @ a_meas)
            sim_sq += float(a_sim @ a_sim)
            if ceiling:
                expected_dot += float(expected_amplitude(a_signal, noise_power) @ a_sim)
        if not (meas_sq > 0 and sim_sq > 0 and np.isfinite(dot)):
            return Match(0.0, 0.0, 0.0, self.f_top)
        return Match(dot / np.sqrt(meas_sq * sim_sq), 2.0 * dot / (meas_sq + sim_sq), expected_dot / sim_sq, self.f_top)


def spectral_match(problem, j: int, predicted, band: tuple[float, float], span: float = np.inf) -> Match:
    """How well the amplitude spectrum expected from `predicted` `(L, T, C)` plus the
    channel's white noise (`problem.sigma[j]`: `A_sim = sqrt(|FFT(w y_sim)|^2 + sigma^2
    sum(w^2))`) matches the measured one `A_meas` of channel index `j`, in `band` (Hz), each
    log from its onset up to `span` s after it, the inner products summed over the logs
    that record the channel. Returns a `Match`:

    - `shape = <A_meas, A_sim> / (|A_meas| |A_sim|)`, the cosine similarity: blind to the
      spectrum's scale;
    - `level = 2 <A_meas, A_sim> / (|A_meas|^2 + |A_sim|^2) = shape * 2r / (1 + r^2)`,
      `r = |A_sim| / |A_meas|`: 1 only when shape and scale both match (a factor-2 error
      in scale alone gives 0.8);
    - `ceiling = <E A, A_sim> / |A_sim|^2`: the shape similarity expected if the log were
      this model's output plus the channel's noise (`E A` per bin from
      `expected_amplitude`, and `E A^2 = A_sim^2`). Noise makes a bin's amplitude random,
      so a band where noise dominates cannot reach 1 even with the true model: noise alone
      gives `sqrt(pi) / 2 = 0.886` (the Rayleigh mean over its RMS);
    - `f_top`: the highest frequency compared, Hz (the band's top, or the logs' Nyquist
      frequency if lower).

    All but `f_top` are 0 when either spectrum has no power in the band. Without the noise
    term, a channel whose noise hides its flexural motion matched a model whose spectrum is
    as flat as the noise's: the stiffest link tried."""
    spectra = _Spectra(problem, j, band, span)
    return spectra.match(spectra.measured, spectra.amplitudes(np.asarray(predicted)[:, :, j]))


def spurious_gain(spectra: _Spectra, signals, guess: int, series, sigma: float, level: bool, rng) -> float:
    """The largest gain in match over the guess that noise alone gives: `ROUNDS` logs
    simulated as `series` `(L, T)` (the model at the guess) plus white noise of standard
    deviation `sigma`, each matched against every tried EI's spectrum `signals[i]` (from
    `spectra.amplitudes`; `guess` the index of the guess's); the largest of the rounds'
    `max_i match_i - match_guess` (`level` or shape, as the estimate compares). A parametric
    bootstrap of the estimate under the hypothesis that the guess is right: a best match
    that beats the guess's by less than this is what noise does, and the guess is kept."""
    series = np.asarray(series)
    out = 0.0
    for _ in range(ROUNDS):
        noisy = spectra.amplitudes(series + rng.normal(0.0, sigma, series.shape))
        matches = [spectra.match(noisy, s, ceiling=False) for s in signals]
        scores = [m.level if level else m.shape for m in matches]
        out = max(out, max(scores) - scores[guess])
    return out


def flexural_frequency(chain: fd.Chain, link: int) -> float | None:
    """Natural frequency (Hz) of the lowest mode of `chain` about its resting pose (hanging
    under gravity, if any) with more than 30 % of its modal kinetic energy (diagonal mass
    approximation) in link `link`'s (0-based) modal coordinates; None if there is none."""
    g = np.asarray(chain.gravity, float)
    lay = chain.layout
    if not lay.modal[link]:
        return None
    Q0 = np.zeros(lay.n_dof)
    if np.linalg.norm(g) > 0:  # about the hanging equilibrium
        Q0[lay.theta[0]] = np.arctan2(g[1], g[0])
        if lay.rotor[0] is not None:
            Q0[lay.rotor[0]] = Q0[lay.theta[0]]
    modes = fd.modal_analysis(chain, jnp.asarray(Q0))
    M = np.diag(np.asarray(fd.mass_matrix(chain, jnp.asarray(Q0))))
    freqs, shapes = np.asarray(modes.natural_frequency), np.asarray(modes.shapes)
    idx = list(lay.modal[link])
    for r in range(len(freqs)):
        energy = M * shapes[:, r] ** 2
        if freqs[r] > 0 and energy[idx].sum() > 0.3 * energy.sum():
            return float(freqs[r])
    return None


def initialise_stiffness(
    problems: Sequence,
    thetas: np.ndarray,
    limits: tuple[np.ndarray, np.ndarray],
    simulate: Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]],
    say: Callable[[str], None],
) -> np.ndarray:
    """`thetas` `(B, P)` (SI, `names` order) with every free `link<i>.EI` that has a
    recorded flexural channel replaced by the matched-spectra estimate (module docstring),
    one link after another, each with the others' current values.

    `problems`: `B` problems with the same parameters, channels and rig structure, each with
    its own parameter values `thetas[b]`: one fit's problem (`identify.fit`, `B = 1`), or
    the one-log problems of independent fits (`identify.fit_independent`), whose
    simulations run as one batch. `limits`: SI bounds `(lower, upper)` `(P,)` that a tried
    value must lie in; `simulate(thetas, span)`: outputs `(B, L, T, C)` of every log of
    every problem up to `span` s (`PERIODS` flexural periods of the model at the guess)
    after its onset, and whether each problem's simulations succeeded `(B,)`."""
    thetas = np.array(thetas, float).reshape(len(problems), -1)
    lower, upper = (np.asarray(b, float) for b in limits)
    first = problems[0]
    for k, name in enumerate(first.names):
        m = STIFFNESS.fullmatch(name)
        if m is None:
            continue
        i = int(m[1]) - 1
        channel = next((c for c in (f"tip{i + 1}", f"curvature{i + 1}") if c in first.channels), None)
        if channel is None or not first.chain.layout.modal[i]:
            continue
        _initialise_link(problems, thetas, (lower[k], upper[k]), simulate, say, k, i, channel)
    return thetas


def _initialise_link(problems, thetas, limits, simulate, say, k: int, link: int, channel: str) -> None:
    """Replace column `k` of `thetas` (`link + 1`'s EI, in place) by the factor of the guess
    whose simulated `channel` spectrum matches the measured one best (grid, then
    golden-section refinement), where it beats the guess by more than noise does."""
    name, n_items = problems[0].names[k], len(problems)
    j = problems[0].channels.index(channel)
    f_model = _flexural_frequencies(problems, thetas, link)
    bands = [None if f is None else (BAND[0] * f, BAND[1] * f) for f in f_model]
    # a mode over 4x the Nyquist frequency leaves no bin of the band in the spectrum
    nyquist = [_nyquist(p, j) for p in problems]
    unresolved = [b is not None and b[0] >= f for b, f in zip(bands, nyquist)]
    if any(unresolved):
        b = unresolved.index(True)
        say(
            f"  frequency initialisation: the model's flexural frequency at the guess of {name} "
            f"({f_model[b]:.3g} Hz) is over 4x the Nyquist frequency of {channel} ({nyquist[b]:.3g} Hz)"
            + (f" in {sum(unresolved)} of {n_items} logs" if n_items > 1 else "")
            + f": the spectrum cannot tell {name}; guess kept"
        )
        if all(unresolved):
            return
        bands = [None if u else b for b, u in zip(bands, unresolved)]
        f_model = [None if u else f for f, u in zip(f_model, unresolved)]
    known = [f for f in f_model if f is not None]
    span = PERIODS / min(known) if known else np.inf
    # the spectrum's scale tells EI too (a drive below the flexural mode deflects the
    # link by ~ load / EI), unless a free gain of the channel's sensor absorbs it
    level = f"sensor.{channel}.gain" not in problems[0].names
    spectra = [None if band is None else _Spectra(p, j, band, span) for p, band in zip(problems, bands)]
    trials = _Trials(thetas, k, j, thetas[:, k].copy(), limits, level, span, spectra, simulate)
    best = trials.grid_and_refine()
    unit = int(np.flatnonzero(FACTORS == 1.0)[0])
    at_guess = trials.grid_scores[:, unit]
    moved = np.isfinite(best.similarity) & (best.factor != 1.0) & (best.similarity >= at_guess + MIN_GAIN)
    # a gain over the guess that noise alone gives does not move it (spurious_gain)
    noise_gain = np.zeros(n_items)
    for b in np.flatnonzero(moved):
        if trials.at_unit[b] is None:
            continue
        sigma = max(float(problems[b].sigma[j]), _floor(problems[b], j))
        guess_index = int(np.sum(np.isfinite(trials.grid_scores[b, :unit])))  # tried factors before the guess
        noise_gain[b] = spurious_gain(
            spectra[b], trials.signals[b], guess_index, trials.at_unit[b], sigma, level, np.random.default_rng(b)
        )
    noisy = moved & (best.similarity - at_guess <= noise_gain)
    moved &= ~noisy
    thetas[:, k] = np.where(moved, trials.guess * best.factor, trials.guess)
    poor = np.isfinite(best.best_shape) & (best.best_shape < POOR_MATCH * best.ceiling)
    if n_items == 1:
        band = None if bands[0] is None else (bands[0][0], min(bands[0][1], best.f_top[0]))
        one = (best.factor[0], best.similarity[0], at_guess[0], moved[0], best.best_shape[0], best.ceiling[0])
        _say_one(say, name, channel, band, *one, poor[0], level, noise_gain[0] if noisy[0] else None)
    else:
        _say_many(say, name, channel, best, moved, noisy, poor)


class _Best(NamedTuple):
    """Per problem `(B,)`: the best factor of EI found and its match (`similarity`), the
    best shape of any EI tried with the model's own `ceiling` there, the top frequency."""

    factor: np.ndarray
    similarity: np.ndarray
    best_shape: np.ndarray
    ceiling: np.ndarray
    f_top: np.ndarray


class _Trials:
    """The simulations of one link's EI at factors of its guess, every problem at once,
    with each problem's simulated spectra kept (`signals`, for the noise bootstrap) and its
    simulated channel at the guess (`at_unit`)."""

    def __init__(self, thetas, k, j, guess, limits, level, span, spectra, simulate):
        self.thetas, self.k, self.j, self.guess, self.limits = thetas, k, j, guess, limits
        self.level, self.span, self.spectra, self.simulate = level, span, spectra, simulate
        n_items = len(spectra)
        self.signals = [[] for _ in range(n_items)]  # per problem: each tried EI's simulated spectra
        self.at_unit = [None] * n_items  # per problem: the guess's simulated channel (L, T)
        self.grid_scores = None

    def scores(self, factors):
        """`(score, shape, ceiling, f_top)` `(B,)` each of every problem with EI at
        `guess * factors`: `spectral_match`'s level (shape alone when `level` is False),
        shape, ceiling and top frequency (score and shape -inf where outside the limits,
        where its simulation failed or there is no band)."""
        value = self.guess * factors
        lower, upper = self.limits
        inside = (value >= lower) & (value <= upper)
        out = np.full((4, len(self.spectra)), -np.inf)
        if not inside.any():
            return out
        trial = self.thetas.copy()
        trial[:, self.k] = np.clip(value, lower, upper)
        outputs, ok = self.simulate(trial, self.span)
        for b, spectra in enumerate(self.spectra):
            if inside[b] and ok[b] and spectra is not None:
                series = np.asarray(outputs[b])[:, :, self.j]
                if factors[b] == 1.0:
                    self.at_unit[b] = series
                self.signals[b].append(spectra.amplitudes(series))
                m = spectra.match(spectra.measured, self.signals[b][-1])
                out[:, b] = (m.level if self.level else m.shape, m.shape, m.ceiling, m.f_top)
        return out

    def grid_and_refine(self) -> _Best:
        """The best of `FACTORS` for each problem, refined by a golden-section search of
        log EI between its neighbours (a lightly damped mode's peak is narrower than the
        grid's 9 % steps in frequency)."""
        n_items, n_factors = len(self.spectra), len(FACTORS)
        tried = np.stack([self.scores(np.full(n_items, f)) for f in FACTORS], axis=2)  # (4, B, F)
        scores, shapes, ceilings = tried[0], tried[1], tried[2]
        self.grid_scores = scores
        best = np.argmax(scores, axis=1)
        rows = np.arange(n_items)
        # the warning's measure: the best shape of any EI tried (a channel whose scale is
        # off matches its best shape at another EI than its best level), against the shape
        # that EI's model would reach on its own output plus the channel's noise
        at_best_shape = np.argmax(shapes, axis=1)
        found = _Best(
            FACTORS[best].astype(float),
            scores[rows, best],
            shapes[rows, at_best_shape],
            ceilings[rows, at_best_shape],
            np.max(tried[3], axis=1),
        )
        refine = np.asarray([0 < best[b] < n_factors - 1 and np.isfinite(found.similarity[b]) for b in rows])
        if not refine.any():
            return found
        lo = np.log(FACTORS[np.clip(best - 1, 0, n_factors - 1)])
        hi = np.log(FACTORS[np.clip(best + 1, 0, n_factors - 1)])
        return self._golden(found, refine, lo, hi)

    def _golden(self, found: _Best, refine, lo, hi) -> _Best:
        """Golden-section search of log EI in `[lo, hi]` where `refine`, `REFINE_EVALS`
        simulations, keeping the best level and the best shape seen."""
        state = [found]

        def evaluate(log_factor):
            f = state[0]
            trial = np.where(refine, np.exp(log_factor), f.factor)
            score, shape, ceil, _ = self.scores(trial)
            better = refine & (score > f.similarity)
            shape_better = refine & (shape > f.best_shape)
            state[0] = f._replace(
                factor=np.where(better, trial, f.factor),
                similarity=np.where(better, score, f.similarity),
                best_shape=np.where(shape_better, shape, f.best_shape),
                ceiling=np.where(shape_better, ceil, f.ceiling),
            )
            return np.where(np.isfinite(score), score, -np.inf)

        inner = [hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)]
        value = [evaluate(inner[0]), evaluate(inner[1])]
        for _ in range(REFINE_EVALS - 2):
            left = value[0] >= value[1]  # the maximum lies in [lo, inner[1]]
            hi = np.where(left, inner[1], hi)
            lo = np.where(left, lo, inner[0])
            new = np.where(left, hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo))
            score = evaluate(new)
            inner = [np.where(left, new, inner[1]), np.where(left, inner[0], new)]
            value = [np.where(left, score, value[1]), np.where(left, value[0], score)]
        return state[0]


def _say_many(say, name, channel, best: _Best, moved, noisy, poor) -> None:
    """The progress lines of one link's initialisation over many logs."""
    n_items = len(moved)
    moved_by = best.factor[moved]
    say(
        f"  frequency initialisation of {name} from {channel}'s spectrum, {n_items} logs: "
        + (
            f"moved in {int(moved.sum())} (x{moved_by.min():.3g} to x{moved_by.max():.3g}, "
            f"median x{np.median(moved_by):.3g}), "
            if moved.any()
            else ""
        )
        + f"guess kept in {int((~moved).sum())}"
        + (
            f" ({int(noisy.sum())} where the best match beat the guess's by no more than noise does)"
            if noisy.any()
            else ""
        )
    )
    if poor.any():
        worst = int(np.argmin(np.where(poor, best.best_shape / best.ceiling, np.inf)))
        say(
            f"  frequency initialisation: WARNING: in {int(poor.sum())} log(s) no {name} tried makes the "
            f"model's {channel} spectrum match the shape of the log's well (at worst shape similarity "
            f"{best.best_shape[worst]:.3f}, where the model with the channel's noise would reach "
            f"{best.ceiling[worst]:.3f}): little flexural motion recorded, noise above the channel's, or the "
            "model misses what shapes it"
        )


def _floor(problem, j: int) -> float:
    """The model-free noise floor (`identify.noise_floor.series_floor`; at least a declared
    resolution's noise: `quality.noise_floors`) of channel index `j`, RMS over the logs
    that record it (by their samples)."""
    floor, count = noise_floors(problem)
    n = count[:, j].sum()
    return float(np.sqrt(np.sum(count[:, j] * floor[:, j] ** 2) / n)) if n else 0.0


def _nyquist(problem, j: int) -> float:
    """The highest Nyquist frequency (Hz, half the rate at the median interval) of the
    problem's logs that record channel index `j`; 0 if none does."""
    valid, present = np.asarray(problem.valid), np.asarray(problem.present)
    out = 0.0
    for l in range(valid.shape[0]):
        t = np.asarray(problem.t[l])[valid[l]]
        if present[l, j] and len(t) > 1:
            out = max(out, 0.5 / float(np.median(np.diff(t))))
    return out


def _flexural_frequencies(problems, thetas, link: int) -> list[float | None]:
    """`flexural_frequency` of each problem's rig at its parameters (one modal analysis per
    distinct parameter vector and known values: at the start, every independent fit has the
    same guess, but each log may set its own payload, `LogData.set`, or fit its own,
    `Parameter.per_log`: the first log's rig is taken)."""
    seen = {}
    out = []
    for problem, theta in zip(problems, thetas):
        first = np.asarray(problem.log_set[0]) if problem.log_set_names else None  # (the first log's known values)
        key = theta.tobytes() + (b"" if first is None else first.tobytes())
        if key not in seen:
            seen[key] = flexural_frequency(chain_at(problem, jnp.asarray(theta), first, 0), link)
        out.append(seen[key])
    return out


def _say_one(say, name, channel, band, factor, similarity, at_guess, moved, best_shape, ceiling, poor, level, noise):
    if band is not None and band[1] <= 0:
        say(f"  frequency initialisation: no log records 16 samples of {channel} from its onset: {name} kept")
        return
    if band is None or not np.isfinite(similarity):
        say(f"  frequency initialisation: no spectrum of {channel} to compare (failed simulations): {name} kept")
        return
    where = f"{channel}'s spectrum ({band[0]:.3g}-{band[1]:.3g} Hz{'' if level else ', shape only: its gain is free'})"
    if poor:
        say(
            f"  frequency initialisation: WARNING: no {name} tried makes the model match the shape of {where} well "
            f"(best shape similarity {best_shape:.3f}, where the model with the channel's noise would reach "
            f"{ceiling:.3f}): the channel may record little flexural motion (noise only? units?), its noise may be "
            "larger than the fit assumes, or the model misses what shapes it"
        )
    if factor == 1.0:
        say(f"  frequency initialisation: {where} matches the model best at the guess of {name} ({similarity:.3f})")
    elif noise is not None:
        say(
            f"  frequency initialisation: {where} does not single out {name}: its best match (x{factor:.3g}, "
            f"{similarity:.3f}) beats the guess's ({at_guess:.3f}) by no more than noise alone does (up to "
            f"{noise:.3f} in {ROUNDS} simulated logs of the model at the guess with the channel's noise): guess kept"
        )
    elif not moved:
        say(
            f"  frequency initialisation: {where} does not single out {name} (match {similarity:.3f} at "
            f"x{factor:.3g}, {at_guess:.3f} at the guess): guess kept"
        )
    else:
        say(
            f"  frequency initialisation: {where} matches the model's best at {name} x{factor:.3g} "
            f"(match {similarity:.3f}; {at_guess:.3f} at the guess)"
        )
