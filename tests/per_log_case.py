"""A payload sweep nobody weighed, as an experiment file (`per_log = true`): a flexible
link in a horizontal plane logged at 10, 20 and 50 g (fit logs) and 35 g (a validation
log), EI shared. Shared by `tests/identify/test_run.py` and `tests/identify/test_cli.py`."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

import flexdyn as fd
import identify

MASSES = {"m10": 0.01, "m20": 0.02, "m50": 0.05, "m35": 0.035}  # kg; m35 is held out
EI = 2.3  # N m^2
NOISE = {"theta1": math.radians(0.05), "curvature1": 2e-3}


def link(mass: float) -> fd.Chain:
    return fd.Chain(
        [fd.FlexibleLink(0.6, 0.3, EI, n_modes=2, damping_ratio=0.01)],
        [fd.RigidJoint(damping=5e-3)],
        [fd.Hub(inertia=4e-3)],
        payload=fd.Payload(mass=mass),
    )


def write_per_log_experiment(folder: Path, seed: int = 11) -> Path:
    """The logs (CSV) and the experiment file in `folder`; returns the file's path.
    (The coverage of these intervals is measured in test_fit's
    test_coverage_of_per_log_payloads, on this layout: seed 7 reads EI 2.7 SE high, a
    1-in-100 draw, and is not used here.)"""
    t = np.arange(0.0, 1.0, 2e-3)
    tau = (np.where((t >= 0.1) & (t < 0.3), 0.2, 0.0) - np.where((t >= 0.3) & (t < 0.5), 0.2, 0.0))[:, None]
    rng = np.random.default_rng(seed)
    entries = []
    (folder / "logs").mkdir(parents=True)
    for name, m in MASSES.items():
        log = identify.simulate_log(link(m), t, torque=tau, channels=("theta1", "curvature1"), noise=NOISE, rng=rng)
        identify.write_log(log, folder / "logs" / f"{name}.csv")
        role = 'role = "validation"' if name == "m35" else ""
        entries.append(f'[[logs]]\nname = "{name}"\nfile = "logs/{name}.csv"\n{role}\n')
    body = """
        [rig]
        gravity = [0.0, 0.0]

        [[rig.links]]
        type = "flexible"
        length = 0.6
        rho = 0.3
        EI = 1.8
        n_modes = 2
        damping_ratio = 0.01

        [[rig.joints]]
        type = "rigid"
        damping = 5e-3

        [[rig.hubs]]
        inertia = 4e-3

        [parameters]
        "link1.EI" = { guess = 1.8, lower = 0.1, upper = 20.0 }
        "payload.mass" = { guess = 0.03, lower = 1e-4, upper = 1.0, per_log = true }

        [noise]
        theta1 = "0.05 deg"
        curvature1 = 2e-3
        """
    path = folder / "experiment.toml"
    path.write_text(textwrap.dedent(body) + "\n".join(entries))
    return path
