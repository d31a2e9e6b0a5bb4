"""Experiment files (`identify.experiment`): building the rig, free parameters, noise and
logs from TOML, and a clear error (file, line, key path, expectation) for each mistake."""

import math
import os
import re
import textwrap

import numpy as np
import pytest
import scipy.io

import flexdyn as fd
from identify._data.columns import LogError
from identify._data.experiment_file import load_experiment
from identify._data.toml_reader import ExperimentError


def msg(*parts: str) -> str:
    """A `match` pattern requiring every fragment, in order."""
    return "(?s)" + ".*".join(re.escape(p) for p in parts)


def write_log(path, n=20, header=("time [s]", "theta1 [deg]", "tip1 [mm]"), start=0.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(header)]
    for k in range(n):
        t = start + 0.01 * k
        lines.append(",".join([f"{t:.4f}"] + [f"{10.0 * math.cos(t) + j:.6f}" for j in range(len(header) - 1)]))
    path.write_text("\n".join(lines) + "\n")
    return path


RIG = """
[rig]
base = "flexible_pendulum"
options = { n_modes = 2 }
"""

LOG = """
[[logs]]
file = "logs/drop.csv"
columns = { time = "time [s]", theta1 = "theta1 [deg]", tip1 = "tip1 [mm]" }
"""


def experiment(tmp_path, body, log=True, name="exp.toml"):
    """Write an experiment file (and by default a log it can use) into tmp_path."""
    if log:
        write_log(tmp_path / "logs" / "drop.csv")
    path = tmp_path / name
    path.write_text(textwrap.dedent(body))
    return path


def line_of(path, text):
    """1-based line of the first line of `path` containing `text`."""
    return next(i for i, line in enumerate(path.read_text().splitlines(), start=1) if text in line)


# ---------------------------------------------------------------------------
# Valid experiments
# ---------------------------------------------------------------------------

FULL = """
[experiment]
name = "flexible pendulum drops"

[rig]
base = "flexible_pendulum"
options = { n_modes = 2, damping_ratio = 0.01 }

[rig.set]
"payload.mass" = 0.02

[parameters]
"link1.EI" = { guess = 2.0, lower = 0.5, upper = 20.0 }
"joint1.damping" = { guess = 1e-3, lower = 1e-6, upper = 0.1 }
"hub1.inertia" = {}
"gravity[1]" = { lower = -10.0, upper = -9.0 }

[noise]
theta1 = "0.1 deg"
tip1 = "estimate"

[[logs]]
file = "logs/drop.csv"
columns = { time = "time [s]", theta1 = "theta1 [deg]", tip1 = "gauge [V]" }
calibration = { tip1 = { scale = 0.0125, offset = 0.001 } }
initial = { theta1 = "measured", theta1_rate = 0.0, "q1_1" = 0.001 }
fit_initial = ["theta1", "q1_1"]
offsets = ["theta1"]

[[logs]]
name = "check"
file = "logs/mat/held_out.mat"
columns = { time = "t [ms]", theta1 = "enc [mrad]", torque1 = "tau [N mm]" }
initial = { theta1 = "-97 deg" }
role = "validation"
"""


def test_round_trip_named_rig(tmp_path):
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "gauge [V]", "status [V]"))
    (tmp_path / "logs" / "mat").mkdir()
    t_ms = np.arange(15) * 2.0
    scipy.io.savemat(tmp_path / "logs/mat/held_out.mat", {"t": t_ms, "enc": np.full(15, 500.0), "tau": np.ones(15)})
    path = tmp_path / "drops.toml"
    path.write_text(FULL)
    before = sorted((p, p.stat().st_mtime_ns) for p in tmp_path.rglob("*"))

    exp = load_experiment(path)

    assert sorted((p, p.stat().st_mtime_ns) for p in tmp_path.rglob("*")) == before  # nothing written
    assert exp.name == "flexible pendulum drops" and exp.path == path
    # The chain: the named rig with its options and rig.set applied.
    ref = fd.rigs.flexible_pendulum(n_modes=2, damping_ratio=0.01, payload_mass=0.02)
    for name in fd.parameter_names(ref):
        assert float(fd.get_parameter(exp.chain, name)) == pytest.approx(float(fd.get_parameter(ref, name)), rel=1e-15)
    assert exp.chain.coordinate_names() == ["theta1", "q1_1", "q1_2"]
    # Free parameters: guesses default to the rig's values; positive ones are log-scaled.
    free = {p.name: p for p in exp.free}
    assert list(free) == ["link1.EI", "joint1.damping", "hub1.inertia", "gravity[1]"]
    assert (free["link1.EI"].guess, free["link1.EI"].lower, free["link1.EI"].upper) == (2.0, 0.5, 20.0)
    assert free["link1.EI"].unit == "N m^2" and free["link1.EI"].log_scale
    assert free["hub1.inertia"].guess == pytest.approx(2e-5) and free["hub1.inertia"].lower is None
    assert free["gravity[1]"].guess == pytest.approx(-9.81) and not free["gravity[1]"].log_scale
    assert float(fd.get_parameter(exp.chain_at_guess(), "link1.EI")) == 2.0
    # Noise: units converted; channels not listed are estimated (None).
    assert exp.noise == {"theta1": pytest.approx(math.radians(0.1)), "tip1": None}
    assert exp.output_channels == ("theta1", "tip1") and exp.input_channels == ("torque1",)
    # Logs: roles, conversions, initial values.
    fit, val = exp.logs
    assert exp.fit_logs == (fit,) and exp.validation_logs == (val,)
    assert fit.name == "drop" and fit.file == (tmp_path / "logs" / "drop.csv").resolve()
    t = 0.01 * np.arange(20)
    np.testing.assert_allclose(fit.log.outputs["theta1"], np.deg2rad(np.round(10 * np.cos(np.round(t, 4)), 6)))
    np.testing.assert_allclose(
        fit.log.outputs["tip1"], 0.0125 * np.round(10 * np.cos(np.round(t, 4)) + 1, 6) + 0.001, rtol=1e-12
    )
    assert fit.log.ignored == ("status [V]",)
    assert fit.initial == {"theta1": pytest.approx(math.radians(10.0)), "theta1_rate": 0.0, "q1_1": 0.001}
    assert fit.fit_initial == ("theta1", "q1_1") and fit.offsets == ("theta1",)
    assert fit.torque(1) is None
    assert val.name == "check" and val.role == "validation"
    np.testing.assert_allclose(val.log.t, 2e-3 * np.arange(15), atol=1e-15)
    np.testing.assert_allclose(val.log.outputs["theta1"], 0.5)
    np.testing.assert_allclose(val.torque(1), np.full((15, 1), 1e-3))
    assert val.initial == {"theta1": pytest.approx(math.radians(-97.0))}
    assert "flexible pendulum drops" in exp.summary()


def test_explicit_chain(tmp_path):
    write_log(tmp_path / "logs" / "arm.csv", header=("time [s]", "theta1 [deg]", "motor2 [deg]"))
    path = experiment(
        tmp_path,
        """
        [rig]
        gravity = [0.0, -9.81]

        [[rig.links]]
        type = "rigid"
        length = 0.4
        mass = 0.3

        [[rig.links]]
        type = "flexible"
        length = 0.3
        rho = 0.39
        EI = 3.3
        n_modes = 2
        damping_ratio = [0.01, 0.02]
        geometric_stiffening = true

        [[rig.joints]]
        type = "rigid"
        damping = 1.9e-3

        [[rig.joints]]
        type = "elastic"
        stiffness = 50.0
        rotor_inertia = 1e-4
        gear_ratio = 10
        spong_approximation = true

        [[rig.hubs]]
        inertia = 2e-5

        [[rig.hubs]]
        mass = 0.1

        [rig.payload]
        mass = 0.05

        [rig.set]
        "joint1.damping" = 2e-3

        [[logs]]
        file = "logs/arm.csv"
        columns = { time = "time [s]", theta1 = "theta1 [deg]", alpha2 = "motor2 [deg]" }
        initial = { theta2 = 0.5, theta2_rate = 0.1 }
        """,
    )
    exp = load_experiment(path)
    ref = fd.Chain(
        links=[
            fd.RigidLink(length=0.4, mass=0.3),
            fd.FlexibleLink(length=0.3, rho=0.39, EI=3.3, n_modes=2, damping_ratio=[0.01, 0.02]),
        ],
        joints=[
            fd.RigidJoint(damping=2e-3),
            fd.ElasticJoint(stiffness=50.0, rotor_inertia=1e-4, gear_ratio=10.0, spong_approximation=True),
        ],
        hubs=[fd.Hub(inertia=2e-5), fd.Hub(mass=0.1)],
        payload=fd.Payload(mass=0.05),
        gravity=(0.0, -9.81),
    )
    assert fd.parameter_names(exp.chain) == fd.parameter_names(ref)
    for name in fd.parameter_names(ref):
        assert float(fd.get_parameter(exp.chain, name)) == float(fd.get_parameter(ref, name)), name
    assert exp.chain.joints[1].spong_approximation
    assert exp.chain.links[1].geometric_stiffening
    assert exp.chain.coordinate_names() == ["theta1", "alpha2", "theta2", "q2_1", "q2_2"]
    # Rotor angle and rate default to the link's (unloaded spring).
    assert exp.logs[0].initial == {"theta2": 0.5, "theta2_rate": 0.1, "alpha2": 0.5, "alpha2_rate": 0.1}
    assert exp.output_channels == ("alpha2", "theta1")


def test_csv_header_channels_without_mapping(tmp_path):
    write_log(tmp_path / "logs" / "drop.csv", header=("time [ms]", "theta1 [deg]", "tip1 [um]", "torque1 [N m]"))
    path = experiment(tmp_path, RIG + '[[logs]]\nfile = "logs/drop.csv"\n', log=False)
    exp = load_experiment(path)
    assert set(exp.logs[0].log.outputs) == {"theta1", "tip1"} and exp.input_channels == ("torque1",)
    np.testing.assert_allclose(exp.logs[0].log.t[1], 1e-5)


# ---------------------------------------------------------------------------
# Malformed experiment files
# ---------------------------------------------------------------------------


def test_toml_syntax_error(tmp_path):
    path = experiment(tmp_path, RIG + '[parameters]\n"link1.EI" = { guess = 2.0, \n' + LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml", "not valid TOML", "line 6")):
        load_experiment(path)


def test_missing_experiment_file(tmp_path):
    with pytest.raises(ExperimentError, match=msg(str(tmp_path / "none.toml"), "does not exist")):
        load_experiment(tmp_path / "none.toml")


def special_paths(tmp_path):
    """A directory, a named pipe (where the system has them) and a symbolic link loop, with
    what a message says each is."""
    (tmp_path / "folder.toml").mkdir(parents=True)
    out = [(tmp_path / "folder.toml", "is a directory")]
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.toml")
        out.append((tmp_path / "pipe.toml", "is not a regular file (a named pipe (FIFO))"))
    (tmp_path / "loop.toml").symlink_to(tmp_path / "loop.toml")
    out.append((tmp_path / "loop.toml", "is a symbolic link loop"))
    return out


def test_an_experiment_path_that_is_not_a_file_says_what_it_is(tmp_path):
    """Review: a directory or a named pipe was reported as "does not exist", and a symbolic
    link loop escaped as RuntimeError. A pipe is never opened (reading it would block)."""
    for path, what in special_paths(tmp_path):
        with pytest.raises(ExperimentError, match=msg(str(path), f"experiment file {what}", "expected a TOML file")):
            load_experiment(path)


def test_a_log_path_that_is_not_a_file_says_what_it_is(tmp_path):
    for path, what in special_paths(tmp_path / "logs"):
        body = RIG + LOG.replace("logs/drop.csv", f"logs/{path.name}")
        exp = experiment(tmp_path, body)
        with pytest.raises(ExperimentError, match=msg("exp.toml, line 7: logs[1].file", f"{path.name} {what}")):
            load_experiment(exp)
    exp = experiment(tmp_path, RIG + LOG.replace("logs/drop.csv", "~no_such_user_here/drop.csv"))
    with pytest.raises(ExperimentError, match=msg("logs[1].file", "~no_such_user_here/drop.csv does not exist")):
        load_experiment(exp)


def test_a_byte_order_mark_before_the_toml_is_skipped(tmp_path):
    """Review: a UTF-8 byte-order mark (Windows editors write one) gave "Invalid statement
    (line 1, column 1)"."""
    path = experiment(tmp_path, RIG + LOG)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert load_experiment(path).logs[0].name == "drop"


@pytest.mark.parametrize("separator", ["\u2028", "\u2029", "\x85"])
def test_a_unicode_line_separator_in_a_comment_keeps_the_line_numbers(tmp_path, separator):
    """str.splitlines() splits at U+2028 and other separators that TOML does not: the
    messages' line numbers after such a comment were one too many."""
    body = f"# rig 3{separator}bench 2\n" + RIG + LOG + 'role = "test"\n'
    path = experiment(tmp_path, body)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 10: logs[1].role", 'expected "fit"')):
        load_experiment(path)


def test_unknown_key_typo(tmp_path):
    path = experiment(tmp_path, RIG + LOG.replace("columns =", "colums ="))
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 8: logs[1].colums", "unknown key", "columns")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + "[noises]\ntheta1 = 1e-3\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 5: noises", "unknown key", "noise")):
        load_experiment(path)


def test_unknown_rig_base(tmp_path):
    path = experiment(tmp_path, '[rig]\nbase = "flexible_pendulm"\n' + LOG)
    with pytest.raises(
        ExperimentError, match=msg("exp.toml, line 2: rig.base", "unknown rig 'flexible_pendulm'", "flexible_pendulum")
    ):
        load_experiment(path)


def test_named_rig_with_geometric_stiffening(tmp_path):
    path = experiment(tmp_path, '[rig]\nbase = "flexible_pendulum"\noptions = { geometric_stiffening = true }\n' + LOG)
    assert load_experiment(path).chain.links[0].geometric_stiffening
    path = experiment(tmp_path, '[rig]\nbase = "flexible_pendulum"\noptions = { geometric_stiffening = "yes" }\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.options.geometric_stiffening", "expected true or false")):
        load_experiment(path)


def test_bad_rig_option(tmp_path):
    path = experiment(tmp_path, '[rig]\nbase = "flexible_pendulum"\noptions = { modes = 2 }\n' + LOG)
    with pytest.raises(
        ExperimentError,
        match=msg("exp.toml, line 3: rig.options.modes", "has no option 'modes'", "n_modes (default 2)"),
    ):
        load_experiment(path)
    path = experiment(tmp_path, '[rig]\nbase = "flexible_pendulum"\noptions = { n_modes = 1.5 }\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.options.n_modes", "expected an integer >= 1", "1.5")):
        load_experiment(path)
    path = experiment(tmp_path, '[rig]\nbase = "rigid_pendulum"\noptions = { payload_mass = "20 g" }\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.options.payload_mass", "expected a number (SI units)")):
        load_experiment(path)


def test_base_and_explicit_chain(tmp_path):
    path = experiment(tmp_path, RIG + "gravity = [0.0, -9.81]\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.gravity", "either base", "not both")):
        load_experiment(path)


def test_explicit_chain_errors(tmp_path):
    link = '[[rig.links]]\ntype = "flexible"\nlength = 0.3\nrho = 0.39\n'
    path = experiment(tmp_path, "[rig]\n" + link + LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 2: rig.links[1]", "FlexibleLink needs EI")):
        load_experiment(path)
    path = experiment(tmp_path, "[rig]\n" + link + "EI = -1.0\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.links[1]", "FlexibleLink.EI", "> 0")):
        load_experiment(path)
    path = experiment(tmp_path, "[rig]\n" + link.replace("flexible", "bendy") + LOG)
    with pytest.raises(ExperimentError, match=msg("line 3: rig.links[1].type", "'rigid' or 'flexible'", "'bendy'")):
        load_experiment(path)
    path = experiment(tmp_path, "[rig]\n" + link + "EI = 3.3\nwidth = 0.02\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("line 7: rig.links[1].width", "no parameter 'width'", "EI")):
        load_experiment(path)
    path = experiment(tmp_path, "[rig]\n" + link + "EI = 3.3\ngeometric_stiffening = 1\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("line 7: rig.links[1].geometric_stiffening", "true or false", "1")):
        load_experiment(path)
    joints = "[[rig.joints]]\ndamping = 0.1\n[[rig.joints]]\ndamping = 0.1\n"
    path = experiment(tmp_path, "[rig]\n" + link + "EI = 3.3\n" + joints + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.joints", "2 [[rig.joints]] table(s) for 1 link(s)")):
        load_experiment(path)


def test_rig_set_errors(tmp_path):
    path = experiment(tmp_path, RIG + '[rig.set]\n"link1.E" = 2.0\n' + LOG)
    with pytest.raises(
        ExperimentError,
        match=msg('line 6: rig.set."link1.E"', "unknown parameter (did you mean 'link1.EI'?)", "link1.EI"),
    ):
        load_experiment(path)
    path = experiment(tmp_path, RIG + '[rig.set]\n"link1.EI" = 0.0\n' + LOG)
    with pytest.raises(ExperimentError, match=msg('rig.set."link1.EI"', "FlexibleLink.EI", "> 0")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + "[rig.set]\npayload.mass = 0.02\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("rig.set.payload", "quote the name", '"payload.mass"')):
        load_experiment(path)


def test_unknown_free_parameter(tmp_path):
    path = experiment(tmp_path, RIG + '[parameters]\n"link1.stiffness" = { guess = 1.0 }\n' + LOG)
    with pytest.raises(
        ExperimentError,
        match=msg('exp.toml, line 6: parameters."link1.stiffness"', "unknown parameter", "link1.EI", "joint1.damping"),
    ):
        load_experiment(path)


def test_an_optional_term_named_in_parameters_or_rig_set_is_added_to_a_named_rig(tmp_path):
    """Review: `"joint2.coulomb"` on a named rig said "unknown parameter" (the README lists
    it, and a named rig takes no joint tables). Naming an optional term adds it: at the
    value `rig.set` gives, or at 0.0 (neutral) with the fit starting from the guess."""
    body = RIG + '[rig.set]\n"link1.drag" = 0.002\n[parameters]\n"joint1.coulomb" = { guess = 1e-3, upper = 0.1 }\n'
    exp = load_experiment(experiment(tmp_path, body + LOG))
    assert float(fd.get_parameter(exp.chain, "link1.drag")) == 0.002
    assert float(fd.get_parameter(exp.chain, "joint1.coulomb")) == 0.0
    (p,) = exp.free
    assert (p.name, p.guess, p.upper, p.unit, p.log_scale) == ("joint1.coulomb", 1e-3, 0.1, "N m", True)
    # with no guess, the term's neutral 0 cannot start a log-space fit: said so
    path = experiment(tmp_path, RIG + '[parameters]\n"joint1.coulomb" = {}\n' + LOG, log=False, name="b.toml")
    with pytest.raises(ExperimentError, match=msg('"joint1.coulomb".guess', "expected a guess > 0")):
        load_experiment(path)
    # backlash is an elastic joint's: on a rigid one still unknown
    path = experiment(tmp_path, RIG + '[parameters]\n"joint1.backlash" = 1e-3\n' + LOG, log=False, name="c.toml")
    with pytest.raises(ExperimentError, match=msg('parameters."joint1.backlash"', "unknown parameter")):
        load_experiment(path)


@pytest.mark.parametrize(
    "entry, expected",
    [
        ("{ guess = 30.0, lower = 0.5, upper = 20.0 }", ("guess = 30 is outside [0.5, 20]", "lower <= guess <= upper")),
        ("{ guess = 2.0, lower = 5.0, upper = 5.0 }", ("lower = 5 is not below upper = 5",)),
        ("{ guess = 2.0, lower = 0.0, upper = 20.0 }", ('"link1.EI".lower', "log space", "expected lower > 0")),
        ("{ guess = -2.0 }", ('"link1.EI".guess', "expected a guess > 0")),
        ("{ guess = 2.0, upper = 1.0 }", ("guess = 2 is outside [unbounded, 1]",)),
        ('{ guess = "2" }', ("guess", "expected a number (SI units)", "'2'")),
        ("{ guess = 2.0, max = 3.0 }", ('"link1.EI".max', "unknown key", "guess, lower, upper")),
    ],
)
def test_bad_bounds(tmp_path, entry, expected):
    path = experiment(tmp_path, RIG + f'[parameters]\n"link1.EI" = {entry}\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 6", *expected)):
        load_experiment(path)


STARTS_PARAMETERS = """
[parameters]
"link1.EI" = { guess = 2.0, lower = 0.5, upper = 20.0 }
"joint1.damping" = { guess = 1e-3 }
"gravity[1]" = { guess = -9.81 }
"""


def test_starts_are_read_in_si_and_reach_the_fit(tmp_path, monkeypatch):
    """`[[starts]]`: extra points for the multi-start stage (`identify.fit`'s
    `extra_starts`), each naming some free parameters; `fit_experiment` passes them on
    unless the caller gives its own."""

    import identify._workflow as run

    diagnose_module = run

    body = (
        RIG
        + STARTS_PARAMETERS
        + '[[starts]]\n"link1.EI" = 8.0\n\n[[starts]]\n"joint1.damping" = 0.02\n"gravity[1]" = -9.7\n'
    )
    exp = load_experiment(experiment(tmp_path, body + LOG))
    assert exp.starts == ({"link1.EI": 8.0}, {"joint1.damping": 0.02, "gravity[1]": -9.7})
    assert "start 2: joint1.damping = 0.02, gravity[1] = -9.7" in exp.summary()
    seen = {}
    monkeypatch.setattr(run, "fit", lambda problem, params, **kw: seen.update(kw))
    run.fit_experiment(exp)
    assert seen["extra_starts"] == exp.starts
    run.fit_experiment(exp, extra_starts=())
    assert seen["extra_starts"] == ()
    # and `identify diagnose`'s baseline fit
    monkeypatch.setattr(diagnose_module, "diagnose_logs", lambda *a, **kw: kw["fit_options"])
    assert diagnose_module.diagnose(exp) == {"extra_starts": exp.starts}
    assert diagnose_module.diagnose(exp, fit_options={"n_starts": 2}) == {"extra_starts": exp.starts, "n_starts": 2}
    assert load_experiment(experiment(tmp_path, RIG + STARTS_PARAMETERS + LOG, name="none.toml")).starts == ()


@pytest.mark.parametrize(
    "start, expected",
    [
        (
            '"link1.EI" = 30.0',
            ('starts[2]."link1.EI"', "30 is outside [0.5, 20] N m^2", "inside the parameter's bounds"),
        ),
        ('"joint1.damping" = -1e-3', ('starts[2]."joint1.damping"', "log space", "expected a value > 0, got -0.001")),
        ('"payload.mass" = 0.1', ('starts[2]."payload.mass"', "not a free parameter", "link1.EI, joint1.damping")),
        ("link1.EI = 3.0", ("starts[2].link1", "quote the name", '"link1.EI" = ...')),
        ('"link1.EI" = "3"', ('starts[2]."link1.EI"', "expected a number (SI units)", "'3'")),
    ],
)
def test_bad_starts_name_the_line_and_parameter(tmp_path, start, expected):
    body = RIG + STARTS_PARAMETERS + '[[starts]]\n"link1.EI" = 4.0\n\n[[starts]]\n' + start + "\n"
    path = experiment(tmp_path, body + LOG)
    with pytest.raises(ExperimentError, match=msg(f"exp.toml, line {line_of(path, start)}", *expected)):
        load_experiment(path)


def test_starts_need_tables_and_free_parameters(tmp_path):
    path = experiment(tmp_path, "starts = 3\n" + RIG + LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 1: starts", "expected [[starts]] tables")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + '[[starts]]\n"link1.EI" = 4.0\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("starts", "no free parameters")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + STARTS_PARAMETERS + "[[starts]]\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("starts[1]", "empty start")):
        load_experiment(path)


def test_guess_from_rig_outside_bounds(tmp_path):
    path = experiment(tmp_path, RIG + '[parameters]\n"link1.EI" = { lower = 10.0, upper = 20.0 }\n' + LOG)
    with pytest.raises(
        ExperimentError, match=msg("line 6", "the rig's value (no guess given) 3.33", "outside [10, 20]")
    ):
        load_experiment(path)


def test_noise_errors(tmp_path):
    path = experiment(tmp_path, RIG + "[noise]\ntip2 = 1e-3\n" + LOG)
    with pytest.raises(
        ExperimentError, match=msg("exp.toml, line 6: noise.tip2", "no log measures tip2", "theta1, tip1")
    ):
        load_experiment(path)
    path = experiment(tmp_path, RIG + "[noise]\ntorque1 = 1e-3\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("noise.torque1", "not an output channel")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + "[noise]\ntip1 = 0.0\n" + LOG)
    with pytest.raises(ExperimentError, match=msg("noise.tip1", "expected a standard deviation > 0")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + '[noise]\ntip1 = "0.1 deg"\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("noise.tip1", "'0.1 deg' is an angle; expected a length", "mm")):
        load_experiment(path)
    # found in review: a string without a unit was read as SI (0.03 meant as degrees became 0.03 rad)
    path = experiment(tmp_path, RIG + '[noise]\ntheta1 = "0.03"\n' + LOG)
    with pytest.raises(ExperimentError, match=msg("line 6: noise.theta1", "'0.03' has no unit", "'0.03 deg'", "(rad)")):
        load_experiment(path)
    assert load_experiment(experiment(tmp_path, RIG + '[noise]\ntheta1 = "0.03 Deg"\n' + LOG)).noise[
        "theta1"
    ] == pytest.approx(math.radians(0.03), rel=1e-14)


def test_an_initial_value_held_at_a_noisy_first_sample_is_warned_about(tmp_path):
    """Found in review: `theta1 = "measured"` without `fit_initial` holds one noisy sample
    as exact and biases the fit beyond its intervals, in silence."""
    held = LOG + 'initial = { theta1 = "measured" }\n'
    exp = load_experiment(experiment(tmp_path, RIG + held))
    assert exp.logs[0].measured == ("theta1",)
    assert "warning: log 'drop': theta1 = \"measured\" holds the first sample" in exp.summary()
    assert "add theta1 to fit_initial" in exp.summary()
    fitted = load_experiment(experiment(tmp_path, RIG + held + 'fit_initial = ["theta1"]\n', name="b.toml"))
    assert fitted.logs[0].warnings() == [] and "warning" not in fitted.summary()
    # the noise is shown with its unit
    assert "noise theta1: estimate" in exp.summary()
    with_noise = load_experiment(experiment(tmp_path, RIG + '[noise]\ntip1 = "20 um"\n' + LOG, name="c.toml"))
    assert "noise tip1: 2e-05 m (0.02 mm)" in with_noise.summary()


def test_log_file_missing(tmp_path):
    path = experiment(tmp_path, RIG + LOG.replace("drop.csv", "drop_0deg.csv"))
    resolved = (tmp_path / "logs" / "drop_0deg.csv").resolve()
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 7: logs[1].file", str(resolved), "does not exist")):
        load_experiment(path)


def test_missing_time_mapping(tmp_path):
    path = experiment(tmp_path, RIG + LOG.replace('time = "time [s]", ', ""))
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 8: logs[1].columns", "no time column", "[s]")):
        load_experiment(path)


@pytest.mark.parametrize(
    "rig, channel, expected",
    [
        (RIG, "tip2", "the rig has 1 link(s)"),
        ('[rig]\nbase = "rigid_pendulum"\n', "tip1", "link 1 is rigid (no deflection)"),
        (RIG, "alpha1", "joint 1 is rigid (no rotor angle alpha1)"),
        (RIG, "tipp1", "'tipp1' is not a channel"),
    ],
)
def test_channel_not_on_rig(tmp_path, rig, channel, expected):
    path = experiment(tmp_path, rig + LOG.replace("tip1 = ", f"{channel} = "))
    with pytest.raises(ExperimentError, match=msg(f"logs[1].columns.{channel}", expected)):
        load_experiment(path)


def test_csv_header_channel_not_on_rig(tmp_path):
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "tip2 [mm]"))
    path = experiment(tmp_path, RIG + '[[logs]]\nfile = "logs/drop.csv"\n', log=False)
    with pytest.raises(ExperimentError, match=msg("logs[1].file", "'tip2 [mm]'", "the rig has 1 link(s)")):
        load_experiment(path)


def test_log_error_names_log_and_experiment_entry(tmp_path):
    # the file's side (line and column of the header) and the mapping entry's line (8)
    path = experiment(tmp_path, RIG + LOG.replace("tip1 [mm]", "tip1 [deg]"))
    with pytest.raises(
        LogError,
        match=msg(
            "drop.csv, line 1, column 3",
            "header says [mm]",
            "make them agree",
            "exp.toml, line 8: logs[1].columns.tip1]",
        ),
    ) as info:
        load_experiment(path)
    assert info.value.channel == "tip1"
    # a unit typo in the mapping is named as an unknown unit, not as a disagreement
    path = experiment(tmp_path, RIG + LOG.replace("tip1 [mm]", "tip1 [mmm]"))
    with pytest.raises(
        LogError,
        match=msg("drop.csv, line 1, column 3", "unknown unit [mmm]", "known units", "line 8: logs[1].columns.tip1]"),
    ):
        load_experiment(path)
    path = experiment(tmp_path, RIG + LOG.replace('theta1 = "theta1 [deg]"', 'theta1 = "enc [deg]"'))
    with pytest.raises(
        LogError,
        match=msg(
            "drop.csv, line 1", "no column 'enc'", "exp.toml logs[1].columns.theta1", "line 8: logs[1].columns.theta1]"
        ),
    ):
        load_experiment(path)
    # the mapping written as a sub-table: the entry's own line
    table = '[[logs]]\nfile = "logs/drop.csv"\n[logs.columns]\n'
    table += 'time = "time [s]"\ntheta1 = "theta1 [deg]"\ntip1 = "tip1 [m]"\n'
    path = experiment(tmp_path, RIG + table)
    with pytest.raises(LogError, match=msg("header says [mm]", "exp.toml, line 10: logs[1].columns.tip1]")):
        load_experiment(path)
    # a problem in the file itself (no mapping entry concerned) still points at the log
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "tip1 [mm]"), n=3)
    path = experiment(tmp_path, RIG + LOG, log=False)
    with pytest.raises(LogError, match=msg("drop.csv", "exp.toml, line 6: logs[1]]")) as info:
        load_experiment(path)
    assert info.value.channel is None


def test_calibration_errors(tmp_path):
    path = experiment(tmp_path, RIG + LOG + "calibration = { tip1 = { offset = 1.0 } }\n")
    with pytest.raises(ExperimentError, match=msg("line 9: logs[1].calibration.tip1", "missing 'scale'")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + LOG + "calibration = { tip1 = { scale = 1.0 } }\n")
    with pytest.raises(LogError, match=msg("column 3", "calibration scale is given for tip1", "not [V]")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + LOG + "calibration = { tip1 = { gear_ratio = 70 } }\n")
    with pytest.raises(ExperimentError, match=msg("line 9: logs[1].calibration.tip1.gear_ratio", "not tip1")):
        load_experiment(path)


def test_a_motor_side_encoder_through_the_experiment_file(tmp_path):
    """`gear_ratio` refers a motor-side angle column to the link side: theta1 = motor / G."""
    plain = load_experiment(experiment(tmp_path, RIG + LOG)).logs[0]
    geared = load_experiment(
        experiment(tmp_path, RIG + LOG + "calibration = { theta1 = { gear_ratio = -20 } }\n", name="g.toml")
    ).logs[0]
    np.testing.assert_allclose(geared.log.outputs["theta1"], -plain.log.outputs["theta1"] / 20.0, rtol=1e-15)
    np.testing.assert_array_equal(geared.log.outputs["tip1"], plain.log.outputs["tip1"])


@pytest.mark.parametrize(
    "extra, expected",
    [
        ("initial = { phi1 = 0.0 }", ("logs[1].initial.phi1", "not a coordinate", "theta1, q1_1, q1_2, theta1_rate")),
        ('fit_initial = ["theta1", "q1_3"]', ("logs[1].fit_initial", "'q1_3' is not a coordinate", "q1_2_rate")),
        ('offsets = ["tip2"]', ("logs[1].offsets", "'tip2' is not an output channel of this log", "theta1, tip1")),
        ('initial = { q1_1 = "measured" }', ("logs[1].initial.q1_1", '"measured" needs a q1_1 channel')),
        ('initial = { theta1 = "ten" }', ("logs[1].initial.theta1", "expected a number with a unit", "'ten'")),
        ('initial = { q1_1 = "2 deg" }', ("logs[1].initial.q1_1", "'2 deg' is an angle", "expected a length")),
        ('initial = { theta1_rate = "5 deg" }', ("logs[1].initial.theta1_rate", "rad/s for an angle rate")),
        ('role = "test"', ("logs[1].role", 'expected "fit" or "validation"', "'test'")),
    ],
)
def test_log_entry_errors(tmp_path, extra, expected):
    path = experiment(tmp_path, RIG + LOG + extra + "\n")
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 9", *expected)):
        load_experiment(path)


def test_duplicate_log_names_and_no_fit_log(tmp_path):
    path = experiment(tmp_path, RIG + LOG + LOG)
    assert line_of(path, "[[logs]]") == 6
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 10: logs[2].name", "'drop' is also used by logs[1]")):
        load_experiment(path)
    path = experiment(tmp_path, RIG + LOG + 'role = "validation"\n')
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 6: logs", 'expected at least one with role = "fit"')):
        load_experiment(path)


def test_the_same_file_listed_twice_is_refused(tmp_path):
    """Review: one file under two names counted its samples twice and narrowed the
    intervals without a word. With other columns (another channel) it is two logs."""
    path = experiment(
        tmp_path, RIG + LOG + LOG.replace('file = "logs/drop.csv"', 'file = "logs/drop.csv"\nname = "again"')
    )
    with pytest.raises(ExperimentError, match=msg("exp.toml", "logs[2].file", "logs[1] already reads drop.csv")):
        load_experiment(path)
    other = LOG.replace(', tip1 = "tip1 [mm]"', "").replace(
        'file = "logs/drop.csv"', 'file = "logs/drop.csv"\nname = "b"'
    )
    assert len(load_experiment(experiment(tmp_path, RIG + LOG + other)).logs) == 2


def test_no_rig_or_no_logs(tmp_path):
    path = experiment(tmp_path, LOG)
    with pytest.raises(ExperimentError, match=msg("exp.toml", "missing [rig]", "base")):
        load_experiment(path)
    path = experiment(tmp_path, RIG)
    with pytest.raises(ExperimentError, match=msg("exp.toml", "no [[logs]]", "file =")):
        load_experiment(path)


def test_format_md_example_loads(tmp_path):
    """The complete example in docs/experiment-format.md is a valid experiment file."""
    import pathlib

    doc = (pathlib.Path(__file__).parents[2] / "docs" / "experiment-format.md").read_text()
    example = doc.split("## A complete example", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    # gauge column: 10 cos(t) + 1 V, so 11 V at t = 0
    write_log(tmp_path / "logs" / "drop_0deg.csv", header=("time [s]", "enc [deg]", "gauge [V]", "status"))
    t = np.arange(12) * 1.0
    scipy.io.savemat(tmp_path / "logs" / "drop_m97.mat", {"t": t, "enc": -97 + 0 * t, "tip": 0 * t})
    path = tmp_path / "drops.toml"
    path.write_text(example)
    exp = load_experiment(path)
    assert [p.name for p in exp.free] == ["link1.EI", "joint1.damping", "hub1.inertia"]
    assert [entry.role for entry in exp.logs] == ["fit", "validation"]
    np.testing.assert_allclose(exp.logs[0].log.outputs["tip1"][0], 12.5e-3 * 11.0, rtol=1e-12)
    assert exp.logs[1].name == "drop from -97 deg"


# ---------------------------------------------------------------------------
# The measurement model: [sensors.<channel>], [actuators.joint<i>], free sensor parameters
# ---------------------------------------------------------------------------


def test_sensors_and_actuators_build_the_measurement_model_in_si(tmp_path):
    path = experiment(
        tmp_path,
        RIG
        + LOG
        + """
[sensors.tip1]
gain = 1.02
offset = "0.5 mm"
highpass = "2 Hz"

[sensors.theta1]
delay = "3 ms"

[actuators.joint1]
lag = 0.004

[parameters]
"sensor.tip1.gain" = { lower = 0.5, upper = 2.0 }
"sensor.theta1.highpass" = 0.1
""",
    )
    exp = load_experiment(path)
    from identify._data import measurement as meas

    m = exp.measurement
    assert float(meas.get_parameter(m, "sensor.tip1.gain")) == 1.02
    assert float(meas.get_parameter(m, "sensor.tip1.offset")) == pytest.approx(0.5e-3)
    assert float(meas.get_parameter(m, "sensor.tip1.highpass")) == 2.0
    assert float(meas.get_parameter(m, "sensor.theta1.delay")) == pytest.approx(3e-3)
    assert float(meas.get_parameter(m, "actuator1.lag")) == 0.004
    # a free measurement parameter not given under [sensors] is present at its neutral value
    assert float(meas.get_parameter(m, "sensor.theta1.highpass")) == 0.0
    free = {p.name: p for p in exp.free}
    assert free["sensor.tip1.gain"].guess == 1.02 and free["sensor.tip1.gain"].log_scale
    assert free["sensor.theta1.highpass"].guess == 0.1 and free["sensor.theta1.highpass"].unit == "Hz"
    assert float(meas.get_parameter(exp.measurement_at_guess(), "sensor.theta1.highpass")) == 0.1
    assert exp.chain_at_guess() is not None  # the chain ignores measurement parameters
    assert "measurement sensor.tip1.highpass = 2 Hz" in exp.summary()


@pytest.mark.parametrize(
    "body, fragments",
    [
        ("[sensors.tip2]\ngain = 1.1\n", ("sensors.tip2", "no log measures tip2", "theta1, tip1")),
        ('[sensors.tip1]\ndelay = "3 mm"\n', ("sensors.tip1.delay", "'3 mm' is a length; expected a time")),
        ("[sensors.tip1]\nhighpass = -1.0\n", ("sensors.tip1.highpass", "expected a value >= 0")),
        ("[sensors.tip1]\ngain = 0.0\n", ("sensors.tip1.gain", "expected a gain > 0")),
        ("[sensors.tip1]\ngian = 1.0\n", ("sensors.tip1.gian", "unknown key; expected one of gain, offset")),
        ("[actuators.joint2]\nlag = 0.01\n", ("actuators.joint2", "expected joint1 ... joint1")),
        ('[actuators.joint1]\nlag = "5 deg"\n', ("actuators.joint1.lag", "is an angle; expected a time")),
        ('[parameters]\n"sensor.tip3.gain" = 1.0\n', ('parameters."sensor.tip3.gain"', "no log measures tip3")),
        ('[parameters]\n"actuator2.lag" = 0.01\n', ('parameters."actuator2.lag"', "joints 1 to 1")),
        (
            '[parameters]\n"sensor.tip1.delay" = {}\n',
            ('parameters."sensor.tip1.delay".guess', "the model's value of sensor.tip1.delay", "expected a guess > 0"),
        ),
    ],
)
def test_measurement_mistakes_name_the_line_and_key(tmp_path, body, fragments):
    path = experiment(tmp_path, RIG + LOG + body)
    line = line_of(path, body.splitlines()[1].split("=")[0].strip()) if "parameters" in body else None
    with pytest.raises(ExperimentError, match=msg(*((f"line {line}",) if line else ()), *fragments)):
        load_experiment(path)


def test_a_reversed_column_through_the_experiment_file(tmp_path):
    """`sign = -1` in a log's calibration negates a column in any unit (here mm, where a
    scale is refused); another sign is an error naming the line and key."""
    plain = load_experiment(experiment(tmp_path, RIG + LOG)).logs[0]
    reversed_ = load_experiment(
        experiment(tmp_path, RIG + LOG + "calibration = { tip1 = { sign = -1 } }\n", name="r.toml")
    ).logs[0]
    np.testing.assert_array_equal(reversed_.log.outputs["tip1"], -plain.log.outputs["tip1"])
    np.testing.assert_array_equal(reversed_.log.outputs["theta1"], plain.log.outputs["theta1"])
    path = experiment(tmp_path, RIG + LOG + "calibration = { tip1 = { sign = 2 } }\n", name="s.toml")
    with pytest.raises(
        ExperimentError, match=msg("s.toml, line 9: logs[1].calibration.tip1.sign", "expected -1", "or 1", "got 2")
    ):
        load_experiment(path)


def test_a_sensor_kind_and_resolution_are_read_onto_the_sensor(tmp_path):
    body = RIG + LOG + '[sensors.theta1]\nkind = "encoder"\nresolution = "0.088 deg"\noffset = "1 deg"\n'
    body += '[sensors.tip1]\nkind = "strain_gauge"\nhighpass = "2 Hz"\n'
    exp = load_experiment(experiment(tmp_path, body))
    theta1, tip1 = exp.measurement.sensors["theta1"], exp.measurement.sensors["tip1"]
    assert theta1.kind == "encoder" and theta1.resolution == pytest.approx(math.radians(0.088), rel=1e-15)
    assert tip1.kind == "strain_gauge" and tip1.resolution is None
    assert "sensor theta1: encoder, resolution 0.00153589 rad (0.088 deg)" in exp.summary()
    assert "sensor tip1: strain_gauge" in exp.summary()
    # the step reaches the fit's noise floors (the log's smooth theta1 has almost none)
    from identify._fit.quality import noise_floors
    from identify._workflow import problem_from_experiment

    problem = problem_from_experiment(exp)
    floor = noise_floors(problem)[0][0]
    assert floor[problem.channels.index("theta1")] == pytest.approx(math.radians(0.088) / math.sqrt(12), rel=1e-12)
    assert floor[problem.channels.index("tip1")] < 1e-6
    # no kind, no resolution: the sensor is as before
    exp = load_experiment(experiment(tmp_path, RIG + LOG + "[sensors.theta1]\ndelay = 0.001\n", name="b.toml"))
    assert exp.measurement.sensors["theta1"].kind is None and exp.measurement.sensors["theta1"].resolution is None


_KINDS = "encoder, potentiometer, strain_gauge, accelerometer, optical"


@pytest.mark.parametrize(
    "body, key, fragments",
    [
        ('[sensors.theta1]\nkind = "encodr"\n', "kind", ("sensors.theta1.kind", f"'encodr'; expected one of {_KINDS}")),
        ("[sensors.theta1]\nkind = 3\n", "kind", ("sensors.theta1.kind", f"kind 3; expected one of {_KINDS}")),
        (
            '[sensors.tip1]\nkind = "encoder"\n',
            "kind",
            (
                "sensors.tip1.kind",
                "encoder (",
                "measures angles (theta<i>",
                "not tip1",
                "strain_gauge or optical for tip1",
            ),
        ),
        (
            '[sensors.theta1]\nkind = "encoder"\ngain = 1.02\n',
            "gain",
            ("sensors.theta1.gain", "kind = 'encoder' has no gain", "counts per revolution"),
        ),
        (
            '[sensors.theta1]\nkind = "potentiometer"\nhighpass = "1 Hz"\n',
            "highpass",
            ("sensors.theta1.highpass", "kind = 'potentiometer' has no highpass", "DC-coupled"),
        ),
        (
            '[sensors.theta1]\nkind = "encoder"\n[parameters]\n"sensor.theta1.gain" = 1.0\n',
            '"sensor.theta1.gain"',
            ('parameters."sensor.theta1.gain"', "kind = 'encoder', which has no gain", "counts per revolution"),
        ),
        ('[sensors.theta1]\nresolution = "0.1 mm"\n', "resolution", ("sensors.theta1.resolution", "is a length")),
        ("[sensors.theta1]\nresolution = 0.0\n", "resolution", ("sensors.theta1.resolution", "step > 0, got 0")),
    ],
)
def test_sensor_kind_and_resolution_mistakes_name_the_line_and_key(tmp_path, body, key, fragments):
    path = experiment(tmp_path, RIG + LOG + body)
    with pytest.raises(ExperimentError, match=msg(f"line {line_of(path, key)}", *fragments)):
        load_experiment(path)


@pytest.mark.parametrize(
    ("gravity", "text"),
    [
        ((0.0, -9.81), "hangs at theta1 = -90 deg"),  # the papers' convention: theta = 0 horizontal
        ((-9.81, 0.0), "hangs at theta1 = 180 deg"),  # a log whose zero is upright
        ((9.81, 0.0), "hangs at theta1 = 0 deg"),  # a log whose zero is hanging
        ((0.0, 0.0), "a rig in a horizontal plane"),
    ],
)
def test_the_summary_says_where_gravity_makes_the_first_link_hang(gravity, text):
    """Oracle: the direction of the gravity vector in the base frame (`atan2(g_y, g_x)`):
    where a link with its centre of mass beyond the joint hangs. A log swinging about
    another angle has its zero elsewhere (the commonest set-up error on the real pendulum)."""
    from identify._data.experiment import gravity_text

    assert text in gravity_text(gravity)


def test_a_modal_initial_value_takes_a_length_unit(tmp_path):
    """Review: `q1_1 = "2 mm"` was refused while [noise] takes units for any channel."""
    path = experiment(tmp_path, RIG + LOG + 'initial = { q1_1 = "2 mm", theta1 = "10 deg" }\n')
    (entry,) = load_experiment(path).logs
    assert entry.initial == {"q1_1": pytest.approx(2e-3), "theta1": pytest.approx(math.radians(10.0))}


def test_an_unused_torque_column_is_a_warning(tmp_path):
    """Review: a log whose `torque2` was left out of `columns` ran with joint 2 unpowered;
    only "columns not used: 'tau2 [N m]'" hinted at it. A column with a torque unit or
    name that no channel uses is now a warning; other unused columns are not."""
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "tip1 [mm]", "tau1 [N m]"))
    exp = load_experiment(experiment(tmp_path, RIG + LOG, log=False))
    (spec,) = exp.logs
    (w,) = spec.warnings()
    assert "'tau1 [N m]' looks like a torque" in w and "unpowered" in w and "torque columns mapped: none" in w
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "tip1 [mm]", "strain [mm]"))
    (spec,) = load_experiment(experiment(tmp_path, RIG + LOG, log=False)).logs
    assert spec.log.ignored == ("strain [mm]",) and spec.warnings() == []


def test_a_log_sets_its_own_known_parameter_values(tmp_path):
    """`[[logs]] set = {...}`: a payload sweep's known tip mass per log reaches the log's
    `LogSpec.set`, the summary and the fit's `LogData.set`; a name the rig lacks, a value
    the rig refuses and a parameter that is also free are errors naming the line."""
    from identify._workflow import log_data

    path = experiment(tmp_path, RIG + LOG + 'set = { "payload.mass" = 0.02 }\n')
    exp = load_experiment(path)
    assert exp.logs[0].set == {"payload.mass": 0.02} and exp.name == "exp"  # (review: the name was overwritten)
    assert "set: payload.mass = 0.02 kg" in exp.summary()
    other = experiment(tmp_path, RIG + LOG + 'fit_initial = ["theta1"]\noffsets = ["tip1"]\n', name="other.toml")
    # (review: `identify check` did not list what each log estimates)
    assert "estimated for this log: initial state theta1; sensor offset of tip1" in load_experiment(other).summary()
    assert log_data(exp.logs[0], exp.chain.n_links).set == {"payload.mass": 0.02}
    line = line_of(path, "set =")
    for body, expected in (
        ('set = { "payload.mas" = 0.02 }\n', "did you mean 'payload.mass'"),
        ('set = { "payload.mass" = -0.02 }\n', "expected a value >= 0"),
        ('set = { "payload.mass" = "20 g" }\n', "expected a number (SI units)"),
    ):
        path = experiment(tmp_path, RIG + LOG + body)
        with pytest.raises(ExperimentError, match=msg(f"line {line}: logs[1].set.", expected)):
            load_experiment(path)
    body = RIG + '[parameters]\n"payload.mass" = { guess = 0.01 }\n' + LOG + 'set = { "payload.mass" = 0.02 }\n'
    path = experiment(tmp_path, body)
    with pytest.raises(ExperimentError, match=msg('logs[1].set."payload.mass"', "also a free parameter")):
        load_experiment(path)


def test_a_strain_gauge_column_through_the_experiment_file(tmp_path):
    """A microstrain column with its gauge's neutral-axis distance, as an experiment file
    declares it (the calibration is checked once by the loader and once more by
    `load_log`: an earlier version refused its own default offset the second time)."""
    write_log(tmp_path / "logs" / "sg.csv", header=("time [s]", "theta1 [deg]", "sg [ue]"))
    body = (
        RIG
        + """
[[logs]]
file = "logs/sg.csv"
columns = { time = "time [s]", theta1 = "theta1 [deg]", curvature1 = "sg [ue]" }
calibration = { curvature1 = { neutral_axis_distance = "0.5 mm" } }
"""
    )
    exp = load_experiment(experiment(tmp_path, body, log=False))
    ue = np.asarray([10.0 * math.cos(0.01 * k) + 1 for k in range(20)])
    np.testing.assert_allclose(exp.logs[0].log.outputs["curvature1"], ue * 1e-6 / 0.5e-3, rtol=1e-6)


def test_a_log_with_decimal_commas_says_so_in_its_entry(tmp_path):
    """A comma is read as a decimal mark only where the log's entry says `decimal = ","`:
    `1,234` could be 1.234 or 1234 (review: it was read as 1.234 by guess)."""
    path = write_log(tmp_path / "logs" / "eu.csv")
    text = path.read_text()
    path.write_text(text.replace(",", ";").replace(".", ","))
    body = RIG + LOG.replace("drop.csv", "eu.csv")
    with pytest.raises(
        LogError,
        match=msg("eu.csv, line 2, column 1 ('time [s]')", "got '0,0000': a decimal comma (0.0000)?", 'decimal = ","'),
    ):
        load_experiment(experiment(tmp_path, body, log=False))
    exp = load_experiment(experiment(tmp_path, body + 'decimal = ","\n', log=False))
    np.testing.assert_allclose(exp.logs[0].log.t, 0.01 * np.arange(20), rtol=0, atol=1e-15)
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 9: logs[1].decimal", 'expected "." or ","', "';'")):
        load_experiment(experiment(tmp_path, body + 'decimal = ";"\n', log=False))
    mat = tmp_path / "logs" / "run.mat"
    scipy.io.savemat(mat, {"t": 0.01 * np.arange(20), "enc": np.zeros(20)})
    body = RIG + '[[logs]]\nfile = "logs/run.mat"\ncolumns = { time = "t [s]", theta1 = "enc [deg]" }\ndecimal = ","\n'
    with pytest.raises(ExperimentError, match=msg("exp.toml, line 8: logs[1].decimal: applies to CSV logs")):
        load_experiment(experiment(tmp_path, body, log=False))


DRIVEN = """
[[logs]]
file = "logs/drop.csv"
columns = { time = "time [s]", theta1 = "theta1 [deg]", torque1 = "torque1 [N m]" }
"""


@pytest.mark.parametrize(
    ("entry", "expected"),
    [
        ("", "linear"),
        ('hold = "zoh"\n', "zoh"),
        ('hold = "linear"\n', "linear"),
        ('hold = { torque1 = "zoh" }\n', "zoh"),
    ],
)
def test_a_logs_torque_hold(tmp_path, entry, expected):
    """`hold`: how a log's torque samples are read between samples (docs/experiment-format.md),
    carried to the fit's `LogData` and `Problem`."""
    import identify

    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "torque1 [N m]"))
    exp = load_experiment(experiment(tmp_path, RIG + DRIVEN + entry, log=False))
    assert exp.logs[0].hold == expected
    assert identify.log_data(exp.logs[0], 1).hold == expected
    assert identify.problem_from_experiment(exp).hold == expected


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ('hold = "cubic"', ("logs[1].hold", 'expected "linear" or "zoh"', "'cubic'")),
        ("hold = 1", ("logs[1].hold", "expected a table, got 1")),
        ('hold = { torque2 = "zoh" }', ("logs[1].hold.torque2", "not an input column of this log", "torque1")),
        ('hold = { torque1 = "held" }', ("logs[1].hold.torque1", 'expected "linear" or "zoh"', "'held'")),
    ],
)
def test_a_bad_torque_hold_names_its_key(tmp_path, entry, message):
    write_log(tmp_path / "logs" / "drop.csv", header=("time [s]", "theta1 [deg]", "torque1 [N m]"))
    path = experiment(tmp_path, RIG + DRIVEN + entry + "\n", log=False)
    with pytest.raises(ExperimentError, match=msg(f"exp.toml, line {line_of(path, 'hold')}", *message)):
        load_experiment(path)


@pytest.mark.parametrize(("entry", "warned"), [("", True), ('hold = "zoh"\n', False), ('hold = "linear"\n', False)])
def test_a_staircase_torque_read_linearly_by_default_is_warned(tmp_path, entry, warned):
    """A torque column in runs of equal samples (a command held by a 50 Hz controller,
    logged at 100 Hz) read linearly only because nothing was declared: a warning that
    names the column and `hold = "zoh"`; none once the hold is declared either way, and
    none for a column that changes at every sample (`write_log`'s cosines)."""
    path = tmp_path / "logs" / "drop.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = ["time [s],theta1 [deg],torque1 [N m]"]
    rows += [f"{0.01 * k:.2f},{math.cos(0.01 * k):.6f},{0.1 * ((k // 2) % 3):.3f}" for k in range(20)]
    path.write_text("\n".join(rows) + "\n")
    exp = load_experiment(experiment(tmp_path, RIG + DRIVEN + entry, log=False))
    text = exp.summary()
    assert ("torque1 is piecewise constant (53 % of consecutive samples equal)" in text) is warned, text
    assert ('declare hold = "zoh"' in text) is warned
    write_log(path, header=("time [s]", "theta1 [deg]", "torque1 [N m]"))
    assert "piecewise constant" not in load_experiment(experiment(tmp_path, RIG + DRIVEN, log=False)).summary()
