"""Display units of the reports (`identify.report`)."""

from __future__ import annotations

import math

import pytest

from identify.report import display_unit, state_display_unit


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
