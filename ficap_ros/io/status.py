"""What a processed frame reports, decided once for the node and the bag tools: its label record
(``LabelRecord`` from a ``FrameResult`` or a cap pose), status level and message, status values
and quality numbers (the node's ``status`` and ``quality``, labels.mcap's and labels.csv's).

Levels are ``diagnostic_msgs/DiagnosticStatus``'s numbers (OK 0, WARN 1, ERROR 2); this module is
ROS-free, so the node turns them into its message type.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.metrics import yaw_pitch_roll_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pipeline import FrameResult
from ficap_ros.vision.pose import CapPose

__all__ = ["OK", "WARN", "ERROR", "WARN_RELIABILITY", "DEFAULT_CAMERA_FRAME", "LabelRecord",
           "record_from_pose", "record_from_result", "frame_status", "record_status", "quality_values",
           "status_values", "health_status", "health_values", "PeriodStats", "SKIPPED_PREFIX",
           "skipped_reason", "is_skipped"]

OK, WARN, ERROR = 0, 1, 2

#: Status level is WARN below this reliability (the node's ``warn_reliability`` default).
WARN_RELIABILITY = 0.5

#: frame_id of labels whose images carry none.
DEFAULT_CAMERA_FRAME = "camera_optical_frame"


def frame_status(has_pose: bool, reliability: float, reason: str = "", error: str = "",
                 warn_reliability: float = WARN_RELIABILITY) -> tuple[int, str]:
    """(level, message) of one frame.

    Args:
        has_pose: the frame has a cap pose.
        reliability: the pose's reliability (ignored without a pose).
        reason: why there is no pose ('' = no tags).
        error: the input could not be processed (an undecodable image, no intrinsics): ERROR.
        warn_reliability: a pose less reliable than this is a WARN.
    """
    if error:
        return ERROR, error
    if not has_pose:
        return WARN, f"no pose: {reason or 'no tags'}"
    if math.isfinite(reliability) and reliability < warn_reliability:
        return WARN, f"low reliability {reliability:.2f}"
    return OK, "pose"


#: The reason of a frame that could not be decoded (it is counted, labelled and reported as lost).
SKIPPED_PREFIX = "undecodable: "


def skipped_reason(error: object) -> str:
    """The reason recorded for an image that could not be decoded."""
    return f"{SKIPPED_PREFIX}{error}"


def is_skipped(reason: str) -> bool:
    """Whether a frame's reason says its image could not be decoded."""
    return reason.startswith(SKIPPED_PREFIX.rstrip(": "))


@dataclass(frozen=True)
class LabelRecord:
    """The label of one image.

    Attributes:
        frame: image index in the recording.
        stamp_ns: image stamp, ns.
        frame_id: the image's optical frame.
        tags_detected, tags_used: model tags seen / used by the estimator.
        detected_ids, used_ids: their ids, sorted.
        rms_px, reliability: estimator quality (NaN without a pose).
        T_cam_cap: cap pose in the camera optical frame, or None.
        T_frontal_head: head pose in the frontal frame, or None.
        covariance_cam: the cap pose's 6x6 covariance (ROS order, camera axes), or None.
        R_frontal_cam: orientation of the camera in F (to rotate the covariance).
        calibrated: whether a head calibration was applied.
        method: pose method name.
        reason: why there is no pose ("" with a pose); ``undecodable: ...`` for a skipped image.
        rot_err95_deg, trans_err95_mm: predicted 95 % bounds of the cap pose's rotation error
            (geodesic, deg) and translation error (mm); NaN without a pose.
    """

    frame: int
    stamp_ns: int
    frame_id: str
    tags_detected: int
    tags_used: int
    detected_ids: tuple[int, ...]
    used_ids: tuple[int, ...]
    rms_px: float
    reliability: float
    T_cam_cap: Transform | None
    T_frontal_head: Transform | None
    covariance_cam: np.ndarray | None
    R_frontal_cam: Rotation
    calibrated: bool
    method: str
    reason: str
    rot_err95_deg: float = math.nan
    trans_err95_mm: float = math.nan

    @property
    def skipped(self) -> bool:
        return is_skipped(self.reason)


def record_from_pose(
    frame: int, stamp_ns: int, frame_id: str, pose: CapPose | None,
    detected_ids: Sequence[int], reason: str, calibration: HeadCalibration, method: str = "",
) -> LabelRecord:
    """The label of one processed frame.

    The head pose comes from the cap pose through ``calibration`` (the ``HeadCalibration`` methods
    the pipeline uses), so a calibration found after processing applies to every frame.

    Args:
        frame: image index.
        stamp_ns: image stamp.
        frame_id: the image's optical frame ("" -> ``camera_optical_frame``).
        pose: the cap pose, or None.
        detected_ids: ids of the model tags detected.
        reason: why there is no pose; ``undecodable: ...`` marks a skipped image.
        calibration: head calibration to apply.
        method: pose method name (used when there is no pose).
    """
    R_frontal_cam = calibration.R_cam_frontal.inv()
    frame_id = frame_id or DEFAULT_CAMERA_FRAME
    detected = tuple(sorted(set(int(i) for i in detected_ids)))
    if pose is None:
        return LabelRecord(frame, int(stamp_ns), frame_id, len(detected), 0, detected, (),
                           math.nan, math.nan, None, None, None, R_frontal_cam,
                           calibration.calibrated, method, reason or "no pose")
    T_cam_head = calibration.head_in_camera(pose.T_cam_cap)
    T_frontal_head = Transform(R_frontal_cam, np.zeros(3)) * T_cam_head
    return LabelRecord(
        frame, int(stamp_ns), frame_id, pose.tags_detected, pose.tags_used, detected,
        tuple(sorted(pose.used_ids)), float(pose.rms_px), float(pose.reliability), pose.T_cam_cap,
        T_frontal_head, np.asarray(pose.covariance, dtype=np.float64).reshape(6, 6),
        R_frontal_cam, calibration.calibrated, pose.method or method, "",
        float(pose.rot_err95_deg), float(pose.trans_err95_mm),
    )


def record_from_result(result: FrameResult, calibration: HeadCalibration, frame: int = 0,
                       frame_id: str = "") -> LabelRecord:
    """The label of a ``FrameResult`` (see ``record_from_pose``)."""
    return record_from_pose(frame, result.stamp_ns, frame_id, result.pose,
                            [d.tag_id for d in result.detections], result.reason, calibration,
                            result.pose.method if result.pose is not None else "")


def quality_values(rec: LabelRecord) -> dict[str, float]:
    """The numbers of the ``quality`` topic (the node adds its latency): NaN without a pose,
    reliability 0."""
    return {
        "tags_detected": float(rec.tags_detected),
        "tags_used": float(rec.tags_used),
        "reliability": float(rec.reliability) if math.isfinite(rec.reliability) else 0.0,
        "rms_px": float(rec.rms_px),
        "rot_err95_deg": float(rec.rot_err95_deg),
        "trans_err95_mm": float(rec.trans_err95_mm),
    }


def status_values(rec: LabelRecord) -> dict[str, float | int | bool]:
    """The values of a frame's status (labels.mcap's; the node adds search, latency and dropped
    frames): tags, quality, calibrated and, with a pose, the head angles in the frontal frame."""
    values: dict[str, float | int | bool] = {
        "tags_detected": int(rec.tags_detected),
        "tags_used": int(rec.tags_used),
        "rms_px": float(rec.rms_px),
        "reliability": float(rec.reliability),
        "rot_err95_deg": float(rec.rot_err95_deg),
        "trans_err95_mm": float(rec.trans_err95_mm),
        "calibrated": bool(rec.calibrated),
    }
    if rec.T_frontal_head is not None:
        ypr = yaw_pitch_roll_deg(rec.T_frontal_head.rotation)
        values.update({f"{k}_deg": float(v) for k, v in zip(("yaw", "pitch", "roll"), ypr)})
    return values


def record_status(rec: LabelRecord, warn_reliability: float = WARN_RELIABILITY) -> tuple[int, str]:
    """(level, message) of a label record (``frame_status``; a skipped image is an ERROR)."""
    return frame_status(rec.T_cam_cap is not None, rec.reliability, rec.reason,
                        error=rec.reason if rec.skipped else "", warn_reliability=warn_reliability)


def health_status(received: int, errors: int, last_error: str, calibrated: bool) -> tuple[int, str]:
    """(level, message) of ``/diagnostics`` over one period: ERROR on input errors, WARN without
    images, else OK (saying whether the head calibration is in place)."""
    if errors:
        return ERROR, f"input errors: {last_error}"
    if received == 0:
        return WARN, "no images"
    return OK, "running" if calibrated else "running, not calibrated"


def health_values(period: dict[str, float], dt_s: float, dropped_total: int, calibrated: bool,
                  mode: str) -> dict[str, object]:
    """The values of ``/diagnostics`` over one period (counts of received, dropped, processed
    frames, tags, errors and the summed latency) lasting ``dt_s``."""
    n = period["processed"]
    received = period["received"]
    return {
        "fps": n / dt_s, "input_fps": received / dt_s,
        "drop_rate": period["dropped"] / received if received else 0.0,
        "mean_tags": period["tags"] / n if n else 0.0,
        "mean_latency_ms": period["latency_ms"] / n if n else float("nan"),
        "errors": period["errors"], "dropped_frames_total": dropped_total,
        "calibrated": calibrated, "calibration_mode": mode,
    }


class PeriodStats:
    """What ``/diagnostics`` reports over one period: frames processed, tags, latency and input
    errors (thread-safe: the worker counts, the timer takes)."""

    def __init__(self) -> None:
        import threading

        self._lock = threading.Lock()
        self._period = {"processed": 0, "tags": 0, "errors": 0, "latency_ms": 0.0}
        self._counted = (0, 0)  # the input's (received, dropped) at the last take
        self._since = time.monotonic()
        self.last_error = ""

    def frame(self, tags: int, latency_ms: float) -> None:
        with self._lock:
            self._period["processed"] += 1
            self._period["tags"] += tags
            self._period["latency_ms"] += latency_ms

    def error(self, reason: str) -> None:
        with self._lock:
            self._period["errors"] += 1
            self.last_error = reason

    def take(self, received_dropped: tuple[int, int]) -> tuple[dict[str, float], str]:
        """The period's counts (with ``received`` and ``dropped`` frames since the last take, from
        the input's running totals) and the last error; starts the next period."""
        with self._lock:
            p, last_error = dict(self._period), self.last_error
            self._period = {"processed": 0, "tags": 0, "errors": 0, "latency_ms": 0.0}
            p["received"] = received_dropped[0] - self._counted[0]
            p["dropped"] = received_dropped[1] - self._counted[1]
            self._counted = received_dropped
        return p, last_error

    def health(self, received_dropped: tuple[int, int], calibrated: bool,
               mode: str) -> tuple[int, str, dict[str, object]]:
        """(level, message, values) of ``/diagnostics`` for the period since the last call
        (``take``, ``health_status``, ``health_values``)."""
        now = time.monotonic()
        dt_s, self._since = max(now - self._since, 1e-3), now
        p, last_error = self.take(received_dropped)
        level, message = health_status(p["received"], p["errors"], last_error, calibrated)
        return level, message, health_values(p, dt_s, received_dropped[1], calibrated, mode)
