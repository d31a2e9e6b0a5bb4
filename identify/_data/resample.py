"""One time base for series sampled at their own times (a bag's topics): the span they all
cover, the base's times in it, and linear interpolation onto them.

Times are integer nanoseconds (a ROS stamp), differenced before they become float seconds:
1.7e18 ns since 1970 as a float64 keeps only ~200 ns, a difference of a few hours every
nanosecond. Values are never extrapolated: the base is trimmed to the span every series
covers, so each interpolated value lies between two samples of its own series.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .columns import GAP_FACTOR


def common_span(stamps: Mapping[str, np.ndarray]) -> tuple[int, int]:
    """`(start, end)`, ns: the latest first stamp and the earliest last stamp of the series
    (`start >= end` when they do not overlap)."""
    return max(int(s[0]) for s in stamps.values()), min(int(s[-1]) for s in stamps.values())


def base_times(stamps: Mapping[str, np.ndarray], base: str | None, rate_hz: float | None) -> tuple[int, np.ndarray]:
    """`(ref, t)`: the time base in the common span (`common_span`, which must not be empty),
    as `ref` (ns, its first time) and `t` (s from `ref`): the stamps of series `base`
    inside the span, or times `k / rate_hz` from the span's start up to its end."""
    start, end = common_span(stamps)
    if rate_hz is None:
        s = stamps[base]
        inside = s[(s >= start) & (s <= end)]
        return int(inside[0]), (inside - inside[0]) / 1e9
    span = (end - start) / 1e9
    t = np.arange(int(np.floor(span * rate_hz)) + 1) / rate_hz
    return start, t[t <= span]


def interpolate(t: np.ndarray, ref: int, stamps: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`values` sampled at `stamps` (ns), linearly interpolated at `t` (s from `ref`), which
    lie inside the stamps' span (`base_times`)."""
    return np.interp(t, (stamps - ref) / 1e9, values)


def gaps(stamps: np.ndarray, start: int, end: int) -> tuple[np.ndarray, float]:
    """The indices `k` of the intervals `stamps[k] .. stamps[k + 1]` longer than `GAP_FACTOR`
    times the median interval that reach into `[start, end]` (ns), and the median (ns)."""
    dt = np.diff(stamps)
    if dt.size == 0:
        return np.zeros(0, int), 0.0
    median = float(np.median(dt))
    inside = (stamps[1:] > start) & (stamps[:-1] < end)
    return np.flatnonzero((dt > GAP_FACTOR * median) & inside), median
