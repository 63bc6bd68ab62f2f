"""Order statistics of one 1-D array without NaN, numpy's numbers without numpy's general
set-up: `percentile` is np.percentile's (linear method) and `median` np.median's, in the
array's own dtype (float32 arithmetic for float32 values, as numpy's), from one partition of
the one or two neighbours they need. For the per-frame loops that take many of them on a few
hundred to a few thousand values, where numpy's argument handling is most of the time."""
from __future__ import annotations

import numpy as np


def percentile(values: np.ndarray, q: float):
    """The q-th percentile of a non-empty 1-D array without NaN: np.percentile's number (a
    numpy scalar of its dtype), the linear interpolation between the order statistics either
    side of (n - 1) q / 100, written as numpy's (`_lerp`: from the lower one below a weight of
    0.5, from the upper one from there)."""
    n = len(values)
    at = (n - 1) * (q / 100)
    lo = int(np.floor(at))
    hi = min(lo + 1, n - 1)
    part = np.partition(values, [lo, hi] if hi > lo else lo)
    a, b, t = part[lo], part[hi], at - lo
    return a + (b - a) * t if t < 0.5 else b - (b - a) * (1 - t)


def median(values: np.ndarray):
    """The median of a non-empty 1-D array without NaN: np.median's number (a numpy scalar of
    its dtype), the middle order statistic or the mean of the two middle ones."""
    n = len(values)
    h = n // 2
    if n % 2:
        return np.partition(values, h)[h]
    part = np.partition(values, [h - 1, h])
    return (part[h - 1] + part[h]) / 2
