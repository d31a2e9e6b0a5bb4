"""Log loading (`identify.logs`): unit conversion, .mat files, and a clear error for each
kind of malformed log (file, line, column or variable, and what was expected)."""

import math
import os
import re
import sys
import warnings

import numpy as np
import pytest
import scipy.io

from identify._data.columns import Calibration, LogError
from identify._data.logs import load_log


def msg(*parts: str) -> str:
    """A `match` pattern requiring every fragment, in order."""
    return "(?s)" + ".*".join(re.escape(p) for p in parts)


def write_csv(path, header, rows, comments=(), delimiter=","):
    lines = [f"# {c}" for c in comments] + [delimiter.join(header)]
    lines += [delimiter.join(str(c) for c in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def samples(n=20, dt=0.01):
    t = np.arange(n) * dt
    return t, np.sin(t), 0.5 * np.cos(t)


def good_rows(n=20):
    t, a, b = samples(n)
    return [[f"{ti:.4f}", f"{ai:.6f}", f"{bi:.6f}"] for ti, ai, bi in zip(t, a, b)]


HEADER = ["time [s]", "theta1 [deg]", "tip1 [mm]"]
COLUMNS = {"time": "time [s]", "theta1": "theta1 [deg]", "tip1": "tip1 [mm]"}


# ---------------------------------------------------------------------------
# Valid logs
# ---------------------------------------------------------------------------


def test_a_header_without_rows_is_an_error_naming_the_file(tmp_path):
    # review: an IndexError from inside the loader
    path = write_csv(tmp_path / "empty.csv", HEADER, [])
    with pytest.raises(LogError, match=msg("empty.csv", "no data rows after the header on line 1")):
        load_log(path, COLUMNS)


def test_a_last_row_cut_off_mid_write_is_warned_about(tmp_path):
    """Review: `1.9950,-51.` (the write interrupted inside -51.90) loaded as -51.0 without a
    word. A file that merely lacks the final newline is not warned about."""
    rows = good_rows()
    path = tmp_path / "cut.csv"
    text = "\n".join([",".join(HEADER)] + [",".join(r) for r in rows])
    path.write_text(text[:-3])  # cut inside the last number, no final newline
    with pytest.warns(UserWarning, match=msg("cut.csv, line 21", "ends without a newline", "cut off mid-write")):
        load_log(path, COLUMNS)
    path.write_text(text)  # complete, no final newline: quiet
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(load_log(path, COLUMNS).t) == 20
        # a short last row in a file that ends with its newline is complete (the real
        # single pendulum's vad1.csv ends '55,3.17389,-1.928')
        path.write_text(text[:-3] + "\n")
        assert len(load_log(path, COLUMNS).t) == 20


def test_a_last_row_cut_off_before_its_last_cell_says_so(tmp_path):
    # review: the cell-count error gave no hint that the write was cut off
    text = "\n".join([",".join(HEADER)] + [",".join(r) for r in good_rows()])
    path = tmp_path / "cut.csv"
    path.write_text(text[: text.rindex(",")])  # cut at the last row's second comma, no final newline
    with pytest.raises(LogError, match=msg("cut.csv, line 21: 2 cells; expected 3", "may have been cut off mid-write")):
        load_log(path, COLUMNS)
    path.write_text(text[: text.rindex(",")] + "\n")  # a short row followed by a newline: no such hint
    with pytest.raises(LogError, match=r"2 cells; expected 3 like the header on line 1$"):
        load_log(path, COLUMNS)


def test_an_angle_labelled_radians_reaching_many_turns_is_warned_about(tmp_path):
    """Review: degrees labelled [rad] (87-273 "rad") loaded without a word; the fit failed
    minutes later. The spinning-link example's 7 turns stay quiet."""
    t = np.arange(20) * 0.01
    rows = [[f"{ti:.4f}", f"{d:.6f}", "0.0"] for ti, d in zip(t, np.linspace(87.0, 273.0, 20))]
    path = write_csv(tmp_path / "deg.csv", ["time [s]", "theta1 [rad]", "tip1 [mm]"], rows)
    with pytest.warns(UserWarning, match=msg("deg.csv, column 2 ('theta1 [rad]')", "273 rad (43.4 turns)", "[deg]")):
        load_log(path)
    rows = [[f"{ti:.4f}", f"{d:.6f}", "0.0"] for ti, d in zip(t, np.linspace(0.0, 7 * 2 * np.pi, 20))]
    path = write_csv(tmp_path / "spin.csv", ["time [s]", "theta1 [rad]", "tip1 [mm]"], rows)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_log(path)


def test_csv_units_converted_to_si(tmp_path):
    path = write_csv(tmp_path / "drop.csv", HEADER + ["torque1 [N mm]"], [r + ["250"] for r in good_rows()], ["a"])
    log = load_log(path, {**COLUMNS, "torque1": "torque1 [N mm]"})
    t, a, b = samples()
    assert log.name == "drop" and log.path == path and len(log) == 20
    assert log.t.dtype == np.float64
    np.testing.assert_allclose(log.t, np.round(t, 4), rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.outputs["theta1"], np.deg2rad(np.round(a, 6)), rtol=1e-12)
    np.testing.assert_allclose(log.outputs["tip1"], 1e-3 * np.round(b, 6), rtol=1e-12)
    np.testing.assert_allclose(log.inputs["torque1"], 0.25, rtol=1e-12)
    assert set(log.outputs) == {"theta1", "tip1"} and set(log.inputs) == {"torque1"}
    with pytest.raises(ValueError):
        log.t[0] = 1.0  # read-only


def test_an_absolute_millisecond_clock_keeps_its_intervals_exact(tmp_path):
    """Found in review: a DAQ clock in ms since 1970 (~1.7e12), scaled to seconds before
    the first sample was subtracted, kept ~2e-7 s of resolution: a 500 Hz log read as
    intervals of 0.00199986-0.00200009 s. The relative times are differenced in ms first."""
    start = 1_733_300_000_000  # ms since 1970
    rows = [[str(start + 2 * k), "1.0", "2.0"] for k in range(400)]
    log = load_log(write_csv(tmp_path / "daq.csv", ["time [ms]", "theta1 [deg]", "tip1 [mm]"], rows))
    assert np.array_equal(log.t_relative, 2e-3 * np.arange(400))  # exact: integers times 1e-3
    # intervals to rounding (before: 1e-4 relative)
    assert log.sampling.min_dt == pytest.approx(2e-3, rel=1e-12) and log.sampling.max_dt == pytest.approx(
        2e-3, rel=1e-12
    )
    assert log.t[0] == pytest.approx(start * 1e-3, rel=1e-15)  # absolute, as in the file


def test_header_mapping_by_default_and_absolute_time(tmp_path):
    rows = [[f"{100 + 0.001 * k:.3f}", "1.0", "2.0", "ok"] for k in range(12)]
    path = write_csv(tmp_path / "a.csv", ["time [ms]", "theta1 [mrad]", "tip1 [um]", "status"], rows)
    log = load_log(path)
    np.testing.assert_allclose(log.t[0], 0.1, rtol=1e-12)  # absolute, as in the file
    np.testing.assert_allclose(log.t_relative, 1e-6 * np.arange(12), atol=1e-15)
    np.testing.assert_allclose(log.outputs["theta1"], 1e-3)
    np.testing.assert_allclose(log.outputs["tip1"], 2e-6)
    assert log.ignored == ("status",)
    assert "ignored: status" in log.summary()


def test_semicolon_with_decimal_comma(tmp_path):
    rows = [[f"{0.01 * k:.2f}".replace(".", ","), "1,5", "2"] for k in range(10)]
    path = write_csv(tmp_path / "eu.csv", ["time [s]", "theta1 [deg]", "tip1 [mm]"], rows, delimiter=";")
    log = load_log(path, COLUMNS, decimal=",")
    np.testing.assert_allclose(log.t, 0.01 * np.arange(10), atol=1e-15)
    np.testing.assert_allclose(log.outputs["theta1"], math.radians(1.5))


def test_a_comma_in_a_number_is_never_read_by_guess(tmp_path):
    """Review: `1,234` in a `;`-separated file was read as 1.234 without a word, a thousands
    separator taken for a decimal comma. A decimal comma is read only where the log says so
    (`decimal = ","`); a thousands separator is never read, with either decimal mark."""
    rows = [[f"{0.01 * k:.2f}", "1.5", "2"] for k in range(10)]
    rows[3][1] = "1,234"
    path = write_csv(tmp_path / "eu.csv", HEADER, rows, delimiter=";")
    with pytest.raises(
        LogError,
        match=msg(
            "eu.csv, line 5, column 2 ('theta1 [deg]'): expected a number, got '1,234': a decimal comma (1.234) or a "
            "thousands separator (1234)?",
            'decimal = "," in its [[logs]] entry',
        ),
    ):
        load_log(path, COLUMNS)
    with pytest.raises(LogError, match=msg("eu.csv, line 2, column 1", "got '0.00'", "decimal commas", "'.'")):
        load_log(path, COLUMNS, decimal=",")  # (the file writes decimal points)
    for cell, decimal, fix in [("1,234.5", ".", "'1234.5'"), ("1.234,5", ",", "'1234,5'"), ("1 234", ".", "'1234'")]:
        rows = [[f"{0.01 * k:.2f}".replace(".", decimal), "1", "2"] for k in range(10)]
        rows[6][2] = cell
        path = write_csv(tmp_path / "sep.csv", HEADER, rows, delimiter=";")
        with pytest.raises(LogError, match=msg("sep.csv, line 8, column 3", f"got {cell!r}", "thousands", fix)):
            load_log(path, COLUMNS, decimal=decimal)
    path = write_csv(tmp_path / "commas.csv", HEADER, good_rows())
    with pytest.raises(LogError, match=msg("commas.csv, line 1", 'decimal = ","', "separated by commas", "semicolons")):
        load_log(path, COLUMNS, decimal=",")
    with pytest.raises(LogError, match=msg("commas.csv", "decimal = ';'", 'expected "." or ","')):
        load_log(path, COLUMNS, decimal=";")


def test_an_underscore_in_a_number_is_an_error(tmp_path):
    """Review: `-16_6.9411` was read as -166.9411 (Python's float takes underscores between
    digits)."""
    rows = good_rows()
    rows[7][1] = "-16_6.9411"
    path = write_csv(tmp_path / "under.csv", HEADER, rows)
    with pytest.raises(
        LogError,
        match=msg(
            "under.csv, line 9, column 2 ('theta1 [deg]'): expected a number, got '-16_6.9411': an underscore is "
            "not part of a number"
        ),
    ):
        load_log(path, COLUMNS)


def test_volts_with_calibration(tmp_path):
    rows = [[f"{0.01 * k:.2f}", "0", f"{0.1 * k:.1f}"] for k in range(10)]
    path = write_csv(tmp_path / "v.csv", ["time [s]", "theta1 [rad]", "gauge [V]"], rows)
    columns = {"time": "time [s]", "theta1": "theta1 [rad]", "tip1": "gauge [V]"}
    log = load_log(path, columns, calibration={"tip1": {"scale": 0.0125, "offset": 0.001}})
    np.testing.assert_allclose(log.outputs["tip1"], 0.0125 * 0.1 * np.arange(10) + 0.001, rtol=1e-12)
    # a calibration in mm per volt
    log = load_log(path, columns, calibration={"tip1": Calibration(scale=12.5, unit="mm")})
    np.testing.assert_allclose(log.outputs["tip1"], 0.0125 * 0.1 * np.arange(10), rtol=1e-12, atol=1e-15)


def test_motor_side_columns_referred_to_the_link_side_by_the_gear_ratio(tmp_path):
    """A motor encoder and a motor torque behind a gear of ratio G (motor turns per link
    turn): the link-side angle is the motor angle / G, the link-side torque G x the motor
    torque (power through an ideal gear: tau_m omega_m = tau_l omega_l). A volt column's
    scale and offset apply first, on the motor side."""
    motor_deg = 700.0 * np.sin(np.arange(10.0))
    motor_mNm = 12.0 * np.cos(np.arange(10.0))
    volts = 0.5 * np.arange(10.0)
    rows = [
        [f"{0.01 * k:.2f}", repr(float(motor_deg[k])), repr(float(motor_mNm[k])), repr(float(volts[k]))]
        for k in range(10)
    ]
    header = ["time [s]", "motor [deg]", "tau_m [mN m]", "current [V]"]
    path = write_csv(tmp_path / "m.csv", header, rows)
    columns = {"time": "time [s]", "alpha1": "motor [deg]", "torque1": "tau_m [mN m]"}
    log = load_log(path, columns, calibration={"alpha1": {"gear_ratio": 70}, "torque1": Calibration(gear_ratio=70.0)})
    np.testing.assert_allclose(log.outputs["alpha1"], np.radians(motor_deg) / 70.0, rtol=1e-12)
    np.testing.assert_allclose(log.inputs["torque1"], 70.0 * 1e-3 * motor_mNm, rtol=1e-12)
    # power balance through the ideal gear, sample by sample
    omega_m = np.gradient(np.radians(motor_deg), log.t)
    omega_l = np.gradient(log.outputs["alpha1"], log.t)
    np.testing.assert_allclose(1e-3 * motor_mNm * omega_m, log.inputs["torque1"] * omega_l, rtol=1e-12)
    assert "gear ratio 70: motor side to link side" in log.sources["alpha1"]
    # a reversing gear; a rigid joint's motor encoder (theta); a motor current amplifier in
    # volts: 0.02 N m per volt (k_t x amplifier gain) on the motor side, then x G
    columns = {"time": "time [s]", "theta1": "motor [deg]", "torque1": "current [V]"}
    cal = {"theta1": {"gear_ratio": -50}, "torque1": {"scale": 0.02, "offset": 0.001, "gear_ratio": 50}}
    log = load_log(path, columns, calibration=cal)
    np.testing.assert_allclose(log.outputs["theta1"], -np.radians(motor_deg) / 50.0, rtol=1e-12)
    np.testing.assert_allclose(log.inputs["torque1"], 50.0 * (0.02 * volts + 0.001), rtol=1e-12)
    assert log.sources["torque1"].endswith("(calibrated, gear ratio 50: motor side to link side)")


def test_gear_ratio_errors(tmp_path):
    rows = [[f"{0.01 * k:.2f}", "1.0", "2.0"] for k in range(10)]
    path = write_csv(tmp_path / "g.csv", ["time [s]", "motor [deg]", "gauge [mm]"], rows)
    columns = {"time": "time [s]", "theta1": "motor [deg]", "tip1": "gauge [mm]"}
    for channel, spec, expected in (
        ("tip1", {"gear_ratio": 10}, ("calibration.tip1.gear_ratio", "theta<i>, alpha<i> or torque<i>", "not tip1")),
        ("theta1", {"gear_ratio": 0}, ("calibration.theta1.gear_ratio", "a non-zero number", "got 0")),
        ("theta1", {"gear_ratio": "70:1"}, ("calibration.theta1.gear_ratio", "got '70:1'")),
        ("theta1", {"gear_ratio": 70, "offset": 1.0}, ("calibration.theta1", "an offset without a scale")),
        ("theta1", {"gear_ratio": 70, "unit": "deg"}, ("calibration.theta1.unit", "no scale is given")),
        ("theta1", {"ratio": 70}, ("calibration.theta1", "unknown key(s) ['ratio']", "gear_ratio")),
        # a volt scale on a column in degrees: it would convert twice; the gear alone is the way
        (
            "theta1",
            {"scale": 2.0, "gear_ratio": 70},
            ("column 2", "scale is given for theta1", "not [V]", "a gear_ratio alone"),
        ),
    ):
        with pytest.raises(LogError, match=msg(*expected)):
            load_log(path, columns, calibration={channel: spec})


def test_a_reversed_column_is_read_negated_in_any_unit(tmp_path):
    """`sign = -1` negates the channel's value last, after every other conversion: a
    column in mm (no scale allowed there), a volt column after its scale and offset, a
    motor encoder after its gear ratio, in a CSV and in a .mat log."""
    t, a, b = samples(15)
    volts = 0.4 * np.arange(15.0)
    rows = [
        [f"{ti:.4f}", repr(float(np.rad2deg(ai))), repr(float(1e3 * bi)), repr(float(v))]
        for ti, ai, bi, v in zip(t, a, b, volts)
    ]
    path = write_csv(tmp_path / "r.csv", ["time [s]", "enc [deg]", "gauge [mm]", "bridge [V]"], rows)
    columns = {"time": "time [s]", "theta1": "enc [deg]", "tip1": "gauge [mm]"}
    log = load_log(path, columns, calibration={"tip1": {"sign": -1}, "theta1": {"gear_ratio": 4, "sign": -1}})
    np.testing.assert_allclose(log.outputs["tip1"], -b, rtol=1e-13)
    np.testing.assert_allclose(log.outputs["theta1"], -a / 4.0, rtol=1e-13)
    assert log.sources["tip1"] == "column 3 'gauge [mm]' (sign reversed)"
    assert log.sources["theta1"].endswith("(gear ratio 4: motor side to link side, sign reversed)")
    columns["tip1"] = "bridge [V]"
    log = load_log(path, columns, calibration={"tip1": Calibration(scale=12.5, offset=0.5, unit="mm", sign=-1.0)})
    np.testing.assert_allclose(log.outputs["tip1"], -1e-3 * (12.5 * volts + 0.5), rtol=1e-13)
    # sign = 1 is the column as recorded
    log = load_log(path, {"time": "time [s]", "tip1": "gauge [mm]"}, calibration={"tip1": {"sign": 1}})
    np.testing.assert_allclose(log.outputs["tip1"], b, rtol=1e-13)
    mat = tmp_path / "r.mat"
    scipy.io.savemat(mat, {"t": t, "gauge": 1e3 * b})
    log = load_log(mat, {"time": "t [s]", "tip1": "gauge [mm]"}, calibration={"tip1": {"sign": -1}})
    np.testing.assert_allclose(log.outputs["tip1"], -b, rtol=1e-13)


@pytest.mark.parametrize("sign", [2, -2, 0, -1.5, True, "-1", "reversed"])
def test_a_sign_other_than_minus_one_or_one_is_an_error(tmp_path, sign):
    path = write_csv(tmp_path / "s.csv", HEADER, good_rows())
    with pytest.raises(LogError, match=msg("calibration.tip1.sign", "expected -1", "or 1", f"got {sign!r}")):
        load_log(path, COLUMNS, calibration={"tip1": {"sign": sign}})
    with pytest.raises(LogError, match=msg("calibration.time", "measured channels, not 'time'")):
        load_log(path, COLUMNS, calibration={"time": {"sign": -1}})


def test_strain_gauge_columns_become_root_curvature(tmp_path):
    """A root strain gauge read in microstrain (or in volts with a bridge calibration to
    microstrain) maps to `curvature1` through its distance `c` from the neutral axis:
    Euler-Bernoulli bending strain is `epsilon = c * kappa` (the surface of a strip of
    thickness 2c), so kappa = 1e-6 * reading / c."""
    ue = 25.0 * np.sin(np.arange(10.0))
    rows = [[f"{0.01 * k:.2f}", "0", repr(float(ue[k])), repr(float(ue[k] / 500.0))] for k in range(10)]
    path = write_csv(tmp_path / "sg.csv", ["time [s]", "theta1 [rad]", "gauge [ue]", "bridge [V]"], rows)
    columns = {"time": "time [s]", "theta1": "theta1 [rad]", "curvature1": "gauge [ue]"}
    log = load_log(path, columns, calibration={"curvature1": {"neutral_axis_distance": "1 mm"}})
    np.testing.assert_allclose(log.outputs["curvature1"], 1e-6 * ue / 1e-3, rtol=1e-12)
    assert (
        log.sources["curvature1"] == "column 3 ('gauge [ue]') (calibrated)" or "gauge [ue]" in log.sources["curvature1"]
    )
    # the bridge's volts: 500 ue per volt, then over the same distance
    columns["curvature1"] = "bridge [V]"
    cal = Calibration(scale=500.0, unit="ue", neutral_axis_distance=1e-3)
    log = load_log(path, columns, calibration={"curvature1": cal})
    np.testing.assert_allclose(log.outputs["curvature1"], 1e-6 * ue / 1e-3, rtol=1e-12)
    # other spellings of microstrain
    for spelling in ("µε", "microstrain"):
        p2 = write_csv(
            tmp_path / f"sg_{spelling}.csv", ["time [s]", "theta1 [rad]", f"gauge [{spelling}]"], [r[:3] for r in rows]
        )
        columns["curvature1"] = f"gauge [{spelling}]"
        log = load_log(p2, columns, calibration={"curvature1": {"neutral_axis_distance": 0.002}})
        np.testing.assert_allclose(log.outputs["curvature1"], 1e-6 * ue / 2e-3, rtol=1e-12)


def test_strain_gauge_column_errors(tmp_path):
    rows = [[f"{0.01 * k:.2f}", "0", "1.0"] for k in range(10)]
    path = write_csv(tmp_path / "sg.csv", ["time [s]", "theta1 [rad]", "gauge [ue]"], rows)
    columns = {"time": "time [s]", "theta1": "theta1 [rad]", "curvature1": "gauge [ue]"}
    with pytest.raises(
        LogError, match=msg("column 3", "curvature1 is a curvature", "a strain", "neutral_axis_distance")
    ):
        load_log(path, columns)
    with pytest.raises(LogError, match=msg("column 3", "scale is given for curvature1", "only neutral_axis_distance")):
        load_log(path, columns, calibration={"curvature1": {"scale": 2.0, "neutral_axis_distance": 1e-3}})
    with pytest.raises(LogError, match=msg("column 3", "tip1 is a length but [ue] is a strain unit")):
        load_log(path, {"time": "time [s]", "theta1": "theta1 [rad]", "tip1": "gauge [ue]"})
    with pytest.raises(LogError, match=msg("column 3", "curvature1 is a curvature but [deg]", "or a strain ([ue]")):
        load_log(
            write_csv(tmp_path / "d.csv", ["time [s]", "theta1 [rad]", "gauge [deg]"], rows),
            {"time": "time [s]", "theta1": "theta1 [rad]", "curvature1": "gauge [deg]"},
        )
    for spec, expected in (
        ({"neutral_axis_distance": 0.0}, "expected a distance > 0"),
        ({"neutral_axis_distance": "1 deg"}, "expected a length"),
        ({"neutral_axis_distance": 1e-3, "offset": 1.0}, "an offset without a scale"),
        ({"scale": 500.0, "unit": "mm", "neutral_axis_distance": 1e-3}, "[mm] is not a strain unit"),
    ):
        with pytest.raises(LogError, match=msg(expected)):
            load_log(path, columns, calibration={"curvature1": spec})
    # a curvature column already in 1/m: the distance would divide it a second time
    with pytest.raises(LogError, match=msg("column 3", "neutral_axis_distance is given for curvature1", "[1/m]")):
        load_log(
            write_csv(tmp_path / "k.csv", ["time [s]", "theta1 [rad]", "gauge [1/m]"], rows),
            {"time": "time [s]", "theta1": "theta1 [rad]", "curvature1": "gauge [1/m]"},
            calibration={"curvature1": {"neutral_axis_distance": 1e-3}},
        )
    with pytest.raises(
        LogError, match=msg("neutral_axis_distance", "applies to a strain gauge's curvature<i>", "tip1")
    ):
        load_log(path, columns, calibration={"tip1": {"neutral_axis_distance": 1e-3}})
    # a noise level in microstrain (experiment files' [noise]) says how to write it
    from identify._data import units

    with pytest.raises(ValueError, match=msg("'2 ue' is a strain; expected a curvature", "'0.002 1/m'")):
        units.parse_quantity("2 ue", units.CURVATURE)


def test_non_uniform_sampling_and_gap_accepted(tmp_path):
    t = np.concatenate([np.arange(10) * 0.01, 0.5 + np.arange(10) * 0.01, [0.6005, 0.6103]])
    rows = [[f"{ti:.4f}", "0", "0"] for ti in t]
    log = load_log(write_csv(tmp_path / "gap.csv", HEADER, rows), COLUMNS)
    s = log.sampling
    assert s.n_samples == 22 and not s.uniform and s.n_gaps == 1
    np.testing.assert_allclose(s.median_dt, 0.01, rtol=1e-9)
    np.testing.assert_allclose(s.max_dt, 0.41, rtol=1e-9)
    np.testing.assert_allclose(s.largest_gap_at, 0.09, rtol=1e-9)
    np.testing.assert_allclose(s.duration, 0.6103, rtol=1e-12)
    assert "largest 0.41 s at t = 0.09 s" in str(s)


def test_a_gap_of_an_hour_is_an_error_naming_both_sides(tmp_path):
    """Review: an hour's gap in a 200 Hz log passed `identify check` with a note, and the fit
    would integrate the model across it. A gap longer than 1000 median intervals and 1 s is
    an error naming the lines and times on both sides; dropped samples stay a note."""
    t = np.concatenate([np.arange(2000) * 0.005, 3609.995 + np.arange(2000) * 0.005])
    rows = [[f"{ti:.3f}", "0", "0"] for ti in t]
    path = write_csv(tmp_path / "hour.csv", HEADER, rows)
    with pytest.raises(
        LogError,
        match=msg(
            "hour.csv, line 2002, column 1 ('time [s]'): a gap of 3600 s in the time stamps (t = 9.995 s at line "
            "2001, column 1 ('time [s]'), then t = 3609.995 s), 7.2e+05 times the median interval 0.005 s",
            "integrate the model across it",
            "Split the log into two logs at this sample",
        ),
    ):
        load_log(path, COLUMNS)
    mat = tmp_path / "hour.mat"
    scipy.io.savemat(mat, {"t": t, "enc": np.zeros_like(t)})
    with pytest.raises(LogError, match=msg("hour.mat", "variable 't', sample 2001", "a gap of 3600 s", "Split")):
        load_log(mat, {"time": "t [s]", "theta1": "enc [deg]"})


@pytest.mark.parametrize(
    ("dt", "gap", "refused"),
    [
        (0.005, 0.5, False),  # 100 intervals: dropped samples
        (0.005, 4.9, False),  # 980 intervals
        (0.005, 5.2, True),  # 1040 intervals, 5.2 s
        (1e-4, 0.5, False),  # 5000 intervals of a 10 kHz log, but 0.5 s
        (1e-4, 1.5, True),
        (1.0, 120.0, False),  # a 1 Hz log: 120 intervals
    ],
)
def test_only_a_gap_long_in_intervals_and_in_seconds_is_refused(tmp_path, dt, gap, refused):
    t = np.concatenate([np.arange(50) * dt, 49 * dt + gap + np.arange(50) * dt])
    rows = [[f"{ti:.6f}", "0", "0"] for ti in t]
    path = write_csv(tmp_path / "gap.csv", HEADER, rows)
    if refused:
        with pytest.raises(LogError, match=msg("gap.csv, line 52, column 1", f"a gap of {gap:g} s")):
            load_log(path, COLUMNS)
    else:
        assert load_log(path, COLUMNS).sampling.n_gaps == 1


def test_mat_log(tmp_path):
    t, a, b = samples(15)
    path = tmp_path / "run.mat"
    scipy.io.savemat(path, {"t": t, "enc": np.rad2deg(a)[:, None], "gauge": b * 1e3, "extra": np.ones(3)})
    log = load_log(path, {"time": "t [s]", "theta1": "enc [deg]", "tip1": "gauge [mm]"})
    np.testing.assert_allclose(log.t, t, rtol=0, atol=0)
    np.testing.assert_allclose(log.outputs["theta1"], a, rtol=1e-13)
    np.testing.assert_allclose(log.outputs["tip1"], b, rtol=1e-13)
    assert log.ignored == ("extra",)


# ---------------------------------------------------------------------------
# Malformed CSV logs
# ---------------------------------------------------------------------------


def test_missing_column(tmp_path):
    path = write_csv(tmp_path / "m.csv", ["time [s]", "theta1 [deg]"], [r[:2] for r in good_rows()])
    with pytest.raises(LogError, match=msg("m.csv, line 1", "no column 'tip1'", "columns.tip1", "theta1")):
        load_log(path, COLUMNS)


def test_missing_time_column(tmp_path):
    path = write_csv(tmp_path / "nt.csv", ["t [s]", "theta1 [deg]", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("nt.csv, line 1", "no 'time' column", "time [s]")):
        load_log(path)
    with pytest.raises(LogError, match=msg("nt.csv", "columns", "no 'time' entry")):
        load_log(path, {"theta1": "theta1 [deg]"})


def test_extra_columns_strict(tmp_path):
    rows = [r + ["1"] for r in good_rows()]
    path = write_csv(tmp_path / "x.csv", HEADER + ["temp [s]"], rows, ["c1", "c2"])
    assert load_log(path, COLUMNS).ignored == ("temp [s]",)
    with pytest.raises(LogError, match=msg("x.csv, line 3", "['temp [s]']", "not mapped", "strict = true")):
        load_log(path, COLUMNS, strict=True)


def test_unknown_unit(tmp_path):
    path = write_csv(tmp_path / "u.csv", ["time [s]", "theta1 [grad]", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("u.csv, line 1, column 2", "unknown unit [grad]", "[deg]", "[N mm]")):
        load_log(path, {"time": "time [s]", "theta1": "theta1", "tip1": "tip1"})


def test_wrong_dimension(tmp_path):
    path = write_csv(tmp_path / "d.csv", ["time [s]", "theta1 [deg]", "tip1 [deg]"], good_rows())
    with pytest.raises(LogError, match=msg("d.csv, line 1, column 3 ('tip1 [deg]')", "tip1 is a length", "[mm]")):
        load_log(path)


def test_missing_unit(tmp_path):
    path = write_csv(tmp_path / "nu.csv", ["time [s]", "theta1", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("nu.csv, line 1, column 2", "no unit", "theta1 [rad]")):
        load_log(path, {"time": "time", "theta1": "theta1", "tip1": "tip1"})


def test_a_unit_in_parentheses_is_pointed_at_square_brackets(tmp_path):
    # found in review: 'enc (deg)' got the suggestion "e.g. 'enc (deg) [rad]'"
    path = write_csv(tmp_path / "p.csv", ["time [s]", "enc (deg)", "tip1 [mm]"], good_rows())
    with pytest.raises(
        LogError, match=msg("p.csv, line 1, column 2", "square brackets", "'enc [deg]', not 'enc (deg)'")
    ):
        load_log(path, {"time": "time [s]", "theta1": "enc (deg)", "tip1": "tip1 [mm]"})
    wrong = write_csv(tmp_path / "w.csv", ["time [s]", "theta1 [mm]", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("theta1 is an angle but [mm] is a length unit")):
        load_log(wrong)


@pytest.mark.parametrize("typo", ["tip_1", "Tip1", "TIP 1"])
def test_a_header_that_misspells_a_channel_is_an_error(tmp_path, typo):
    """Found in review: with the header naming the channels, 'tip_1 [mm]' was ignored as an
    unused column and the log's tip gauge dropped in silence."""
    path = write_csv(
        tmp_path / "t.csv", ["time [s]", "theta1 [deg]", f"{typo} [mm]", "status"], [r + ["1"] for r in good_rows()]
    )
    with pytest.raises(
        LogError, match=msg("t.csv, line 1, column 3", f"'{typo} [mm]' is not a channel name", "'tip1'")
    ):
        load_log(path)
    # an unrelated extra column is still ignored and listed
    ok = write_csv(
        tmp_path / "ok.csv", ["time [s]", "theta1 [deg]", "tip1 [mm]", "status"], [r + ["1"] for r in good_rows()]
    )
    assert load_log(ok).ignored == ("status",)


def test_mapping_unit_disagrees_with_header(tmp_path):
    path = write_csv(tmp_path / "dis.csv", HEADER, good_rows())
    with pytest.raises(LogError, match=msg("dis.csv, line 1, column 2", "[deg]", "theta1 [rad]", "agree")):
        load_log(path, {**COLUMNS, "theta1": "theta1 [rad]"})


def test_malformed_header_cell(tmp_path):
    path = write_csv(tmp_path / "h.csv", ["time [s]", "theta1 [deg", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("h.csv, line 1, column 2", "expected 'name [unit]'")):
        load_log(path, COLUMNS)


def test_duplicate_header(tmp_path):
    path = write_csv(tmp_path / "dup.csv", ["time [s]", "tip1 [deg]", "tip1 [mm]"], good_rows())
    with pytest.raises(LogError, match=msg("dup.csv, line 1", "columns 2 and 3", "'tip1'")):
        load_log(path, COLUMNS)


def test_non_numeric_cell(tmp_path):
    rows = good_rows()
    rows[4][2] = "n/a"
    path = write_csv(tmp_path / "nn.csv", HEADER, rows, ["comment"])
    # comment on line 1, header on line 2, rows[4] on line 7
    with pytest.raises(LogError, match=msg("nn.csv, line 7, column 3 ('tip1 [mm]')", "expected a number", "'n/a'")):
        load_log(path, COLUMNS)


def test_empty_cell(tmp_path):
    rows = good_rows()
    rows[0][1] = ""
    path = write_csv(tmp_path / "e.csv", HEADER, rows)
    with pytest.raises(LogError, match=msg("e.csv, line 2, column 2", "expected a number, got an empty cell")):
        load_log(path, COLUMNS)


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-inf"])
def test_nan_or_inf_sample(tmp_path, bad):
    rows = good_rows()
    rows[9][1] = bad
    path = write_csv(tmp_path / "nan.csv", HEADER, rows)
    with pytest.raises(LogError, match=msg("nan.csv, line 11, column 2", "in theta1", "expected a finite number")):
        load_log(path, COLUMNS)


def test_time_not_increasing(tmp_path):
    rows = good_rows()
    rows[5][0], rows[6][0] = rows[6][0], rows[5][0]
    path = write_csv(tmp_path / "back.csv", HEADER, rows)
    with pytest.raises(LogError, match=msg("back.csv, line 8, column 1", "time goes backwards", "line 7", "strictly")):
        load_log(path, COLUMNS)


def test_duplicate_time_stamp(tmp_path):
    rows = good_rows()
    rows[3][0] = rows[2][0]
    path = write_csv(tmp_path / "dupt.csv", HEADER, rows)
    with pytest.raises(LogError, match=msg("dupt.csv, line 5", "duplicate time stamp", "line 4")):
        load_log(path, COLUMNS)


def test_too_short(tmp_path):
    path = write_csv(tmp_path / "short.csv", HEADER, good_rows(5))
    with pytest.raises(LogError, match=msg("short.csv", "5 samples", "at least 10")):
        load_log(path, COLUMNS)
    assert len(load_log(path, COLUMNS, min_samples=5)) == 5


def test_ragged_row(tmp_path):
    rows = good_rows()
    rows[2] = rows[2][:2]
    path = write_csv(tmp_path / "rag.csv", HEADER, rows)
    with pytest.raises(LogError, match=msg("rag.csv, line 4", "2 cells", "expected 3", "header on line 1")):
        load_log(path, COLUMNS)


def test_empty_file(tmp_path):
    path = tmp_path / "empty.csv"
    path.write_text("# only a comment\n\n")
    with pytest.raises(LogError, match=msg("empty.csv", "no header row")):
        load_log(path, COLUMNS)


def test_volts_need_calibration(tmp_path):
    path = write_csv(tmp_path / "v.csv", ["time [s]", "theta1 [rad]", "gauge [V]"], good_rows())
    columns = {"time": "time [s]", "tip1": "gauge [V]"}
    with pytest.raises(LogError, match=msg("v.csv, line 1, column 3", "tip1 is in [V]", "needs a calibration")):
        load_log(path, columns)
    columns = {"time": "time [s]", "theta1": "theta1"}
    with pytest.raises(LogError, match=msg("column 2", "calibration scale is given for theta1", "not [V]")):
        load_log(path, columns, calibration={"theta1": {"scale": 2.0}})


def test_bad_channel_name_in_mapping(tmp_path):
    path = write_csv(tmp_path / "c.csv", HEADER, good_rows())
    with pytest.raises(LogError, match=msg("c.csv", "columns.tipp1", "not a channel", "tip{i}")):
        load_log(path, {"time": "time [s]", "tipp1": "tip1 [mm]"})


def test_missing_file_and_unknown_type(tmp_path):
    with pytest.raises(LogError, match=msg(str(tmp_path / "nope.csv"), "does not exist")):
        load_log(tmp_path / "nope.csv", COLUMNS)
    path = tmp_path / "log.xlsx"
    path.write_bytes(b"PK")
    with pytest.raises(LogError, match=msg("log.xlsx", "unknown log type '.xlsx'", ".csv", ".mat")):
        load_log(path, COLUMNS)


def test_a_log_path_that_is_not_a_file_says_what_it_is(tmp_path):
    """Review: a directory or a named pipe read as "does not exist", a symbolic link loop
    escaped as RuntimeError; a pipe is never opened (reading it would block)."""
    (tmp_path / "dir.csv").mkdir()
    (tmp_path / "loop.csv").symlink_to(tmp_path / "loop.csv")
    (tmp_path / "dangling.csv").symlink_to(tmp_path / "gone.csv")
    cases = [
        ("dir.csv", "is a directory"),
        ("loop.csv", "is a symbolic link loop"),
        ("dangling.csv", "is a broken symbolic link"),
    ]
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.csv")
        cases.append(("pipe.csv", "is not a regular file (a named pipe (FIFO))"))
    for name, what in cases:
        with pytest.raises(LogError, match=msg(str(tmp_path / name), f"log file {what}", "expected a .csv or .mat")):
            load_log(tmp_path / name, COLUMNS)


# ---------------------------------------------------------------------------
# Malformed .mat logs
# ---------------------------------------------------------------------------

MAT_COLUMNS = {"time": "t [s]", "theta1": "enc [deg]"}


def save_mat(path, **variables):
    scipy.io.savemat(path, variables)
    return path


def test_mat_needs_mapping_with_units(tmp_path):
    path = save_mat(tmp_path / "a.mat", t=np.arange(12.0), enc=np.zeros(12))
    with pytest.raises(LogError, match=msg("a.mat", "needs a column mapping", "enc [deg]")):
        load_log(path)
    with pytest.raises(LogError, match=msg("a.mat: variable 'enc'", "no unit", "enc [rad]")):
        load_log(path, {"time": "t [s]", "theta1": "enc"})


def test_mat_missing_variable(tmp_path):
    path = save_mat(tmp_path / "b.mat", t=np.arange(12.0), encoder=np.zeros(12))
    with pytest.raises(LogError, match=msg("b.mat", "no variable 'enc'", "columns.theta1", "['encoder', 't']")):
        load_log(path, MAT_COLUMNS)


def test_mat_length_mismatch(tmp_path):
    path = save_mat(tmp_path / "c.mat", t=np.arange(12.0), enc=np.zeros(11))
    with pytest.raises(LogError, match=msg("c.mat", "'enc' (theta1) has 11 samples", "expected 12", "'t'")):
        load_log(path, MAT_COLUMNS)


def test_mat_nan_and_time(tmp_path):
    enc = np.zeros(12)
    enc[6] = np.nan
    path = save_mat(tmp_path / "d.mat", t=np.arange(12.0), enc=enc)
    with pytest.raises(LogError, match=msg("d.mat, variable 'enc', sample 7", "nan in theta1", "finite")):
        load_log(path, MAT_COLUMNS)
    t = np.arange(12.0)
    t[4] = t[3]
    path = save_mat(tmp_path / "e.mat", t=t, enc=np.zeros(12))
    with pytest.raises(LogError, match=msg("e.mat, variable 't', sample 5", "duplicate time stamp", "sample 4")):
        load_log(path, MAT_COLUMNS)


def test_mat_not_a_vector_or_not_numeric(tmp_path):
    path = save_mat(tmp_path / "f.mat", t=np.arange(12.0), enc=np.zeros((12, 2)))
    with pytest.raises(LogError, match=msg("f.mat: variable 'enc'", "shape (12, 2)", "expected a vector")):
        load_log(path, MAT_COLUMNS)
    path = save_mat(tmp_path / "g.mat", t=np.arange(12.0), enc="twelve")
    with pytest.raises(LogError, match=msg("g.mat: variable 'enc'", "expected a real numeric vector", "text")):
        load_log(path, MAT_COLUMNS)
    # review: a cell array was "object", a struct a list of dtype fields
    path = save_mat(tmp_path / "h.mat", t=np.arange(12.0), enc=np.array([np.zeros(12), "x"], dtype=object))
    with pytest.raises(LogError, match=msg("h.mat: variable 'enc'", "got a cell array")):
        load_log(path, MAT_COLUMNS)
    path = save_mat(tmp_path / "i.mat", t=np.arange(12.0), enc={"deg": np.zeros(12), "raw": np.zeros(12)})
    with pytest.raises(LogError, match=msg("i.mat: variable 'enc'", "got a struct with fields ['deg', 'raw']")):
        load_log(path, MAT_COLUMNS)


def test_mat_variables_inside_a_struct_are_named(tmp_path):
    """A file holding one struct (`save('run.mat', 'data')` with `data.t`, `data.enc`)
    mapped by the fields' bare names: the message names the field and how to map it
    (review: only "no variable 't'; the file has ['data']")."""
    path = save_mat(tmp_path / "s.mat", data={"t": np.arange(12.0), "enc": np.zeros(12)})
    with pytest.raises(
        LogError,
        match=msg(
            "s.mat: no variable 't'", "['data.enc', 'data.t']", "the field 'data.t' of a struct", "'data.t [unit]'"
        ),
    ):
        load_log(path, MAT_COLUMNS)


def test_mat_struct_fields_are_read_by_their_path(tmp_path):
    """MATLAB logs often come as structs (`log.t`, `log.enc`, nested `log.gauges.tip`):
    a field is mapped by its path, `struct.field`, nested to any depth, and read exactly
    as a variable is (oracle: the arrays written). Unmapped fields are listed as ignored by
    their paths; a struct mapped itself names its fields; a field of a struct array (which
    element?) is refused, naming the array."""
    t, a, b = samples(15)
    path = save_mat(
        tmp_path / "st.mat",
        log={"t": t, "enc": np.rad2deg(a), "gauges": {"tip": b * 1e3, "root": np.ones(15)}},
        note=np.ones(2),
    )
    log = load_log(path, {"time": "log.t [s]", "theta1": "log.enc [deg]", "tip1": "log.gauges.tip [mm]"})
    np.testing.assert_allclose(log.t, t, rtol=0, atol=0)
    np.testing.assert_allclose(log.outputs["theta1"], a, rtol=1e-13)
    np.testing.assert_allclose(log.outputs["tip1"], b, rtol=1e-13)
    assert log.ignored == ("log.gauges.root", "note")
    assert "variable 'log.gauges.tip' [mm]" in log.sources["tip1"]
    with pytest.raises(LogError, match=msg("variable 'log.gauges'", "a struct with fields", "'log.gauges.tip [unit]'")):
        load_log(path, {"time": "log.t [s]", "theta1": "log.enc [deg]", "tip1": "log.gauges [mm]"})
    with pytest.raises(LogError, match=msg("not mapped", "strict = true")):
        load_log(path, {"time": "log.t [s]", "theta1": "log.enc [deg]", "tip1": "log.gauges.tip [mm]"}, strict=True)
    runs = np.empty((1, 2), dtype=[("t", object), ("enc", object)])
    for k in range(2):
        runs[0, k] = (t, np.rad2deg(a))
    path = save_mat(tmp_path / "sa.mat", runs=runs)
    with pytest.raises(LogError, match=msg("no variable 'runs.t'", "'runs' is a struct array of 2 elements")):
        load_log(path, {"time": "runs.t [s]", "theta1": "runs.enc [deg]"})


def test_mat_scalar_time_is_named(tmp_path):
    """A time variable holding one value (a sampling interval saved as `t`): the message
    names the time variable, not the first channel whose length differs (review)."""
    path = save_mat(tmp_path / "ts.mat", t=0.001, enc=np.zeros(12))
    with pytest.raises(
        LogError, match=msg("ts.mat: variable 't' (time)", "holds 1 value(s)", "vector of sample times")
    ):
        load_log(path, MAT_COLUMNS)


def test_mat_v73_and_garbage(tmp_path, monkeypatch):
    # A v7.3 (HDF5) file announces version 0x0200 in its 128-byte header.
    header = b"MATLAB 7.3 MAT-file".ljust(116, b" ") + b"\0" * 8 + b"\x00\x02" + b"IM"
    path = tmp_path / "v73.mat"
    path.write_bytes(header + b"\0" * 512)
    monkeypatch.setitem(__import__("sys").modules, "h5py", None)  # as if h5py were not installed
    with pytest.raises(LogError, match=msg("v73.mat", "v7.3 (HDF5)", "'-v7'")):
        load_log(path, MAT_COLUMNS)
    path = tmp_path / "junk.mat"
    path.write_bytes(b"this is not a mat file")
    with pytest.raises(LogError, match=msg("junk.mat", "not a readable MATLAB .mat file")):
        load_log(path, MAT_COLUMNS)


def test_mat_v73_struct_fields_are_read_by_their_path(tmp_path):
    """A v7.3 (HDF5) file as MATLAB writes one: a 512-byte header, each struct a group,
    its fields datasets, arrays stored transposed. Needs the optional h5py (not a
    dependency: skipped without it, as in CI; run by hand with h5py 3 on 2026-12-05)."""
    h5py = pytest.importorskip("h5py")
    t, a, b = samples(15)
    path = tmp_path / "v73s.mat"
    with h5py.File(path, "w", userblock_size=512) as f:
        log = f.create_group("log")
        log.create_dataset("t", data=t[None, :])  # a 15 x 1 column in MATLAB
        log.create_dataset("enc", data=np.rad2deg(a)[None, :])
        log.create_group("gauges").create_dataset("tip", data=(b * 1e3)[None, :])
        f.create_dataset("note", data=np.ones((1, 2)))
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file".ljust(116, b" ") + b"\0" * 8 + b"\x00\x02" + b"IM")
    loaded = load_log(path, {"time": "log.t [s]", "theta1": "log.enc [deg]", "tip1": "log.gauges.tip [mm]"})
    np.testing.assert_allclose(loaded.t, t, rtol=0, atol=0)
    np.testing.assert_allclose(loaded.outputs["theta1"], a, rtol=1e-13)
    np.testing.assert_allclose(loaded.outputs["tip1"], b, rtol=1e-13)
    assert loaded.ignored == ("note",)


@pytest.mark.parametrize(
    ("dt", "hint"),
    [(1e-6, "labelled [ms] or [us]"), (1.0 / 200.0, ""), (2.0, "in milliseconds but labelled [s]")],
)
def test_an_implausible_sampling_rate_asks_about_the_time_unit(dt, hint):
    """A 1 kHz log whose seconds were labelled [ms] loads at 1 MHz (the numbers are valid,
    so the loader cannot refuse them); its summary asks about the unit."""
    from identify._data.logs import _sampling

    sampling = _sampling(dt * np.arange(100), 0.0)
    assert (hint in str(sampling)) if hint else sampling.time_unit_hint == ""


# ---------------------------------------------------------------------------
# Exports of spreadsheets and Windows software (found in a new-user review)
# ---------------------------------------------------------------------------


def test_an_excel_separator_line_sets_the_separator(tmp_path):
    """Excel's CSV export may start with `sep=;`: it was read as the header ("no column
    't'; the header has ['sep=']")."""
    rows = [[f"{0.01 * k:.2f}".replace(".", ","), "1,5", "2"] for k in range(10)]
    path = write_csv(tmp_path / "excel.csv", ["time [s]", "theta1 [deg]", "tip1 [mm]"], rows, delimiter=";")
    path.write_text("sep=;\n" + path.read_text())
    log = load_log(path, COLUMNS, decimal=",")
    np.testing.assert_allclose(log.t, 0.01 * np.arange(10), atol=1e-15)
    np.testing.assert_allclose(log.outputs["theta1"], math.radians(1.5))


def test_a_utf16_file_is_decoded(tmp_path):
    """Windows' "Unicode text" export is UTF-16 with a byte-order mark: its header was
    shown as mojibake."""
    path = tmp_path / "unicode.csv"
    text = "\n".join([",".join(HEADER)] + [",".join(r) for r in good_rows()]) + "\n"
    path.write_bytes(text.encode("utf-16"))  # (Python writes the byte-order mark)
    log = load_log(path, COLUMNS)
    t, a, _ = samples()
    np.testing.assert_allclose(log.outputs["theta1"], np.deg2rad(np.round(a, 6)), rtol=1e-12)


def test_a_file_without_a_header_row_says_so(tmp_path):
    path = tmp_path / "bare.csv"
    path.write_text("\n".join(",".join(r) for r in good_rows()) + "\n")
    with pytest.raises(LogError, match=msg("bare.csv, line 1", "all numbers", "no header row", "time [s]")):
        load_log(path, COLUMNS)


def test_space_separated_cells_are_named_as_such(tmp_path):
    path = write_csv(tmp_path / "spaces.txt", HEADER, good_rows(), delimiter=" ")
    with pytest.raises(LogError, match=msg("spaces.txt, line 1", "separated by spaces", "commas, semicolons or tabs")):
        load_log(path, COLUMNS)


def test_a_byte_order_mark_before_the_header_is_skipped(tmp_path):
    path = tmp_path / "bom.csv"
    text = "\n".join(["sep=;", ";".join(HEADER)] + [";".join(r) for r in good_rows()]) + "\n"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert len(load_log(path, COLUMNS)) == 20


@pytest.mark.parametrize("separator", ["\f", "\v", "\u2028", "\u2029", "\x85", "\x1c"])
def test_a_line_separator_inside_a_comment_does_not_end_the_line(tmp_path, separator):
    """Review: str.splitlines() splits at a form feed, U+2028 and other separators: the tail
    of a comment holding one (pasted from a word processor) became the header row."""
    path = tmp_path / "sep.csv"
    lines = [f"# rig 3{separator}gauge 2", ",".join(HEADER)] + [",".join(r) for r in good_rows()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert len(load_log(path, COLUMNS)) == 20
    rows = good_rows()
    rows[4][2] = "n/a"  # line 7: the line numbers count only \n, \r\n and \r
    path.write_text("\n".join(lines[:2] + [",".join(r) for r in rows]) + "\n", encoding="utf-8")
    with pytest.raises(LogError, match=msg("sep.csv, line 7, column 3", "'n/a'")):
        load_log(path, COLUMNS)


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r"])
def test_line_ends_of_every_system(tmp_path, newline):
    path = tmp_path / "ends.csv"
    rows = good_rows()
    path.write_bytes(newline.join(["# a", ",".join(HEADER)] + [",".join(r) for r in rows]).encode() + b"\n")
    assert len(load_log(path, COLUMNS)) == 20
    rows[15][1] = "x"
    path.write_bytes(newline.join(["# a", ",".join(HEADER)] + [",".join(r) for r in rows]).encode() + b"\n")
    with pytest.raises(LogError, match=msg("ends.csv, line 18, column 2", "'x'")):
        load_log(path, COLUMNS)


@pytest.mark.parametrize(("unit", "factor"), [("cm", 1e-2), ("mm", 1e-3)])
def test_centimetres(tmp_path, unit, factor):
    rows = [[f"{0.01 * k:.2f}", "0", "2.5"] for k in range(10)]
    log = load_log(write_csv(tmp_path / "cm.csv", ["time [s]", "theta1 [deg]", f"tip1 [{unit}]"], rows))
    np.testing.assert_allclose(log.outputs["tip1"], 2.5 * factor, rtol=1e-15)


def test_format_md_lists_every_unit_and_spelling():
    """docs/experiment-format.md's units table and its list of other spellings name every key of
    `units.UNITS` and `units.ALIASES` (review: five accepted spellings were not listed)."""
    import pathlib

    from identify._data import units

    doc = (pathlib.Path(__file__).parents[2] / "docs" / "experiment-format.md").read_text()
    missing = [k for k in [*units.UNITS, *units.ALIASES] if f"`[{k}]`" not in doc and f"`{k}`" not in doc]
    assert not missing, missing


def test_write_log_is_read_back_bit_for_bit_and_never_overwrites(tmp_path):
    """Review: users simulating logs had to write the CSV layout of docs/experiment-format.md by hand.
    Oracle: the CSV reader (`load_log`, its own unit table) gives back the same float64
    values (the deg/mm scaling round-trips to within one rounding); an existing file is
    refused, named, and left as it was."""
    import identify

    t = np.linspace(0.0, 0.5, 51)
    log = identify.LogData(
        t=t,
        outputs={"theta1": 0.3 * np.sin(7 * t), "tip1": 1e-3 * np.cos(11 * t)},
        torque=np.stack([0.1 * t, -0.2 * t], axis=1),
        name="synthetic",
    )
    path = identify.write_log(
        log, tmp_path / "a.csv", units={"theta1": "deg", "tip1": "mm"}, comments=["made by the test"]
    )
    text = path.read_text().splitlines()
    assert text[0] == "# made by the test" and text[1] == "time [s],theta1 [deg],tip1 [mm],torque1 [N m],torque2 [N m]"
    back = load_log(path)
    np.testing.assert_array_equal(back.t, t)
    np.testing.assert_allclose(back.outputs["theta1"], log.outputs["theta1"], rtol=4e-16, atol=1e-17)
    np.testing.assert_allclose(back.outputs["tip1"], log.outputs["tip1"], rtol=4e-16, atol=1e-20)
    np.testing.assert_array_equal(back.inputs["torque2"], -0.2 * t)
    with pytest.raises(FileExistsError, match=r"a\.csv: exists; not overwritten"):
        identify.write_log(log, path)
    assert path.read_text().splitlines() == text
    identify.write_log(log, path, overwrite=True)  # SI this time
    assert path.read_text().splitlines()[0].startswith("time [s],theta1 [rad],tip1 [m]")
    with pytest.raises(ValueError, match=r"units\['tip1'\] = 'deg': expected a length unit, e.g. 'mm'"):
        identify.write_log(log, tmp_path / "b.csv", units={"tip1": "deg"})
    with pytest.raises(ValueError, match=r"units for \['tip2'\]"):
        identify.write_log(log, tmp_path / "b.csv", units={"tip2": "mm"})
    assert not (tmp_path / "b.csv").exists()


def test_a_loaded_log_converts_to_log_data(tmp_path):
    """Review: passing `load_log`'s `Log` to `make_problem` raised a bare AttributeError
    and the conversion was left to the user. `LogData.from_log` does it; `make_problem`
    names it. Oracle: the values written (`write_log`) come back, torque per joint."""
    import identify

    t = np.linspace(1.0, 1.5, 51)  # a clock that does not start at 0
    src = identify.LogData(t=t, outputs={"theta1": np.sin(t)}, torque=np.stack([t, -t], axis=1), name="x")
    log = load_log(identify.write_log(src, tmp_path / "run.csv"))
    data = identify.LogData.from_log(log, 2, fit_initial=("theta1",))
    np.testing.assert_allclose(data.t, t - t[0], atol=1e-15)
    np.testing.assert_array_equal(data.torque, np.stack([t, -t], axis=1))
    assert (data.name, data.fit_initial) == ("run", ("theta1",))
    with pytest.raises(ValueError, match="has torque2, the rig 1 joint"):
        identify.LogData.from_log(log, 1)
    import flexdyn as fd

    params = [identify.Parameter("joint1.damping", 1e-3)]
    with pytest.raises(TypeError, match=r"got Log: convert it with identify.LogData.from_log"):
        identify.make_problem(fd.rigs.rigid_pendulum(), params, [log], {"theta1": 1e-3})


# ---------------------------------------------------------------------------
# Large logs: the fast reader, the careful one, and the memory check
# ---------------------------------------------------------------------------


def chunked_log(tmp_path, rows, header=("time [s]", "theta1 [deg]", "status", "tip1 [mm]"), newline="\n"):
    path = tmp_path / "big.csv"
    path.write_bytes(newline.join([",".join(header)] + rows).encode() + newline.encode())
    return path


def mixed_rows(n=400):
    """Plain rows and, here and there, what only the careful reader reads: comments, blank
    lines, quoted cells, white space around a row."""
    rows = [f"{0.005 * k:.3f},{np.sin(k):.9f},ok,{1e-3 * k:.6e}" for k in range(n)]
    rows[50] = "# a comment inside the rows"
    rows[120] = ""
    rows[200] = f'{0.005 * 200:.3f},1.5,"quoted, with a comma",2.5'
    rows[300] = f"  {0.005 * 300:.3f},1.5,ok,2.5  "
    return rows


def _without_pyarrow(monkeypatch):
    """Imports of PyArrow fail from here on (an install without it: `pip --no-deps`)."""
    for name in ("pyarrow", "pyarrow.csv"):
        monkeypatch.setitem(sys.modules, name, None)


@pytest.mark.parametrize("reader", ["pyarrow", "loadtxt"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_the_fast_reader_reads_what_the_careful_one_reads(tmp_path, monkeypatch, newline, reader):
    """The rows are read in chunks (here of 300 bytes): PyArrow (or `np.loadtxt` without
    it) for plain ones, the careful line-by-line reader for the rest; the results agree bit
    for bit, line numbers included."""
    from identify._data import csv_log, csv_rows

    if reader == "loadtxt":
        _without_pyarrow(monkeypatch)
    else:
        pytest.importorskip("pyarrow")
    monkeypatch.setattr(csv_rows, "CHUNK_BYTES", 300)
    careful = []
    monkeypatch.setattr(csv_rows, "_careful", lambda *a, _f=csv_rows._careful: careful.append(1) or _f(*a))
    path = chunked_log(tmp_path, mixed_rows(), newline=newline)
    fast = load_log(path)
    n_chunks = len(careful)
    slow = csv_log._read_csv(path, None, {}, False, "columns", fast=False)
    assert len(careful) > 3 * n_chunks  # (the fast reader read most chunks)
    assert len(fast) == 398 and fast.ignored == ("status",)
    np.testing.assert_array_equal(fast.t, slow[0])
    np.testing.assert_array_equal(fast.outputs["theta1"], slow[2]["theta1"])
    np.testing.assert_array_equal(fast.outputs["tip1"], slow[2]["tip1"])
    rows = mixed_rows()
    rows[350] = rows[350].replace("ok,", "ok,1_")  # line 352, in a chunk the fast reader refuses
    rows[360] = rows[360].replace(",ok", ",ok,more")
    with pytest.raises(LogError, match=msg("big.csv, line 352, column 4 ('tip1 [mm]')", "underscore")):
        load_log(chunked_log(tmp_path, rows, newline=newline))
    rows = mixed_rows()
    rows[380] = rows[380].replace(",ok", ",ok,more")
    with pytest.raises(LogError, match=msg("big.csv, line 382: 5 cells; expected 4 like the header on line 1")):
        load_log(chunked_log(tmp_path, rows, newline=newline))
    rows = mixed_rows()
    rows[390] = f"{0.005 * 389:.3f},0,ok,0"
    with pytest.raises(LogError, match=msg("big.csv, line 392, column 1", "duplicate time stamp", "line 391")):
        load_log(chunked_log(tmp_path, rows, newline=newline))


def test_decimal_commas_through_the_fast_reader(tmp_path, monkeypatch):
    from identify._data import csv_rows

    monkeypatch.setattr(csv_rows, "CHUNK_BYTES", 300)
    rows = [f"{0.005 * k:.3f};{np.sin(k):.9f};{1e-3 * k:.6e}".replace(".", ",") for k in range(300)]
    path = tmp_path / "eu.csv"
    path.write_text("\n".join(["time [s];theta1 [deg];tip1 [mm]"] + rows) + "\n")
    log = load_log(path, decimal=",")
    np.testing.assert_array_equal(log.t, [float(f"{0.005 * k:.3f}") for k in range(300)])
    np.testing.assert_array_equal(log.outputs["tip1"], [float(f"{1e-3 * k:.6e}") * 1e-3 for k in range(300)])
    rows[250] = rows[250].replace(",", ".", 1)
    path.write_text("\n".join(["time [s];theta1 [deg];tip1 [mm]"] + rows) + "\n")
    with pytest.raises(LogError, match=msg("eu.csv, line 252, column 1", "decimal commas")):
        load_log(path, decimal=",")


def test_a_log_too_large_for_the_memory_is_refused_before_it_is_read(tmp_path, monkeypatch):
    from identify._data import csv_rows

    monkeypatch.setattr(csv_rows, "available_memory", lambda: 10_000)
    monkeypatch.setattr(csv_rows, "CHUNK_BYTES", 300)
    path = chunked_log(tmp_path, mixed_rows())
    with pytest.raises(
        LogError, match=msg("big.csv: about", "rows x 3 mapped column(s) need about", "GB", "split the log")
    ):
        load_log(path)


TRICKY_CELLS = [
    "1", "-1.5", "+.5", "5.", "1e5", "1.5E-3", "-0.000", "nan", "-NaN", "inf", "-Infinity", "1_0", "-16_6.9411",
    "0x10", "1,5", "1,234.5", "1.234,5", "1 234", "1'234", "١٢", "１２", "1e", "e5", ".", "+", "--1", "1.5f",
    "nan(1)", "1d5", " 2.5 ", "\t3", "", "NA", "null", "N/A", "0x1p3", "1e400", "4.9e-324", "1.#INF",
]  # fmt: skip


@pytest.mark.parametrize("reader", ["pyarrow", "loadtxt"])
@pytest.mark.parametrize("decimal", [".", ","])
def test_one_number_grammar_for_both_readers(decimal, reader, monkeypatch):
    """The careful reader's `parse_number`, the grammar its messages use, and the fast
    reader (PyArrow, or `np.loadtxt` without it; after a decimal comma is turned into a
    point) agree on every cell: which reader reads a chunk never changes a value or what is
    refused (a cell the fast reader refuses goes to the careful one)."""
    from identify._data.csv_numbers import _NUMBER, parse_number
    from identify._data.csv_rows import Columns, _numbers

    if reader == "loadtxt":
        _without_pyarrow(monkeypatch)
    else:
        pytest.importorskip("pyarrow")
    columns = Columns(1, ["t", "x"], ";", ".", [2])

    for cell in TRICKY_CELLS:
        try:
            value = parse_number(cell, decimal)
        except ValueError:
            value = None
        assert (value is not None) == bool(_NUMBER[decimal].fullmatch(cell.strip())), cell
        if decimal == "," and "." in cell:
            continue  # (the fast reader leaves such a chunk to the careful one)
        row = f"0;{cell.replace(',', '.') if decimal == ',' else cell}\n".encode()
        read = _numbers(row, columns, 1)
        fast = None if read is None else float(read[0, 0])
        if fast is not None:
            assert value is not None and (value == fast or (math.isnan(value) and math.isnan(fast))), cell
