"""What a processed frame reports: its status level and message (the node's ``status``, labels.mcap's
``status`` and ``/diagnostics`` decide it here, once).

Levels are ``diagnostic_msgs/DiagnosticStatus``'s numbers (OK 0, WARN 1, ERROR 2); this module is
ROS-free, so the node turns them into its message type.
"""

from __future__ import annotations

import math

__all__ = ["OK", "WARN", "ERROR", "WARN_RELIABILITY", "frame_status"]

OK, WARN, ERROR = 0, 1, 2

#: Status level is WARN below this reliability (the node's ``warn_reliability`` default).
WARN_RELIABILITY = 0.5


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
