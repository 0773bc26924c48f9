"""ficap_ros.io.status: one status level and message per frame for the node and labels.mcap."""

from __future__ import annotations

import math

from ficap_ros.io.status import ERROR, OK, WARN, WARN_RELIABILITY, frame_status


def test_frame_status_levels() -> None:
    assert frame_status(True, 0.9) == (OK, "pose")
    assert frame_status(True, WARN_RELIABILITY - 0.01) == (WARN, "low reliability 0.49")
    assert frame_status(True, 0.3, warn_reliability=0.2) == (OK, "pose")
    assert frame_status(False, math.nan, "no tag of the model detected") == (
        WARN, "no pose: no tag of the model detected")
    assert frame_status(False, math.nan) == (WARN, "no pose: no tags")
    assert frame_status(False, math.nan, error="undecodable: bad JPEG") == (ERROR, "undecodable: bad JPEG")


def test_label_record_values_feed_status_and_quality() -> None:
    """One record per frame gives the status values, quality numbers and level of the node and
    labels.mcap alike (``record_status`` = ``frame_status`` of its fields)."""
    from ficap_ros.io.status import (
        quality_values,
        record_from_pose,
        record_status,
        status_values,
    )
    from ficap_ros.vision.calibration import HeadCalibration

    cal = HeadCalibration()
    none = record_from_pose(3, 10, "", None, (4, 2), "no tag of the model detected", cal)
    assert none.frame_id == "camera_optical_frame" and none.detected_ids == (2, 4)
    assert record_status(none) == (WARN, "no pose: no tag of the model detected")
    assert quality_values(none)["reliability"] == 0.0 and math.isnan(quality_values(none)["rms_px"])
    assert list(status_values(none)) == ["tags_detected", "tags_used", "rms_px", "reliability",
                                         "rot_err95_deg", "trans_err95_mm", "calibrated"]
    bad = record_from_pose(4, 11, "cam", None, (), "undecodable: bad JPEG", cal)
    assert record_status(bad) == (ERROR, "undecodable: bad JPEG")


def test_period_stats_and_health() -> None:
    from ficap_ros.io.status import PeriodStats, health_status, health_values

    stats = PeriodStats()
    stats.frame(10, 20.0)
    stats.frame(12, 30.0)
    p, last = stats.take((5, 1))
    assert (p["processed"], p["tags"], p["received"], p["dropped"], last) == (2, 22, 5, 1, "")
    v = health_values(p, 2.0, 1, True, "frontal")
    assert v["fps"] == 1.0 and v["mean_tags"] == 11.0 and v["mean_latency_ms"] == 25.0
    assert v["drop_rate"] == 0.2
    stats.error("bad JPEG")
    p, last = stats.take((6, 1))  # one more frame received since the last take
    assert p["received"] == 1 and p["errors"] == 1
    assert health_status(p["received"], p["errors"], last, True) == (ERROR, "input errors: bad JPEG")
    assert health_status(0, 0, "", True) == (WARN, "no images")
    assert health_status(3, 0, "", False) == (OK, "running, not calibrated")


def test_period_health_in_one_call() -> None:
    from ficap_ros.io.status import PeriodStats

    stats = PeriodStats()
    stats.frame(5, 10.0)
    level, message, values = stats.health((3, 0), False, "none")
    assert (level, message) == (OK, "running, not calibrated")
    assert values["mean_tags"] == 5.0 and values["fps"] > 0 and values["calibration_mode"] == "none"
