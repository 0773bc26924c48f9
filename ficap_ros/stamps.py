"""Stamps: message time to ns, nearest-stamp pairing and time windows (the one implementation
the live node, the bag tools and the CLI share).

Bottom layer: numpy only, no ROS and no other ficap module.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["stamp_to_ns", "pair_by_stamp", "window_mask", "window_from_start_ns", "last_window_ns"]

#: The largest int64 stamp: the end of an open window.
END_OF_TIME_NS = 2**63 - 1


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (sec, nanosec; an rclpy or a rosbags message) to integer ns."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def pair_by_stamp(truth_ns: np.ndarray, est_ns: np.ndarray,
                  max_dt_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_truth, i_est) of nearest-stamp pairs within ``max_dt_ns``, one-to-one.

    Each truth takes its nearest estimate (the earlier one on a tie); when several truths take the
    same estimate the closest keeps it. ``est_ns`` must be sorted; the pairs come in truth order.
    """
    t = np.asarray(truth_ns, dtype=np.int64)
    e = np.asarray(est_ns, dtype=np.int64)
    if t.size == 0 or e.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    j = np.clip(np.searchsorted(e, t), 1, e.size - 1) if e.size > 1 else np.zeros(t.size, int)
    if e.size > 1:
        left = j - 1
        j = np.where(np.abs(e[left] - t) <= np.abs(e[j] - t), left, j)
    dt = np.abs(e[j] - t)
    ok = dt <= max_dt_ns
    i_t = np.nonzero(ok)[0]
    i_e = j[ok]
    d = dt[ok]
    order = np.lexsort((d, i_e))  # by estimate, closest first
    first = np.ones(order.size, dtype=bool)
    first[1:] = i_e[order][1:] != i_e[order][:-1]
    keep = np.sort(order[first])
    return i_t[keep], i_e[keep]


def window_from_start_ns(start_ns: int, window_s: tuple[float, float]) -> tuple[int, int]:
    """(lo_ns, hi_ns) of ``window_s`` = (start, end) seconds after ``start_ns`` (end may be inf)."""
    lo = int(start_ns) + int(window_s[0] * 1e9)
    hi = int(start_ns) + int(window_s[1] * 1e9) if math.isfinite(window_s[1]) else END_OF_TIME_NS
    return lo, hi


def last_window_ns(newest_ns: int, window_s: float) -> tuple[int, int]:
    """(lo_ns, hi_ns) of the last ``window_s`` seconds up to ``newest_ns``."""
    return int(newest_ns) - int(window_s * 1e9), int(newest_ns)


def window_mask(stamps_ns: np.ndarray, window_ns: tuple[int, int]) -> np.ndarray:
    """Which stamps lie in the window (both ends included)."""
    s = np.asarray(stamps_ns, dtype=np.int64)
    return (s >= window_ns[0]) & (s <= window_ns[1])
