"""Frequency-domain initial guesses of flexural stiffness (`link<i>.EI`) before a fit.

A 2x error in EI puts a simulated oscillation out of phase after a few periods, and the
time-domain loss has a local minimum per period slip (`identify.fit`); the amplitude
spectrum of a recorded flexural channel (tip deflection or root curvature) carries no
phase, so matching it is a nearly convex one-dimensional problem in EI.

**Matched spectra, not peak picking.** For each free `link<i>.EI` whose link has modes and
whose `tip<i>` or `curvature<i>` channel is recorded, the model is simulated with the
logs' own inputs and initial states at the guesses, with EI scaled by each factor of
`FACTORS` (1/16 to 16: the flexural frequency from 1/4 to 4 times the guess's), and the
factor is chosen whose simulated channel's amplitude spectrum, with the channel's noise
floor, matches the measured one best in shape and in level,

    match(s) = 2 <A_meas, A_model(s)> / (|A_meas|^2 + |A_model(s)|^2),
    A_meas = |FFT(w (y - mean y))|,   A_model(s) = sqrt(|FFT(w (y_sim(s) - mean))|^2 + sigma^2 sum w^2)

(`w` the Hann window, `sigma` the channel's noise level) of each log from its onset
(`identify.log_onset`), the inner products summed over the logs. `match` is the cosine
similarity of the two spectra (their shape) times `2r / (1 + r^2)`, `r = |A_model| /
|A_meas|` (their level); it is 1 only when both agree. When the channel's sensor gain is a
free parameter (`sensor.<channel>.gain`), the gain absorbs the level, and the shape alone
(the cosine) is compared. The spectra are compared over
the band from 1/4 to 4 times the model's flexural frequency at the guess (the modal
analysis about the resting pose), the inner products summed over the logs. A parabola
through the best factor and its neighbours (in log EI) refines it with one more
simulation. Both spectra see the same input, window and record length, so whatever the
input puts into the spectrum (a driving sine's line, a square wave's harmonics, the
leakage of a short record) is in both. At most `PERIODS` (60) flexural periods of the
model at the guess are compared from each log's onset, and simulated: a long log costs
no more than one of that length.

Picking the largest peak of the measured spectrum and scaling EI by the squared ratio of
its frequency to the model's natural frequency (what `identify.fit` did before) assumed
that the peak is the free flexural vibration. Measured on the 4-parameter flexible arm
(`tests/identify/test_frequency_init.py`, flexural mode 4.2 Hz, guesses EI x0.5 or x2,
the other three parameters 20 % off): a 1.5 Hz sine drive put EI at 0.14 of the truth, a
7 Hz drive at 3.0, a 1 Hz square wave at 0.05, a record that ends 0.2 s after its
doublet at 0.52, and the default fit from the sine-driven logs ended in a wrong basin
(damping on its bound, payload +46 %) where the fit without the initialisation
converged. Matched spectra put EI at the truth within the factor grid's resolution in
every one of those cases.

`identify.fit_independent` does this for every log on its own (each log its own EI), the
simulations of all logs batched: one vmapped call per factor.

**Shape and level.** The shape alone (the cosine similarity, which this module compared
until 2026-12-02) cannot tell EI when the response is forced well below the flexural
mode: the spectrum is the drive's lines at every EI, and only their height, the
quasi-static deflection ~ load / EI, depends on it. Measured on paper 004's two-link arm
(`fd.rigs.flexible_link_joint_arm`) driven by 1.0 and 1.7 Hz sines for 2 s, guesses (EI1,
EI2) at (0.5, 2), (2, 0.5), (1.4, 1.4) of the truth: with the shape alone EI1 went to
0.85, 1.34, 0.88 and EI2 hardly moved (2.0, 0.58, 1.4: its tip's spectrum had a cosine of
0.99-1.00 at every factor tried); with the level as well, (0.91, 1.04), (1.00, 1.00),
(0.99, 0.99) (`tests/identify/test_frequency_init.py`). The single-link cases above are
found either way. The level is what the fit's own time-domain loss sees: a tip channel
recorded twice too large with its gain fixed puts EI at 0.78 of the truth here (a softer
link deflects more), where the fit would go too; with the gain free, at the truth.

The spectrum cannot always tell: when the best match is less than `MIN_GAIN` above
the guess's (a record with no flexural motion, a drive whose response hardly depends on
EI), the guess is kept. The links are initialised one at a time, each with the others'
current values. A tip channel that records only noise (1 % of the true deflection's RMS)
matched a 4 to 16 times stiffer link than the guess (8 trials, shape alone): the flattest
simulated spectra; the data then say that the link hardly deflects, as the fit itself
would. The progress line warns when no EI tried reaches a shape similarity of `POOR_MATCH`.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .residuals import _chain

#: EI factors tried around the guess (flexural frequency ~ sqrt(EI): 1/4 to 4 times the
#: guess's, in steps of 2^(1/4), 19 %)
FACTORS = 2.0 ** (np.arange(-8, 9) / 2)
#: the band of the spectra compared, in multiples of the model's flexural frequency at
#: the guess (it contains the flexural frequency of every factor in `FACTORS`)
BAND = (0.25, 4.0)
#: the best factor replaces the guess only if its match exceeds the guess's by this
MIN_GAIN = 1e-3
#: below this best shape similarity (cosine) of any EI tried, the progress line warns that
#: no EI matches the spectrum well (measured: >= 0.99 on every synthetic log the model
#: generated; 0.75-0.86 for a tip channel of noise only; 0.79 on the spinning-link example,
#: whose model lacks geometric stiffening)
POOR_MATCH = 0.9
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


def spectral_match(problem, j: int, predicted, band: tuple[float, float], span: float = np.inf) -> tuple[float, float]:
    """How well the amplitude spectrum expected from `predicted` `(L, T, C)` plus the
    channel's white noise (`problem.sigma[j]`: `A_sim = sqrt(|FFT(w y_sim)|^2 + sigma^2
    sum(w^2))`) matches the measured one `A_meas` of channel index `j`, in `band` (Hz), each
    log from its onset up to `span` s after it, the inner products summed over the logs
    that record the channel. Returns `(shape, level)`:

    - `shape = <A_meas, A_sim> / (|A_meas| |A_sim|)`, the cosine similarity: blind to the
      spectrum's scale;
    - `level = 2 <A_meas, A_sim> / (|A_meas|^2 + |A_sim|^2) = shape * 2r / (1 + r^2)`,
      `r = |A_sim| / |A_meas|`: 1 only when shape and scale both match (a factor-2 error
      in scale alone gives 0.8).

    Both are 0 when either spectrum has no power in the band. Without the noise term, a
    channel whose noise hides its flexural motion matched a model whose spectrum is as flat
    as the noise's: the stiffest link tried."""
    dot = meas_sq = sim_sq = 0.0
    valid, present = np.asarray(problem.valid), np.asarray(problem.present)
    for l in range(valid.shape[0]):
        if not present[l, j]:
            continue
        t = np.asarray(problem.t[l])
        keep = valid[l] & (t >= float(problem.onset[l])) & (t <= float(problem.onset[l]) + span)
        if keep.sum() < 16:
            continue
        f, a_meas, _ = amplitude_spectrum(t[keep], np.asarray(problem.measured[l, :, j])[keep])
        _, a_sim, white = amplitude_spectrum(t[keep], np.asarray(predicted[l, :, j])[keep])
        a_sim = np.sqrt(a_sim**2 + float(problem.sigma[j]) ** 2 * white)
        inside = (f >= band[0]) & (f <= band[1])
        dot += float(a_meas[inside] @ a_sim[inside])
        meas_sq += float(a_meas[inside] @ a_meas[inside])
        sim_sq += float(a_sim[inside] @ a_sim[inside])
    if not (meas_sq > 0 and sim_sq > 0 and np.isfinite(dot)):
        return 0.0, 0.0
    return dot / np.sqrt(meas_sq * sim_sq), 2.0 * dot / (meas_sq + sim_sq)


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
    n_items, n_factors = len(problems), len(FACTORS)
    unit = int(np.flatnonzero(FACTORS == 1.0)[0])
    for k, name in enumerate(first.names):
        m = STIFFNESS.fullmatch(name)
        if m is None:
            continue
        i = int(m[1]) - 1
        channel = next((c for c in (f"tip{i + 1}", f"curvature{i + 1}") if c in first.channels), None)
        if channel is None or not first.chain.layout.modal[i]:
            continue
        j = first.channels.index(channel)
        f_model = _flexural_frequencies(problems, thetas, i)
        bands = [None if f is None else (BAND[0] * f, BAND[1] * f) for f in f_model]
        known = [f for f in f_model if f is not None]
        span = PERIODS / min(known) if known else np.inf
        guess = thetas[:, k].copy()
        # the spectrum's scale tells EI too (a drive below the flexural mode deflects the
        # link by ~ load / EI), unless a free gain of the channel's sensor absorbs it
        level = f"sensor.{channel}.gain" not in first.names

        def scores_at(factors, k=k, j=j, bands=bands, guess=guess, span=span, level=level):
            """`(score, shape)` `(B,)` each of every problem with EI at `guess * factors`:
            `spectral_match`'s level (shape alone when `level` is False) and shape (-inf
            where outside the limits, where its simulation failed or there is no band)."""
            value = guess * factors
            inside = (value >= lower[k]) & (value <= upper[k])
            score, shape = np.full(n_items, -np.inf), np.full(n_items, -np.inf)
            if not inside.any():
                return score, shape
            trial = thetas.copy()
            trial[:, k] = np.clip(value, lower[k], upper[k])
            outputs, ok = simulate(trial, span)
            for b in range(n_items):
                if inside[b] and ok[b] and bands[b] is not None:
                    shape[b], matched = spectral_match(problems[b], j, outputs[b], bands[b], span)
                    score[b] = matched if level else shape[b]
            return score, shape

        tried = [scores_at(np.full(n_items, f)) for f in FACTORS]
        scores = np.stack([score for score, _ in tried], axis=1)  # (B, F)
        shapes = np.stack([shape for _, shape in tried], axis=1)
        best = np.argmax(scores, axis=1)
        factor = FACTORS[best].astype(float)
        similarity = scores[np.arange(n_items), best]
        # the warning's measure: the best shape of any EI tried (a channel whose scale is
        # off matches its best shape at another EI than its best level)
        best_shape = np.max(shapes, axis=1)
        # the vertex of the parabola through the best factor and its neighbours (log EI)
        vertex = factor.copy()
        refine = np.zeros(n_items, bool)
        h = np.log(FACTORS[1] / FACTORS[0])
        for b in range(n_items):
            if 0 < best[b] < n_factors - 1:
                s_m, s_0, s_p = scores[b, best[b] - 1 : best[b] + 2]
                curvature = s_m - 2.0 * s_0 + s_p
                if np.all(np.isfinite([s_m, s_0, s_p])) and curvature < 0:
                    vertex[b] = factor[b] * np.exp(0.5 * h * (s_m - s_p) / curvature)
                    refine[b] = True
        if refine.any():
            at_vertex, shape_at_vertex = scores_at(vertex)
            better = refine & (at_vertex > similarity)
            factor = np.where(better, vertex, factor)
            similarity = np.where(better, at_vertex, similarity)
            best_shape = np.maximum(best_shape, np.where(refine, shape_at_vertex, -np.inf))
        at_guess = scores[:, unit]
        moved = np.isfinite(similarity) & (factor != 1.0) & (similarity >= at_guess + MIN_GAIN)
        thetas[:, k] = np.where(moved, guess * factor, guess)
        if n_items == 1:
            one = (factor[0], similarity[0], at_guess[0], moved[0], best_shape[0])
            _say_one(say, name, channel, bands[0], *one, level)
        else:
            moved_by = factor[moved]
            say(
                f"  frequency initialisation of {name} from {channel}'s spectrum, {n_items} logs: "
                + (
                    f"moved in {int(moved.sum())} (x{moved_by.min():.3g} to x{moved_by.max():.3g}, "
                    f"median x{np.median(moved_by):.3g}), "
                    if moved.any()
                    else ""
                )
                + f"guess kept in {int((~moved).sum())}"
            )
            poor = np.isfinite(best_shape) & (best_shape < POOR_MATCH)
            if poor.any():
                say(
                    f"  frequency initialisation: WARNING: in {int(poor.sum())} log(s) no {name} tried makes the "
                    f"model's {channel} spectrum match the shape of the log's well (shape similarity "
                    f"{best_shape[poor].min():.3f} at worst): little flexural motion recorded, or the model misses "
                    "what shapes it"
                )
    return thetas


def _flexural_frequencies(problems, thetas, link: int) -> list[float | None]:
    """`flexural_frequency` of each problem's rig at its parameters (one modal analysis per
    distinct parameter vector: at the start, every independent fit has the same guess)."""
    seen = {}
    out = []
    for problem, theta in zip(problems, thetas):
        key = theta.tobytes()
        if key not in seen:
            seen[key] = flexural_frequency(_chain(problem, jnp.asarray(theta)), link)
        out.append(seen[key])
    return out


def _say_one(say, name, channel, band, factor, similarity, at_guess, moved, best_shape, level):
    if band is None or not np.isfinite(similarity):
        say(f"  frequency initialisation: no spectrum of {channel} to compare (failed simulations): {name} kept")
        return
    where = f"{channel}'s spectrum ({band[0]:.3g}-{band[1]:.3g} Hz{'' if level else ', shape only: its gain is free'})"
    if best_shape < POOR_MATCH:
        say(
            f"  frequency initialisation: WARNING: no {name} tried makes the model match the shape of {where} well "
            f"(best shape similarity {best_shape:.3f}): the channel may record little flexural motion "
            "(noise only? units?), or the model misses what shapes it"
        )
    if factor == 1.0:
        say(f"  frequency initialisation: {where} matches the model best at the guess of {name} ({similarity:.3f})")
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
