"""Make the logs of the `pendulum_friction` example (synthetic, seeded, reproducible).

Paper 000's rigid pendulum (`flexdyn.rigs.rigid_pendulum()`: 0.30 m / 0.180 kg steel
link, hub inertia 2e-5 kg m^2, 0.020 kg tip payload, vertical plane) whose joint has,
besides viscous damping, **dry (Coulomb) friction** that the paper's model lacks (the
paper's linear-damping model "matched for about 7 s", then drifted "due to the
non-linear effect of damping"). It is released from rest three times:

| log         | release angle (from horizontal) | role       |
| ----------- | ------------------------------- | ---------- |
| drop_0deg   |   0 deg                         | fit        |
| drop_m30deg | -30 deg                         | fit        |
| drop_m60deg | -60 deg                         | validation |

Each log is 8 s at 100 Hz of the potentiometer angle `theta1 [deg]`, with white
noise of 0.1 deg and a small constant offset per log. The hidden truth (what
`identify diagnose` should find): `joint1.coulomb = 1.0e-3 N m` (smoothed with
`coulomb_velocity = 0.01 rad/s`), `joint1.damping = 0.8e-3 N m s`.

    python identify/examples/pendulum_friction/make_logs.py

rewrites `logs/*.csv` next to this script (nothing else); the output is the same on
every run (seed `SEED`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import flexdyn as fd
from identify import simulate_log

SEED = 20261124
RATE_HZ = 100.0
DURATION_S = 8.0
NOISE_DEG = 0.1
COULOMB = 1.0e-3  # N m, hidden
VISCOUS = 0.8e-3  # N m s

#: log name -> (release angle [deg], true potentiometer offset [deg])
DROPS = {"drop_0deg": (0.0, 0.2), "drop_m30deg": (-30.0, -0.1), "drop_m60deg": (-60.0, 0.15)}


def truth() -> fd.Chain:
    rig = fd.rigs.rigid_pendulum()
    return fd.Chain(
        rig.links,
        [fd.RigidJoint(damping=VISCOUS, coulomb=COULOMB)],
        rig.hubs,
        rig.payload,
        rig.gravity,
    )


def make_logs(folder: Path | None = None) -> list[Path]:
    folder = Path(__file__).resolve().parent / "logs" if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    t = np.arange(int(round(DURATION_S * RATE_HZ)) + 1) / RATE_HZ
    rng = np.random.default_rng(SEED)
    written = []
    for name, (angle_deg, offset_deg) in DROPS.items():
        log = simulate_log(
            truth(),
            t,
            initial={"theta1": np.radians(angle_deg)},
            channels=("theta1",),
            noise={"theta1": np.radians(NOISE_DEG)},
            true_offsets={"theta1": np.radians(offset_deg)},
            rng=rng,
            name=name,
        )
        lines = [
            f"# synthetic: rigid pendulum with hidden dry joint friction, released at {angle_deg:g} deg;",
            f"# potentiometer noise {NOISE_DEG} deg, offset {offset_deg:+g} deg; make_logs.py (seed {SEED})",
            "time [s],theta1 [deg]",
        ]
        lines += [f"{tk:.3f},{v:.4f}" for tk, v in zip(t, np.degrees(log.outputs["theta1"]))]
        path = folder / f"{name}.csv"
        path.write_text("\n".join(lines) + "\n")
        written.append(path)
    return written


if __name__ == "__main__":
    for p in make_logs():
        print(p)
