"""Write the synthetic logs of the servo and flexible link example (`logs/*.csv`).

The rig: a rotary servo of the kind most flexible-link labs own (datasheet values of the
Quanser SRV02 class: a 2.6 ohm DC motor, 7.68 mN m/A, rotor 3.9e-7 kg m^2, a 70:1 gear of
90 % efficiency) turning a clamped 0.45 m aluminium strip (20 x 1.5 mm, EI 0.388 N m^2,
0.081 kg/m) carrying a 50 g tip mass, in the horizontal plane. The gear has dry friction
(0.03 N m at the link, smoothed as `flexdyn.RigidJoint`'s law), so the hub stops short of
each reference and holds while the link rings on.

A digital controller at 500 Hz reads the motor encoder (4096 counts per motor turn: 2.19e-5
rad at the link) and the strain gauge (calibrated to the tip deflection in counts of 0.05
mm) and commands the amplifier's voltage, held over each period:

    V_k = clip(KP (ref_k - theta_k) + K_TIP tip_k - KD (theta_k - theta_{k-1}) / h, +-LIMIT)

with the readings in whole counts. The gauge is wired reversed: its column is `-tip1`.

The loop is simulated here tick by tick, independently of `identify`'s closed-loop model:
`flexdyn.simulate` of the chain over each period under the held voltage at tight
tolerances (rtol 1e-10), the law evaluated in NumPy from the rounded readings. The logs
record what the controller read (the counts, in degrees and millimetres), its reference
and its command; their only noise is the sensors' quantisation.

    python identify/examples/servo_flexible_link/make_logs.py
"""

from __future__ import annotations

import math
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import flexdyn as fd  # noqa: E402

HERE = Path(__file__).resolve().parent

# the rig's truth (SI; link side of the gear unless named motor)
MOTOR = {"resistance": 2.6, "torque_constant": 7.68e-3, "efficiency": 0.9}
ROTOR_INERTIA, GEAR = 3.9e-7, 70.0
LINK = {"length": 0.45, "rho": 0.081, "EI": 0.388, "damping_ratio": 0.005}
TIP_MASS = 0.05
TRUTH = {"hub1.inertia": 2.0e-3, "joint1.damping": 4.0e-3, "joint1.coulomb": 0.03, "link1.EI": LINK["EI"]}

# the controller and the sensors
PERIOD = 2e-3  # s
KP, KD, K_TIP, LIMIT = 10.0, 0.5, 40.0, 1.0  # V/rad, V s/rad, V/m, V
ENCODER = 2 * math.pi / (4096 * GEAR)  # rad per count at the link
GAUGE = 5e-5  # m per count of the tip deflection

DURATION = 3.0  # s
# name: (first step, second step) of the hub angle's reference (rad), at 0.2 s and 1.6 s
STEPS = {"step_a": (0.30, 0.05), "step_b": (-0.25, 0.10), "step_c": (0.20, -0.10)}


def rig(values: dict | None = None) -> fd.Chain:
    """The rig at the truth (or with `values`: `TRUTH`'s names)."""
    v = {**TRUTH, **(values or {})}
    link = fd.FlexibleLink(LINK["length"], LINK["rho"], v["link1.EI"], n_modes=1, damping_ratio=LINK["damping_ratio"])
    joint = fd.RigidJoint(
        damping=v["joint1.damping"], coulomb=v["joint1.coulomb"], rotor_inertia=ROTOR_INERTIA, gear_ratio=GEAR
    )
    return fd.Chain(
        [link],
        [joint],
        [fd.Hub(inertia=v["hub1.inertia"])],
        payload=fd.Payload(mass=TIP_MASS),
        motors=[fd.DCMotor(**MOTOR)],
    )


class SensorNoise:
    """Where the sensors' counts fall, and what they add before rounding, for seeded
    variants of the logs.

    The shipped logs have the rounding as their only noise, its pattern fixed by the
    trajectory. With a seed, each sensor's count edges sit at a random fraction of a count
    from its zero (`encoder_offset`, `gauge_offset`, uniform over one count; homing the
    encoder and nulling the gauge's bridge at rest make the first readings 0), which draws
    a new rounding pattern; and the gauge's bridge amplifier may add white Gaussian noise
    of `gauge_sigma_m` (m of tip deflection) to each reading, which the controller then
    feeds back."""

    def __init__(self, seed: int | None = None, gauge_sigma_m: float = 0.0):
        self._rng = np.random.default_rng(seed)
        self.gauge_sigma_m = gauge_sigma_m
        drawn = seed is not None
        self.encoder_offset = float(self._rng.uniform(-0.5, 0.5)) * ENCODER if drawn else 0.0
        self.gauge_offset = float(self._rng.uniform(-0.5, 0.5)) * GAUGE if drawn else 0.0
        self.encoder_home_count = round(self.encoder_offset / ENCODER)
        self.gauge_home_count = round(self.gauge_offset / GAUGE)

    def gauge_sample(self) -> float:
        return float(self._rng.normal(0.0, self.gauge_sigma_m)) if self.gauge_sigma_m > 0 else 0.0

    def tip_noise_m(self) -> float:
        """The gauge channel's noise standard deviation (m): the amplifier's and the
        rounding's, `sqrt(sigma^2 + q^2 / 12)`."""
        return math.sqrt(self.gauge_sigma_m**2 + GAUGE**2 / 12)


def reference(t, steps) -> np.ndarray:
    """The hub angle's reference (rad): 0, then `steps[0]` from 0.2 s, `steps[1]` from 1.6 s."""
    return np.where(t < 0.2, 0.0, np.where(t < 1.6, steps[0], steps[1]))


def run_loop(chain: fd.Chain, t, ref, noise: SensorNoise | None = None):
    """The loop over the ticks `t`: `(readings of theta1 (rad), of tip1 (m), commands (V))`,
    the command of tick k the one held from it. With `noise`, the controller reads (and the
    log records) the sensors through it."""
    asm = fd.assemble(chain)
    y = np.zeros(2 * asm.layout.n_dof)  # at rest, the link straight
    tip_of = jax.jit(lambda y_: fd.tip_deflections(asm, y_[: asm.layout.n_dof])[0])
    noise = noise or SensorNoise()

    def read(y_):
        theta_counts = round((float(y_[0]) + noise.encoder_offset) / ENCODER) - noise.encoder_home_count
        tip_counts = (
            round((float(tip_of(y_)) + noise.gauge_offset + noise.gauge_sample()) / GAUGE) - noise.gauge_home_count
        )
        return ENCODER * theta_counts, GAUGE * tip_counts

    theta, tip = read(y)
    theta_prev = theta
    readings, commands = [], []
    for k in range(len(t)):
        volts = float(np.clip(KP * (ref[k] - theta) + K_TIP * tip - KD * (theta - theta_prev) / PERIOD, -LIMIT, LIMIT))
        readings.append((theta, tip))
        commands.append(volts)
        if k + 1 == len(t):
            break
        held = fd.SampledTorque(np.array([t[k], t[k + 1]]), np.full((2, 1), volts), hold="zoh")
        run = fd.simulate(chain, y, np.array([t[k], t[k + 1]]), held, rtol=1e-10, atol=1e-12)
        y = np.concatenate([np.asarray(run.Q[-1]), np.asarray(run.Qd[-1])])
        theta_prev = theta
        theta, tip = read(y)
    r = np.asarray(readings)
    return r[:, 0], r[:, 1], np.asarray(commands)


def write_log(path: Path, t, theta, tip, ref, volts) -> None:
    rows = ["time [s],encoder [deg],gauge [mm],reference [deg],amplifier [V]"]
    rows += [
        f"{a:.6f},{math.degrees(b):.9g},{-1e3 * c + 0.0:.6g},{math.degrees(d):.9g},{e:.12g}"
        for a, b, c, d, e in zip(t, theta, tip, ref, volts)
    ]
    path.write_text("\n".join(rows) + "\n")


def write_logs(folder: Path, seed: int | None = None, gauge_sigma_m: float = 0.0, quiet: bool = False) -> None:
    """Write `folder/<name>.csv` for each of `STEPS`. Without a seed, the shipped logs;
    with one, the sensors read through `SensorNoise(seed, gauge_sigma_m)`: one session on
    the rig, homed and nulled once, its count phases the same in every log."""
    folder.mkdir(parents=True, exist_ok=True)
    t = np.arange(round(DURATION / PERIOD) + 1) * PERIOD
    chain = rig()
    noise = None if seed is None else SensorNoise(seed, gauge_sigma_m)
    for name, steps in STEPS.items():
        ref = reference(t, steps)
        theta, tip, volts = run_loop(chain, t, ref, noise)
        write_log(folder / f"{name}.csv", t, theta, tip, ref, volts)
        if not quiet:
            saturated = np.mean(np.abs(volts) >= LIMIT)
            print(f"{name}: {len(t)} ticks, command saturated {100 * saturated:.1f} % of them")


def main() -> None:
    write_logs(HERE / "logs")
    print("truth:", TRUTH)


if __name__ == "__main__":
    main()
