"""Plots of a fit: measured vs fitted outputs, residuals, residual spectra and
autocorrelation, and the parameter correlation matrix.

Every function is pure: it takes the fit's numbers (`FitResult`, the dict of
`identify.fitted_outputs`, the dict of `identify.residual_report`) and a folder, writes
one PNG there under a fixed name (`PLOT_FILES`) and returns the written paths. They use
matplotlib's Agg canvas directly (no pyplot, no global backend state), as
`flexdyn.example` does. Angles are drawn in degrees, lengths in millimetres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._data.units import display_unit

FIT_PLOT = "measured_vs_fitted.png"


RESIDUALS_PLOT = "residuals.png"


SPECTRUM_PLOT = "residual_spectrum.png"


AUTOCORRELATION_PLOT = "residual_autocorrelation.png"


CORRELATION_PLOT = "parameter_correlation.png"


BY_LOG_PLOT = "parameters_by_log.png"


PLOT_FILES = (FIT_PLOT, RESIDUALS_PLOT, SPECTRUM_PLOT, AUTOCORRELATION_PLOT, CORRELATION_PLOT)


DPI = 110


def _figure(rows, cols, title, width=5.0, height=2.8):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * cols, height * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    fig.suptitle(wrapped_title(title, width * cols))
    return fig, axes


def wrapped_title(title: str, width_in: float) -> str:
    """`title` broken into lines that fit a figure `width_in` inches wide at the default
    title size (~9 characters per inch), so that a long experiment name is not clipped."""
    import textwrap

    return textwrap.fill(title, width=max(20, int(9 * width_in)))


def _panels(outputs: dict) -> list[tuple[str, str]]:
    """(log, channel) pairs, logs in order, channels sorted."""
    return [(name, c) for name, entry in outputs.items() for c in sorted(entry["measured"])]


def _grid(outputs: dict):
    logs = list(outputs)
    channels = sorted({c for entry in outputs.values() for c in entry["measured"]})
    return logs, channels


def _label(name: str, roles: dict | None) -> str:
    role = (roles or {}).get(name, "fit")
    return f"{name} (validation)" if role == "validation" else name


def plot_fit(outputs: dict, folder, title: str = "", roles: dict | None = None) -> list[Path]:
    """Measured and fitted (simulated) output per log (rows) and channel (columns).
    `roles`: log name -> 'fit' or 'validation' (validation logs are labelled)."""
    folder = Path(folder)
    logs, channels = _grid(outputs)
    fig, ax = _figure(len(logs), len(channels), f"Measured vs fitted{': ' + title if title else ''}")
    for i, name in enumerate(logs):
        entry = outputs[name]
        for j, c in enumerate(channels):
            a = ax[i, j]
            if c not in entry["measured"]:
                a.set_visible(False)
                continue
            scale, unit = display_unit(c)
            t = entry["t"]
            a.plot(t, scale * entry["measured"][c], ".", ms=2.0, color="0.45", label="measured")
            a.plot(t, scale * entry["simulated"][c], lw=1.1, color="tab:blue", label="fitted model")
            a.set(title=f"{_label(name, roles)}: {c}", xlabel="t [s]", ylabel=f"{c} [{unit}]")
            a.legend(fontsize="small", loc="best")
    path = folder / FIT_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def plot_residuals(outputs: dict, folder, sigma: dict | None = None, roles: dict | None = None) -> list[Path]:
    """Residual (fitted - measured) over time per log and channel, with +-2 sigma of the
    noise level used by the fit (`sigma`: channel -> SI standard deviation) if given."""
    folder = Path(folder)
    logs, channels = _grid(outputs)
    fig, ax = _figure(len(logs), len(channels), "Residuals (fitted - measured)")
    for i, name in enumerate(logs):
        entry = outputs[name]
        for j, c in enumerate(channels):
            a = ax[i, j]
            if c not in entry["residual"]:
                a.set_visible(False)
                continue
            scale, unit = display_unit(c)
            r = scale * np.asarray(entry["residual"][c])
            a.plot(entry["t"], r, lw=0.6, color="tab:blue")
            a.axhline(0.0, color="0.4", lw=0.6)
            if sigma and sigma.get(c):
                s = 2 * scale * sigma[c]
                a.axhspan(-s, s, color="tab:green", alpha=0.12, lw=0, label="+-2 sigma (the fit's noise weight)")
                a.legend(fontsize="small", loc="upper right")
            rms = float(np.sqrt(np.mean(r**2)))
            a.set(
                title=f"{_label(name, roles)}: {c} (RMS {rms:.3g} {unit})", xlabel="t [s]", ylabel=f"residual [{unit}]"
            )
    path = folder / RESIDUALS_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def residual_spectrum(t, r) -> tuple[np.ndarray, np.ndarray]:
    """Welch power spectral density of a residual (mean removed), sampled at the median
    interval of `t`: (frequency [Hz], PSD [unit^2/Hz]). Segments of a quarter of the log
    (at least 256 samples; ~7 averaged with Welch's half overlap), so the resolution is
    ~4 / (the log's duration): a fixed 256 samples would give 0.78 Hz at 200 Hz sampling,
    too coarse to show a residual at a pendulum's 1.27 Hz swing."""
    from scipy import signal

    t = np.asarray(t, float)
    r = np.asarray(r, float)
    fs = 1.0 / float(np.median(np.diff(t)))
    nperseg = int(min(len(r), max(256, len(r) // 4)))
    return signal.welch(r - r.mean(), fs=fs, nperseg=nperseg)


def plot_spectrum(
    outputs: dict, folder, natural_frequencies=(), roles: dict | None = None, where: str = ""
) -> list[Path]:
    """Welch spectrum of each residual (log-log), one panel per channel (a line per log),
    with the model's natural frequencies (Hz; 0 = rigid-body mode, not drawn) as vertical
    lines. A peak of the residual at a natural frequency means the model misses that mode's
    frequency or damping."""
    folder = Path(folder)
    logs, channels = _grid(outputs)
    fig, ax = _figure(1, len(channels), "Residual spectrum (Welch)", width=6.0, height=3.4)
    freqs = [float(f) for f in natural_frequencies if f > 0]
    for j, c in enumerate(channels):
        a = ax[0, j]
        scale, unit = display_unit(c)
        for name in logs:
            entry = outputs[name]
            if c not in entry["residual"] or len(entry["t"]) < 8:
                continue
            f, p = residual_spectrum(entry["t"], scale * np.asarray(entry["residual"][c]))
            keep = f > 0
            a.loglog(f[keep], p[keep], lw=0.9, label=_label(name, roles))
        for k, fn in enumerate(freqs):
            label = f"natural frequency{' (' + where + ')' if where else ''}" if k == 0 else None
            a.axvline(fn, color="tab:red", lw=0.9, ls="--", label=label)
            a.annotate(
                f"{fn:.3g} Hz",
                xy=(fn, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(3, -12),
                textcoords="offset points",
                fontsize="small",
                color="tab:red",
            )
        a.set(title=f"{c} residual", xlabel="frequency [Hz]", ylabel=f"PSD [{unit}^2/Hz]")
        a.legend(fontsize="small")
    path = folder / SPECTRUM_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def plot_autocorrelation(report: dict, folder, roles: dict | None = None) -> list[Path]:
    """Residual autocorrelation per log and channel (`residual_report`'s whiteness test)
    with the 99 % band of a white sequence."""
    folder = Path(folder)
    logs = list(report)
    channels = sorted({c for d in report.values() for c in d})
    fig, ax = _figure(len(logs), len(channels), "Residual autocorrelation (99 % band of white noise)", width=6.0)
    for i, name in enumerate(logs):
        for j, c in enumerate(channels):
            a = ax[i, j]
            if c not in report[name]:
                a.set_visible(False)
                continue
            w = report[name][c]["whiteness"]
            lags, rho, band = np.asarray(w["lags"]), np.asarray(w["autocorrelation"]), w["band99"]
            a.vlines(lags, 0, rho, color="tab:blue", lw=1.5)
            a.plot(lags, rho, "o", ms=3, color="tab:blue")
            a.axhspan(-band, band, color="tab:green", alpha=0.15, lw=0, label="99 % band")
            a.axhline(0.0, color="0.4", lw=0.6)
            verdict = "white" if w["white"] else "NOT white"
            a.set(
                title=f"{_label(name, roles)}: {c}\n{verdict} (Ljung-Box p = {w['p_value']:.2g})",
                xlabel="lag [samples]",
                ylabel="autocorrelation",
            )
            a.legend(fontsize="small", loc="upper right")
    path = folder / AUTOCORRELATION_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def plot_correlation(names, correlation, folder) -> list[Path]:
    """The parameters' correlation matrix as a labelled heat map (-1 .. 1)."""
    folder = Path(folder)
    corr = np.asarray(correlation, float)
    n = len(names)
    size = max(3.8, 0.9 * n + 2.6)
    fig, ax = _figure(1, 1, "Parameter correlation", width=size, height=size - 0.6)
    a = ax[0, 0]
    im = a.imshow(corr, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    a.set_xticks(range(n), labels=list(names), rotation=45, ha="right")
    a.set_yticks(range(n), labels=list(names))
    for i in range(n):
        for j in range(n):
            v = corr[i, j]
            a.text(
                j,
                i,
                f"{v:+.2f}" if np.isfinite(v) else "n/a",
                ha="center",
                va="center",
                fontsize="small",
                color="white" if np.isfinite(v) and abs(v) > 0.6 else "black",
            )
    fig.colorbar(im, ax=a, shrink=0.8, label="correlation")
    path = folder / CORRELATION_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def plot_by_log(results, between, folder) -> list[Path]:
    """Independent fits (`identify.fit_independent`'s results): each parameter's value per
    log with its 95 % interval, and the logs' weighted mean with its standard error as a
    band (`between`: `identify.between_logs(results)`, or None)."""
    folder = Path(folder)
    names = list(results[0].names)
    labels = [", ".join(r.problem.log_names) for r in results]
    fig, ax = _figure(len(names), 1, "Parameters fitted to each log", width=max(5.0, 0.5 * len(results) + 3.0))
    x = np.arange(len(results))
    for i, name in enumerate(names):
        a = ax[i, 0]
        v = np.asarray([r.values[i] for r in results], float)
        lo = np.asarray([r.ci_low[i] for r in results], float)
        hi = np.asarray([r.ci_high[i] for r in results], float)
        ok = np.asarray([bool(r.converged) for r in results])
        err = np.stack([np.clip(v - lo, 0, None), np.clip(hi - v, 0, None)])
        err = np.where(np.isfinite(err), err, 0.0)
        a.errorbar(x[ok], v[ok], yerr=err[:, ok], fmt="o", ms=4, capsize=3, label="log (95 %)")
        if (~ok).any():
            a.plot(x[~ok], v[~ok], "x", color="tab:red", label="not converged")
        if between is not None:
            m, s = float(between.mean[i]), float(between.mean_se[i])
            a.axhline(m, color="k", lw=0.9, label="weighted mean (band: its SE)")
            a.axhspan(m - s, m + s, color="k", alpha=0.12)
            a.set_title(
                f"{name}: p = {float(between.p[i]):.2g} (chi-square, same value in every log)", fontsize="small"
            )
        a.set_ylabel(name)
        a.set_xlim(-0.5, len(results) - 0.5)
        a.set_xticks(x, labels=labels if i == len(names) - 1 else [""] * len(x), rotation=45, ha="right")
        if i == 0:
            a.legend(fontsize="small")
    path = folder / BY_LOG_PLOT
    fig.savefig(path, dpi=DPI)
    return [path]


def plot_per_log(result, between, folder) -> list[Path]:
    """`plot_by_log` of one joint fit's per-log parameters (`Parameter.per_log`): each
    one's value per log with its 95 % interval, and their common value (`between`:
    `identify.between_logs(result)`, or None)."""
    from types import SimpleNamespace

    problem = result.problem
    views = []
    for l, log in enumerate(problem.log_names):
        idx = [index[l] for _, index in problem.per_log]
        views.append(
            SimpleNamespace(
                names=[name for name, _ in problem.per_log],
                values=np.asarray(result.values)[idx],
                ci_low=np.asarray(result.ci_low)[idx],
                ci_high=np.asarray(result.ci_high)[idx],
                converged=result.converged,
                problem=SimpleNamespace(log_names=(log,)),
            )
        )
    return plot_by_log(views, between, folder)


def write_plots(
    result,
    outputs: dict,
    report: dict,
    folder,
    *,
    natural_frequencies=(),
    where: str = "",
    roles: dict | None = None,
    title: str = "",
) -> list[Path]:
    """All plots of a fit (`result`: a `FitResult`; `outputs`: `fitted_outputs(result)`,
    optionally with validation logs added; `report`: `residual_report(result)`, likewise)
    into `folder`, which must exist. Returns the written paths (`PLOT_FILES`)."""
    paths = []
    paths += plot_fit(outputs, folder, title=title, roles=roles)
    paths += plot_residuals(outputs, folder, sigma=result.sigma, roles=roles)
    paths += plot_spectrum(outputs, folder, natural_frequencies, roles=roles, where=where)
    paths += plot_autocorrelation(report, folder, roles=roles)
    paths += plot_correlation(result.names, result.correlation, folder)
    return paths
