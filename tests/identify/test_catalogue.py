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


_CONTEXT = {"torque_scale": 0.2, "log_duration": 3.0, "lowest_mode_hz": 2.9}


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
    ],
)
def test_plausible_values_pass(name, values):
    assert cat.implausible(name, values, **_CONTEXT) == []


def test_highpass_is_not_judged_without_a_mode():
    assert (
        cat.implausible("sensor_highpass", {"sensor.theta1.highpass": 5.0}, **{**_CONTEXT, "lowest_mode_hz": None})
        == []
    )


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
