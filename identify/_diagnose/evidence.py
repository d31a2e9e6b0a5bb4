"""Evidence of what a fitted model gets wrong, from its residuals: numbers a person can
read and check, computed after the baseline fit by `identify.diagnose`.

- `windows`: residual RMS per channel in consecutive time windows (does the miss grow
  with time, as an unmodelled dissipation law makes it?).
- `spectrum_peaks`: the largest peaks of the residual's periodogram, each with the
  nearest natural frequency of the fitted model (a peak far from every mode is an
  unmodelled mode or a sensor/drive effect) and whether it stands above the noise around
  it (a false-alarm probability below 1 %).
- `decay_law`: for a free oscillation, the envelope of successive half swings
  `A_k` (`swing_amplitudes`) fitted three ways: exponential (`log A` linear in t: viscous damping), linear
  (`A` linear in t: dry friction, losing `2 F_c / k` per half period) and hyperbolic
  (`1/A` linear in t: quadratic drag, `dA/dt ~ -A^2`); R^2 of each, for the
  measurement and the simulation.
- `frequency_drift`: oscillation frequency from successive zero crossings against
  amplitude (a pendulum's frequency falls with amplitude; a model that misses it
  shows a drift the data do not have, or the other way round).
- `feature_correlation`: correlation of the residual with features of the simulated
  motion (sign of velocity, velocity |velocity|, position, velocity, acceleration, the
  input): dry friction correlates with sign(v), drag with v|v|, a delay with v, a gain
  error with the position itself.

Model checks (not residual statistics: what the fitted model assumes that the logs may
break):

- `stiffening_checks`: for every flexible link without geometric stiffening, how much
  the stiffening it leaves out would raise its first mode's squared frequency at the
  fastest spin of the logs (and the largest acceleration of its root, on a chain) and
  under the rig's gravity (`flexdyn.stiffening`); above 1 % the check is flagged. A
  fitted EI absorbs the missing stiffness: on a chain fitted without it, `EI_fitted /
  EI_true = 1 / (1 - shift)` (`ei_bias_factor`).
"""

from __future__ import annotations

import numpy as np

from flexdyn.stiffening import first_mode_stiffening

from .._data.units import display_unit
from . import residual_tests as diagnostics

STIFFENING_THRESHOLD = 0.01  # relative change of omega_1^2 above which a check is flagged


def _uniform(t, y):
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    return grid, np.interp(grid, t, y), dt


def windows(t, residual, n: int = 5) -> list[dict]:
    edges = np.linspace(t[0], t[-1], n + 1)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        k = (t >= a) & (t <= b)
        out.append(
            {"t0": float(a), "t1": float(b), "rms": float(np.sqrt(np.mean(residual[k] ** 2))) if k.any() else 0.0}
        )
    return out


def periodogram(t, y):
    """One-sided periodogram (Hann window, mean removed): frequencies (Hz), power density."""
    _, y, dt = _uniform(t, y)
    w = np.hanning(len(y))
    y = (y - y.mean()) * w
    n = 4 * len(y)
    p = np.abs(np.fft.rfft(y, n)) ** 2 * dt / np.sum(w**2)
    return np.fft.rfftfreq(n, dt), p


#: `spectrum_peaks`: the false-alarm probability below which a peak is called significant
PEAK_FALSE_ALARM = 0.01
#: `spectrum_peaks`: periods in the log below which a peak is not judged (a trend, not a line)
PEAK_MIN_PERIODS = 8
#: `spectrum_peaks`: effectively independent maxima per independent frequency (calibrated
#: on white noise, see the docstring)
PEAK_SEARCH_FACTOR = 3.0


def _background(independent, k: int) -> float:
    """Mean of the independent periodogram ordinates around bin `k`: half of `k` bins on
    each side (20 to 100), leaving out the 3 nearest each side (a Hann-windowed peak's own
    lobe)."""
    w = int(min(max(0.5 * k, 20), 100))
    near = np.concatenate([independent[max(k - w, 0) : max(k - 3, 0)], independent[k + 4 : k + w + 1]])
    return float(np.mean(near)) if near.size else 0.0


def spectrum_peaks(t, residual, modal_frequencies_hz, n_peaks: int = 3) -> list[dict]:
    """The `n_peaks` largest local maxima of the residual's periodogram, each with its share
    of the total power, the nearest natural frequency of the model, and whether it stands
    above the noise around it.

    Significance: an ordinate of the periodogram of Gaussian noise of smooth spectral
    density S is S times an Exp(1) variable (chi^2 with 2 degrees of freedom over 2). S is
    estimated by the mean of the ordinates around the peak (`_background`: a window that
    widens with frequency, so a coloured background is followed). A peak of `ratio` times
    it arises by chance somewhere in the spectrum with probability `false_alarm = 1 -
    (1 - exp(-ratio))^M` (Fisher's test for the largest of M such variables), M the
    number of maxima noise can put there: the n/2 independent frequencies of n samples
    times `PEAK_SEARCH_FACTOR` = 3, which accounts for the peak searched on a 4x finer
    grid between them and for the error of the estimated background (calibrated on
    white noise: with it, one of the 3 peaks is `significant`, `false_alarm <
    PEAK_FALSE_ALARM`, in 0.7-1.3 % of records of 300 to 10,000 samples, and in 0-1 % of
    AR(1) noise of coefficient 0.9 or 0.99, whose spectrum falls steeply; 300 records
    each). A peak of fewer than `PEAK_MIN_PERIODS` periods in the log is a trend, not a
    line: its `significant` is None (a lower limit lets coloured noise pass for a line:
    docs/performance.md)."""
    f, p = periodogram(t, residual)
    if len(p) < 5:
        return []
    pad = 4  # `periodogram` zero-pads 4x: bins of the padded grid per independent one
    n_search = PEAK_SEARCH_FACTOR * max((len(p) - 1) // pad, 1)
    is_peak = (p[1:-1] > p[:-2]) & (p[1:-1] >= p[2:])
    idx = np.nonzero(is_peak)[0] + 1
    idx = idx[np.argsort(-p[idx])][:n_peaks]
    modes = np.asarray([m for m in modal_frequencies_hz if m > 0], float)
    total = float(np.sum(p)) or 1.0
    independent = p[::pad]
    out = []
    for i in idx:
        k = int(round(i / pad))
        entry = {"frequency_hz": float(f[i]), "power_fraction": float(p[i] / total)}
        background = _background(independent, k)
        if k < PEAK_MIN_PERIODS or background <= 0:
            entry.update(above_background=None, false_alarm=None, significant=None)
        else:
            ratio = float(p[i] / background)
            false_alarm = float(-np.expm1(n_search * np.log1p(-np.exp(-ratio))))
            entry.update(above_background=ratio, false_alarm=false_alarm, significant=false_alarm < PEAK_FALSE_ALARM)
        if modes.size:
            j = int(np.argmin(np.abs(modes - f[i])))
            entry["nearest_mode_hz"] = float(modes[j])
            entry["relative_distance"] = float(abs(modes[j] - f[i]) / modes[j])
        out.append(entry)
    return out


def _peak_text(p: dict) -> str:
    """One spectrum peak as the report shows it."""
    if p["significant"] is None:
        judged = f"under {PEAK_MIN_PERIODS} periods in the log: a trend, not judged"
    else:
        verdict = "significant" if p["significant"] else "within the noise"
        judged = f"{p['above_background']:.3g}x the local background: {verdict}"
    mode = f"; model mode {p['nearest_mode_hz']:.3g} Hz" if "nearest_mode_hz" in p else ""
    return f"{p['frequency_hz']:.3g} Hz ({judged}{mode})"


#: `decay_law`: the R^2 below which no decay law is named (the envelope is not a straight
#: line in any of the three coordinates)
DECAY_R2_MIN = 0.9


START_SWING_FRACTION = 0.9  # of the next half swing's time (see `swing_amplitudes`)


def swing_amplitudes(t, y, noise: float = 0.0):
    """Times and amplitudes of the half swings of an oscillation `y(t)`: between each turning
    point and the next (a maximum, then a minimum, ...), half their difference, at their
    mid-time.

    Half a swing does not depend on the level the oscillation is centred on: a log's
    sensor offset, or an equilibrium a log does not settle at within its span (the
    amplitudes of the extrema about a mean level alternate between two sequences then,
    which no decay law fits, as on the real pendulum). A turning point counts when
    `y` has moved back from it by more than `max(10 noise, 2 quantum, 1e-3 range)`
    (`quantum`: the smallest change between samples, an encoder's step; a peak-detector's
    hysteresis: near a turning point, where the signal is flat for tens of samples, the
    running extremes of white noise reach +-2.5 standard deviations, so 3 of them would
    make false turning points; one turning point per plateau of a quantised encoder). The
    decay laws hold for half swings as for amplitudes: a constant loss per half period
    (dry friction) stays linear, a constant ratio (viscous) stays exponential.

    The log's start counts as the first turning point (a release from rest: its largest
    half swing) when the time from it to the first turning point found is at least
    `START_SWING_FRACTION` of the next half swing's: a log that starts mid-swing would
    otherwise add a partial half swing, too small for its time."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    if y.size < 3:
        return np.zeros(0), np.zeros(0)
    steps = np.abs(np.diff(y))
    quantum = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0  # an encoder's step
    delta = max(10.0 * float(noise), 2.0 * quantum, 1e-3 * float(np.ptp(y)), 1e-300)
    turns_t, turns_y = [], []
    hi_i = lo_i = 0  # the running maximum / minimum since the last turning point
    rising = None  # unknown until y has moved by delta
    start = None  # the extreme y moved away from first: a turning point if y started at rest
    for i in range(1, y.size):
        if y[i] > y[hi_i]:
            hi_i = i
        if y[i] < y[lo_i]:
            lo_i = i
        if rising is None:
            if y[hi_i] - y[lo_i] > delta:
                rising = hi_i > lo_i
                start = lo_i if rising else hi_i
            continue
        if rising and y[hi_i] - y[i] > delta:  # a maximum at hi_i
            turns_t.append(t[hi_i]), turns_y.append(y[hi_i])
            rising, lo_i = False, i
        elif not rising and y[i] - y[lo_i] > delta:  # a minimum at lo_i
            turns_t.append(t[lo_i]), turns_y.append(y[lo_i])
            rising, hi_i = True, i
    if len(turns_t) >= 2 and turns_t[0] - t[start] >= START_SWING_FRACTION * (turns_t[1] - turns_t[0]):
        turns_t.insert(0, t[start]), turns_y.insert(0, y[start])
    turns_t, turns_y = np.asarray(turns_t), np.asarray(turns_y)
    return 0.5 * (turns_t[1:] + turns_t[:-1]), 0.5 * np.abs(np.diff(turns_y))


def _r2(x, y):
    if len(x) < 3 or np.ptp(x) == 0:
        return float("nan"), float("nan")
    A = np.vstack([x, np.ones_like(x)]).T
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    ss = np.sum((y - y.mean()) ** 2)
    return float(1 - resid @ resid / ss) if ss > 0 else float("nan"), float(coef[0])


def decay_law(t, y, noise: float = 0.0) -> dict | None:
    """Envelope fits of a free oscillation (see the module docstring) to its half swings
    (`swing_amplitudes`); None if it has fewer than 6 half swings above 5x the noise.
    `best`: the law of highest R^2, or "inconclusive" when none reaches `DECAY_R2_MIN`."""
    tp, a = swing_amplitudes(t, y, noise)
    keep = a > max(5 * noise, 1e-12)
    tp, a = tp[keep], a[keep]
    if len(a) < 6:
        return None
    r_exp, s_exp = _r2(tp, np.log(a))
    r_lin, s_lin = _r2(tp, a)
    r_hyp, s_hyp = _r2(tp, 1.0 / a)
    fits = {"exponential": r_exp, "linear": r_lin, "hyperbolic": r_hyp}
    best = max(fits, key=lambda k: -np.inf if np.isnan(fits[k]) else fits[k])
    return {
        "n_half_swings": int(len(a)),
        "r2": fits,
        "best": best if fits[best] >= DECAY_R2_MIN else "inconclusive",
        "exponential_rate_per_s": -s_exp,
        "linear_slope_per_s": s_lin,
        "amplitude_first_last": [float(a[0]), float(a[-1])],
    }


def frequency_drift(t, y) -> dict | None:
    """Frequency from zero crossings of `y - mean` against the local amplitude."""
    level = np.mean(y[int(0.8 * len(y)) :])
    d = y - level
    s = np.signbit(d)
    k = np.nonzero(s[1:] != s[:-1])[0]
    if len(k) < 6:
        return None
    tc = t[k] - d[k] * (t[k + 1] - t[k]) / (d[k + 1] - d[k])
    half = np.diff(tc)
    freq = 0.5 / half
    amp = np.array([np.max(np.abs(d[a : b + 1])) for a, b in zip(k[:-1], k[1:])])
    r2, slope = _r2(amp, freq)
    return {
        "frequency_hz_first_last": [float(freq[0]), float(freq[-1])],
        "amplitude_first_last": [float(amp[0]), float(amp[-1])],
        "slope_hz_per_unit": slope,
        "r2": r2,
    }


def features(t, simulated, torque=None) -> dict:
    """Features of the simulated motion of one channel (see the module docstring)."""
    v = np.gradient(simulated, t)
    acc = np.gradient(v, t)
    scale = 0.05 * (np.std(v) or 1.0)
    out = {
        "sign(velocity)": np.tanh(v / scale),
        "velocity|velocity|": v * np.abs(v),
        "velocity": v,
        "position": simulated - np.mean(simulated),
        "acceleration": acc,
    }
    if torque is not None and np.any(torque != 0):
        out["input"] = torque
    return out


def feature_correlation(residual, feats: dict) -> dict:
    out = {}
    for name, f in feats.items():
        if np.std(f) == 0 or np.std(residual) == 0:
            out[name] = 0.0
        else:
            out[name] = float(np.corrcoef(residual, f)[0, 1])
    return out


def evidence(outputs: dict, sigma: dict, modal_frequencies_hz, torques: dict | None = None) -> dict:
    """All of the above for every log and channel of `fitted_outputs(...)`."""
    report = {}
    for log, entry in outputs.items():
        t = entry["t"]
        per = {}
        for c, r in entry["residual"].items():
            m, s = entry["measured"][c], entry["simulated"][c]
            tq = None if not torques or log not in torques else torques[log]
            item = {
                "rms": float(np.sqrt(np.mean(r**2))),
                "noise_sigma": float(sigma.get(c, 0.0)),
                "windows": windows(t, r),
                "spectrum_peaks": spectrum_peaks(t, r, modal_frequencies_hz),
                "whiteness": {
                    k: v for k, v in diagnostics.whiteness(r).items() if k in ("ljung_box_q", "p_value", "white")
                },
                "decay_law": {"measured": decay_law(t, m, sigma.get(c, 0.0)), "simulated": decay_law(t, s)},
                "frequency_drift": {"measured": frequency_drift(t, m), "simulated": frequency_drift(t, s)},
                "feature_correlation": feature_correlation(r, features(t, s, tq)),
            }
            per[c] = item
        report[log] = per
    return report


def summary_lines(ev: dict) -> list[str]:
    """A few readable lines per log and channel."""
    lines = []
    for log, per in ev.items():
        for c, item in per.items():
            scale, unit = display_unit(c)
            w = ", ".join(f"{scale * x['rms']:.3g}" for x in item["windows"])
            lines.append(
                f"- `{log}` / `{c}`: residual RMS {scale * item['rms']:.3g} {unit} (the fit's noise weight sigma "
                f"{scale * item['noise_sigma']:.3g} {unit}: declared, or re-estimated from the residuals); "
                f"by window ({unit}): {w}"
            )
            dl = item["decay_law"]
            if dl["measured"] and dl["simulated"]:
                rm, rs = dl["measured"]["r2"], dl["simulated"]["r2"]
                lines.append(
                    f"  - decay envelope: measured best fit **{dl['measured']['best']}** "
                    f"(R^2 exp {rm['exponential']:.4f}, lin {rm['linear']:.4f}, hyp {rm['hyperbolic']:.4f}); "
                    f"simulated best **{dl['simulated']['best']}** "
                    f"(exp {rs['exponential']:.4f}, lin {rs['linear']:.4f})"
                )
            corr = item["feature_correlation"]
            top = sorted(corr.items(), key=lambda kv: -abs(kv[1]))[:3]
            lines.append("  - residual correlates with: " + ", ".join(f"{k} {v:+.2f}" for k, v in top))
            peaks = item["spectrum_peaks"]
            if peaks:
                lines.append("  - residual spectrum peaks: " + ", ".join(_peak_text(p) for p in peaks))
            lines.append(f"  - whiteness: Ljung-Box p = {item['whiteness']['p_value']:.3g}")
    return lines


def _link_angles(chain, sim: dict) -> list:
    """Absolute angle of each link's root frame (rad) from the channels in `sim`: `phi<i>` if
    recorded, else the sum of `theta1..theta<i>` (tip slopes of flexible links in between
    left out); None where neither is available."""
    out = []
    for i in range(1, chain.n_links + 1):
        if f"phi{i}" in sim:
            out.append(np.asarray(sim[f"phi{i}"], float))
        elif all(f"theta{j}" in sim for j in range(1, i + 1)):
            out.append(sum(np.asarray(sim[f"theta{j}"], float) for j in range(1, i + 1)))
        else:
            out.append(None)
    return out


def _over_logs(chain, traces: dict, key: str, per_log) -> dict:
    """`{"link<i>": max over the logs of per_log(t, angles, i)}` (None where every log gives
    None)."""
    out = {f"link{i + 1}": None for i in range(chain.n_links)}
    for entry in traces.values():
        t = np.asarray(entry["t"], float)
        if len(t) < 5:
            continue
        angles = _link_angles(chain, entry.get(key, {}))
        for i in range(chain.n_links):
            value = per_log(t, angles, i)
            name = f"link{i + 1}"
            if value is not None:
                out[name] = value if out[name] is None else max(out[name], value)
    return out


def link_spin_rates(chain, traces: dict, key: str = "baseline") -> dict:
    """Largest absolute angular rate (rad/s) of each link's root frame over the logs, from
    the simulated angle channels of `traces` (`{log: {"t": ..., key: {channel: values}}}`:
    diagnose's traces with `key="baseline"`, `identify.fitted_outputs` with
    `key="simulated"`); see `_link_angles`. None where unknown."""

    def rate(t, angles, i):
        return None if angles[i] is None else float(np.max(np.abs(np.gradient(angles[i], t, edge_order=2))))

    return _over_logs(chain, traces, key, rate)


def link_spin_rms(chain, traces: dict, key: str = "baseline") -> dict:
    """Root-mean-square angular rate (rad/s) of each link's root frame over every sample of
    every log (pooled), from the same simulated angles as `link_spin_rates`; None where
    unknown. What a fitted EI absorbs on average (`stiffening_checks`), where the largest
    rate bounds it."""
    sums = {f"link{i + 1}": None for i in range(chain.n_links)}
    for entry in traces.values():
        t = np.asarray(entry["t"], float)
        if len(t) < 5:
            continue
        for i, a in enumerate(_link_angles(chain, entry.get(key, {}))):
            if a is not None:
                rate = np.gradient(a, t, edge_order=2)
                s, n = sums[f"link{i + 1}"] or (0.0, 0)
                sums[f"link{i + 1}"] = (s + float(np.sum(rate**2)), n + len(rate))
    return {name: None if v is None else float(np.sqrt(v[0] / v[1])) for name, v in sums.items()}


def link_root_accelerations(chain, traces: dict, key: str = "baseline", window: dict | None = None) -> dict:
    """Largest axial acceleration (m/s^2) of each link's root over the logs: the component
    along the link (its root frame's angle) of the root's acceleration, from the angles of
    the links before it and its own (`_link_angles`; the root of link i is at `sum_{j<i} l_j
    [cos phi_j, sin phi_j]`, deflections left out): 0 for the first link (the base is
    fixed), None where an angle is unknown. On a spinning chain its centripetal part pulls
    the link outwards like gravity along it (`flexdyn.stiffening`: `gravity` coefficient);
    the transverse part bends the link, it does not stretch it.

    `window`: link name -> seconds, a moving average of the axial acceleration over that
    span first (`stiffening_checks_of`: the link's first clamped-mass period). Stiffening is
    a quasi-static effect: an axial load that alternates faster than the mode averages out
    (unaveraged, the 45-78 Hz joint ringing of a two-link arm with elastic joints would read
    as a 64 % stiffening of its 4.7 Hz mode; the ringing's rectified centripetal part, its
    mean, is what remains)."""

    def acceleration(t, angles, i):
        if i == 0:
            return 0.0
        if any(a is None for a in angles[: i + 1]):
            return None
        pos = sum(float(chain.links[j].length) * np.stack([np.cos(angles[j]), np.sin(angles[j])]) for j in range(i))
        acc = np.gradient(np.gradient(pos, t, axis=1, edge_order=2), t, axis=1, edge_order=2)
        axial = acc[0] * np.cos(angles[i]) + acc[1] * np.sin(angles[i])
        span = (window or {}).get(f"link{i + 1}")
        if span:
            n = int(round(span / float(np.median(np.diff(t)))))
            if n >= len(axial):
                axial = np.asarray([np.mean(axial)])
            elif n > 1:
                axial = np.convolve(axial, np.ones(n) / n, mode="valid")
        return float(np.max(np.abs(axial)))

    return _over_logs(chain, traces, key, acceleration)


def stiffening_checks_of(chain, traces: dict, key: str = "baseline") -> list[dict]:
    """`stiffening_checks` with the spin rates and root accelerations of `traces`' simulated
    angle channels under `key` (`link_spin_rates`, `link_root_accelerations` averaged over
    each link's first clamped-mass period)."""
    periods = {name: 2 * np.pi / e.frequency for name, e in first_mode_stiffening(chain).items() if e.frequency > 0}
    return stiffening_checks(
        chain,
        link_spin_rates(chain, traces, key=key),
        link_root_accelerations(chain, traces, key=key, window=periods),
        spin_rms=link_spin_rms(chain, traces, key=key),
    )


def stiffening_checks(
    chain,
    spin_rates: dict,
    root_accelerations: dict | None = None,
    threshold: float = STIFFENING_THRESHOLD,
    *,
    spin_rms: dict | None = None,
) -> list[dict]:
    """One entry per flexible link of `chain` without geometric stiffening (module
    docstring): its first clamped-mass frequency, the largest spin rate of the logs
    (`spin_rates`, from `link_spin_rates`; None if unknown), the first-order change of
    `omega_1^2` that stiffening would make from the motion and from gravity (`flexdyn.
    stiffening`), whether that exceeds `threshold`, and a sentence saying so.

    The motion's part is `spin Omega^2 + gravity a_root` with `a_root` the largest
    acceleration of the link's root (`root_accelerations`, from `link_root_accelerations`;
    0 if not given), counted as if it pulled along the link: exact to first order for a
    straight chain spinning as one body (the root's centripetal `Omega^2 R`), an upper
    estimate otherwise, like the largest rate and the whole of gravity.

    With `spin_rms` (`link_spin_rms`), also the shift at the logs' RMS rate (the root's
    acceleration left out) and its EI bias, `ei_bias_factor_rms`: a fitted EI absorbs the
    stiffening the logs' motion makes on average, not at its peak. On the spinning-link
    example (coasting at 4-14 rad/s; the fit logs' encoder angles, the chain at the linear
    fit's values) the two bracket the linear fit's EI: 1.08 (RMS rate) < 1.158 (fitted) <
    1.26 (largest rate)."""
    estimates = first_mode_stiffening(chain)
    g = float(np.hypot(*np.asarray(chain.gravity, float)))
    out = []
    for name, e in estimates.items():
        link = chain.links[int(name[4:]) - 1]
        if link.geometric_stiffening:
            continue
        rate = spin_rates.get(name)
        rms = (spin_rms or {}).get(name)
        a_root = (root_accelerations or {}).get(name) or 0.0
        spin = e.relative_shift(spin_rate=rate, axial_gravity=a_root) if rate is not None else None
        from_root = e.relative_shift(axial_gravity=a_root) if rate is not None and a_root > 0 else None
        spin_typical = e.relative_shift(spin_rate=rms) if rms is not None else None
        grav = e.relative_shift(axial_gravity=g)
        worst = max(spin or 0.0, grav)
        flagged = worst > threshold
        w1 = e.frequency
        # the clamped-mass mode is not a mode of the whole arm (it carries the links outboard
        # as a rigid body at the tip), so the text says what it is; it is the ratio of
        # stiffnesses that matters
        mode = (
            f"its first clamped-mass mode, {w1:.3g} rad/s = {w1 / (2 * np.pi):.3g} Hz: the link alone, root "
            "clamped, all outboard of it rigid at its tip, not a mode of the whole arm"
        )
        parts = []
        if rate is not None:
            parts.append(
                f"spins at up to {rate:.3g} rad/s"
                + (f" (RMS {rms:.3g} rad/s over the logs)" if rms is not None else "")
                + (
                    f", its root accelerating along it at up to {a_root:.3g} m/s^2 (averaged over the mode's period)"
                    if a_root > 0
                    else ""
                )
                + f": its centrifugal stiffening at that rate is {100 * spin:.2g} % of the bending stiffness of "
                + mode
                + (
                    f" ({100 * (spin - from_root):.2g} % from its own spin, "
                    f"{100 * from_root:.2g} % from its root's pull)"
                    if from_root is not None
                    else ""
                )
                + (f"; {100 * spin_typical:.2g} % at the RMS rate" if spin_typical is not None else "")
            )
        else:
            parts.append(f"spin rate unknown (no angle channel for it); {mode}")
        if g > 0:
            parts.append(f"gravity {g:.3g} m/s^2 along the link: +-{100 * grav:.2g} %")
        # a fitted EI' absorbs the missing stiffness: omega_1'^2 = omega_1^2 + spin Omega^2, and
        # `worst` is that over omega_1'^2 (this chain is the fitted one), so EI' / EI = 1 / (1 - worst)
        bias = 1.0 / (1.0 - worst) if worst < 1.0 else None
        typical = max(spin_typical, grav) if spin_typical is not None else None
        bias_typical = 1.0 / (1.0 - typical) if typical is not None and typical < 1.0 else None
        if flagged:
            # said even for a fit at the noise: the warning is about a real link, whose
            # stiffening a fitted EI absorbs (only logs simulated without it leave EI exact)
            if bias is None:
                size = "the linear model is far off"
            elif bias_typical is not None:
                size = (
                    f"EI / true EI about {bias_typical:.3g} at the RMS rate, up to {bias:.3g} at the largest: "
                    "first-order estimates"
                )
            else:
                size = f"EI / true EI up to about {bias:.3g}, a first-order upper estimate"
            verdict = (
                f"the model has no geometric stiffening, which a real link has: a fitted EI absorbs it ({size}), "
                "so a fit at the noise does not rule it out; set `geometric_stiffening = true` on "
                "this link ([[rig.links]]) and fit again to compare EI"
            )
        else:
            verdict = f"below {100 * threshold:.2g} %: the linear link model is adequate here"
        out.append(
            {
                "check": "geometric_stiffening",
                "link": name,
                "first_frequency_rad_s": w1,
                "spin_rate_max_rad_s": rate,
                "root_acceleration_max_m_s2": a_root,
                "spin_coefficient": e.spin,
                "gravity_m_s2": g,
                "gravity_coefficient_per_m": e.gravity,
                "relative_shift_spin": spin,
                "relative_shift_gravity": grav,
                "ei_bias_factor": bias,
                "spin_rate_rms_rad_s": rms,
                "relative_shift_spin_rms": spin_typical,
                "ei_bias_factor_rms": bias_typical,
                "flagged": bool(flagged),
                "message": f"{name}: " + "; ".join(parts) + f"; {verdict}.",
            }
        )
    return out
