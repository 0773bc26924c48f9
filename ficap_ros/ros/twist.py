"""The node's twist output: ``head_twist`` (geometry_msgs/TwistStamped), the head's velocity at
the image's stamp.

The head frame's origin is the cap's and it turns with the cap, so the head's twist is the cap's
(``CapPose.velocity``: the origin's linear velocity in m/s, then the angular velocity in rad/s,
in the camera's axes), whatever the head calibration. It goes out in the pose outputs' frame:
``output_frame`` through ``camera_mount`` (both vectors turned into its axes; a fixed mount adds
no motion), else the image's frame. A frame whose estimator does not measure the velocity
(``CapPose.velocity`` None) has none: nothing is published for it, and its poses are unchanged.
labels.mcap carries the same message (``ficap_ros.io.labels``, in the camera's frame).
"""

from __future__ import annotations

from typing import Any

from geometry_msgs.msg import TwistStamped
from std_msgs.msg import Header

from ficap_ros.geometry.transform import Transform, rotate_twist
from ficap_ros.io import messages
from ficap_ros.io.labels import FrameRecord
from ficap_ros.ros.msgs import RCLPY

__all__ = ["TOPIC", "create_publisher", "head_twist"]

#: The topic, relative to the node's namespace.
TOPIC = "head_twist"


def create_publisher(node: Any) -> Any:
    """The node's ``head_twist`` publisher (the pose outputs' depth)."""
    return node.create_publisher(TwistStamped, TOPIC, 10)


def head_twist(header: Header, record: FrameRecord, output_frame: str,
               mount: Transform | None) -> Any | None:
    """The frame's ``head_twist`` message (stamp = the image's), or None without a measured
    velocity.

    Args:
        header: the image's header (stamp and camera frame).
        record: the frame's record.
        output_frame: frame_id of the pose outputs ('' = the image's).
        mount: T_output_cam (``camera_mount``), used when ``output_frame`` is set.
    """
    twist = record.head_twist_cam
    if twist is None:
        return None
    if output_frame and mount is not None:
        twist = rotate_twist(twist, mount.rotation)
    out = Header(stamp=header.stamp, frame_id=output_frame or header.frame_id)
    return messages.twist_stamped(RCLPY, out, twist)
