"""What ficap_node publishes: its publishers, made on a node, and the outputs of one image.

Per image, stamped with it (topics relative, remappable; units SI beside the human ones):
    ``head_pose``, ``head_pose/with_covariance``, ``cap_pose``, ``head_pose/frontal``,
    ``head_rpy_deg`` (degrees), ``head_rpy`` (radians), ``/tf`` for a posed image reliable enough
    (``publish_min_reliability``), with ``head_twist`` (m/s, rad/s) when the estimator measures
    the head's velocity (``ficap_ros.io.frames.pose_outputs``); the mount on ``/tf_static`` from
    the first processed image; ``quality`` (JointState of named numbers) and ``status``
    (DiagnosticArray) for every image; ``detections`` (apriltag_msgs/AprilTagDetectionArray) and
    ``detections/fit`` (JointState) for every processed image; ``markers`` and ``debug_image``
    while someone subscribes. ``/diagnostics`` is the node's 1 Hz health (its timer publishes it
    here).

Without apriltag_msgs (a ROS install lacking ``ros-jazzy-apriltag-msgs``) ``detections`` is left
out, said in one log line at start; TF: ``ficap_ros.ros.tf``.
"""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import (
    PoseStamped,
    PoseWithCovarianceStamped,
    TwistStamped,
    Vector3Stamped,
)
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io import messages
from ficap_ros.io.detections import apriltag_array, fit_values
from ficap_ros.io.frames import OutputFrames, pose_outputs
from ficap_ros.ros import live
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.tf import TfOutput
from ficap_ros.stamps import stamp_to_ns

__all__ = ["NodeOutputs", "STATUS_NAME"]

#: The per-frame status's name.
STATUS_NAME = "ficap"


def _apriltag_array_class(node: Node) -> Any | None:
    try:
        from apriltag_msgs.msg import AprilTagDetectionArray
    except ImportError:
        node.get_logger().warning("no detections topic: apriltag_msgs is not importable (install "
                                  "ros-jazzy-apriltag-msgs); detections/fit is published")
        return None
    return AprilTagDetectionArray


class NodeOutputs:
    """The node's publishers (made on ``node``) and the publishing of one image's outputs."""

    def __init__(self, node: Node) -> None:
        self._node = node
        pub = node.create_publisher
        # The pose outputs by io.frames.pose_outputs' names.
        self.pubs = {"head": pub(PoseStamped, "head_pose", 10),
                     "head_cov": pub(PoseWithCovarianceStamped, "head_pose/with_covariance", 10),
                     "cap": pub(PoseStamped, "cap_pose", 10),
                     "head_frontal": pub(PoseStamped, "head_pose/frontal", 10),
                     "rpy_deg": pub(Vector3Stamped, "head_rpy_deg", 10),
                     "rpy_rad": pub(Vector3Stamped, "head_rpy", 10),
                     "twist": pub(TwistStamped, "head_twist", 10)}
        self.quality = pub(JointState, "quality", 10)
        self.status = pub(DiagnosticArray, "status", 10)
        self.diagnostics = pub(DiagnosticArray, "/diagnostics", 10)
        self.markers = pub(MarkerArray, "markers", 10)
        # Reliable publishers match both reliable and best-effort subscribers (rviz, rqt).
        self.debug = pub(Image, "debug_image", 2)
        self.fit = pub(JointState, "detections/fit", 10)
        array = _apriltag_array_class(node)
        self.detections = pub(array, "detections", 10) if array is not None else None
        self.tf = TfOutput(node)

    def frame(self, header: Header, frame: live.LiveFrame, frames: OutputFrames,
              model: CapModel, latency_ms: float, dropped: int) -> None:
        """Everything of a processed image (module docstring)."""
        rec = frame.record
        stamp_ns = stamp_to_ns(header.stamp)
        if frame.publish_pose:
            for name, out in pose_outputs(ros_msgs.RCLPY, stamp_ns, rec, frames).items():
                self.pubs[name].publish(out)
        self.tf.publish(rec, frames, with_pose=frame.publish_pose)
        self.status_of(header, frame, latency_ms, dropped, frames.output_frame)
        if rec.tags is not None:
            cam = Header(stamp=header.stamp, frame_id=header.frame_id)
            self.fit.publish(messages.named_values(ros_msgs.RCLPY, cam, fit_values(rec.tags)))
            if self.detections is not None:
                self.detections.publish(apriltag_array(ros_msgs.RCLPY, cam, rec.tags))
        self._drawings(header, frame, model)

    def status_of(self, header: Header, frame: live.LiveFrame, latency_ms: float, dropped: int,
                  output_frame: str) -> None:
        """``quality`` and ``status`` of an image (``ficap_ros.io.status``'s values, as
        labels.mcap's; ``latency_ms`` NaN for an image that failed)."""
        self.quality.publish(messages.named_values(ros_msgs.RCLPY, header,
                                                   frame.quality_values(latency_ms)))
        status = ros_msgs.diagnostic_status(
            STATUS_NAME, bytes([frame.level]), frame.message,
            frame.status_values(latency_ms, dropped), hardware_id=header.frame_id)
        out = Header(stamp=header.stamp, frame_id=output_frame or header.frame_id)
        self.status.publish(ros_msgs.diagnostic_array(out, status))

    def _drawings(self, header: Header, frame: live.LiveFrame, model: CapModel) -> None:
        """``markers`` and ``debug_image``, while someone subscribes (drawn in camera coordinates:
        the camera's frame)."""
        cam_header = Header(stamp=header.stamp, frame_id=header.frame_id)
        if self.markers.get_subscription_count() > 0:
            self.markers.publish(ros_msgs.markers_msg(cam_header, model, frame.record))
        if self.debug.get_subscription_count() > 0 and frame.image is not None:
            self.debug.publish(ros_msgs.debug_image_msg(
                frame.image, frame.detections, frame.record.T_cam_head, frame.camera, cam_header))

    def destroy(self) -> None:
        """Remove every publisher (the lifecycle node's cleanup)."""
        for p in [*self.pubs.values(), self.quality, self.status, self.diagnostics, self.markers,
                  self.debug, self.fit, self.detections]:
            if p is not None:
                self._node.destroy_publisher(p)
        self.tf.destroy()
