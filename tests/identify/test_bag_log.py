"""ROS bag logs (`identify._data.bag_log`): joint states and scalar topics read from ROS 2
(sqlite3 and MCAP) and ROS 1 bags written here with `rosbags`' writers, checked against the
values written (resampling against closed forms), and a clear error for each mistake (the
bag, topic, field, message and what was expected)."""

import hashlib
import math
import re
import textwrap
import warnings

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

from identify._data.columns import LogError
from identify._data.experiment_file import load_experiment
from identify._data.logs import load_log
from identify._data.toml_reader import ExperimentError


def msg(*parts: str) -> str:
    """A `match` pattern requiring every fragment, in order."""
    return "(?s)" + ".*".join(re.escape(p) for p in parts)


#: a custom message type, its definition written into the bags
GAUGES = "float64[] values\ngeometry_msgs/Vector3 v\nstring label\nbool ok\n"

KINDS = ("sqlite3", "mcap", "ros1")


def typestore(kind: str):
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(GAUGES, "rig_msgs/msg/Gauges"))
    return store


TYPESTORES = {kind: typestore(kind) for kind in KINDS}

T0 = 1_733_300_000_000_000_000  # ns since 1970 (2024-12-04)
MS = 1_000_000  # ns


def write_bag(path, kind: str, topics: dict) -> "Path":  # noqa: F821
    """Write `topics` (topic -> (message type, [(receive time ns, message), ...])) as a bag
    of `kind` at `path` (a ROS 2 folder, or `path.bag` for ROS 1); returns the bag's path.
    A message given as `bytes` is written as they are (a damaged one)."""
    if kind == "ros1":
        path = path.with_suffix(".bag")
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        store = TYPESTORES[kind]
        connections = {topic: writer.add_connection(topic, t, typestore=store) for topic, (t, _) in topics.items()}
        records = [(at, topic, m) for topic, (_, items) in topics.items() for at, m in items]
        for at, topic, message in sorted(records, key=lambda r: r[0]):
            raw = message if isinstance(message, bytes) else serialized(kind, message, topics[topic][0])
            writer.write(connections[topic], at, raw)
    return path


def serialized(kind: str, message, msgtype: str) -> bytes:
    """`message` as a bag of `kind` stores it (ROS 1 or CDR bytes)."""
    store = TYPESTORES[kind]
    return bytes(store.serialize_ros1(message, msgtype) if kind == "ros1" else store.serialize_cdr(message, msgtype))


def split_bag(path, kind: str, topics: dict, at: int) -> "Path":  # noqa: F821
    """`topics` as a ROS 2 bag folder `path` split while recording into two storage files, as
    rosbag2 writes one: the messages received before `at` in `<name>_0`, the rest in
    `<name>_1`, one `metadata.yaml` listing both with the counts and times summed (rosbags'
    writer does not split: each part is written as a bag of its own, their metadata merged)."""
    yaml = YAML(typ="safe")
    path.mkdir()
    infos = []
    for i in (0, 1):
        part = {topic: (t, [(r, m) for r, m in items if (r >= at) == i]) for topic, (t, items) in topics.items()}
        bag = write_bag(path.parent / f"{path.name}_part{i}", kind, part)
        file = storage_file(bag)
        info = yaml.load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        (entry,) = info["files"]
        entry["path"] = f"{path.name}_{i}{file.suffix}"
        file.rename(path / entry["path"])
        infos.append(info)
    first, second = infos
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in second["topics_with_message_count"]}
    for t in first["topics_with_message_count"]:
        t["message_count"] += counts[t["topic_metadata"]["name"]]
    first["files"] += second["files"]
    first["relative_file_paths"] = [entry["path"] for entry in first["files"]]
    first["message_count"] += second["message_count"]
    start = first["starting_time"]["nanoseconds_since_epoch"]
    end = second["starting_time"]["nanoseconds_since_epoch"] + second["duration"]["nanoseconds"]
    first["duration"]["nanoseconds"] = end - start
    with (path / "metadata.yaml").open("w") as f:
        yaml.dump({"rosbag2_bagfile_information": first}, f)
    return path


def storage_file(bag):
    """The one storage file of a ROS 2 bag folder (`.db3` or `.mcap`)."""
    (file,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    return file


def header(kind: str, stamp: int):
    t = TYPESTORES[kind].types
    seq = {"seq": 0} if kind == "ros1" else {}
    time = t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
    return t["std_msgs/msg/Header"](**seq, stamp=time, frame_id="")


def joint_state(kind: str, stamp: int, names, position, velocity=(), effort=()):
    return TYPESTORES[kind].types["sensor_msgs/msg/JointState"](
        header=header(kind, stamp),
        name=list(names),
        position=np.asarray(position, float),
        velocity=np.asarray(velocity, float),
        effort=np.asarray(effort, float),
    )


def float64(kind: str, value: float):
    return TYPESTORES[kind].types["std_msgs/msg/Float64"](data=float(value))


def gauges(kind: str, values, v=(0.0, 0.0, 0.0), label="", ok=True):
    t = TYPESTORES[kind].types
    vector = t["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2])
    return t["rig_msgs/msg/Gauges"](values=np.asarray(values, float), v=vector, label=label, ok=ok)


# ---------------------------------------------------------------------------
# The rig's bag: closed-form signals at their own rates
# ---------------------------------------------------------------------------

OMEGA = 2 * math.pi * 1.3  # rad/s, the shoulder's angle sin(OMEGA t)
JOINT_DT = 5 * MS  # /joint_states at 200 Hz, header stamps from T0, received 2 ms later
JOINT_N = 201  # 0 ... 1 s
STRAIN_START, STRAIN_DT, STRAIN_N = 13 * MS, 2 * MS, 444  # /strain at 500 Hz, received 13 ... 899 ms
GAUGE_START, GAUGE_DT, GAUGE_N = 1 * MS, 10 * MS, 100  # /gauges at 100 Hz, received 1 ... 991 ms


def shoulder(t):
    return np.sin(OMEGA * t)


def elbow(t):
    return 0.5 * np.cos(OMEGA * t)


def effort(t):
    return 0.1 + 0.2 * t


def volts(t):  # the strain bridge's output: linear in time, so linear interpolation is exact
    return 0.2 + 1.5 * t


def rig_topics(kind: str) -> dict:
    joints = []
    for k in range(JOINT_N):
        stamp = T0 + k * JOINT_DT
        t = k * JOINT_DT / 1e9
        joints.append(
            (
                stamp + 2 * MS,
                joint_state(kind, stamp, ["shoulder", "elbow"], [shoulder(t), elbow(t)], [0.0, 0.0], [effort(t), 0.0]),
            )
        )
    strain = [
        (T0 + STRAIN_START + j * STRAIN_DT, float64(kind, volts((STRAIN_START + j * STRAIN_DT) / 1e9)))
        for j in range(STRAIN_N)
    ]
    gauge = [
        (T0 + at, gauges(kind, [1.0, -2.0 * at / 1e9], v=(0.0, 0.0, 3.0 * at / 1e9)))
        for at in (GAUGE_START + j * GAUGE_DT for j in range(GAUGE_N))
    ]
    return {
        "/joint_states": ("sensor_msgs/msg/JointState", joints),
        "/strain": ("std_msgs/msg/Float64", strain),
        "/gauges": ("rig_msgs/msg/Gauges", gauge),
        "/diagnostics": ("std_msgs/msg/Float64", [(T0 + 500 * MS, float64(kind, 1.0))]),
    }


@pytest.fixture(scope="module")
def rig_bags(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bags")
    return {kind: write_bag(folder / f"rig_{kind}", kind, rig_topics(kind)) for kind in KINDS}


COLUMNS = {
    "theta1": {"topic": "/joint_states", "joint": "shoulder", "field": "position", "unit": "rad"},
    "torque1": {"topic": "/joint_states", "joint": "shoulder", "field": "effort", "unit": "N m"},
    "tip1": {"topic": "/strain", "field": "data", "unit": "V"},
}
CALIBRATION = {"tip1": {"scale": 12.5, "unit": "mm"}}  # 12.5 mm per volt


def load(bag, columns=None, **kw):
    kw.setdefault("calibration", CALIBRATION if columns is None else None)
    return load_log(bag, COLUMNS if columns is None else columns, **kw)


# ---------------------------------------------------------------------------
# Valid bags
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind, storage", [(k, False) for k in KINDS] + [("sqlite3", True), ("mcap", True)])
def test_joint_states_and_a_scalar_topic_on_the_joint_states_stamps(rig_bags, kind, storage):
    """`time_base = "/joint_states"`: its header stamps inside the span every topic covers
    (/strain starts at 13 ms and ends at 899 ms), its own values exactly, /strain's
    interpolated (exact: a linear signal)."""
    bag = storage_file(rig_bags[kind]) if storage else rig_bags[kind]
    log = load(bag, time_base="/joint_states")
    k = np.arange(3, 180)  # stamps 15 ... 895 ms
    t = k * JOINT_DT / 1e9
    assert np.array_equal(log.t_relative, (k - 3) * JOINT_DT / 1e9)
    assert log.t[0] == pytest.approx((T0 + 15 * MS) / 1e9, rel=1e-15)
    assert np.array_equal(log.outputs["theta1"], shoulder(t))  # the values written, to the bit
    assert np.array_equal(log.inputs["torque1"], effort(t))
    np.testing.assert_allclose(log.outputs["tip1"], 12.5e-3 * volts(t), rtol=1e-13, atol=0)
    assert log.name == bag.stem and log.ignored == ("/diagnostics", "/gauges")
    assert log.sources["theta1"] == "/joint_states position of joint 'shoulder' [rad] (header stamps)"
    assert log.sources["tip1"] == (
        "/strain data [V] (receive times, interpolated onto the stamps of /joint_states) (calibrated)"
    )


@pytest.mark.parametrize("kind", KINDS)
def test_a_uniform_rate_interpolates_every_topic_inside_the_common_span(rig_bags, kind):
    """`rate_hz = 1000`: times k / 1000 s from the common span's start (13 ms) to its end
    (899 ms); a linear interpolation of sin within its bound h^2 / 8 max|f''|, and exact at
    the stamps it passes through."""
    log = load(rig_bags[kind], rate_hz=1000)
    k = np.arange(887)
    assert np.array_equal(log.t_relative, k / 1000)
    assert log.t[0] == pytest.approx((T0 + STRAIN_START) / 1e9, rel=1e-15)
    t = (STRAIN_START + k * MS) / 1e9
    error = log.outputs["theta1"] - shoulder(t)
    bound = (JOINT_DT / 1e9) ** 2 / 8 * OMEGA**2
    assert np.max(np.abs(error)) <= bound and np.max(np.abs(error)) > 0.5 * bound
    on_stamp = (STRAIN_START / MS + k) % 5 == 0  # 15, 20, ... ms: /joint_states' own stamps
    np.testing.assert_allclose(log.outputs["theta1"][on_stamp], shoulder(t[on_stamp]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(log.inputs["torque1"], effort(t), rtol=1e-13)  # linear: exact
    np.testing.assert_allclose(log.outputs["tip1"], 12.5e-3 * volts(t), rtol=1e-13)
    assert log.sampling.rate == pytest.approx(1000.0) and log.sampling.uniform
    assert log.sources["theta1"].endswith("(header stamps, interpolated onto 1000 Hz)")


def test_header_stamps_by_default_receive_times_when_chosen(rig_bags):
    """One topic needs no time base: its own stamps. `stamp = "receive"` takes when the bag
    recorded each message (here 2 ms after its header stamp)."""
    columns = {"theta1": COLUMNS["theta1"]}
    by_header = load(rig_bags["mcap"], columns)
    by_receipt = load(rig_bags["mcap"], columns, stamp="receive")
    assert len(by_header) == len(by_receipt) == JOINT_N
    assert by_header.t[0] == pytest.approx(T0 / 1e9, rel=1e-15)
    assert by_receipt.t[0] == pytest.approx((T0 + 2 * MS) / 1e9, rel=1e-15)
    assert np.array_equal(by_header.t_relative, np.arange(JOINT_N) * JOINT_DT / 1e9)
    assert np.array_equal(by_header.outputs["theta1"], by_receipt.outputs["theta1"])
    assert by_header.sources["theta1"].endswith("(header stamps)")
    assert by_receipt.sources["theta1"].endswith("(receive times)")
    assert by_header.ignored == ("/diagnostics", "/gauges", "/strain")


@pytest.mark.parametrize("kind", KINDS)
def test_numbers_of_a_custom_message_by_field_path(rig_bags, kind):
    columns = {
        "tip1": {"topic": "/gauges", "field": "v.z", "unit": "mm"},
        "curvature1": {"topic": "/gauges", "field": "values[1]", "unit": "1/m"},
    }
    log = load(rig_bags[kind], columns)
    t = (GAUGE_START + np.arange(GAUGE_N) * GAUGE_DT) / 1e9
    np.testing.assert_allclose(log.outputs["tip1"], 1e-3 * 3.0 * t, rtol=1e-15)
    np.testing.assert_allclose(log.outputs["curvature1"], -2.0 * t, rtol=1e-15)
    assert log.sources["tip1"] == "/gauges v.z [mm] (receive times)"


@pytest.mark.parametrize("kind", KINDS)
def test_a_reversed_topic_is_read_negated(rig_bags, kind):
    """`sign = -1` on a bag's channels: a joint's position in rad and a strain bridge's
    volts after their scale come back as the negated values written."""
    calibration = {"theta1": {"sign": -1}, "tip1": {**CALIBRATION["tip1"], "sign": -1}}
    log = load(rig_bags[kind], calibration=calibration, time_base="/joint_states")
    t = np.arange(3, 180) * JOINT_DT / 1e9
    assert np.array_equal(log.outputs["theta1"], -shoulder(t))
    np.testing.assert_allclose(log.outputs["tip1"], -12.5e-3 * volts(t), rtol=1e-13, atol=0)
    assert np.array_equal(log.inputs["torque1"], effort(t))
    assert log.sources["theta1"].endswith("(header stamps) (sign reversed)")


def test_an_experiment_file_reads_a_bag(rig_bags, tmp_path):
    path = tmp_path / "exp.toml"
    path.write_text(
        textwrap.dedent(
            f"""
            [rig]
            base = "flexible_pendulum"
            options = {{ n_modes = 1 }}

            [[logs]]
            file = "{rig_bags["sqlite3"]}"
            time_base = "/joint_states"

            [logs.columns]
            theta1 = {{ topic = "/joint_states", joint = "shoulder", field = "position", unit = "rad" }}
            torque1 = {{ topic = "/joint_states", joint = "shoulder", field = "effort", unit = "N m" }}
            tip1 = {{ topic = "/strain", field = "data", unit = "V" }}

            [logs.calibration]
            tip1 = {{ scale = 12.5, unit = "mm" }}

            [[logs]]
            name = "uniform"
            file = "{storage_file(rig_bags["mcap"])}"
            columns = {{ theta1 = {{ topic = "/joint_states", joint = "shoulder", field = "position", unit = "deg" }} }}
            stamp = "receive"
            rate_hz = 250
            role = "validation"
            """
        )
    )
    exp = load_experiment(path)
    first, second = exp.logs
    assert first.name == "rig_sqlite3" and len(first.log) == 177
    assert first.columns["tip1"] == {"topic": "/strain", "field": "data", "unit": "V"}
    k = np.arange(3, 180)
    assert np.array_equal(first.log.outputs["theta1"], shoulder(k * JOINT_DT / 1e9))
    # receive times 2 ... 1002 ms at 250 Hz: 251 samples, theta1 read in degrees
    assert len(second.log) == 251 and second.log.t[0] == pytest.approx((T0 + 2 * MS) / 1e9, rel=1e-15)
    on_stamp = np.radians(shoulder(0.02 * np.arange(51)))  # every 5th: 2 + 20 j ms, a message's receive time
    np.testing.assert_allclose(second.log.outputs["theta1"][::5], on_stamp, rtol=0, atol=1e-15)
    assert "/joint_states position of joint 'shoulder' [rad] (header stamps)" in exp.summary()


def test_loading_leaves_the_bag_as_it_was(rig_bags):
    """Nothing is written next to the bag (an sqlite3 journal, an index) or into it."""
    bag = rig_bags["sqlite3"]

    def snapshot():
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(bag.iterdir())}

    before = snapshot()
    load(bag, time_base="/joint_states")
    assert snapshot() == before


SPLIT = 125 * MS


def rig_split(tmp_path, kind):
    """/joint_states (24 messages, 0 ... 230 ms) and /strain (24, 5 ... 235 ms) in one bag,
    and split at 125 ms: 13 and 12 messages in the first storage file, 11 and 12 in the second."""
    topics = {"/joint_states": joints(kind, n=24), "/strain": scalars(kind, n=24, start=5 * MS)}
    return write_bag(tmp_path / "whole", kind, topics), split_bag(tmp_path / "run", kind, topics, T0 + SPLIT)


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_a_split_bag_is_read_across_its_storage_files(tmp_path, kind):
    """A bag split while recording (its folder: `run_0`, `run_1` and one metadata.yaml) reads
    as the bag it was split from: every message of both files, in time order, each topic's
    messages numbered across them."""
    whole, bag = rig_split(tmp_path, kind)
    suffix = storage_file(whole).suffix
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", f"run_0{suffix}", f"run_1{suffix}"]
    log = load(bag, THETA)
    assert np.array_equal(log.t_relative, np.arange(24) * 0.01)
    assert np.array_equal(log.outputs["theta1"], 0.01 * np.arange(24))
    strain = {"tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}
    for kw in ({"time_base": "/joint_states"}, {"rate_hz": 250}):
        split, one = load(bag, {**THETA, **strain}, **kw), load(whole, {**THETA, **strain}, **kw)
        assert np.array_equal(split.t, one.t) and len(split) == len(one) >= 23
        assert all(np.array_equal(split.outputs[c], one.outputs[c]) for c in ("theta1", "tip1"))
        assert split.sources == one.sources
    # as an experiment file's log entry: the folder, relative to the file
    theta = '{ topic = "/joint_states", joint = "shoulder", field = "position", unit = "rad" }'
    (entry,) = load_experiment(experiment(tmp_path, f'file = "run"\ncolumns = {{ theta1 = {theta} }}\n')).logs
    assert entry.name == "run" and np.array_equal(entry.log.outputs["theta1"], log.outputs["theta1"])
    # message numbers run on across the files: the 15th message is the second of run_1
    damaged = joints(kind, n=24, stamps=[k * 10 * MS for k in range(14)] + [0] * 10)
    with pytest.raises(LogError, match=msg(str(tmp_path / "bad"), "topic '/joint_states', message 15 of 24: its")):
        load(split_bag(tmp_path / "bad", kind, {"/joint_states": damaged}, T0 + SPLIT), THETA)
    # one storage file on its own is read alone, and says so
    with pytest.warns(UserWarning, match=msg(f"run_1{suffix} is one of the 2 storage files of the bag {bag} (run_0")):
        part = load(bag / f"run_1{suffix}", THETA)
    assert np.array_equal(part.outputs["theta1"], 0.01 * np.arange(13, 24))


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_a_split_bag_missing_a_storage_file_or_listing_them_out_of_order(tmp_path, kind):
    _, bag = rig_split(tmp_path, kind)
    suffix = storage_file(tmp_path / "whole").suffix
    yaml, metadata = YAML(typ="safe"), (bag / "metadata.yaml").read_text()
    info = yaml.load(metadata)
    assert info["rosbag2_bagfile_information"]["relative_file_paths"] == [f"run_0{suffix}", f"run_1{suffix}"]
    info["rosbag2_bagfile_information"]["relative_file_paths"].reverse()
    with (bag / "metadata.yaml").open("w") as f:
        yaml.dump(info, f)
    with pytest.raises(
        LogError,
        match=msg(
            str(bag),
            "topic '/joint_states', message 12: received at 1733300000.000000000 s, before message 11 "
            "(1733300000.230000000 s); expected the messages in the order received",
            "as its metadata.yaml lists them (relative_file_paths), which must be the order they were recorded in",
        ),
    ):
        load(bag, THETA)
    (bag / "metadata.yaml").write_text(metadata)
    (bag / f"run_1{suffix}").unlink()
    with pytest.raises(
        LogError,
        match=msg(
            str(bag),
            f"storage file(s) run_1{suffix} listed in its metadata.yaml are missing from the folder; expected every "
            f"file of the bag (run_0{suffix}, run_1{suffix})",
        ),
    ):
        load(bag, THETA)


def test_the_output_folder_may_not_be_a_bag_folder(rig_bags):
    from identify.cli.output import _Refused, check_output_folder

    bag = rig_bags["mcap"]
    with pytest.raises(_Refused, match=msg(f"refusing to write into {bag}", "holds an input of the experiment")):
        check_output_folder(bag, [bag.parent / "exp.toml", bag], force=True)


# ---------------------------------------------------------------------------
# Mistakes in the bag: the bag, topic, field, message and what was expected
# ---------------------------------------------------------------------------


def joints(kind="mcap", n=12, stamps=None, names=("shoulder",), **per_message):
    """A /joint_states topic of `n` messages at 100 Hz (header stamps = receive times), the
    shoulder at 0.01 k rad; `per_message`: message number (from 1) -> a replacement message."""
    items = []
    for k in range(n):
        stamp = T0 + (k * 10 * MS if stamps is None else stamps[k])
        message = joint_state(kind, stamp, names, [0.01 * k] * len(names), effort=[0.5] * len(names))
        items.append((T0 + k * 10 * MS, per_message.get(f"m{k + 1}", message)))
    return ("sensor_msgs/msg/JointState", items)


def scalars(kind="mcap", n=12, start=0, values=None):
    values = [0.1 * k for k in range(n)] if values is None else values
    return ("std_msgs/msg/Float64", [(T0 + start + k * 10 * MS, float64(kind, v)) for k, v in enumerate(values)])


def bag_of(tmp_path, kind="mcap", **topics):
    """A bag holding `topics` (keyword `joint_states` -> topic "/joint_states")."""
    return write_bag(tmp_path / "run", kind, {f"/{name}": spec for name, spec in topics.items()})


THETA = {"theta1": COLUMNS["theta1"]}


def test_a_topic_not_in_the_bag(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(), strain=scalars())
    columns = {"tip1": {"topic": "/strian", "field": "data", "unit": "mm"}}
    with pytest.raises(
        LogError,
        match=msg(
            str(bag),
            "no topic '/strian' (mapped by columns.tip1)",
            "'/joint_states' (sensor_msgs/msg/JointState, 12",
            "'/strain' (std_msgs/msg/Float64, 12 messages)",
        ),
    ) as e:
        load(bag, columns)
    assert e.value.channel == "tip1"


@pytest.mark.parametrize("kind", KINDS)
def test_a_topic_without_messages(tmp_path, kind):
    """A topic the bag declares (a publisher that never published) is no channel of zeros:
    read for a channel or as the time base, alone or beside another."""
    bag = bag_of(tmp_path, kind, joint_states=joints(kind), strain=("std_msgs/msg/Float64", []))
    strain = {"tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}
    for columns, kw in [({**THETA, **strain}, {"rate_hz": 100}), (strain, {}), (THETA, {"time_base": "/strain"})]:
        with pytest.raises(LogError, match=msg(str(bag), "topic '/strain' has no messages; expected one per sample")):
            load(bag, columns, **kw)


@pytest.mark.parametrize("kind", KINDS)
def test_a_message_that_cannot_be_deserialised_names_it(tmp_path, kind):
    """Bytes that are not the message the topic's type says (cut short, padded): the bag,
    topic, type and message by number and receive time, not rosbags' traceback."""
    whole = serialized(kind, joints(kind)[1][4][1], "sensor_msgs/msg/JointState")
    for i, damaged in enumerate((whole[:-5], whole + bytes(7), b"")):
        (tmp_path / str(i)).mkdir()
        bag = bag_of(tmp_path / str(i), kind, joints=joints(kind, m5=damaged))
        with pytest.raises(
            LogError,
            match=msg(
                str(bag),
                f"topic '/joints', message 5 of 12 (received at 1733300000.040000000 s, {len(damaged)} bytes): "
                "not a readable sensor_msgs/msg/JointState (",
                "); expected the bytes of a sensor_msgs/msg/JointState as its definition in the bag lays them out: "
                "the message is cut short or corrupt",
            ),
        ) as e:
            load(bag, {"theta1": {**COLUMNS["theta1"], "topic": "/joints"}})
        assert e.value.__cause__ is None and e.value.__suppress_context__


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_a_damaged_record_in_the_storage(tmp_path, kind):
    """The storage's own record of message 5 damaged (its length): an error naming the bag
    and where reading stopped, whatever rosbags raises (a `ReaderError`, an `OverflowError`)."""
    bag = bag_of(tmp_path, kind, joint_states=joints(kind))
    file = bag if kind == "ros1" else storage_file(bag)
    data = bytearray(file.read_bytes())
    fifth = data.find(serialized(kind, joints(kind)[1][4][1], "sensor_msgs/msg/JointState"))
    assert fifth > 0 and data.count(data[fifth - 8 : fifth + 60]) == 1  # stored as written (no compression)
    # ROS 1: the data's uint32 length before it; MCAP: the message record's uint64 length
    length = slice(fifth - 4, fifth) if kind == "ros1" else slice(fifth - 30, fifth - 22)
    data[length] = b"\xff" * (length.stop - length.start)
    file.write_bytes(data)
    where = "after reading topic '/joint_states', message 4 (received at 1733300000.030000000 s)"
    with pytest.raises(
        LogError,
        match=msg(
            str(bag),
            "a damaged record in the bag's storage, found " + (where if kind == "ros1" else ""),
            "); expected an intact bag: this copy is cut short or corrupt",
        ),
    ) as e:
        load(bag, THETA)
    assert e.value.__cause__ is None and e.value.__suppress_context__


def test_a_joint_not_in_a_message_names_the_message(tmp_path):
    other = joint_state("mcap", T0 + 40 * MS, ["elbow"], [0.0])
    bag = bag_of(tmp_path, joint_states=joints(m5=other))
    with pytest.raises(
        LogError,
        match=msg(
            str(bag),
            "topic '/joint_states', message 5 of 12, field 'position' (mapped by columns.theta1)",
            "no joint 'shoulder'; its joints are ['elbow']",
        ),
    ):
        load(bag, THETA)
    bag = bag_of(tmp_path / "b", joint_states=joints(names=("a", "b")))
    with pytest.raises(LogError, match=msg("message 1", "no joint 'shoulder'; its joints are ['a', 'b']")):
        load(bag, THETA)


def test_an_empty_effort_array_is_named(tmp_path):
    empty = joint_state("mcap", T0 + 20 * MS, ["shoulder"], [0.0], effort=[])
    bag = bag_of(tmp_path, joint_states=joints(m3=empty))
    columns = {"torque1": COLUMNS["torque1"]}
    with pytest.raises(
        LogError,
        match=msg(
            "topic '/joint_states', message 3 of 12, field 'effort'",
            "effort has 0 value(s) for 1 joint name(s)",
            "(the publisher leaves it empty); expected one per joint",
        ),
    ):
        load(bag, columns)


def test_a_joint_state_needs_a_joint_and_a_joint_needs_a_joint_state(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(names=("shoulder", "elbow")), strain=scalars())
    with pytest.raises(
        LogError,
        match=msg(
            "message 1 of 12, field 'position'", "addressed by name; expected joint = one of ['shoulder', 'elbow']"
        ),
    ):
        load(bag, {"theta1": {"topic": "/joint_states", "field": "position", "unit": "rad"}})
    with pytest.raises(LogError, match=msg("addressed by name")):
        load(bag, {"theta1": {"topic": "/joint_states", "field": "position[0]", "unit": "rad"}})
    with pytest.raises(
        LogError,
        match=msg(
            "topic '/strain' (mapped by columns.theta1) is std_msgs/msg/Float64, not sensor_msgs/msg/JointState",
            "joint applies to joint states only: remove it and address the number by its field path",
        ),
    ):
        load(
            bag,
            {
                "tip1": {"topic": "/strain", "field": "data", "unit": "mm"},
                "theta1": {**THETA["theta1"], "topic": "/strain"},
            },
        )


@pytest.mark.parametrize(
    "field, expected",
    [
        (
            "dta",
            "'/strain', message 1 of 12, field 'dta' (mapped by columns.tip1): a std_msgs/msg/Float64 message has no "
            "field 'dta'; its fields are ['data']",
        ),
        ("data.x", "'data' (a float) has no field 'x'"),
        ("data[0]", "'data' is a float, not an array; remove the index [0]"),
    ],
)
def test_a_field_not_in_the_message(tmp_path, field, expected):
    bag = bag_of(tmp_path, strain=scalars())
    with pytest.raises(LogError, match=msg(str(bag), expected)):
        load(bag, {"tip1": {"topic": "/strain", "field": field, "unit": "mm"}})


@pytest.mark.parametrize(
    "field, expected",
    [
        ("label", "'label' is text; expected a number"),
        ("ok", "'ok' is a boolean; expected a number"),
        (
            "v",
            "'v' is a geometry_msgs/msg/Vector3 message with fields ['x', 'y', 'z']: address one, e.g. 'v.x'; "
            "expected a number",
        ),
        ("values", "'values' is an array of 2 value(s): address one element, e.g. 'values[0]'; expected a number"),
        ("values[2]", "'values' has 2 value(s); expected an index below 2"),
    ],
)
def test_a_field_that_is_not_one_number(tmp_path, field, expected):
    items = [(T0 + k * 10 * MS, gauges("mcap", [1.0, 2.0], label="x")) for k in range(12)]
    bag = bag_of(tmp_path, gauges=("rig_msgs/msg/Gauges", items))
    with pytest.raises(LogError, match=msg(str(bag), "topic '/gauges', message 1", f"field {field!r}", expected)):
        load(bag, {"tip1": {"topic": "/gauges", "field": field, "unit": "mm"}})


def test_an_index_past_a_shorter_array_names_the_message(tmp_path):
    items = [(T0 + k * 10 * MS, gauges("mcap", [1.0, 2.0] if k != 6 else [1.0])) for k in range(12)]
    bag = bag_of(tmp_path, gauges=("rig_msgs/msg/Gauges", items))
    with pytest.raises(LogError, match=msg("topic '/gauges', message 7 of 12, field 'values[1]'", "has 1 value(s)")):
        load(bag, {"tip1": {"topic": "/gauges", "field": "values[1]", "unit": "mm"}})


def test_a_value_that_is_not_finite_names_the_message(tmp_path):
    bag = bag_of(tmp_path, strain=scalars(values=[0.0] * 8 + [math.nan] + [0.0] * 3))
    with pytest.raises(
        LogError, match=msg(str(bag), "topic '/strain', message 9 of 12, field 'data': nan in tip1; expected a finite")
    ):
        load(bag, {"tip1": {"topic": "/strain", "field": "data", "unit": "mm"}})


@pytest.mark.parametrize(
    "k, stamp, expected",
    [
        (5, 30 * MS, "message 5 of 12: its header stamp 1733300000.030000000 s is the same as message 4's"),
        (
            7,
            20 * MS,
            "message 7 of 12: its header stamp 1733300000.020000000 s is before message 6's (1733300000.050000000 s)",
        ),
    ],
)
def test_stamps_that_do_not_increase_name_the_message(tmp_path, k, stamp, expected):
    stamps = [j * 10 * MS for j in range(12)]
    stamps[k - 1] = stamp
    bag = bag_of(tmp_path, joint_states=joints(stamps=stamps))
    with pytest.raises(
        LogError,
        match=msg(
            str(bag), "topic '/joint_states', ", expected, "expected strictly increasing stamps", 'stamp = "receive"'
        ),
    ):
        load(bag, THETA)
    assert len(load(bag, THETA, stamp="receive")) == 12  # the receive times increase


def test_unset_header_stamps_suggest_the_receive_times(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(stamps=[-T0] * 12))  # header.stamp = 0 in every message
    with pytest.raises(
        LogError, match=msg("message 2 of 12: its header stamp 0.000000000 s is the same as", "receive")
    ):
        load(bag, THETA)


def test_a_header_stamp_asked_of_a_message_without_one(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(), strain=scalars())
    with pytest.raises(
        LogError, match=msg(str(bag), "topic '/strain' is std_msgs/msg/Float64, which has no header stamp", "receive")
    ):
        load(bag, {**THETA, "tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}, stamp="header", rate_hz=50)


def test_the_time_base(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(), strain=scalars(), late=scalars(start=500 * MS))
    two = {**THETA, "tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}
    with pytest.raises(
        LogError,
        match=msg(str(bag), "from 2 topics (/joint_states, /strain)", 'time_base = "/joint_states"', "rate_hz = ..."),
    ):
        load(bag, two)
    with pytest.raises(LogError, match=msg("time_base = '/clock': no such topic; the bag has '/joint_states'")):
        load(bag, two, time_base="/clock")
    with pytest.raises(LogError, match=msg("both time_base = '/strain' and rate_hz = 100; expected one")):
        load(bag, two, time_base="/strain", rate_hz=100)
    with pytest.raises(LogError, match=msg("rate_hz = 0; expected a sampling rate > 0 (Hz)")):
        load(bag, two, rate_hz=0)
    with pytest.raises(LogError, match=msg("stamp = 'sent'; expected \"header\"", '"receive"')):
        load(bag, two, stamp="sent", rate_hz=100)
    # /late starts at 500 ms, /joint_states ends at 110 ms
    late = {**THETA, "tip1": {"topic": "/late", "field": "data", "unit": "mm"}}
    with pytest.raises(
        LogError,
        match=msg(str(bag), "the topics do not overlap in time ('/joint_states' 0-0.11 s, '/late' 0.5-0.61 s"),
    ):
        load(bag, late, rate_hz=100)
    # a topic of one message cannot be interpolated
    bag = bag_of(tmp_path / "b", joint_states=joints(), one=scalars(n=1))
    with pytest.raises(LogError, match=msg("topic '/one' has 1 message; expected at least 2 to interpolate")):
        load(bag, {**THETA, "tip1": {"topic": "/one", "field": "data", "unit": "mm"}}, time_base="/joint_states")


def test_too_few_samples_in_the_common_span(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(), strain=scalars(start=85 * MS))
    two = {**THETA, "tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}
    with pytest.raises(LogError, match=msg(str(bag), "3 samples; expected at least 10")):
        load(bag, two, time_base="/joint_states")


def test_a_gap_interpolated_across_is_warned_about(tmp_path):
    # /strain loses its messages between 30 and 90 ms; /joint_states is the time base
    values = [0.1 * k for k in range(12)]
    strain = (
        "std_msgs/msg/Float64",
        [(T0 + k * 10 * MS, float64("mcap", v)) for k, v in enumerate(values) if not 3 < k < 9],
    )
    bag = bag_of(tmp_path, joint_states=joints(), strain=strain)
    two = {**THETA, "tip1": {"topic": "/strain", "field": "data", "unit": "mm"}}
    with pytest.warns(
        UserWarning,
        match=msg(str(bag), "topic '/strain' has 1 gap(s)", "the longest 0.06 s after message 4", "interpolated"),
    ):
        log = load(bag, two, time_base="/joint_states")
    np.testing.assert_allclose(log.outputs["tip1"], 1e-4 * np.arange(12), rtol=1e-12)  # a line: exact anyway
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load(bag, THETA)  # the time base's own gaps show in its sampling


def test_strict_makes_unused_topics_an_error(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints(), rosout=scalars())
    assert load(bag, THETA).ignored == ("/rosout",)
    with pytest.raises(LogError, match=msg(str(bag), "topic(s) ['/rosout'] are not mapped to any channel (strict")):
        load(bag, THETA, strict=True)


def test_not_a_bag(tmp_path):
    (tmp_path / "run.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError, match=msg(str(tmp_path / "run.mcap"), "not a readable ROS bag")):
        load(tmp_path / "run.mcap", THETA)
    with pytest.raises(LogError, match=msg(str(tmp_path / "gone.mcap"), "log file does not exist")):
        load(tmp_path / "gone.mcap", THETA)
    (tmp_path / "folder").mkdir()
    with pytest.raises(LogError, match=msg("folder", "is a directory without a metadata.yaml (not a ROS 2 bag)")):
        load(tmp_path / "folder", THETA)


# ---------------------------------------------------------------------------
# Mistakes in the mapping
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "columns, expected",
    [
        ({"time": "t [s]"}, "columns.time: a bag's times are its messages' stamps, not a channel"),
        ({"theta1": "joint_states [rad]"}, "columns.theta1: expected a table { topic = "),
        ({"theta1": {"topic": "/joint_states", "field": "data"}}, "columns.theta1: missing unit"),
        ({"theta1": {**COLUMNS["theta1"], "units": "rad"}}, "columns.theta1: unknown key 'units'"),
        ({"theta1": {**COLUMNS["theta1"], "unit": "radians"}}, "columns.theta1: unit: unknown unit 'radians'"),
        ({"theta1": {**COLUMNS["theta1"], "field": "a..b"}}, "field: 'a..b' is not a field path"),
        ({"theta1": {**COLUMNS["theta1"], "field": "velocity"}}, "a joint's velocity is a rate, and no channel"),
        (
            {"theta1": {**COLUMNS["theta1"], "field": "effort"}},
            "theta1 is an angle, but a sensor_msgs/msg/JointState's effort is a torque; map effort to torque<i>",
        ),
        (
            {"theta1": {**COLUMNS["theta1"], "field": "name"}},
            "field 'name': a sensor_msgs/msg/JointState's joint values",
        ),
        (
            {"theta1": COLUMNS["theta1"], "theta2": COLUMNS["theta1"]},
            "channels 'theta1' and 'theta2' both read /joint_states position of joint 'shoulder' [rad]",
        ),
        ({"theta1": {**COLUMNS["theta1"], "unit": "mm"}}, "theta1 is an angle but [mm] is a length unit"),
        ({"tip1": {"topic": "/joint_states", "field": "data", "unit": "V"}}, "tip1 is in [V] and needs a calibration"),
    ],
)
def test_mapping_mistakes(tmp_path, columns, expected):
    bag = bag_of(tmp_path, joint_states=joints())
    with pytest.raises(LogError, match=msg(str(bag), expected)):
        load(bag, columns)


def test_a_bag_needs_a_mapping_and_other_logs_take_no_time_base(tmp_path):
    bag = bag_of(tmp_path, joint_states=joints())
    with pytest.raises(LogError, match=msg(str(bag), "a ROS bag log needs a column mapping")):
        load_log(bag)
    csv = tmp_path / "log.csv"
    csv.write_text("time [s],theta1 [rad]\n" + "".join(f"{0.01 * k},0\n" for k in range(12)))
    with pytest.raises(LogError, match=msg("log.csv: stamp, time_base and rate_hz apply to ROS bags only")):
        load_log(csv, rate_hz=100)


# ---------------------------------------------------------------------------
# Mistakes in the experiment file point at their line
# ---------------------------------------------------------------------------


def experiment(tmp_path, log: str):
    path = tmp_path / "exp.toml"
    path.write_text('[rig]\nbase = "flexible_pendulum"\noptions = { n_modes = 1 }\n\n[[logs]]\n' + textwrap.dedent(log))
    return path


def test_experiment_file_mistakes_name_their_line(tmp_path):
    bag_of(tmp_path, joint_states=joints(), strain=scalars())
    theta = '{ topic = "/joint_states", joint = "shoulder", field = "position", unit = "rad" }'
    cases = [
        (
            'file = "run"\n',
            "exp.toml, line 5: logs[1]: run is a ROS bag, whose messages carry no units; expected columns",
        ),
        ('file = "run"\ncolumns = { theta1 = "q [rad]" }\n', "line 7: logs[1].columns.theta1: expected a table"),
        (
            f'file = "run"\nrate_hz = -5\ncolumns = {{ theta1 = {theta} }}\n',
            "line 7: logs[1].rate_hz: expected a sampling rate > 0",
        ),
        (
            f'file = "run"\nstamp = "sent"\ncolumns = {{ theta1 = {theta} }}\n',
            'line 7: logs[1].stamp: expected "header"',
        ),
        (
            f'file = "run"\ntime_base = "/strain"\nrate_hz = 10\ncolumns = {{ theta1 = {theta} }}\n',
            "line 8: logs[1].rate_hz: time_base is given too",
        ),
        (f'file = "run"\ncolumns = {{ tip2 = {theta} }}\n', "line 7: logs[1].columns.tip2: the rig has 1 link(s)"),
    ]
    for log, expected in cases:
        with pytest.raises(ExperimentError, match=msg(expected)):
            load_experiment(experiment(tmp_path, log))
    # a problem found in the bag points at its channel's entry
    path = experiment(
        tmp_path,
        f"""
        file = "run"
        time_base = "/joint_states"
        [logs.columns]
        theta1 = {theta}
        tip1 = {{ topic = "/strian", field = "data", unit = "mm" }}
        """,
    )
    with pytest.raises(
        LogError,
        match=msg(
            "no topic '/strian' (mapped by exp.toml logs[1].columns.tip1)",
            "[",
            "exp.toml, line 11: logs[1].columns.tip1]",
        ),
    ):
        load_experiment(path)
    path.write_text(path.read_text().replace('"/strian", field = "data"', '"/strain", field = "dta"'))
    with pytest.raises(
        LogError,
        match=msg("topic '/strain', message 1 of 12, field 'dta'", "[", "exp.toml, line 11: logs[1].columns.tip1]"),
    ):
        load_experiment(path)
    # a CSV log takes no time base
    (tmp_path / "log.csv").write_text("time [s],theta1 [rad]\n" + "".join(f"{0.01 * k},0\n" for k in range(12)))
    with pytest.raises(ExperimentError, match=msg("line 7: logs[1].rate_hz: applies to ROS bags")):
        load_experiment(experiment(tmp_path, 'file = "log.csv"\nrate_hz = 100\n'))


def test_a_topic_of_several_message_types(tmp_path):
    """ROS 1 lets two publishers put different types on one topic; which one a channel
    means would be a guess."""
    bag = tmp_path / "mixed.bag"
    store = TYPESTORES["ros1"]
    with Writer1(bag) as writer:
        a = writer.add_connection("/strain", "std_msgs/msg/Float64", typestore=store)
        b = writer.add_connection("/strain", "std_msgs/msg/Float32", typestore=store)
        for k in range(12):
            writer.write(a, T0 + k * 10 * MS, store.serialize_ros1(float64("ros1", k), "std_msgs/msg/Float64"))
        value = store.types["std_msgs/msg/Float32"](data=1.0)
        writer.write(b, T0 + 5 * MS, store.serialize_ros1(value, "std_msgs/msg/Float32"))
    with pytest.raises(
        LogError, match=msg(str(bag), "topic '/strain' (mapped by columns.tip1) holds messages of several types")
    ):
        load(bag, {"tip1": {"topic": "/strain", "field": "data", "unit": "mm"}})
