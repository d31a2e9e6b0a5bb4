"""Display units and figure titles of the reports (`identify.report`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from identify._data.units import display_unit, state_display_unit


@pytest.mark.parametrize(
    ("entry", "scale", "unit"),
    [
        ("theta1", 180 / math.pi, "deg"),
        ("theta1_rate", 180 / math.pi, "deg/s"),
        ("alpha2_rate", 180 / math.pi, "deg/s"),
        ("q1_1", 1e3, "mm"),  # a modal coordinate is the mode's RMS deflection, m
        ("q2_2_rate", 1e3, "mm/s"),
    ],
)
def test_state_entries_print_in_the_units_of_their_channels(entry, scale, unit):
    """An initial state's rate prints per second in its angle's or length's display unit
    (it used to print as a bare number labelled "SI")."""
    assert state_display_unit(entry) == pytest.approx((scale, unit))
    assert display_unit("tip1") == (1e3, "mm")


def test_a_long_figure_title_is_wrapped_to_the_figure_width():
    """A 5-inch figure titled with a long experiment name clipped it at both ends (seen:
    "easured vs fitted: ... (Kaheman et al"); wrapped, every line fits and nothing is lost."""
    from identify._report.fit_plots import wrapped_title

    title = "Measured vs fitted: single pendulum free swing (Kaheman et al.)"
    lines = wrapped_title(title, 5.0).splitlines()
    assert len(lines) == 2 and all(len(line) <= 45 for line in lines)
    assert " ".join(lines) == title
    assert wrapped_title("Residuals", 5.0) == "Residuals"


def test_residual_spectrum_resolves_a_low_frequency_over_a_long_log():
    """Review: fixed 256-sample segments gave 0.78 Hz bins at 200 Hz, and a residual at a
    pendulum's 1.27 Hz swing showed up between bins. Oracle: the sine's own frequency."""
    from identify._report.fit_plots import residual_spectrum

    t = np.arange(0.0, 30.0, 1 / 200)
    f, p = residual_spectrum(t, np.sin(2 * np.pi * 1.27 * t))
    assert f[1] - f[0] < 0.2
    assert abs(f[np.argmax(p)] - 1.27) < 0.1


def test_diagnosis_json_lists_its_files_and_what_could_not_be_written(tmp_path):
    """A report or plot that fails is left out with a warning; diagnosis.json, written
    first, names the files written and the failures (here a stand-in diagnosis that only
    serialises: every figure fails)."""
    import json

    from identify._report import diagnosis_report

    class OnlyDict:
        def to_dict(self):
            return {"named": ["x"]}

    with pytest.warns(RuntimeWarning) as caught:
        written = diagnosis_report.write_report(OnlyDict(), tmp_path, extra={"command": ["identify"]})
    assert len(caught) == 1 + len(diagnosis_report.PLOT_FILES)
    assert str(caught[0].message).startswith(f"{tmp_path / 'report.md'} not written: AttributeError")
    assert written == [tmp_path / "diagnosis.json"]
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["named"] == ["x"] and doc["command"] == ["identify"]
    assert doc["files"] == ["diagnosis.json"]
    assert [p.split(" ")[0] for p in doc["problems"]] == ["report.md", *diagnosis_report.PLOT_FILES]
    assert all("not written: AttributeError" in p for p in doc["problems"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["diagnosis.json"]  # (no partial figure, no temporary)
