"""ficap_ros.report: one status level and message per frame for the node and labels.mcap."""

from __future__ import annotations

import math

from ficap_ros.report import ERROR, OK, WARN, WARN_RELIABILITY, frame_status


def test_frame_status_levels() -> None:
    assert frame_status(True, 0.9) == (OK, "pose")
    assert frame_status(True, WARN_RELIABILITY - 0.01) == (WARN, "low reliability 0.49")
    assert frame_status(True, 0.3, warn_reliability=0.2) == (OK, "pose")
    assert frame_status(False, math.nan, "no tag of the model detected") == (
        WARN, "no pose: no tag of the model detected")
    assert frame_status(False, math.nan) == (WARN, "no pose: no tags")
    assert frame_status(False, math.nan, error="undecodable: bad JPEG") == (ERROR, "undecodable: bad JPEG")
