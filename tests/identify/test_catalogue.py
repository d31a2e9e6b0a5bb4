"""`identify.catalogue`: entries fitted together (the pair search of `identify.diagnose`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from diagnose_cases import arm  # tests/ is on sys.path

import flexdyn as fd
from identify._diagnose import catalogue as cat


def _entry(name, where, params, starts, structural=False):
    return cat.Candidate(name, where, params, (True,) * len(params), starts, structural=structural)


def test_pair_frees_both_entries_parameters_the_first_at_its_fitted_value():
    drag = _entry("quadratic_damping", "link1", ("link1.drag",), ((1e-4,), (1e-2,)))
    dry = _entry("coulomb_friction", "joint1", ("joint1.coulomb",), ((1e-6,), (1e-4,), (1e-3,)))
    p = cat.pair(drag, (7.7e-3,), dry)
    assert p.params == ("link1.drag", "joint1.coulomb")
    assert p.log_scale == (True, True)
    # one start per start of the second entry, the first entry at its own fit
    assert p.starts == ((7.7e-3, 1e-6), (7.7e-3, 1e-4), (7.7e-3, 1e-3))
    assert p.members == (drag, dry) and not p.structural
    assert p.label == "quadratic_damping:link1 + coulomb_friction:joint1"
    assert drag.label == "quadratic_damping:link1"


def test_pair_of_a_structural_entry_is_refused_by_name():
    drag = _entry("quadratic_damping", "link1", ("link1.drag",), ((1e-4,),))
    mode = _entry("missing_mode", "link1", (), ((),), structural=True)
    with pytest.raises(ValueError, match="missing_mode:link1"):
        cat.pair(drag, (1e-3,), mode)


def test_missing_mode_keeps_the_links_geometric_stiffening():
    for stiffening in (True, False):
        chain = fd.rigs.two_link_flexible_arm(n_modes=1, geometric_stiffening=stiffening)
        mode = _entry("missing_mode", "link2", (), ((),), structural=True)
        extended, guesses = cat.structural_model(chain, mode, max_frequency_hz=50.0)
        assert extended.links[1].n_modes == 2 and guesses == {}
        assert extended.links[1].geometric_stiffening is stiffening


def _candidates(chain, stiffening_links, channels=("theta1", "tip1"), driven=(0,)):
    """`catalogue.candidates` of `chain` with fixed, typical log statistics."""
    return cat.candidates(
        chain,
        channels,
        list(driven),
        torque_rms=0.1,
        rate_rms=1.0,
        sample_interval=0.005,
        channel_rms={},
        offsets_fitted=set(),
        max_frequency_hz=50.0,
        stiffening_links=stiffening_links,
    )


def _offered(chain, stiffening_links):
    return [c.label for c in _candidates(chain, stiffening_links) if c.name == "geometric_stiffening"]


def test_geometric_stiffening_is_offered_only_where_the_model_check_flags_it():
    linear = fd.rigs.two_link_flexible_arm(n_modes=1, geometric_stiffening=False)
    assert _offered(linear, ()) == []
    assert _offered(linear, {"link2"}) == ["geometric_stiffening:link2"]
    assert _offered(linear, {"link1", "link2"}) == ["geometric_stiffening:link1", "geometric_stiffening:link2"]
    # a link that has it already is not offered it again
    stiffened = fd.rigs.two_link_flexible_arm(n_modes=1, geometric_stiffening=True)
    assert _offered(stiffened, {"link1", "link2"}) == []


@pytest.mark.parametrize(
    ("rig", "driven", "stiffening", "absent"),
    [
        # paper 000's rigid pendulum released from rest (the Quickstart example)
        (
            fd.rigs.rigid_pendulum(),
            [],
            (),
            {"actuator_lag", "backlash", "base_tilt", "missing_mode", "geometric_stiffening", "joint_elasticity"},
        ),
        # paper 004's arm, driven, horizontal: every joint elastic already
        (fd.rigs.flexible_link_joint_arm(), [0, 1], (), {"geometric_stiffening", "joint_elasticity"}),
        (fd.rigs.flexible_link_joint_arm(), [0, 1], {"link1"}, {"joint_elasticity"}),
        # paper 002's arm driven at its first joint only: the second joint's elasticity is not offered
        (fd.rigs.two_link_flexible_arm(n_modes=1), [0], (), {"backlash", "geometric_stiffening"}),
        (
            fd.rigs.two_link_flexible_arm(n_modes=fd.modes.MAX_MODES),
            [0, 1],
            (),
            {"backlash", "geometric_stiffening", "missing_mode"},
        ),
    ],
)
def test_not_applicable_names_exactly_the_entries_candidates_leaves_out(rig, driven, stiffening, absent):
    """`not_applicable` against `candidates` itself: every catalogue entry is either offered
    somewhere on the rig or given a reason, never both, and the left-out ones are those the
    rig's structure rules out (no elastic joint for backlash, gravity for a base tilt, ...)."""
    offered = {c.name for c in _candidates(rig, stiffening, channels=("theta1",), driven=driven)}
    why = cat.not_applicable(rig, driven, stiffening)
    assert set(why) == absent
    assert offered | set(why) == set(cat.NAMES) and not offered & set(why)
    assert all(isinstance(text, str) and text for text in why.values())


def test_geometric_stiffening_switches_the_option_on_one_link_and_keeps_its_parameters():
    chain = fd.rigs.two_link_flexible_arm(n_modes=2, geometric_stiffening=False)
    entry = _entry("geometric_stiffening", "link2", (), ((),), structural=True)
    extended, guesses = cat.structural_model(chain, entry, max_frequency_hz=50.0)
    assert guesses == {}
    assert [k.geometric_stiffening for k in extended.links] == [False, True]
    for before, after in zip(chain.links, extended.links):
        assert after.n_modes == before.n_modes
        for field in ("length", "rho", "EI", "damping_ratio"):
            assert float(jnp.sum(getattr(after, field))) == float(jnp.sum(getattr(before, field)))
    assert extended.joints == chain.joints and extended.hubs == chain.hubs


_CONTEXT = {"torque_scale": 0.2, "log_duration": 3.0, "lowest_mode_hz": 2.9, "link_lengths": (0.3,)}


@pytest.mark.parametrize(
    "name, values, words",
    [
        # the spinning link's pair before the catalogue had geometric stiffening
        ("sensor_gain_offset", {"sensor.tip1.gain": 17.0, "sensor.tip1.offset": 0.0}, "sensor.tip1.gain = 17"),
        ("sensor_gain_offset", {"sensor.tip1.gain": 0.3}, "beyond 2x"),
        ("sensor_delay", {"sensor.theta1.delay": 0.5}, "0.1 of the shortest log (3 s)"),
        ("actuator_lag", {"actuator1.lag": 0.4}, "actuator1.lag = 0.4 s"),
        ("coulomb_friction", {"joint1.coulomb": 0.5}, "hold it still"),
        ("sensor_highpass", {"sensor.tip1.highpass": 5.0}, "above the lowest mode (2.9 Hz)"),
        ("base_tilt", {"gravity[0]": 2.0, "gravity[1]": 1.0}, "a tilt of 13.2 deg"),
        ("base_tilt", {"gravity[0]": 12.0, "gravity[1]": 0.0}, "not a tilt"),
        # the servo rig's stand-in for stiction (tests/identify/test_servo_rig.py): above
        # a 0.3 m x 0.3 m flat plate's 1.2 kg/m^3 * 2 * 0.3 m / 2 = 0.36 kg/m^2
        ("quadratic_damping", {"link1.drag": 0.746}, "(0.36 kg/m^2)"),
    ],
)
def test_implausible_values_are_named(name, values, words):
    out = cat.implausible(name, values, **_CONTEXT)
    assert any(words in w for w in out), out
    assert "catalogue lacks" in out[-1]


@pytest.mark.parametrize(
    "name, values",
    [
        ("sensor_gain_offset", {"sensor.tip1.gain": 1.15, "sensor.tip1.offset": 0.3}),
        ("sensor_delay", {"sensor.theta1.delay": 0.02}),
        ("actuator_lag", {"actuator1.lag": 0.02}),
        ("coulomb_friction", {"joint1.coulomb": 0.01}),
        ("sensor_highpass", {"sensor.tip1.highpass": 0.1}),
        # 1.5 deg, the grid's hidden tilt
        ("base_tilt", {"gravity[0]": 0.139, "gravity[1]": 0.217}),
        ("joint_elasticity", {"joint1.stiffness": 40.0, "joint1.rotor_inertia": 0.01}),
        # the real pendulum's fitted drag (paper 000's 25 mm strip): rho C_D w / 2 = 0.018
        ("quadratic_damping", {"link1.drag": 1.79e-2}),
        ("quadratic_damping", {"link1.drag": 0.35}),
    ],
)
def test_plausible_values_pass(name, values):
    assert cat.implausible(name, values, **_CONTEXT) == []


def test_drag_is_not_judged_without_the_links_length():
    context = {**_CONTEXT, "link_lengths": ()}
    assert cat.implausible("quadratic_damping", {"link2.drag": 50.0}, **context) == []
    assert cat.implausible("quadratic_damping", {"link2.drag": 50.0}, **_CONTEXT) == []  # only link 1's given


def test_highpass_is_not_judged_without_a_mode():
    assert (
        cat.implausible("sensor_highpass", {"sensor.theta1.highpass": 5.0}, **{**_CONTEXT, "lowest_mode_hz": None})
        == []
    )


def test_a_pair_is_implausible_when_either_member_is():
    """Issue 61: a candidate that passes with implausible values is not named; for two
    entries fitted together, either member's values make the pair implausible (each
    judged by its own entry's rules), and the closing sentence is said once."""
    judge = cat.Plausibility(**_CONTEXT)
    friction = _entry("coulomb_friction", "joint1", ("joint1.coulomb",), ((1e-3,),))
    tilt = cat.Candidate("base_tilt", "base", ("gravity[0]", "gravity[1]"), (False, False), ((0.0, 0.0),))
    pair = cat.pair(friction, (1e-3,), tilt)
    level = {"gravity[0]": 0.139, "gravity[1]": 0.217}  # 1.5 deg
    assert judge.judge(pair, {"joint1.coulomb": 0.01, **level}) == []
    out = judge.judge(pair, {"joint1.coulomb": 0.5, **level})
    assert len(out) == 2 and "hold it still" in out[0] and out[1] == cat.STANDING_IN
    out = judge.judge(pair, {"joint1.coulomb": 0.5, "gravity[0]": 2.0, "gravity[1]": 1.0})
    assert len(out) == 3 and "a tilt of 13.2 deg" in out[1] and out.count(cat.STANDING_IN) == 1
    # a single entry: as `implausible` says it
    values = {"gravity[0]": 2.0, "gravity[1]": 1.0}
    assert judge.judge(tilt, values) == cat.implausible("base_tilt", values, **_CONTEXT)


def test_wider_starts_go_beyond_the_entrys_own():
    """Issue 61: a fit that never leaves its starts is tried again from wider ones: a
    log-scale parameter 10x above its largest start and 100x below its smallest, a signed
    one at +-10x its scale (its largest start, or the given scale where every start is 0:
    a channel's noise for an offset, a 0.5 deg tilt for in-plane gravity)."""
    dry = _entry("coulomb_friction", "joint1", ("joint1.coulomb",), ((1e-6,), (1e-4,), (1e-3,)))
    assert cat.wider_starts(dry, {}) == ((1e-2,), (1e-8,))
    calib = cat.Candidate(
        "sensor_gain_offset", "theta1", ("sensor.theta1.gain", "sensor.theta1.offset"), (True, False), ((1.0, 0.0),)
    )
    noise = {"theta1": 0.002}
    scale = {n: cat.signed_scale(n, noise) for n in calib.params}
    assert scale["sensor.theta1.offset"] == 0.002
    assert cat.wider_starts(calib, scale) == ((10.0, 0.02), (0.01, -0.02))
    tilt = cat.Candidate("base_tilt", "base", ("gravity[0]", "gravity[1]"), (False, False), ((0.0, 0.0),))
    (above, below) = cat.wider_starts(tilt, {n: cat.signed_scale(n, {}) for n in tilt.params})
    assert np.degrees(np.arcsin(np.hypot(*above) / 9.81)) < cat.MAX_TILT_DEG
    assert above == pytest.approx((10 * cat.TILT_SCALE,) * 2) and below == pytest.approx((-10 * cat.TILT_SCALE,) * 2)


def test_joint_elasticity_holds_the_rigid_joint_as_its_stiff_limit():
    """`catalogue.NESTED_LIMIT`'s claim, against the rigid model it extends: with the rotor
    at its first guess (the inertia taken off the hub), the elastic joint's hub angle and
    tip deflection approach the rigid joint's as 1/k (spring deflection = torque / k)."""
    rigid = arm()
    cand = _entry("joint_elasticity", "joint1", ("joint1.stiffness", "joint1.rotor_inertia"), ((),), structural=True)
    elastic, guesses = cat.structural_model(rigid, cand, max_frequency_hz=20.0)
    assert "joint_elasticity" in cat.NESTED_LIMIT
    ts = np.linspace(0.0, 0.6, 61)
    torque = fd.BangBang(0.2, 0.15)
    ref = fd.simulate(rigid, fd.initial_state(rigid, [0.0]), ts, torque, dt=1e-4)
    errors = []
    for k in (1e3, 1e4):
        chain = fd.with_parameters(
            elastic, {"joint1.stiffness": k, "joint1.rotor_inertia": guesses["joint1.rotor_inertia"]}
        )
        tr = fd.simulate(chain, fd.initial_state(chain, [0.0]), ts, torque, dt=1e-4)
        rel = [
            float(np.max(np.abs(tr.coordinate(n) - ref.coordinate(n))) / np.max(np.abs(ref.coordinate(n))))
            for n in ("theta1", "q1_1")
        ]
        errors.append(max(rel))
    # relative error ~ 1/k: small, and 10x smaller for a 10x stiffer spring
    assert errors[1] < 2e-3, errors
    assert 5.0 < errors[0] / errors[1] < 20.0, errors


def test_a_nested_structural_fit_that_ends_above_its_limit_is_noted():
    from identify._diagnose.notes import _stuck_above_nested

    joint = _entry("joint_elasticity", "joint1", ("joint1.stiffness", "joint1.rotor_inertia"), ((),), structural=True)
    mode = _entry("missing_mode", "link1", (), ((),), structural=True)
    text = _stuck_above_nested(joint, 5000.0, 1500.0, 10.0)
    assert "joint_elasticity:joint1" in text and "local minimum" in text and "5000.0" in text
    assert _stuck_above_nested(joint, 1505.0, 1500.0, 10.0) == ""  # within the BIC threshold
    assert _stuck_above_nested(joint, 1200.0, 1500.0, 10.0) == ""
    # a missing mode cannot be switched off by a parameter: ending above is the data's answer
    assert _stuck_above_nested(mode, 5000.0, 1500.0, 10.0) == ""
    # a continuous entry holds the current model at its parameters' neutral values (seen on
    # the real pendulum: dry friction ended at cost 9251 against the baseline's 9167)
    friction = _entry("coulomb_friction", "joint1", ("joint1.coulomb",), ((1e-3,),))
    text = _stuck_above_nested(friction, 9251.0, 9167.0, 10.0, limit="joint1.coulomb = 0")
    assert text.startswith("coulomb_friction:joint1: its fit ended above") and "(joint1.coulomb = 0)" in text
    assert _stuck_above_nested(friction, 9170.0, 9167.0, 10.0, limit="joint1.coulomb = 0") == ""
    # above by the optimiser's precision only, on a large cost (the spinning-link example's
    # sensor high-pass: 57 over 1.045e8): not a local minimum
    assert _stuck_above_nested(friction, 104508119.3, 104508062.3, 10.0, limit="sensor.theta1.highpass = 0") == ""


def test_dry_friction_is_judged_against_the_peak_torque_not_the_rms():
    """Found on a geared servo's step tests: a dry friction of 0.095 N m was called
    implausible because it exceeds the RMS driving torque, although the peak torque was 5x
    higher and the hub really stands still between moves. The diagnosis's signals carry
    the logs' peak torque, and the plausibility test is against it."""
    from types import SimpleNamespace

    from identify._diagnose.search import _signals

    t = np.arange(0.0, 4.0, 1e-3)
    steps = np.where((t % 2.0) < 0.04, 0.5, 0.0)  # short moves, standing still between them
    log = SimpleNamespace(t=t, torque=steps[:, None], outputs={"theta1": np.zeros_like(t)}, offsets={})
    rigid = fd.Chain([fd.RigidLink(0.5, 0.1)], [fd.RigidJoint(damping=0.01)], [fd.Hub(inertia=0.02)], fd.Payload(0.05))
    base = SimpleNamespace(problem=SimpleNamespace(channels=["theta1"]), chain=rigid)  # horizontal: no gravity
    signals = _signals(base, [log], [], modal=[])
    assert signals.torque_peak == 0.5 and signals.torque_rms == pytest.approx(0.5 * np.sqrt(0.02), rel=1e-3)
    assert cat.characteristic_torque(base.chain, signals.torque_rms) < 0.095  # (what the RMS would have said)
    scale = cat.characteristic_torque(base.chain, signals.torque_peak)
    assert cat.implausible("coulomb_friction", {"joint1.coulomb": 0.095}, **{**_CONTEXT, "torque_scale": scale}) == []
    assert cat.implausible("coulomb_friction", {"joint1.coulomb": 0.6}, **{**_CONTEXT, "torque_scale": scale})


# ---------------------------------------------------------------------------
# Sensor kinds: a channel is offered only the effects its sensor can have
# ---------------------------------------------------------------------------


#: `not_tried`'s reasons for an encoder's theta1 (`identify.measurement.KINDS`)
ENCODER_GAIN = "an encoder's gain is fixed by its counts per revolution (only its offset is tried)"
ENCODER_HIGHPASS = "an encoder is DC-coupled (it counts position: a constant angle reads constant)"


def _sensor_offers(kinds, channels=("theta1", "tip1"), offsets_fitted=()):
    """label -> parameters of the sensor entries `candidates` offers on a flexible pendulum."""
    out = cat.candidates(
        fd.rigs.flexible_pendulum(n_modes=1),
        channels,
        [],
        torque_rms=0.1,
        rate_rms=1.0,
        sample_interval=0.005,
        channel_rms={},
        offsets_fitted=set(offsets_fitted),
        max_frequency_hz=50.0,
        sensor_kinds=kinds,
    )
    return {c.label: c.params for c in out if c.name in cat.SENSOR_FIELDS}


def test_without_a_kind_every_sensor_entry_is_offered_as_before():
    everything = {
        "sensor_delay:theta1": ("sensor.theta1.delay",),
        "sensor_gain_offset:theta1": ("sensor.theta1.gain", "sensor.theta1.offset"),
        "sensor_highpass:theta1": ("sensor.theta1.highpass",),
        "sensor_delay:tip1": ("sensor.tip1.delay",),
        "sensor_gain_offset:tip1": ("sensor.tip1.gain", "sensor.tip1.offset"),
        "sensor_highpass:tip1": ("sensor.tip1.highpass",),
    }
    assert _sensor_offers(None) == _sensor_offers({}) == everything
    assert _sensor_offers({"tip1": "strain_gauge"}) == everything  # a strain gauge can have them all
    assert cat.kind_left_out(("theta1", "tip1"), {}) == {} == cat.kind_left_out(("tip1",), {"tip1": "strain_gauge"})


def test_an_encoder_is_offered_its_delay_and_offset_only():
    """An encoder counts position (DC-coupled: no high-pass) with a gain fixed by its counts
    per revolution; its zero (offset) and a read-out delay are real."""
    offers = _sensor_offers({"theta1": "encoder", "tip1": "strain_gauge"})
    assert offers["sensor_delay:theta1"] == ("sensor.theta1.delay",)
    assert offers["sensor_gain_offset:theta1"] == ("sensor.theta1.offset",)
    assert "sensor_highpass:theta1" not in offers and "sensor_highpass:tip1" in offers
    cand = next(
        c
        for c in cat.candidates(
            fd.rigs.flexible_pendulum(n_modes=1), ("theta1",), [], torque_rms=0.1, rate_rms=1.0,
            sample_interval=0.005, channel_rms={}, offsets_fitted=set(), max_frequency_hz=50.0,
            sensor_kinds={"theta1": "encoder"},
        )
        if c.name == "sensor_gain_offset"
    )  # fmt: skip
    assert cand.log_scale == (False,) and cand.starts == ((0.0,),)  # a signed offset, from 0
    why = cat.kind_left_out(("theta1", "tip1"), {"theta1": "encoder", "tip1": "strain_gauge"})
    assert why == {
        "sensor_gain_offset:theta1": ENCODER_GAIN,
        "sensor_highpass:theta1": ENCODER_HIGHPASS,
    }
    # with the offset fitted per log, nothing of the calibration entry is left to try
    offers = _sensor_offers({"theta1": "encoder"}, offsets_fitted={"theta1"})
    assert "sensor_gain_offset:theta1" not in offers
    assert cat.kind_left_out(("theta1",), {"theta1": "encoder"}, {"theta1"})["sensor_gain_offset:theta1"].endswith(
        "(its offset is fitted per log already)"
    )


@pytest.mark.parametrize("kind", ["potentiometer", "encoder"])
def test_a_dc_coupled_angle_sensor_is_not_offered_a_highpass(kind):
    offers = _sensor_offers({"theta1": kind})
    assert "sensor_highpass:theta1" not in offers and "sensor_delay:theta1" in offers
    assert "DC-coupled" in cat.kind_left_out(("theta1",), {"theta1": kind})["sensor_highpass:theta1"]
    if kind == "potentiometer":  # its gain (supply, wiper span) is a real calibration error
        assert offers["sensor_gain_offset:theta1"] == ("sensor.theta1.gain", "sensor.theta1.offset")


def test_the_superset_has_no_effect_a_channels_kind_cannot_have():
    from identify._data import measurement as meas

    m = meas.Measurement({"theta1": meas.Sensor(kind="encoder")})
    _, sup = cat.superset(fd.rigs.flexible_pendulum(n_modes=1), m, ("theta1", "tip1"), [])
    names = meas.parameter_names(sup)
    assert "sensor.theta1.offset" in names and "sensor.theta1.delay" in names
    assert "sensor.theta1.gain" not in names and "sensor.theta1.highpass" not in names
    assert {"sensor.tip1.gain", "sensor.tip1.highpass"} <= set(names)
    assert sup.sensors["theta1"].kind == "encoder"


def test_not_tried_names_each_entry_a_kind_rules_out_by_channel():
    """`Diagnosis.not_tried` (`notes._not_tried`): an entry a kind rules out on one channel
    but tried on another appears by its label; one ruled out on every channel appears only by
    its labels (no generic line)."""
    from identify._diagnose.notes import _not_tried

    kinds = {"theta1": "encoder", "tip1": "strain_gauge"}
    rig = fd.rigs.flexible_pendulum(n_modes=1)
    offered = cat.candidates(
        rig, ("theta1", "tip1"), [], torque_rms=0.1, rate_rms=1.0, sample_interval=0.005, channel_rms={},
        offsets_fitted=set(), max_frequency_hz=50.0, sensor_kinds=kinds,
    )  # fmt: skip
    by_kind = cat.kind_left_out(("theta1", "tip1"), kinds)
    out = _not_tried(cat.NAMES, offered, offered, (), cat.not_applicable(rig, []), by_kind)
    assert out["sensor_highpass:theta1"].startswith("an encoder is DC-coupled")
    assert "sensor_highpass" not in out and "sensor_gain_offset" not in out  # tried on tip1 (and theta1's offset)
    only_encoder = [c for c in offered if c.where == "theta1"]
    out = _not_tried(cat.NAMES, only_encoder, only_encoder, (), {}, cat.kind_left_out(("theta1",), kinds))
    assert "sensor_highpass" not in out and "sensor_highpass:theta1" in out
    # a caller's catalogue without the entry: not reported at all
    out = _not_tried(("sensor_delay",), only_encoder, only_encoder, (), {}, cat.kind_left_out(("theta1",), kinds))
    assert out == {}


@pytest.mark.slow  # a whole diagnosis (1-5 min on 2 cores): CI's 30-minute budget
def test_a_declared_kind_reaches_the_diagnosis_through_the_experiment_file(tmp_path):
    """`[sensors.theta1] kind = "encoder"` in an experiment file: `identify.diagnose` tries
    only the encoder's delay and offset on theta1, and its `not_tried` names the high-pass
    and the gain with the reason (the path from the file to `diagnose_logs`' candidates)."""
    import textwrap

    import identify
    from identify._data.logs import write_log

    rig = fd.rigs.rigid_pendulum()
    t = np.arange(0.0, 2.0, 0.01)
    for k, start in enumerate((0.3, -0.4)):
        log = identify.simulate_log(
            rig, t, initial={"theta1": start}, noise={"theta1": 1e-3}, rng=np.random.default_rng(k), name=f"l{k}"
        )
        write_log(log, tmp_path / f"l{k}.csv")
    path = tmp_path / "exp.toml"
    path.write_text(
        textwrap.dedent(
            """
            [rig]
            base = "rigid_pendulum"

            [parameters]
            "joint1.damping" = { guess = 1e-3, lower = 1e-6, upper = 1.0 }

            [sensors.theta1]
            kind = "encoder"

            [noise]
            theta1 = 1e-3

            [[logs]]
            file = "l0.csv"
            initial = { theta1 = 0.3 }

            [[logs]]
            file = "l1.csv"
            initial = { theta1 = -0.4 }
            role = "validation"
            """
        )
    )
    sensor_entries = tuple(cat.SENSOR_FIELDS)
    diag = identify.diagnose(
        identify.load_experiment(path), catalogue=sensor_entries, max_effects=1, pair_search=False, n_fit=1
    )
    assert {s.label for s in diag.rounds[0]} == {"sensor_delay:theta1", "sensor_gain_offset:theta1"}
    assert diag.not_tried == {
        "sensor_gain_offset:theta1": ENCODER_GAIN,
        "sensor_highpass:theta1": ENCODER_HIGHPASS,
    }
    assert "sensor_highpass:theta1: an encoder is DC-coupled" in diag.summary()
