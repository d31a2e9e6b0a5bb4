"""Make the logs of the `spinning_link` example (synthetic, seeded, reproducible).

A flexible link spun up by its motor and left to coast, in the horizontal plane: the
link of papers 002/004 (l = 0.5 m, rho = 0.2 kg/m, EI = 1.0 N m^2; two clamped-mass
modes, modal damping ratio 1 %) on a hub of 0.02 kg m^2 (the papers' motor and hub),
joint viscous damping 2e-3 N m s/rad. The motor applies a constant torque for 0.8 s,
then nothing; the link coasts at 4-14 rad/s, 14-44 % of its first clamped frequency
(32.3 rad/s), vibrating. Three runs:

| log        | torque for 0.8 s | coasting rate | role       |
| ---------- | ---------------- | ------------- | ---------- |
| spin_slow  | 0.15 N m         | ~4.2 rad/s    | fit        |
| spin_fast  | 0.50 N m         | ~14 rad/s     | fit        |
| spin_mid   | 0.30 N m         | ~8.5 rad/s    | validation |

Each log is 4 s at 500 Hz of the hub encoder `theta1 [deg]` (noise 0.02 deg), the tip
deflection from the root strain gauges `tip1 [mm]` (noise 0.02 mm) and the commanded
torque `torque1 [N m]`. The hidden truth: the link is a real beam, so it has **geometric
stiffening** (`FlexibleLink(geometric_stiffening=True)`: its centrifugal tension stiffens
it as it spins), which the papers' linear assumed-modes model lacks.

    python identify/examples/spinning_link/make_logs.py

rewrites `logs/*.csv` next to this script (nothing else); the output is the same on
every run (seed `SEED`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import flexdyn as fd
from identify import simulate_log

SEED = 20261126
RATE_HZ = 500.0
DURATION_S = 4.0
ON_S = 0.8  # s of constant torque, then none
NOISE_DEG = 0.02
NOISE_MM = 0.02

#: log name -> motor torque for the first ON_S seconds [N m]
RUNS = {"spin_slow": 0.15, "spin_fast": 0.50, "spin_mid": 0.30}


def truth() -> fd.Chain:
    link = fd.FlexibleLink(0.5, 0.2, 1.0, n_modes=2, damping_ratio=0.01, geometric_stiffening=True)
    return fd.Chain([link], [fd.RigidJoint(damping=2e-3)], [fd.Hub(inertia=0.02)])


def make_logs(folder: Path | None = None) -> list[Path]:
    folder = Path(__file__).resolve().parent / "logs" if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    t = np.arange(int(round(DURATION_S * RATE_HZ)) + 1) / RATE_HZ
    rng = np.random.default_rng(SEED)
    written = []
    for name, level in RUNS.items():
        torque = np.where(t < ON_S - 0.5 / RATE_HZ, level, 0.0)
        log = simulate_log(
            truth(),
            t,
            torque=torque[:, None],
            channels=("theta1", "tip1"),
            noise={"theta1": np.radians(NOISE_DEG), "tip1": NOISE_MM * 1e-3},
            rng=rng,
            name=name,
        )
        lines = [
            f"# synthetic: a flexible link spun up by {level:g} N m for {ON_S:g} s, then coasting (horizontal plane);",
            f"# encoder noise {NOISE_DEG} deg, strain-gauge tip noise {NOISE_MM} mm; make_logs.py (seed {SEED})",
            "time [s],theta1 [deg],tip1 [mm],torque1 [N m]",
        ]
        lines += [
            f"{tk:.3f},{a:.5f},{d:.5f},{q:g}"
            for tk, a, d, q in zip(t, np.degrees(log.outputs["theta1"]), 1e3 * log.outputs["tip1"], torque)
        ]
        path = folder / f"{name}.csv"
        path.write_text("\n".join(lines) + "\n")
        written.append(path)
    return written


if __name__ == "__main__":
    for p in make_logs():
        print(p)
