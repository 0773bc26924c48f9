"""Worker processes for whole segments (``ficap_ros.tools.worker_pool``): results in order, each
segment with its look-ahead, in processes other than this one."""

from __future__ import annotations

import multiprocessing
import os

from probe_cases import echo_segment, no_setup

from ficap_ros.tools.worker_pool import parallel_frames


def test_segments_come_back_in_order_with_their_look_ahead() -> None:
    segments = [([0, 1, 2], 3), ([3, 4, 5], 6), ([6], None)]
    counter = multiprocessing.get_context("spawn").Value("q", 0)
    seen: list[int] = []
    out = list(parallel_frames(iter(segments), 2, no_setup, (), echo_segment, counter, seen.append,
                               None))
    assert [o[0] for o in out] == list(range(7))
    assert [o[1] for o in out] == [3, 3, 3, 6, 6, 6, None]
    assert all(o[2] != os.getpid() for o in out)
