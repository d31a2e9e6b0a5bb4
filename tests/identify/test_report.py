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
