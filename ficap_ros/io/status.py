"""What a processed frame reports, decided once for the node and the bag tools from its record
(``ficap_ros.io.labels.FrameRecord``): its status level and message, status values and quality
numbers (the node's ``status`` and ``quality``, labels.mcap's); and the node's health over a period
(``/diagnostics``).

Levels are ``diagnostic_msgs/DiagnosticStatus``'s numbers (OK 0, WARN 1, ERROR 2); this module is
ROS-free, so the node turns them into its message type.
"""

from __future__ import annotations

import math
import time
from enum import Enum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ficap_ros.io.labels import FrameRecord

__all__ = ["OK", "WARN", "ERROR", "WARN_RELIABILITY", "FrameStatus", "record_status",
           "status_reason", "quality_values", "status_values", "health_status", "health_values",
           "PeriodStats"]

OK, WARN, ERROR = 0, 1, 2

#: Status level is WARN below this reliability (the node's ``warn_reliability`` default).
WARN_RELIABILITY = 0.5


class FrameStatus(str, Enum):
    """What became of a frame (``FrameRecord.status``; a ``str`` that prints as its value)."""

    POSE = "pose"  # a cap pose
    NO_POSE = "no pose"  # processed, no pose: the record's reason says why
    #: A recording's image that could not be decoded (or has no intrinsics): a lost frame.
    UNDECODABLE = "undecodable"
    #: The live node could not process the image (input or internal error: the reason).
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value


def status_reason(rec: FrameRecord) -> str:
    """The frame's reason as its label and status state it: an undecodable image's reason after
    ``undecodable: ``; any other as it is ('' with a pose)."""
    if rec.status is FrameStatus.UNDECODABLE:
        return f"{FrameStatus.UNDECODABLE}: {rec.reason}"
    return rec.reason


def record_status(rec: FrameRecord, warn_reliability: float = WARN_RELIABILITY) -> tuple[int, str]:
    """(level, message) of a frame: ERROR with its reason when it could not be processed, WARN
    "no pose: ..." without a pose, WARN "low reliability ..." below ``warn_reliability``, else
    OK "pose"."""
    if rec.status in (FrameStatus.UNDECODABLE, FrameStatus.FAILED):
        return ERROR, status_reason(rec)
    if rec.status is FrameStatus.NO_POSE:
        return WARN, f"no pose: {rec.reason or 'no tags'}"
    if math.isfinite(rec.reliability) and rec.reliability < warn_reliability:
        return WARN, f"low reliability {rec.reliability:.2f}"
    return OK, "pose"


def quality_values(rec: FrameRecord) -> dict[str, float]:
    """The numbers of the ``quality`` topic (the node adds its latency): NaN without a pose,
    reliability 0. The 95 % bounds come in degrees and mm and in SI units (``rot_err95_rad``,
    ``trans_err95_m``)."""
    return {
        "tags_detected": float(rec.tags_detected),
        "tags_used": float(rec.tags_used),
        "reliability": float(rec.reliability) if math.isfinite(rec.reliability) else 0.0,
        "rms_px": float(rec.rms_px),
        "rot_err95_deg": float(rec.rot_err95_deg),
        "trans_err95_mm": float(rec.trans_err95_mm),
        "rot_err95_rad": math.radians(rec.rot_err95_deg),
        "trans_err95_m": float(rec.trans_err95_mm) / 1000.0,
    }


def status_values(rec: FrameRecord) -> dict[str, float | int | bool]:
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
    if rec.head_ypr_deg is not None:
        values.update({f"{k}_deg": float(v)
                       for k, v in zip(("yaw", "pitch", "roll"), rec.head_ypr_deg)})
    return values


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
