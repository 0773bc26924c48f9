"""ficap_ros.io.status: one status level, message and values per frame record, for the node and
labels.mcap alike; the node's health over a period."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.transform import Transform
from ficap_ros.io.labels import FrameRecord
from ficap_ros.io.status import (
    ERROR,
    OK,
    WARN,
    WARN_RELIABILITY,
    FrameStatus,
    quality_values,
    record_status,
    status_reason,
    status_values,
)
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pose import CapPose


def _pose(reliability: float) -> CapPose:
    T = Transform(Rotation.from_euler("xyz", [170.0, 5.0, -3.0], degrees=True), [0.01, -0.02, 0.6])
    return CapPose(T, 6, 5, (1, 2, 3, 4, 5), 0.12, np.eye(6) * 1e-8, reliability, "joint", 0.4, 0.9)


def test_levels_and_messages() -> None:
    """OK with a reliable pose, WARN below ``warn_reliability`` or without a pose, ERROR when the
    image could not be processed (an undecodable image says so, a failed one gives its reason)."""
    posed = FrameRecord.processed(0, 10, "cam", _pose(0.9), (1, 2, 3, 4, 5, 6))
    assert posed.status is FrameStatus.POSE and record_status(posed) == (OK, "pose")
    weak = FrameRecord.processed(0, 10, "cam", _pose(WARN_RELIABILITY - 0.01), (1,))
    assert record_status(weak) == (WARN, "low reliability 0.49")
    assert record_status(weak, warn_reliability=0.2) == (OK, "pose")
    none = FrameRecord.processed(3, 10, "", None, (4, 2, 4), "no tag of the model detected")
    assert none.status is FrameStatus.NO_POSE and none.frame_id == "camera_optical_frame"
    assert none.detected_ids == (2, 4) and none.tags_detected == 2
    assert record_status(none) == (WARN, "no pose: no tag of the model detected")
    assert record_status(FrameRecord.processed(0, 10, "cam", None, ())) == (WARN, "no pose: no pose")
    bad = FrameRecord.unprocessed(4, 11, "cam", "bad JPEG")
    assert bad.skipped and status_reason(bad) == "undecodable: bad JPEG"
    assert record_status(bad) == (ERROR, "undecodable: bad JPEG")
    failed = FrameRecord.unprocessed(0, 11, "cam", "no CameraInfo received", FrameStatus.FAILED)
    assert not failed.skipped and record_status(failed) == (ERROR, "no CameraInfo received")


def test_values_and_quality_come_from_the_record() -> None:
    cal = HeadCalibration(calibrated=True)
    none = FrameRecord.processed(3, 10, "", None, (4, 2), "no tag", cal)
    assert quality_values(none)["reliability"] == 0.0 and math.isnan(quality_values(none)["rms_px"])
    assert list(status_values(none)) == ["tags_detected", "tags_used", "rms_px", "reliability",
                                         "rot_err95_deg", "trans_err95_mm", "calibrated"]
    assert status_values(none)["calibrated"] is True
    posed = FrameRecord.processed(0, 10, "cam", _pose(0.9), (1, 2, 3, 4, 5, 6), calibration=cal)
    values = status_values(posed)
    assert (values["tags_detected"], values["tags_used"], values["reliability"]) == (6, 5, 0.9)
    assert values["rot_err95_deg"] == 0.4 and values["trans_err95_mm"] == 0.9
    assert {"yaw_deg", "pitch_deg", "roll_deg"} <= set(values)
    assert quality_values(posed) == {"tags_detected": 6.0, "tags_used": 5.0, "reliability": 0.9,
                                     "rms_px": 0.12, "rot_err95_deg": 0.4, "trans_err95_mm": 0.9,
                                     "rot_err95_rad": pytest.approx(0.4 * math.pi / 180, rel=1e-15),
                                     "trans_err95_m": pytest.approx(0.9e-3, rel=1e-15)}
    # The SI bounds come after the human ones (a name order readers of labels.mcap rely on).
    assert list(quality_values(posed))[-2:] == ["rot_err95_rad", "trans_err95_m"]
    assert math.isnan(quality_values(none)["rot_err95_rad"])
    assert math.isnan(quality_values(none)["trans_err95_m"])


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
