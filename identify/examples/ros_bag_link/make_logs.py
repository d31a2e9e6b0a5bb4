"""Make the ROS 2 bags of the `ros_bag_link` example (synthetic, seeded, reproducible).

Paper 000's flexible pendulum (`flexdyn.rigs.flexible_pendulum(n_modes=2,
damping_ratio=0.01)`: a 0.30 x 0.025 x 0.002 m spring-steel strip, EI = 3.33 N m^2, on a
hub of 2e-5 kg m^2, joint damping 1.9e-3 N m s/rad, vertical plane) hangs at rest and is
driven by its motor. A robot's ROS 2 drivers record two runs as bags with MCAP storage
(zstd-compressed chunks), each 3 s:

| bag           | motor torque                                   | role       |
| ------------- | ---------------------------------------------- | ---------- |
| `drive_fit`   | a chirp of 0.05 N m sweeping 0.5-8 Hz           | fit        |
| `drive_check` | two half-sine pulses of 0.06 and -0.05 N m      | validation |

Each bag has three topics:

- `/joint_states` (`sensor_msgs/msg/JointState`, 200 Hz): joint `shoulder`, its encoder
  angle (rad, noise 0.02 deg), its rate and the motor torque (effort, N m, as commanded);
  header stamps at the sampling instants, received 0.8 ms later.
- `/strain_gauge` (`std_msgs/msg/Float64`, ~500 Hz, no header): the root strain gauge's
  bridge in volts, 500 microstrain per volt, noise 1 microstrain; sampled when received,
  with 0-0.2 ms of jitter.
- `/motor_temperature` (`std_msgs/msg/Float64`, 1 Hz): not used by the experiment.

    python identify/examples/ros_bag_link/make_logs.py

rewrites `bags/drive_fit` and `bags/drive_check` next to this script (nothing else); the
numbers are the same on every run (seed `SEED`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

import flexdyn as fd
from identify import simulate_log

SEED = 20261207
DURATION_S = 3.0
JOINT_RATE_HZ = 200.0
STRAIN_RATE_HZ = 500.0
ENCODER_NOISE_DEG = 0.02
STRAIN_NOISE_UE = 1.0
UE_PER_VOLT = 500.0  # the bridge amplifier's calibration
NEUTRAL_AXIS_M = 1e-3  # the gauge's distance from the neutral axis (half the strip's 2 mm)
START_NS = 1_765_000_000_000_000_000  # the robot's clock at the first sample (ns since 1970)
RECEIVE_LATENCY_NS = 800_000  # /joint_states received 0.8 ms after its header stamp
HANGING = -np.pi / 2

BAGS = ("drive_fit", "drive_check")


def truth() -> fd.Chain:
    return fd.rigs.flexible_pendulum(n_modes=2, damping_ratio=0.01)


def motor_torque(name: str, t: np.ndarray) -> np.ndarray:
    """The commanded torque (N m) of run `name` at times `t` (s)."""
    if name == "drive_fit":  # a chirp 0.5 -> 8 Hz, faded in and out over 0.2 s
        f0, f1 = 0.5, 8.0
        phase = 2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * DURATION_S))
        fade = np.clip(np.minimum(t, DURATION_S - t) / 0.2, 0.0, 1.0)
        return 0.05 * fade * np.sin(phase)
    pulses = [(0.2, 0.15, 0.06), (1.2, 0.1, -0.05)]  # (start s, width s, peak N m)
    out = np.zeros_like(t)
    for start, width, peak in pulses:
        inside = (t >= start) & (t <= start + width)
        out[inside] = peak * np.sin(np.pi * (t[inside] - start) / width)
    return out


def record(name: str, rng: np.random.Generator) -> dict:
    """The topics of run `name`: topic -> (message type, [(receive ns, fields), ...])."""
    t_joint = np.arange(int(round(DURATION_S * JOINT_RATE_HZ)) + 1) / JOINT_RATE_HZ
    n_strain = int(round(DURATION_S * STRAIN_RATE_HZ))
    t_strain = 3e-4 + np.arange(n_strain) / STRAIN_RATE_HZ + rng.uniform(0.0, 2e-4, n_strain)
    t = np.union1d(t_joint, t_strain)
    # the motor follows the commanded torque as the driver holds it: linear between the
    # 200 Hz samples the bag records (and the fit reads)
    torque = np.interp(t, t_joint, motor_torque(name, t_joint))
    log = simulate_log(
        truth(), t, initial={"theta1": HANGING}, torque=torque[:, None], channels=("theta1", "curvature1"), name=name
    )
    at_joint, at_strain = np.isin(t, t_joint), np.isin(t, t_strain)
    angle = log.outputs["theta1"][at_joint]
    rate = np.gradient(angle, t_joint)
    angle = angle + rng.normal(0.0, np.radians(ENCODER_NOISE_DEG), angle.shape)
    strain_ue = log.outputs["curvature1"][at_strain] * NEUTRAL_AXIS_M * 1e6
    volts = (strain_ue + rng.normal(0.0, STRAIN_NOISE_UE, strain_ue.shape)) / UE_PER_VOLT
    stamps = START_NS + np.round(t_joint * 1e9).astype(np.int64)
    joints = [
        (int(s) + RECEIVE_LATENCY_NS, {"stamp": int(s), "position": p, "velocity": v, "effort": e})
        for s, p, v, e in zip(stamps, angle, rate, motor_torque(name, t_joint))
    ]
    strain = [(START_NS + int(round(ts * 1e9)), {"data": v}) for ts, v in zip(t_strain, volts)]
    temperature = [(START_NS + k * 1_000_000_000 + 500_000_000, {"data": 41.0 + 0.1 * k}) for k in range(3)]
    return {
        "/joint_states": ("sensor_msgs/msg/JointState", joints),
        "/strain_gauge": ("std_msgs/msg/Float64", strain),
        "/motor_temperature": ("std_msgs/msg/Float64", temperature),
    }


def write_bag(path: Path, topics: dict) -> Path:
    """Write `topics` as a ROS 2 bag folder at `path` (MCAP storage, zstd-compressed chunks)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)

    def message(msgtype: str, fields: dict):
        if msgtype == "std_msgs/msg/Float64":
            return types[msgtype](data=float(fields["data"]))
        sec, nanosec = divmod(fields["stamp"], 1_000_000_000)
        stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="")
        return types[msgtype](
            header=header,
            name=["shoulder"],
            position=np.array([fields["position"]]),
            velocity=np.array([fields["velocity"]]),
            effort=np.array([fields["effort"]]),
        )

    with writer:
        connections = {topic: writer.add_connection(topic, t, typestore=store) for topic, (t, _) in topics.items()}
        records = sorted(
            ((at, topic, fields) for topic, (_, items) in topics.items() for at, fields in items), key=lambda r: r[0]
        )
        for at, topic, fields in records:
            msgtype = topics[topic][0]
            writer.write(connections[topic], at, store.serialize_cdr(message(msgtype, fields), msgtype))
    return path


def make_logs(folder: Path | None = None) -> list[Path]:
    """Simulate both runs and write them as ROS 2 bags into `folder` (default: ./bags next to
    this script), replacing bags of the same names. Returns the written bags' folders."""
    folder = Path(__file__).resolve().parent / "bags" if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(SEED)
    written = []
    for name in BAGS:
        topics = record(name, rng)
        path = folder / name
        if path.exists():  # the writer creates a bag, never overwrites one
            shutil.rmtree(path)
        written.append(write_bag(path, topics))
    return written


if __name__ == "__main__":
    for p in make_logs():
        print(p)
