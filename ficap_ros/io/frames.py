"""The frames the outputs are in, one rule for the node and ``ficap replay``: the camera mount
(``camera_mount``, ``output_frame``), the TF tree of a frame, and the pose messages of a frame
record in those frames. ROS-free: messages come from ``ficap_ros.io.messages``' builders over a
``MessageClasses`` (rclpy's in the node, rosbags' in labels.mcap).

The TF tree composes with a robot's: the camera's optical frame (the image's ``frame_id``) is a
child of the mount's parent frame on ``/tf_static`` when there is a mount, and has no parent at all
without one. Per posed image, stamped with it, ``/tf`` carries camera -> ``ficap_cap`` (T_cam_cap)
-> ``ficap_head`` (R_cap_head) and, without a mount, camera -> the frontal frame (R_cam_frontal,
origin at the camera), so the frontal frame of ``head_pose/frontal`` is in the tree either way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.transform import Transform, rotate_covariance, rotate_twist
from ficap_ros.io import messages

if TYPE_CHECKING:
    from ficap_ros.io.labels import FrameRecord

__all__ = ["FRONTAL_FRAME", "CAP_FRAME", "HEAD_FRAME", "camera_mount_transform", "parse_camera_mount", "frames_reason", "OutputFrames",
           "FrameTransform", "static_transforms", "frame_transforms", "tf_message",
           "pose_outputs"]

#: Frame names of the outputs besides the camera's (the image's ``frame_id``): the frontal frame F
#: when no ``output_frame`` names it, the cap and the head.
FRONTAL_FRAME = "ficap_frontal"
CAP_FRAME = "ficap_cap"
HEAD_FRAME = "ficap_head"


def camera_mount_transform(values: Any) -> Transform | None:
    """A ``camera_mount`` (x y z in m, qx qy qz qw: ``static_transform_publisher``'s order) as
    T_parent_cam, or None when it is all zeros (not set).

    Raises:
        ConfigError: not 7 finite numbers or not a unit quaternion.
    """
    v = np.asarray(list(values), dtype=np.float64)
    if v.size == 7 and not np.any(v):
        return None
    return Transform.from_xyz_q_xyzw(v, "camera_mount")


def parse_camera_mount(text: str) -> Transform | None:
    """``camera_mount_transform`` of 7 numbers in a string, separated by spaces or commas (the
    command line's form).

    Raises:
        ConfigError: not 7 numbers, not finite, or not a unit quaternion.
    """
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise ConfigError(f"camera_mount {text!r}: expected 7 numbers x y z qx qy qz qw") from None
    return camera_mount_transform(values)


def frames_reason(output_frame: str, mount: Transform | None) -> str:
    """Why an ``output_frame`` without a mount is refused ('' when the pair is fine)."""
    if output_frame and mount is None:
        return (f"output_frame {output_frame!r} needs camera_mount (the camera's optical frame in "
                "it: x y z qx qy qz qw); without it the poses would only be relabelled")
    return ""


@dataclass(frozen=True)
class OutputFrames:
    """Where the outputs go.

    Attributes:
        output_frame: frame of the pose outputs ('' = the image's), reached through ``mount``.
        mount: T_parent_cam, the camera's optical frame in ``output_frame`` (or in
            ``frontal_frame`` when ``output_frame`` is ''); None = not set.
        frontal_frame: name of the frontal frame F when ``output_frame`` is '' (with an
            ``output_frame``, F is ``output_frame``: the mount gives F its axes).

    Raises:
        ConfigError: an ``output_frame`` without a mount.
    """

    output_frame: str = ""
    mount: Transform | None = None
    frontal_frame: str = FRONTAL_FRAME

    def __post_init__(self) -> None:
        if reason := frames_reason(self.output_frame, self.mount):
            raise ConfigError(reason)

    @property
    def frontal(self) -> str:
        """The frame of ``head_pose/frontal`` and the head angles: ``output_frame``, else
        ``frontal_frame``."""
        return self.output_frame or self.frontal_frame

    @property
    def moved(self) -> bool:
        """The pose outputs are moved into ``output_frame`` through the mount."""
        return bool(self.output_frame) and self.mount is not None


@dataclass(frozen=True)
class FrameTransform:
    """One edge of the TF tree: ``T`` is T_parent_child."""

    parent: str
    child: str
    T: Transform


def static_transforms(frames: OutputFrames, camera_frame: str) -> tuple[FrameTransform, ...]:
    """``/tf_static``: the mount's parent (``frames.frontal``) -> the camera, or nothing without a
    mount (the camera keeps whatever parent a robot's tree gives it)."""
    if frames.mount is None:
        return ()
    return (FrameTransform(frames.frontal, camera_frame, frames.mount),)


def frame_transforms(record: FrameRecord, frames: OutputFrames) -> tuple[FrameTransform, ...]:
    """``/tf`` of a posed frame (empty without a pose): camera -> cap -> head and, without a mount,
    camera -> the frontal frame (module docstring)."""
    if record.T_cam_cap is None:
        return ()
    cam = record.frame_id
    out = [FrameTransform(cam, CAP_FRAME, record.T_cam_cap),
           FrameTransform(CAP_FRAME, HEAD_FRAME, Transform(record.calibration.R_cap_head, np.zeros(3)))]
    if frames.mount is None:
        out.append(FrameTransform(cam, frames.frontal,
                                  Transform(record.calibration.R_cam_frontal, np.zeros(3))))
    return tuple(out)


def tf_message(c: messages.MessageClasses, stamp_ns: int,
               transforms: Sequence[FrameTransform]) -> Any:
    """``tf2_msgs/TFMessage`` of the transforms, each stamped ``stamp_ns``."""
    return c.types["tf2_msgs/msg/TFMessage"](transforms=[
        messages.transform_stamped(c, messages.header(c, stamp_ns, t.parent), t.child, t.T)
        for t in transforms])


def pose_outputs(c: messages.MessageClasses, stamp_ns: int, record: FrameRecord,
                 frames: OutputFrames) -> dict[str, Any]:
    """The pose messages of a posed frame, by output: ``head`` (PoseStamped), ``head_cov``
    (PoseWithCovarianceStamped), ``cap`` (PoseStamped), in ``output_frame`` through the mount or
    else the image's frame; ``head_frontal`` (PoseStamped), ``rpy_deg`` and ``rpy_rad``
    (Vector3Stamped: x roll, y pitch, z yaw) in the frontal frame (``frames.frontal``); ``twist``
    (TwistStamped: the head's twist, m/s and rad/s, in the frame of ``head``) only when the
    estimator measures the velocity (``FrameRecord.head_twist_cam``).

    The head's origin is the cap's and it turns with the cap, so its twist is the cap's whatever
    the head calibration; a fixed mount turns both vectors and adds no motion. Without a move the
    record's transforms and twist go out as they are (labels.mcap's values to the bit).
    """
    pose, T_cam_head, T_frontal_head = record.pose, record.T_cam_head, record.T_frontal_head
    assert pose is not None and T_cam_head is not None and T_frontal_head is not None
    out = messages.header(c, stamp_ns, frames.output_frame or record.frame_id)
    T_head, T_cap, cov, twist = T_cam_head, pose.T_cam_cap, pose.covariance, record.head_twist_cam
    if frames.moved:
        assert frames.mount is not None
        T_head, T_cap = frames.mount * T_cam_head, frames.mount * pose.T_cam_cap
        cov = rotate_covariance(pose.covariance, frames.mount.rotation)
        twist = None if twist is None else rotate_twist(twist, frames.mount.rotation)
    # The head in F: through the mount (the camera's place in F too), or the record's (the
    # camera at F's origin).
    frontal = messages.header(c, stamp_ns, frames.frontal)
    T_frontal = frames.mount * T_cam_head if frames.mount is not None else T_frontal_head
    return {
        "head": messages.pose_stamped(c, out, T_head),
        "head_cov": messages.pose_with_covariance_stamped(c, out, T_head, cov),
        "cap": messages.pose_stamped(c, out, T_cap),
        "head_frontal": messages.pose_stamped(c, frontal, T_frontal),
        "rpy_deg": messages.rpy_deg(c, frontal, T_frontal_head.rotation),
        "rpy_rad": messages.rpy_rad(c, frontal, T_frontal_head.rotation),
        **({"twist": messages.twist_stamped(c, out, twist)} if twist is not None else {}),
    }
