"""The report of `identify diagnose`: `diagnosis.json` (everything, machine-readable) and
`report.md` (for a person) with its plots: measured vs baseline vs extended model,
residuals, residual spectra with the model's modes, decay envelopes, candidate scores."""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .._data.units import display_unit
from .._diagnose import evidence as ev  # noqa: E402
from .._diagnose.diagnosis import DETECTION_LIMITS_MEANING
from .._diagnose.notes import note_text
from .._diagnose.scores import round_verdicts  # noqa: E402
from .._fit import covariance
from .fit_plots import wrapped_title  # noqa: E402
from .json import jsonable

JSON_FILE = "diagnosis.json"
REPORT_FILE = "report.md"
PLOT_FILES = (
    "diagnosis_traces.png",
    "diagnosis_residuals.png",
    "diagnosis_spectra.png",
    "diagnosis_envelopes.png",
    "diagnosis_scores.png",
)
FILES = (JSON_FILE, REPORT_FILE, *PLOT_FILES)


def _panels(diag):
    rows = []
    for log, entry in diag.outputs.items():
        for c in entry["measured"]:
            rows.append((log, c, entry))
    return rows


def _fig(n, title):
    fig, axes = plt.subplots(n, 1, figsize=(9, 2.4 * n + 0.6), squeeze=False)
    fig.suptitle(wrapped_title(title, 9))
    return fig, axes[:, 0]


def _time_panels(diag, folder: Path, title: str, file: str, draw) -> Path:
    """One panel per log and channel against time: `draw(ax, t, series, scale)` plots the
    panel's curves, `series(name)` being the log's `name` trace (`measured`, `baseline`,
    `extended`; None when absent) of the panel's channel; returns the written file."""
    rows = _panels(diag)
    fig, axes = _fig(len(rows), title)
    for ax, (log, c, e) in zip(axes, rows):
        s, unit = display_unit(c)
        draw(ax, e["t"], lambda name, e=e, c=c: e[name][c] if name in e else None, s)
        ax.set_ylabel(f"{c} [{unit}]")
        ax.set_title(f"{log} ({e['role']})", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    path = folder / file
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_traces(diag, folder: Path) -> Path:
    def draw(ax, t, series, s):
        ax.plot(t, s * series("measured"), ".", ms=2, color="0.4", label="measured")
        ax.plot(t, s * series("baseline"), "-", lw=1, color="tab:red", label="baseline")
        if series("extended") is not None:
            ax.plot(t, s * series("extended"), "-", lw=1, color="tab:blue", label="extended")

    return _time_panels(diag, folder, "measured vs baseline vs extended model", PLOT_FILES[0], draw)


def plot_residuals(diag, folder: Path) -> Path:
    def draw(ax, t, series, s):
        for name, color in (("baseline", "tab:red"), ("extended", "tab:blue")):
            if series(name) is not None:
                ax.plot(t, s * (series(name) - series("measured")), lw=0.8, color=color, label=name)

    return _time_panels(diag, folder, "residuals (model - measured)", PLOT_FILES[1], draw)


def plot_spectra(diag, folder: Path) -> Path:
    rows = _panels(diag)
    fig, axes = _fig(len(rows), "residual spectra (dashed: the fitted model's natural frequencies)")
    for ax, (log, c, e) in zip(axes, rows):
        t = e["t"]
        for name, color in (("baseline", "tab:red"), ("extended", "tab:blue")):
            if name in e:
                f, p = ev.periodogram(t, e[name][c] - e["measured"][c])
                ax.semilogy(f[1:], p[1:], lw=0.8, color=color, label=name)
        for fm in diag.modal_frequencies_hz:
            if fm > 0:
                ax.axvline(fm, ls="--", color="0.5", lw=0.8)
        ax.set_ylabel(f"{c} PSD")
        ax.set_title(f"{log} ({e['role']})", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("frequency [Hz]")
    fig.tight_layout()
    path = folder / PLOT_FILES[2]
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_envelopes(diag, folder: Path) -> Path:
    rows = _panels(diag)
    fig, axes = _fig(
        len(rows),
        "decay envelopes: half swings (falling in a straight line: dry friction; flattening out: viscous damping "
        "or drag)",
    )
    for ax, (log, c, e) in zip(axes, rows):
        s, unit = display_unit(c)
        for name, style in (("measured", "o"), ("baseline", "-"), ("extended", "--")):
            if name in e and name != "measured" or name == "measured":
                y = e["measured"][c] if name == "measured" else e.get(name, {}).get(c)
                if y is None:
                    continue
                noise = diag.baseline.sigma.get(c, 0.0) if name == "measured" else 0.0  # as `decay_law`
                tp, a = ev.swing_amplitudes(e["t"], y, noise)
                ax.plot(tp, s * a, style, ms=3, label=name)
        ax.set_ylabel(f"{c} half swing [{unit}]")
        ax.set_title(f"{log} ({e['role']})", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    path = folder / PLOT_FILES[3]
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_scores(diag, folder: Path) -> Path:
    n = max(len(diag.rounds), 1)
    fig, axes = plt.subplots(
        1, n, figsize=(6 * n, 0.4 * max((len(r) for r in diag.rounds), default=1) + 1.5), squeeze=False
    )
    for k, (ax, scores) in enumerate(zip(axes[0], diag.rounds or [[]])):
        labels = [s.label for s in scores]
        vals = [0.0 if s.not_fitted else s.delta_bic for s in scores]  # (no dBIC: no bar)
        colors = ["tab:green" if s.accepted else ("0.7" if s.screened or s.not_fitted else "tab:gray") for s in scores]
        ax.barh(range(len(vals)), vals, color=colors)
        ax.set_yticks(range(len(vals)), labels, fontsize=7)
        ax.set_xscale("symlog", linthresh=10)
        ax.axvline(0, color="k", lw=0.5)
        ax.invert_yaxis()
        ax.set_xlabel("dBIC (negative = better than the model it extends)")
        ax.set_title(f"round {k + 1} (green: accepted, light: screened out or not fitted)", fontsize=9)
    fig.tight_layout()
    path = folder / PLOT_FILES[4]
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def markdown(diag, title: str = "") -> str:
    """`report.md`: causes, held-out gains, the extended model, evidence, candidates round by
    round, notes and detection limits, the baseline fit and the plots."""
    lines = [f"# Diagnosis{': ' + title if title else ''}", ""]
    if diag.interrupted:
        lines += [f"**Interrupted:** {diag.interrupted}. The causes below are those accepted before it.", ""]
    lines.append(f"**Held-out data:** {diag.split}.")
    lines.append("")
    verdict = getattr(diag, "verdict", None)
    if verdict is not None:
        lines += [f"**Verdict: {verdict.kind}.** {verdict.reason}.", ""]
    for section in (_causes, _held_out_gain, _extended_model, _evidence, _candidates, _closing):
        lines.extend(section(diag))
    return "\n".join(lines)


def _causes(diag) -> list[str]:
    """The causes named (with their values and warnings), or why none is."""
    lines = []
    if diag.causes:
        lines.append("## Causes found")
        lines.append("")
        for c in diag.causes:
            lines.append(
                f"- **{c.name}** at `{c.where}`: {c.description} (dBIC {c.delta_bic:.1f}, held-out RMS gain "
                f"{c.held_out_gain:.2f}x"
                + (f", SE {c.held_out_gain_se:.2g}" if math.isfinite(c.held_out_gain_se) else "")
                + (
                    f"; accepted together with {', '.join(f'`{w}`' for w in c.together_with)}, neither passing "
                    "alone: the scores are the pair's)"
                    if c.together_with
                    else ")"
                )
            )
            for n, p in c.parameters.items():
                lines.append(
                    f"  - `{n}` = {p['value']:.{covariance.digits(p['value'], p['std_error'])}g} {p['unit']} "
                    f"+- {p['std_error']:.2g} (95 % CI {covariance.interval_text(*p['ci95'])})"
                )
            for w in c.warnings:
                lines.append(f"  - **Implausible:** {w}")
            if c.marginal(diag.min_gain):
                lines.append(f"  - **Marginal:** {diag.marginal_text(c)}")
    elif diag.verdict is not None and diag.verdict.kind == "inconclusive":
        lines += _inconclusive(diag.verdict)
    else:
        lines.append("## No cause named")
        lines.append("")
        lines.append(
            "No catalogue entry explains the residual significantly (each needs dBIC < -10 on the fit data and "
            "a held-out RMS gain of at least 1.1x). The evidence below shows what the residual looks like."
        )
    if diag.implausible:
        labels = ", ".join(f"`{x}`" for x in diag.implausible)
        lines.append("")
        lines.append(
            f"Not named, passing both tests only with implausible values: {labels} (see the candidates and the "
            "notes): such a value usually stands in for an effect the catalogue lacks."
        )
    lines.append("")
    return lines


def _inconclusive(verdict) -> list[str]:
    """An inconclusive verdict: the competing candidates and what data would decide."""
    lines = ["## Inconclusive: no cause confirmed", ""]
    lines += ["| candidate | dBIC (fit logs) | held-out gain | why not named |", "| --- | --- | --- | --- |"]
    for c in verdict.competing:
        se = c["held_out_gain_se"]
        gain = f"{c['held_out_gain']:.3f}x" + (f" (SE {se:.2g})" if math.isfinite(se) else "")
        lines.append(f"| `{c['label']}` | {c['delta_bic']:.1f} | {gain} | {c['why']} |")
    lines += ["", "What would decide:", ""]
    lines += [f"- {t}" for t in verdict.to_decide]
    return lines


def _held_out_gain(diag) -> list[str]:
    """The held-out RMS per channel, baseline and extended, against the noise floor."""
    lines = []
    lines.append("## Gain on held-out data")
    lines.append("")
    floor = diag.held_out.get("noise_floor", {})
    lines.append("| channel | unit | baseline RMS | extended RMS | gain | noise floor |")
    lines.append("| --- | --- | ---: | ---: | ---: | ---: |")
    for c in diag.held_out["baseline"]:
        scale, unit = display_unit(c)
        base, ext = scale * diag.held_out["baseline"][c], scale * diag.held_out["extended"][c]
        noise = f"{scale * floor[c]:.4g}" if c in floor else ""
        lines.append(f"| {c} | {unit} | {base:.4g} | {ext:.4g} | {diag.held_out['gain'][c]:.2f}x | {noise} |")
    lines.append("")
    lines.append(
        "The noise floor is estimated from the held-out samples alone, without any model "
        "(`identify.noise_floor`): a model that explains the data reaches it."
    )
    for c in diag.left_unexplained:
        lines.append(
            f"The extended model's held-out residual of {c} is still "
            f"{diag.held_out['extended'][c] / floor[c]:.3g} times its noise floor: an effect is left "
            f"unexplained, or the noise is not white{diag.unexplained_hint}."
        )
    lines.append("")
    lines.append(
        f"Total dBIC {diag.delta_bic_total:.1f}; fraction of the held-out residual (sum of squares) explained "
        f"{diag.fraction_explained:.3f}, of its excess over the noise {diag.excess_explained_text}."
    )
    lines.append("")
    return lines


def _extended_model(diag) -> list[str]:
    """The extended model's intervals, per-log values and the baseline's model checks."""
    lines = []
    if diag.causes and diag.extended_intervals:
        lines.append("## Extended model")
        lines.append("")
        lines.append("Every free parameter of the extended model, from the exact Jacobian of its final fit:")
        lines.append("")
        lines.append("| parameter | value | std error | 95 % CI |")
        lines.append("| --- | ---: | ---: | --- |")
        for n, p in diag.extended_intervals.items():
            lines.append(
                f"| `{n}` | {p['value']:.5g} | {p['std_error']:.3g} | [{p['ci95'][0]:.5g}, {p['ci95'][1]:.5g}] |"
            )
        lines.append("")
        for line in diag.at_bound_lines():
            lines.append(f"**On a bound**: `{line.split(' = ', 1)[0]}` = {line.split(' = ', 1)[1]}")
            lines.append("")
    if diag.per_log:
        lines.append("## Per-log parameters")
        lines.append("")
        lines.append(
            "Each log's own value (`Parameter.per_log`) in the extended model: fitted on the fit logs, "
            "refitted on each held-out log with its initial state (the held-out scores were computed there)."
        )
        lines.append("")
        lines.append("| parameter | log | role | value |")
        lines.append("| --- | --- | --- | ---: |")
        for name, by_log in diag.per_log.items():
            for log, value in by_log.items():
                role = "held out" if log in diag.held_out_logs else "fit"
                lines.append(f"| `{name}` | {log} | {role} | {value:.5g} |")
        lines.append("")
    if diag.model_checks:
        lines.append("## Model checks (baseline)")
        lines.append("")
        lines.append(
            "What the baseline model assumes that these logs may break (first-order estimates, `flexdyn.stiffening`):"
        )
        lines.append("")
        for check in diag.model_checks:
            lines.append(f"- {'**flagged**: ' if check['flagged'] else ''}{check['message']}")
        lines.append("")
    return lines


def _evidence(diag) -> list[str]:
    """The residual evidence of the baseline fit."""
    lines = []
    lines.append("## Evidence (baseline fit)")
    lines.append("")
    lines.extend(ev.summary_lines(diag.evidence))
    lines.append("")
    return lines


def _candidates(diag) -> list[str]:
    """Each round's candidates with their scores and verdicts."""
    lines = []
    lines.append("## Candidates")
    for r, scores in enumerate(diag.rounds, start=1):
        lines.append("")
        lines.append(f"Round {r} ({'from the baseline' if r == 1 else 'from the model extended so far'}):")
        lines.append("")
        lines.append("| candidate | parameters | dBIC | F-test p | held-out gain | accepted |")
        lines.append("| --- | --- | ---: | ---: | ---: | --- |")
        verdicts = round_verdicts(scores)
        for s in scores:
            verdict = f"**{verdicts[s.label]}**" if verdicts[s.label] == "named" else verdicts[s.label]
            if s.not_fitted:
                lines.append(f"| {s.label} | | | | | {verdict} |")
                continue
            params = ", ".join(f"`{n}` = {v:.5g}" for n, v in s.params.items()) or (  # a gain near 1: 5 digits
                f"(not fitted: {s.screen_reason})" if s.screened else ""
            )
            gain = "" if s.screened else f"{s.held_out_gain:.3f}x"
            p = "" if s.screened else f"{s.p_value:.2g}"
            dbic = f"({s.delta_bic:.1f})" if s.screened else f"{s.delta_bic:.1f}"
            lines.append(f"| {s.label} | {params} | {dbic} | {p} | {gain} | {verdict} |")
        if any(s.not_fitted for s in scores):
            lines.append("")
            lines.append(
                "A candidate *not fitted* never left its starting values, from its own starts and from wider ones: "
                "the search did not test it, and its row is no evidence for or against the effect."
            )
        if any(s.implausible for s in scores):
            lines.append("")
            lines.append(
                "A candidate that passes both tests with *implausible* values (outside what the component "
                "plausibly does on a working rig, `catalogue.implausible`) is not named: such a value usually "
                "stands in for an effect the catalogue lacks."
            )
        if any(s.screened for s in scores):
            lines.append("")
            lines.append(
                "A dBIC in parentheses is a prediction, not a fit: one Gauss-Newton step from the current model "
                "(exact Jacobian) screens the candidates and only the most promising are fitted in full. "
                "`diagnose_logs(..., n_fit=None)` (`identify diagnose --fit-all`) fits them all."
            )
    return lines


def _closing(diag) -> list[str]:
    """Notes, detection limits, what was not tried, the baseline fit and the plots."""
    lines = []
    if diag.notes:
        lines.append("")
        lines.extend(f"- {note_text(n)[:1].upper()}{note_text(n)[1:]}" for n in diag.notes)
    if diag.detection_limits or diag.not_fitted:
        lines.append("")
        lines.append("## Detection limits")
        lines.append("")
        lines.append(f"What the search could have found: {DETECTION_LIMITS_MEANING}.")
        lines.append("")
        lines.extend(f"- {text}" for text in diag.detection_limit_lines() + diag.not_fitted_lines())
    if diag.not_tried:
        lines.append("")
        lines.append("Not tried:")
        lines.append("")
        lines.extend(f"- `{n}`: {why}" for n, why in diag.not_tried.items())
    lines.append("")
    lines.append("## Baseline fit")
    lines.append("")
    lines.append("```")
    lines.append(diag.baseline.summary())
    lines.append("```")
    lines.append("")
    lines.append("## Plots")
    lines.append("")
    for name in PLOT_FILES:
        lines.append(f"![{name}]({name})")
        lines.append("")
    return lines


def write_report(diag, folder, title: str = "", extra: dict | None = None) -> list[Path]:
    """Write `diagnosis.json`, `report.md` and the plots into `folder` (created); returns
    the paths written. `diagnosis.json` first; the report or a plot that cannot be made
    is left out with a `RuntimeWarning` naming it and the error (the diagnosis is kept).
    `diagnosis.json` then lists the `files` written and, under `problems`, those left out
    and why (rewritten through a temporary file: it never holds half a document)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    doc = diag.to_dict()
    doc.update(extra or {})
    _write_json(folder / JSON_FILE, doc)
    written = [folder / JSON_FILE]
    writers = [(REPORT_FILE, lambda: _write_markdown(diag, title, folder / REPORT_FILE))]
    writers += [
        (name, lambda plot=plot: plot(diag, folder))
        for name, plot in zip(
            PLOT_FILES, (plot_traces, plot_residuals, plot_spectra, plot_envelopes, plot_scores), strict=True
        )
    ]
    problems = []
    for name, write in writers:
        try:
            written.append(write())
        except Exception as e:  # noqa: BLE001 (a figure must not cost the diagnosis)
            (folder / name).unlink(missing_ok=True)  # (it may be partial)
            problems.append(f"{name} not written: {type(e).__name__}: {e}")
            warnings.warn(f"{folder / name} not written: {type(e).__name__}: {e}", RuntimeWarning, stacklevel=2)
    doc["files"] = [p.name for p in written]
    doc["problems"] = problems
    _write_json(folder / JSON_FILE, doc)
    return written


def _write_json(path: Path, doc: dict) -> None:
    """`doc` as JSON into `path`, through a temporary file beside it and a rename."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(jsonable(doc), indent=1) + "\n")
    os.replace(tmp, path)


def _write_markdown(diag, title: str, path: Path) -> Path:
    path.write_text(markdown(diag, title) + "\n")
    return path
