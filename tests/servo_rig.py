"""An independent simulation of a geared servo rig with true stick-slip friction (NumPy).

The traits of the real logs of issue 61, reproduced so that the diagnosis can be checked
against a known truth: a horizontal rigid arm on a 70:1 geared hub, driven by a digital
position controller whose torque command is held constant over each 1 ms sample
(zero-order hold), with stiction that holds the hub still between moves, recorded by a
4096-count motor encoder (quantised to whole counts).

It shares no code with flexdyn: the motion between controller updates is the exact closed
form of

    J theta'' = tau - c theta' - F,      F = F_c sign(theta')            while sliding,
                                         theta' = 0 while |tau| <= F_s   while stuck,

(`J = I_hub + m L^2 / 3`, link side; `tau` the held link-side torque, `c` the viscous
damping, `F_c` the sliding and `F_s > F_c` the breakaway friction: Karnopp's stick-slip
model, Karnopp 1985, J. Dyn. Sys. Meas. Control 107:100). While sliding with sign `s` the
velocity relaxes exponentially to `v_inf = (tau - s F_c) / c` at the rate `k = c / J`:

    theta'(t) = v_inf + (v0 - v_inf) e^{-k t},
    theta(t) = theta0 + v_inf t + (v0 - v_inf) (1 - e^{-k t}) / k,

and the instant it reaches zero, `t0 = ln((v0 - v_inf) / (-v_inf)) / k` (when `s v_inf <
0`), is found exactly: there the hub sticks if the held torque is at most `F_s`, or slides
on the other way. A stuck hub breaks away only at a controller update whose new torque
exceeds `F_s` (the torque is constant in between).

`write_servo_experiment(folder)` writes three 3 s logs (CSV) and an `experiment.toml` whose
baseline model has no friction (one log held out), the encoder declared with
`[sensors.theta1] kind = "encoder"` and its `resolution`, and `hold = "zoh"`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class ServoRig:
    """The rig's truth (SI, link side of the gear unless named motor).

    `hub_inertia_kg_m2` includes the motor rotor reflected through the gear (`G^2 J_rotor`).
    `sliding_friction_n_m` (`F_c`) and `breakaway_friction_n_m` (`F_s`) are the joint's
    dry friction, link side. The controller: `tau = Kp (ref - theta_enc) - Kd omega_enc`
    (`omega_enc`: the encoder's backward difference over one sample), saturated at
    `torque_limit_n_m`, computed from the quantised encoder every `sample_s` and held."""

    link_length_m: float = 0.30
    link_mass_kg: float = 0.20
    hub_inertia_kg_m2: float = 0.005
    damping_n_m_s: float = 0.01
    sliding_friction_n_m: float = 0.085
    breakaway_friction_n_m: float = 0.10
    gear_ratio: float = 70.0
    counts_per_turn: int = 4096
    sample_s: float = 1e-3
    kp_n_m_per_rad: float = 4.0
    kd_n_m_s_per_rad: float = 0.25
    torque_limit_n_m: float = 1.5

    @property
    def inertia_kg_m2(self) -> float:
        """`J = I_hub + m L^2 / 3`: hub plus a uniform rod about its end."""
        return self.hub_inertia_kg_m2 + self.link_mass_kg * self.link_length_m**2 / 3.0

    @property
    def count_rad(self) -> float:
        """One encoder count, link side: `2 pi / (counts_per_turn G)` (a motor encoder)."""
        return 2.0 * math.pi / (self.counts_per_turn * self.gear_ratio)


def advance(rig: ServoRig, theta: float, rate: float, torque: float, duration: float) -> tuple[float, float]:
    """The exact state `(theta [rad], rate [rad/s])` after `duration` [s] under the constant
    link-side `torque` [N m] (module docstring); `rate == 0.0` exactly while stuck."""
    J, c = rig.inertia_kg_m2, rig.damping_n_m_s
    Fc, Fs = rig.sliding_friction_n_m, rig.breakaway_friction_n_m
    k = c / J
    left = duration
    while left > 0.0:
        if rate == 0.0:
            if abs(torque) <= Fs:
                return theta, 0.0  # held by stiction for the rest of the interval
            s = math.copysign(1.0, torque)
        else:
            s = math.copysign(1.0, rate)
        v_inf = (torque - s * Fc) / c
        t_stop = math.inf
        if s * v_inf < 0.0:  # decelerating towards zero
            t_stop = math.log((rate - v_inf) / (-v_inf)) / k
        t = min(left, t_stop)
        decay = -math.expm1(-k * t)  # 1 - e^{-k t}
        theta = theta + v_inf * t + (rate - v_inf) * decay / k
        rate = v_inf + (rate - v_inf) * (1.0 - decay)
        left -= t
        if t == t_stop:
            rate = 0.0
    return theta, rate


def encoder(rig: ServoRig, theta: float) -> float:
    """The recorded angle [rad, link side]: whole motor counts (an incremental encoder
    counts the transitions it has passed: floor)."""
    return rig.count_rad * math.floor(theta / rig.count_rad)


def open_loop(rig: ServoRig, torques, theta0: float = 0.0, rate0: float = 0.0):
    """Exact states at the sample instants for held link-side `torques` [N m], one per
    sample: `(theta, rate)` arrays of `len(torques) + 1` samples."""
    theta, rate = [theta0], [rate0]
    for tau in torques:
        th, v = advance(rig, theta[-1], rate[-1], float(tau), rig.sample_s)
        theta.append(th)
        rate.append(v)
    return np.array(theta), np.array(rate)


def min_jerk(t: np.ndarray, start: float, stop: float, t0: float, duration: float) -> np.ndarray:
    """A minimum-jerk move from `start` to `stop` [rad] over `[t0, t0 + duration]` [s]."""
    x = np.clip((t - t0) / duration, 0.0, 1.0)
    return start + (stop - start) * (10 * x**3 - 15 * x**4 + 6 * x**5)


def reference(t: np.ndarray, rng: np.random.Generator, period_s: float = 0.9, move_s: float = 0.2) -> np.ndarray:
    """Point-to-point moves: every `period_s` a minimum-jerk move of `move_s` to a new
    target, 15-40 deg away from the last, alternating in direction."""
    ref = np.zeros_like(t)
    here, sign = 0.0, 1.0
    for t0 in np.arange(0.1, t[-1] - move_s, period_s):
        there = here + sign * math.radians(rng.uniform(15.0, 40.0))
        ref = np.where(t >= t0, min_jerk(t, here, there, t0, move_s), ref)
        here, sign = there, -sign
    return ref


@dataclasses.dataclass(frozen=True)
class ServoLog:
    """One closed-loop run: `t` [s], the true `theta` and `rate` at the samples, the
    recorded `encoder` angle [rad, link side, whole counts] and the commanded link-side
    `torque` [N m] held over `[t_k, t_k+1)`."""

    t: np.ndarray
    theta: np.ndarray
    rate: np.ndarray
    encoder: np.ndarray
    torque: np.ndarray

    @property
    def still_fraction(self) -> float:
        """Fraction of the sample intervals over which the hub is exactly still."""
        return float(np.mean((self.rate[:-1] == 0.0) & (self.theta[1:] == self.theta[:-1])))


def closed_loop(rig: ServoRig, duration_s: float, rng: np.random.Generator) -> ServoLog:
    """The digital controller tracking `reference` moves for `duration_s`, from rest."""
    n = int(round(duration_s / rig.sample_s)) + 1
    t = np.arange(n) * rig.sample_s
    ref = reference(t, rng)
    theta, rate = np.zeros(n), np.zeros(n)
    enc, torque = np.zeros(n), np.zeros(n)
    previous = 0.0
    for k in range(n):
        enc[k] = encoder(rig, theta[k])
        omega = (enc[k] - previous) / rig.sample_s if k else 0.0
        previous = enc[k]
        u = rig.kp_n_m_per_rad * (ref[k] - enc[k]) - rig.kd_n_m_s_per_rad * omega
        torque[k] = float(np.clip(u, -rig.torque_limit_n_m, rig.torque_limit_n_m))
        if k + 1 < n:
            theta[k + 1], rate[k + 1] = advance(rig, theta[k], rate[k], torque[k], rig.sample_s)
    return ServoLog(t, theta, rate, enc, torque)


#: log name -> (seed, role)
LOGS = {"servo_a": (611, "fit"), "servo_b": (612, "fit"), "servo_c": (613, "validation")}
DURATION_S = 3.0


def write_log(rig: ServoRig, log: ServoLog, path: Path) -> None:
    """CSV as the drive records it: the motor encoder in counts-exact degrees and the motor
    torque command (link torque / G) in N m, both motor side (the experiment's
    `gear_ratio` refers them to the link)."""
    motor_deg = np.degrees(log.encoder * rig.gear_ratio)
    motor_torque = log.torque / rig.gear_ratio
    lines = [
        "# synthetic servo rig (tests/servo_rig.py): motor side, 4096-count encoder",
        "time [s],motor [deg],torque [N m]",
    ]
    lines += [f"{tk!r},{a!r},{q!r}" for tk, a, q in zip(log.t.tolist(), motor_deg.tolist(), motor_torque.tolist())]
    path.write_text("\n".join(lines) + "\n")


def write_logs(folder: Path, rig, names: dict, duration_s: float, closed_loop, write_log, entry: str, hold: str):
    """Simulate and write each log of `names` (`name -> (seed, role)`) into `folder`:
    `closed_loop(rig, duration_s, rng)` runs one, `write_log(rig, log, path)` writes its
    CSV. Returns the logs by name and their `[[logs]]` entries: `entry` formatted with each
    log's `name`, `role`, `hold` and the rig's `gear_ratio`. (Shared with
    `servo_rig_flexible.py`.)"""
    folder.mkdir(parents=True, exist_ok=True)
    logs, entries = {}, []
    for name, (seed, role) in names.items():
        logs[name] = closed_loop(rig, duration_s, np.random.default_rng(seed))
        write_log(rig, logs[name], folder / f"{name}.csv")
        entries.append(entry.format(name=name, role=role, hold=hold, gear_ratio=rig.gear_ratio))
    return logs, entries


def write_servo_experiment(folder: Path, rig: ServoRig = ServoRig(), hold: str = "zoh") -> tuple[Path, dict]:
    """Write the logs and `experiment.toml` into `folder`; returns its path and the logs
    (`name -> ServoLog`). The baseline: a rigid arm (its length and mass known) with the hub
    inertia and the viscous damping free, no friction; the encoder's noise is its
    quantisation, `q / sqrt(12)`."""
    entry = """
[[logs]]
name = "{name}"
file = "{name}.csv"
columns = {{ time = "time [s]", theta1 = "motor [deg]", torque1 = "torque [N m]" }}
calibration = {{ theta1 = {{ gear_ratio = {gear_ratio!r} }}, torque1 = {{ gear_ratio = {gear_ratio!r} }} }}
initial = {{ theta1 = "measured" }}
fit_initial = ["theta1"]
hold = "{hold}"
role = "{role}"
"""
    logs, entries = write_logs(folder, rig, LOGS, DURATION_S, closed_loop, write_log, entry, hold)
    q = rig.count_rad
    text = f"""# synthetic servo rig with stick-slip friction (tests/servo_rig.py)
[experiment]
name = "servo rig"

[rig]

[[rig.links]]
type = "rigid"
length = {rig.link_length_m!r}
mass = {rig.link_mass_kg!r}

[[rig.joints]]
type = "rigid"
damping = 0.02

[[rig.hubs]]
inertia = 0.004

[parameters]
"hub1.inertia" = {{ guess = 0.004, lower = 1e-4, upper = 1.0 }}
"joint1.damping" = {{ guess = 0.02, lower = 1e-5, upper = 1.0 }}

[sensors.theta1]
kind = "encoder"
resolution = {q!r}

[noise]
theta1 = {q / math.sqrt(12.0)!r}
""" + "".join(entries)
    path = folder / "experiment.toml"
    path.write_text(text)
    return path, logs
