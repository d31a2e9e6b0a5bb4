"""The project's main job (until identification lands): simulate the shipped example rigs
and write plots and a short summary.

Run it as `flexdyn-example` (installed script), `python -m flexdyn.example`, or call
`flexdyn.example.main(["--out", "some/folder"])`. It writes, into `--out`
(default `flexdyn-output/`):

- `arm_angles.png`: paper 004's two-link arm with flexible links and flexible joints
  vs. rigid joints under the bang-bang torque (0.2 N m, 0.5 s pulses), RK4 at 1 ms for
  5 s: torque, link and rotor angles, joint deflections (paper 004 Figs. 4(a)-(c), 6(b)).
- `arm_modes.png`: the four modal coordinates (Figs. 4(d), 5(a)-(c)).
- `arm_tip_deflections.png`: tip deflections of both links (Figs. 5(d), 6(a)).
- `pendulum.png`: paper 000's flexible pendulum (two modes, 1 % modal damping)
  released from horizontal, adaptive Tsit5 for 3 s: joint angle, tip deflection and
  the spectrum of the tip deflection with its flexural peak.
- `summary.md`: the numbers behind the plots and a modal-analysis table of every rig
  (also printed).

It refuses to write into a folder that holds anything other than these files, unless
`--force` (which still only writes these names and deletes nothing).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

OUTPUT_FILES = ("arm_angles.png", "arm_modes.png", "arm_tip_deflections.png", "pendulum.png", "summary.md")

ARM_DURATION = 5.0  # s, paper 004 Section 5
ARM_DT = 1e-3  # s, fixed RK4 step of papers 002/004
BANG_BANG_AMPLITUDE = 0.2  # N m, per joint
BANG_BANG_WIDTH = 0.5  # s, paper 004
PENDULUM_DURATION = 3.0  # s
PENDULUM_SAMPLE = 5e-4  # s, output sampling of the pendulum (Nyquist 1 kHz)
RIGID_MODE_HZ = 1e-3  # natural frequencies below this are reported as rigid-body modes


def _parse_args(argv):
    parser = argparse.ArgumentParser(
        prog="flexdyn-example",
        description="Simulate flexdyn's example rigs (paper 004 arm, paper 000 flexible pendulum) "
        "and write plots and a summary.",
    )
    parser.add_argument(
        "--out", default="flexdyn-output", type=Path, help="output folder, created if needed (default: flexdyn-output/)"
    )
    parser.add_argument(
        "--force", action="store_true", help="write into --out even if it holds other files (they are left untouched)"
    )
    return parser.parse_args(argv)


def _check_output_folder(out: Path, force: bool) -> str | None:
    """None if we may write our files into `out`, else the reason we refuse."""
    if out.exists() and not out.is_dir():
        return f"--out {out} exists and is not a folder"
    if not out.exists() or force:
        return None
    foreign = sorted(p.name for p in out.iterdir() if p.name not in OUTPUT_FILES)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f", ... ({len(foreign)} in all)" if len(foreign) > 5 else "")
        return (
            f"refusing to write into {out}/: it holds files this program did not write ({shown}). "
            f"Choose another folder with --out, or pass --force to write our {len(OUTPUT_FILES)} files "
            "there anyway (other files are left untouched)."
        )
    return None


# ---------------------------------------------------------------------------
# Computation (JAX). Imports are local so that `--help` and the folder check are instant.
# ---------------------------------------------------------------------------


@dataclass
class RigResult:
    name: str
    coordinate_names: tuple
    outputs: object  # fd.Outputs, as NumPy arrays
    num_steps: int
    seconds: float  # wall time: simulate + observe + modal analysis, compile included
    modal_q0: object  # configuration of the modal analysis
    frequencies: object  # Hz, ascending
    energy_share: object  # (n_coords, n_modes): share of each coordinate in each mode, sums to 1
    extra: dict = field(default_factory=dict)


def _modal_table_data(chain, Q0):
    """Natural frequencies and, per mode `v`, each coordinate's share `M_kk v_k^2 / sum_j M_jj v_j^2`
    of the mode's kinetic energy without the coupling terms (positive, sums to 1; coordinates
    mix radians and metres, so this is the unit-consistent way to say which ones a mode moves)."""
    import equinox as eqx
    import jax.numpy as jnp

    import flexdyn as fd

    @eqx.filter_jit
    def analyse(chain, Q0):
        modes = fd.modal_analysis(chain, Q0)
        M = fd.mass_matrix(chain, Q0)
        diagonal_energy = jnp.diag(M)[:, None] * modes.shapes**2
        return modes.natural_frequency, diagonal_energy / jnp.sum(diagonal_energy, axis=0)

    return analyse(chain, jnp.asarray(Q0, dtype=float))


def _to_numpy(tree):
    import jax
    import numpy as np

    return jax.tree_util.tree_map(np.asarray, tree)


def _run_arm(rigid_joints: bool) -> RigResult:
    import jax.numpy as jnp
    import numpy as np

    import flexdyn as fd

    start = time.perf_counter()
    chain = fd.rigs.flexible_link_joint_arm(rigid_joints=rigid_joints)
    torque = fd.BangBang([BANG_BANG_AMPLITUDE, BANG_BANG_AMPLITUDE], BANG_BANG_WIDTH)
    y0 = fd.initial_state(chain, joint_angles=[0.0, 0.0])
    ts = jnp.linspace(0.0, ARM_DURATION, int(round(ARM_DURATION / ARM_DT)) + 1)
    traj = fd.simulate(chain, y0, ts, torque, dt=ARM_DT)
    outputs = _to_numpy(fd.observe(chain, traj, torque))
    Q0 = np.zeros(chain.n_dof)  # straight arm at rest (any configuration is an equilibrium, g = 0)
    freqs, share = _to_numpy(_modal_table_data(chain, Q0))
    name = "paper 004 arm, " + ("flexible links, rigid joints" if rigid_joints else "flexible links and joints")
    return RigResult(
        name,
        tuple(chain.coordinate_names()),
        outputs,
        int(traj.num_steps),
        time.perf_counter() - start,
        Q0,
        freqs,
        share,
    )


def _run_pendulum() -> RigResult:
    import jax.numpy as jnp
    import numpy as np

    import flexdyn as fd

    start = time.perf_counter()
    chain = fd.rigs.flexible_pendulum(n_modes=2, damping_ratio=0.01)
    y0 = fd.initial_state(chain, joint_angles=[0.0])  # released from horizontal (rigs.py convention)
    ts = jnp.linspace(0.0, PENDULUM_DURATION, int(round(PENDULUM_DURATION / PENDULUM_SAMPLE)) + 1)
    traj = fd.simulate(chain, y0, ts)  # adaptive Tsit5, rtol 1e-8, atol 1e-10
    outputs = _to_numpy(fd.observe(chain, traj))
    Q0 = np.zeros(chain.n_dof)
    Q0[chain.layout.theta[0]] = -np.pi / 2  # hanging equilibrium
    freqs, share = _to_numpy(_modal_table_data(chain, Q0))
    return RigResult(
        "paper 000 flexible pendulum (2 modes, 1 % modal damping)",
        tuple(chain.coordinate_names()),
        outputs,
        int(traj.num_steps),
        time.perf_counter() - start,
        Q0,
        freqs,
        share,
    )


def _tip_spectrum(ts, deflection):
    """One-sided amplitude spectrum (m) of a uniformly sampled signal, mean removed,
    Hann-windowed (amplitude-corrected)."""
    import numpy as np

    x = deflection - deflection.mean()
    window = np.hanning(x.size)
    amp = 2.0 * np.abs(np.fft.rfft(x * window)) / window.sum()
    return np.fft.rfftfreq(x.size, ts[1] - ts[0]), amp


def _swing_frequency(ts, angle, centre):
    """Mean frequency (Hz) of the swing from its upward crossings of `centre`."""
    import numpy as np

    s = angle - centre
    k = np.nonzero((s[:-1] < 0) & (s[1:] >= 0))[0]
    if k.size < 2:
        return float("nan")
    t_cross = ts[k] - s[k] * (ts[k + 1] - ts[k]) / (s[k + 1] - s[k])
    return float(1.0 / np.mean(np.diff(t_cross)))


# ---------------------------------------------------------------------------
# Plots (matplotlib's Agg canvas directly: no pyplot, no global backend state)
# ---------------------------------------------------------------------------


def _figure(rows, cols, title):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.0 * cols, 3.2 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    fig.suptitle(title)
    return fig, axes


_FJ_STYLE = dict(color="tab:blue", lw=1.2, label="flexible joints")
_RJ_STYLE = dict(color="tab:red", lw=1.2, ls="--", label="rigid joints")


def _plot_arm(fj: RigResult, rj: RigResult, out: Path):
    t = fj.outputs.ts
    title = "Paper 004 arm, bang-bang 0.2 N m / 0.5 s, RK4 at 1 ms"

    fig, ax = _figure(2, 2, title + ": angles")
    a = ax[0, 0]
    a.plot(t, fj.outputs.torque[:, 0], color="k", lw=1.2, label="both joints")
    a.set(title="(a) torque input", xlabel="t [s]", ylabel="torque [N m]")
    a.legend()
    for i, a in enumerate((ax[0, 1], ax[1, 0])):
        a.plot(t, fj.outputs.joint_angle[:, i], **_FJ_STYLE)
        a.plot(
            t, fj.outputs.rotor_angle[:, i], color="tab:green", lw=1.0, ls=":", label="rotor angle (flexible joints)"
        )
        a.plot(t, rj.outputs.joint_angle[:, i], **_RJ_STYLE)
        a.set(title=f"({'bc'[i]}) link-{i + 1} angle", xlabel="t [s]", ylabel=f"theta{i + 1} [rad]")
        a.legend(fontsize="small")
    a = ax[1, 1]
    for i, c in enumerate(("tab:blue", "tab:orange")):
        a.plot(t, 1e3 * fj.outputs.joint_deflection[:, i], color=c, lw=1.0, label=f"joint {i + 1}")
    a.set(title="(d) joint deflection alpha - theta (flexible joints)", xlabel="t [s]", ylabel="[mrad]")
    a.legend()
    fig.savefig(out / "arm_angles.png", dpi=110)

    fig, ax = _figure(2, 2, title + ": modal coordinates")
    n_modes = fj.outputs.modal.shape[1] // 2
    for k, a in enumerate(ax.flat):
        link, mode = divmod(k, n_modes)
        a.plot(t, 1e3 * fj.outputs.modal[:, k], **_FJ_STYLE)
        a.plot(t, 1e3 * rj.outputs.modal[:, k], **_RJ_STYLE)
        a.set(title=f"link {link + 1}, mode {mode + 1}", xlabel="t [s]", ylabel=f"q{link + 1}_{mode + 1} [mm]")
        a.legend(fontsize="small")
    fig.savefig(out / "arm_modes.png", dpi=110)

    fig, ax = _figure(1, 2, title + ": tip deflections")
    for i, a in enumerate(ax.flat):
        a.plot(t, 1e3 * fj.outputs.tip_deflection[:, i], **_FJ_STYLE)
        a.plot(t, 1e3 * rj.outputs.tip_deflection[:, i], **_RJ_STYLE)
        a.set(title=f"link-{i + 1} tip deflection", xlabel="t [s]", ylabel=f"v{i + 1}(l) [mm]")
        a.axhline(0.0, color="0.6", lw=0.6)
        a.legend(fontsize="small")
    fig.savefig(out / "arm_tip_deflections.png", dpi=110)


def _plot_pendulum(p: RigResult, freq, amp, peak_hz, out: Path):
    import numpy as np

    t = p.outputs.ts
    fig, ax = _figure(1, 3, "Paper 000 flexible pendulum released from horizontal (adaptive Tsit5)")
    a = ax[0, 0]
    a.plot(t, np.degrees(p.outputs.joint_angle[:, 0]), lw=1.2)
    a.axhline(-90.0, color="0.6", lw=0.6, ls="--")
    a.set(title="joint angle (from horizontal, CCW +)", xlabel="t [s]", ylabel="theta [deg]")
    a = ax[0, 1]
    a.plot(t, 1e3 * p.outputs.tip_deflection[:, 0], lw=0.8)
    a.set(title="tip deflection", xlabel="t [s]", ylabel="v(l) [mm]")
    a = ax[0, 2]
    keep = (freq > 0) & (freq <= 400.0)
    a.semilogy(freq[keep], 1e3 * amp[keep], lw=0.8)
    flexural = [f for f in p.frequencies if f > 5.0]
    for k, f in enumerate(flexural):
        a.axvline(f, color="tab:red", lw=0.8, ls="--", label="modal analysis (hanging)" if k == 0 else None)
    a.annotate(
        f"{peak_hz:.1f} Hz",
        xy=(peak_hz, 1e3 * amp[np.argmin(np.abs(freq - peak_hz))]),
        xytext=(10, 0),
        textcoords="offset points",
        va="center",
    )
    a.set(title="tip-deflection spectrum (Hann)", xlabel="frequency [Hz]", ylabel="amplitude [mm]")
    a.legend(fontsize="small")
    fig.savefig(out / "pendulum.png", dpi=110)


# ---------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------


def _modal_table(r: RigResult) -> list[str]:
    import numpy as np

    lines = ["| mode | natural frequency [Hz] | main coordinates (share of M_kk v_k^2) |", "| ---: | ---: | --- |"]
    for k, f in enumerate(r.frequencies):
        share = r.energy_share[:, k]
        order = np.argsort(-share)
        main = ", ".join(f"{r.coordinate_names[j]} {100 * share[j]:.0f} %" for j in order[:3] if share[j] >= 0.05)
        freq = "0 (rigid-body)" if f < RIGID_MODE_HZ else f"{f:.3f}"
        lines.append(f"| {k + 1} | {freq} | {main} |")
    return lines


def _summary(fj, rj, p, pend, timings, total) -> str:
    import diffrax
    import jax
    import numpy as np

    import flexdyn as fd

    def last_second_rms(x):
        return float(np.sqrt(np.mean(x[fj.outputs.ts >= ARM_DURATION - 1.0] ** 2, axis=0)).max())

    L = [
        "# flexdyn example run",
        "",
        f"flexdyn {fd.__version__}, jax {jax.__version__}, diffrax {diffrax.__version__}, "
        f"Python {platform.python_version()}, {os.cpu_count()} CPU cores. "
        f"Wall time {total:.1f} s (compilation included; see the timings at the end).",
        "",
        "## Paper 004 arm: flexible links with flexible vs. rigid joints",
        "",
        f"`fd.rigs.flexible_link_joint_arm()`, bang-bang torque {BANG_BANG_AMPLITUDE} N m on both joints "
        f"(+ on [0, {BANG_BANG_WIDTH}) s, - on [{BANG_BANG_WIDTH}, {2 * BANG_BANG_WIDTH}) s), fixed-step RK4 at "
        f"{ARM_DT * 1e3:g} ms for {ARM_DURATION:g} s, horizontal plane, starting straight at rest.",
        "",
        "| quantity | flexible joints | rigid joints |",
        "| --- | ---: | ---: |",
    ]
    rows = [
        ("solver steps", lambda r: f"{r.num_steps}"),
        ("wall time incl. compile [s]", lambda r: f"{r.seconds:.1f}"),
        ("theta1 at 5 s [rad]", lambda r: f"{r.outputs.joint_angle[-1, 0]:.4f}"),
        ("theta2 at 5 s [rad]", lambda r: f"{r.outputs.joint_angle[-1, 1]:.4f}"),
        ("max abs link-1 tip deflection [mm]", lambda r: f"{1e3 * np.abs(r.outputs.tip_deflection[:, 0]).max():.2f}"),
        ("max abs link-2 tip deflection [mm]", lambda r: f"{1e3 * np.abs(r.outputs.tip_deflection[:, 1]).max():.2f}"),
        (
            "RMS tip deflection over the last 1 s, worse link [mm]",
            lambda r: f"{1e3 * last_second_rms(r.outputs.tip_deflection):.3f}",
        ),
        (
            "max abs joint deflection alpha - theta [mrad]",
            lambda r: f"{1e3 * np.abs(r.outputs.joint_deflection).max():.2f}",
        ),
    ]
    L += [f"| {label} | {fmt(fj)} | {fmt(rj)} |" for label, fmt in rows]
    L += [
        "",
        "Figures: `arm_angles.png` (paper 004 Figs. 4(a)-(c), 6(b)), `arm_modes.png` (Figs. 4(d), "
        "5(a)-(c)), `arm_tip_deflections.png` (Figs. 5(d), 6(a)).",
        "",
    ]

    L += [
        "## Paper 000 flexible pendulum released from horizontal",
        "",
        "`fd.rigs.flexible_pendulum(n_modes=2, damping_ratio=0.01)` (strip's own mass 0.118 kg; see "
        "`flexdyn/rigs.py`), `theta0 = 0`, adaptive Tsit5 (rtol 1e-8, atol 1e-10) for "
        f"{PENDULUM_DURATION:g} s, output every {PENDULUM_SAMPLE * 1e3:g} ms.",
        "",
        f"- solver steps: {p.num_steps}; wall time incl. compile {p.seconds:.1f} s",
        f"- swing frequency (mean of upward crossings of -90 deg): {pend['swing_hz']:.3f} Hz "
        f"(small-amplitude linear value {pend['pendulum_mode_hz']:.3f} Hz)",
        f"- max abs tip deflection: {1e3 * np.abs(p.outputs.tip_deflection[:, 0]).max():.3f} mm",
        f"- flexural peak of the tip-deflection spectrum: {pend['peak_hz']:.1f} Hz (resolution "
        f"{pend['resolution_hz']:.2f} Hz); first flexural natural frequency at the hanging equilibrium "
        f"{pend['flexural_hz']:.2f} Hz. The paper's measured 35-37 Hz corresponds to its printed 0.60 kg "
        "link mass (`flexible_pendulum(mass=0.60)`), see `flexdyn/rigs.py`.",
        "",
        "Figure: `pendulum.png`.",
        "",
    ]

    L += ["## Modal analysis (`fd.modal_analysis`, undamped)", ""]
    for r, where in (
        (fj, "straight arm at rest"),
        (rj, "straight arm at rest"),
        (p, "hanging equilibrium, theta = -90 deg"),
    ):
        L += [f"### {r.name}", "", f"About the {where}; coordinates {', '.join(r.coordinate_names)}.", ""]
        L += _modal_table(r) + [""]
    L += ["## Timings [s] (wall clock unless said, compilation included)", "", "| step | seconds |", "| --- | ---: |"]
    L += [f"| {k} | {v:.1f} |" for k, v in timings.items()] + [""]
    return "\n".join(L)


def main(argv=None) -> int:
    args = _parse_args(argv)
    out: Path = args.out
    refusal = _check_output_folder(out, args.force)
    if refusal is not None:
        print(f"flexdyn-example: {refusal}", file=sys.stderr)
        return 2

    start, cpu_start = time.perf_counter(), time.process_time()
    import numpy as np

    import flexdyn as fd  # noqa: F401  (enables float64 before any computation)

    print(
        "flexdyn-example: simulating paper 004's arm (flexible and rigid joints) and paper 000's "
        "flexible pendulum; the first run compiles, about a minute on a laptop ...",
        flush=True,
    )
    # The three rigs have different structures, so each compiles its own programs; XLA compiles
    # outside the GIL, so two threads overlap one rig's compilation with another's tracing.
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        jobs = {
            "arm, flexible joints": pool.submit(_run_arm, False),
            "arm, rigid joints": pool.submit(_run_arm, True),
            "pendulum": pool.submit(_run_pendulum),
        }
        results = {k: job.result() for k, job in jobs.items()}
    fj, rj, p = results["arm, flexible joints"], results["arm, rigid joints"], results["pendulum"]
    t_sim = time.perf_counter() - start

    freq, amp = _tip_spectrum(p.outputs.ts, p.outputs.tip_deflection[:, 0])
    band = freq >= 10.0  # above the swing and its harmonics
    peak_hz = float(freq[band][np.argmax(amp[band])])
    flexural = [float(f) for f in p.frequencies if f > 5.0]
    pendulum_mode = [float(f) for f in p.frequencies if RIGID_MODE_HZ < f <= 5.0]
    pend = dict(
        peak_hz=peak_hz,
        resolution_hz=float(freq[1]),
        flexural_hz=flexural[0],
        pendulum_mode_hz=pendulum_mode[0] if pendulum_mode else float("nan"),
        swing_hz=_swing_frequency(p.outputs.ts, p.outputs.joint_angle[:, 0], -np.pi / 2),
    )

    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    _plot_arm(fj, rj, out)
    _plot_pendulum(p, freq, amp, peak_hz, out)
    t_plot = time.perf_counter() - t0

    timings = {
        f"{k}: simulate + observe + modal analysis (two threads, overlapping)": r.seconds for k, r in results.items()
    }
    timings["all three rigs, elapsed"] = t_sim
    timings["plots"] = t_plot
    total = time.perf_counter() - start
    timings["total"] = total
    timings["CPU time of the process (user + system, all threads)"] = time.process_time() - cpu_start
    summary = _summary(fj, rj, p, pend, timings, total)
    (out / "summary.md").write_text(summary + "\n")

    print()
    print(summary)
    print()
    print(f"flexdyn-example: done in {total:.1f} s. Plots and summary are in {out.resolve()}/:")
    for name in OUTPUT_FILES:
        print(f"  {out / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
