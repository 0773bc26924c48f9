"""ficap_ros.stamps: message time, one-to-one nearest-stamp pairing and time windows."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros import stamps
from ficap_ros.io import sources as bag_io
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.stamps import (
    END_OF_TIME_NS,
    last_window_ns,
    pair_by_stamp,
    stamp_to_ns,
    window_from_start_ns,
    window_mask,
)


def test_stamp_to_ns() -> None:
    assert stamp_to_ns(SimpleNamespace(sec=3, nanosec=7)) == 3_000_000_007


def test_pairs_are_one_to_one_and_nearest() -> None:
    truth = np.array([0, 10, 11, 30, 100])
    est = np.array([9, 12, 29])
    i_t, i_e = pair_by_stamp(truth, est, 5)
    # 10 and 11 both want 9 or 12: 10 -> 9 (1 away), 11 -> 12 (1 away); 0 and 100 too far.
    assert i_t.tolist() == [1, 2, 3] and i_e.tolist() == [0, 1, 2]
    # Two truths wanting the same estimate: the closer keeps it.
    i_t, i_e = pair_by_stamp(np.array([8, 10]), np.array([10]), 5)
    assert i_t.tolist() == [1] and i_e.tolist() == [0]
    assert pair_by_stamp(np.zeros(0), est, 5)[0].size == 0


def test_windows() -> None:
    assert window_from_start_ns(1000, (1.0, 2.0)) == (1000 + 10**9, 1000 + 2 * 10**9)
    assert window_from_start_ns(1000, (0.5, float("inf")))[1] == END_OF_TIME_NS
    assert last_window_ns(5 * 10**9, 3.0) == (2 * 10**9, 5 * 10**9)
    s = np.array([1, 2, 3, 4])
    assert window_mask(s, (2, 3)).tolist() == [False, True, True, False]  # both ends included


def test_stamp_helpers_are_one_implementation() -> None:
    assert ros_msgs.stamp_to_ns is stamps.stamp_to_ns is bag_io.stamp_to_ns


def _pairs_by_brute_force(truth: list[int], est: list[int], tol: int) -> list[tuple[int, int]]:
    """The documented rule, spelled out: each truth's nearest estimate (the earlier on a tie) within
    ``tol``; an estimate wanted by several truths goes to the closest (the first on a tie)."""
    wanted = {}
    for i, t in enumerate(truth):
        if not est:
            break
        j = min(range(len(est)), key=lambda k: (abs(est[k] - t), k))
        if abs(est[j] - t) <= tol:
            wanted.setdefault(j, []).append((abs(est[j] - t), i))
    return sorted((min(claims)[1], j) for j, claims in wanted.items())


@given(st.lists(st.integers(0, 10_000), max_size=40),
       st.lists(st.integers(0, 10_000), max_size=40, unique=True), st.integers(0, 600))
def test_pairs_follow_the_rule_one_to_one_within_the_tolerance(
        truth: list[int], est: list[int], tol: int) -> None:
    est = sorted(est)
    i_t, i_e = pair_by_stamp(np.array(truth, dtype=np.int64), np.array(est, dtype=np.int64), tol)
    pairs = list(zip(i_t.tolist(), i_e.tolist()))
    assert pairs == _pairs_by_brute_force(truth, est, tol)
    assert len(set(i_e.tolist())) == len(pairs) and np.all(np.diff(i_t) > 0)
    if pairs:
        assert np.abs(np.array(truth)[i_t] - np.array(est)[i_e]).max() <= tol


@given(st.lists(st.integers(-10**12, 10**12), max_size=30), st.integers(0, 10**12),
       st.floats(0.0, 100.0), st.floats(0.0, 100.0))
def test_windows_hold_exactly_the_stamps_between_their_ends(
        stamps: list[int], start_ns: int, a_s: float, b_s: float) -> None:
    lo_s, hi_s = min(a_s, b_s), max(a_s, b_s)
    window = window_from_start_ns(start_ns, (lo_s, hi_s))
    assert window == (start_ns + int(lo_s * 1e9), start_ns + int(hi_s * 1e9))
    mask = window_mask(np.array(stamps, dtype=np.int64), window)
    assert mask.tolist() == [window[0] <= s <= window[1] for s in stamps]
    assert last_window_ns(start_ns, hi_s) == (start_ns - int(hi_s * 1e9), start_ns)
