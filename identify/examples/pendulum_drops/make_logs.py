"""Make the logs of the `pendulum_drops` example (synthetic, seeded, reproducible).

Paper 000's rigid pendulum (`flexdyn.rigs.rigid_pendulum()`: 0.30 m / 0.180 kg steel
link, hub inertia 2e-5 kg m^2, 0.020 kg tip payload, joint damping 1.9e-3 N m s,
vertical plane) is released from rest at three angles (theta from the horizontal,
counter-clockwise positive, hanging = -90 deg):

| log            | release angle | role       |
| -------------- | ------------- | ---------- |
| drop_0deg      |   0 deg (horizontal)         | fit        |
| drop_m45deg    | -45 deg (45 deg below)       | fit        |
| drop_m97deg    | -97 deg (7 deg past hanging) | validation |

Each log is 6 s at 200 Hz of the potentiometer angle `theta1 [deg]`, with white
Gaussian noise of 0.1 deg and a small constant potentiometer offset per log (the
`TRUE_OFFSETS_DEG` below; the experiment fits one per log). Run from anywhere:

    python identify/examples/pendulum_drops/make_logs.py

It rewrites `logs/*.csv` next to this script (and nothing else); the output is the
same on every run (seed `SEED`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import flexdyn as fd
from identify import simulate_log

SEED = 20261123
RATE_HZ = 200.0
DURATION_S = 6.0
NOISE_DEG = 0.1
JOINT_DAMPING = 1.9e-3  # N m s, paper 000's log-decrement estimate (the rig's default)
HUB_INERTIA = 2e-5  # kg m^2 (the rig's default)

#: log name -> (release angle [deg], true potentiometer offset [deg])
DROPS = {
    "drop_0deg": (0.0, 0.25),
    "drop_m45deg": (-45.0, -0.15),
    "drop_m97deg": (-97.0, 0.10),
}
TRUE_OFFSETS_DEG = {name: off for name, (_, off) in DROPS.items()}


def make_logs(folder: Path | None = None) -> list[Path]:
    """Simulate the three drops and write them as CSV into `folder` (default: ./logs next
    to this script). Returns the written paths."""
    folder = Path(__file__).resolve().parent / "logs" if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    chain = fd.rigs.rigid_pendulum(joint_damping=JOINT_DAMPING, hub_inertia=HUB_INERTIA)
    t = np.arange(int(round(DURATION_S * RATE_HZ)) + 1) / RATE_HZ
    rng = np.random.default_rng(SEED)
    written = []
    for name, (angle_deg, offset_deg) in DROPS.items():
        log = simulate_log(
            chain,
            t,
            initial={"theta1": np.radians(angle_deg)},
            channels=("theta1",),
            noise={"theta1": np.radians(NOISE_DEG)},
            true_offsets={"theta1": np.radians(offset_deg)},
            rng=rng,
            name=name,
        )
        theta_deg = np.degrees(log.outputs["theta1"])
        path = folder / f"{name}.csv"
        lines = [
            f"# synthetic: flexdyn.rigs.rigid_pendulum(), released from rest at {angle_deg:g} deg,",
            f"# potentiometer noise {NOISE_DEG} deg, offset {offset_deg:+g} deg; made by make_logs.py (seed {SEED})",
            "time [s],theta1 [deg]",
        ]
        lines += [f"{tk:.3f},{v:.4f}" for tk, v in zip(t, theta_deg)]
        path.write_text("\n".join(lines) + "\n")
        written.append(path)
    return written


if __name__ == "__main__":
    for p in make_logs():
        print(p)
