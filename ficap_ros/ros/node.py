"""``ficap_node``: live Fi-Cap head pose from a camera stream (a thin ROS 2 skin over the core).

Subscribes (relative names, remappable):
    ``image`` (sensor_msgs/Image) or ``image/compressed`` (sensor_msgs/CompressedImage), chosen by
    ``image_transport``; ``camera_info`` (sensor_msgs/CameraInfo); the reference head pose
    ``calibration.reference_topic`` (geometry_msgs/PoseStamped) when set.
Publishes (stamp = the image's; poses in the image's frame, or in ``output_frame`` through the
``camera_mount`` transform):
    ``head_pose`` (PoseStamped: T_out_head = T_out_cam * T_cam_cap * R_cap_head),
    ``head_pose/with_covariance`` (PoseWithCovarianceStamped, the estimator's covariance in ROS
    order, rotated into the output frame), ``cap_pose`` (PoseStamped, uncalibrated),
    ``head_pose/frontal`` (PoseStamped: the head in the frontal frame F), ``head_rpy_deg``
    (Vector3Stamped: x roll, y pitch, z yaw of the head in F, degrees, REP-103), ``head_twist``
    (TwistStamped: the head's velocity when the estimator measures it, ``ros.twist``), ``quality``
    (JointState: numeric per-frame tag counts, reliability, rms and error bounds by name), ``status``
    (DiagnosticArray, one per frame), ``/diagnostics`` (1 Hz health), ``markers`` (MarkerArray, in the
    camera frame) and ``debug_image`` (Image) only while someone subscribes.
Services:
    ``~/calibrate`` (std_srvs/Trigger), ``~/clear_calibration`` (std_srvs/Trigger).

Frames arrive in a one-slot mailbox and are processed by a worker thread: the newest frame wins,
replaced frames are counted as dropped, and callbacks (services, CameraInfo) never wait for a frame
to be processed. What a frame becomes (decoding, intrinsics, pipeline, status) is
``ficap_ros.ros.live``; all detection and pose estimation is ``ficap_ros.vision.pipeline.FrameProcessor``.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from ficap_ros.io import messages
from ficap_ros.io.camera_info import CameraInfoCache
from ficap_ros.io.status import PeriodStats
from ficap_ros.ros import live
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros import params as ros_params
from ficap_ros.ros import twist as ros_twist
from ficap_ros.ros.live_calibration import LiveCalibration, compute_calibration
from ficap_ros.ros.mailbox import Mailbox
from ficap_ros.ros.spin import run_node
from ficap_ros.vision.calibration import CalibrationResult, HeadCalibration

__all__ = ["FicapNode", "main"]

NODE_NAME = "ficap_node"
STATUS_NAME = "ficap"


class FicapNode(Node):
    """Fi-Cap head pose node (see the module docstring for its interface)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._config = cfg = ros_params.declare(self)
        self._mount = cfg.mount
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        # Core objects: the pipeline, the intrinsics, the calibration (swapped whole, under a lock).
        self._processor = live.frame_processor(cfg)
        self._cameras = CameraInfoCache.with_file(cfg.camera_info_file)
        if self._cameras.static_error:
            self.get_logger().error(self._cameras.static_error)
        self._calibration = LiveCalibration(self._mount)
        self._recorder = self._calibration.recorder
        for severity, text in self._calibration.start(cfg.calibration_file):
            getattr(self.get_logger(), severity)(text)

        # State shared between callbacks and the worker.
        self._mailbox = Mailbox()
        self._stats = PeriodStats()
        self._camera_frame = ""  # the frame_id of the last image (the default hardware_id)

        self._subscribe(cfg)
        self._advertise()
        self.unknown_parameters = ros_params.unknown_parameters(self)
        if self.unknown_parameters:
            self.get_logger().warning(ros_params.unknown_warning(self.unknown_parameters))
        self._worker = threading.Thread(target=self._work, name="ficap_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ficap_node ready: {cfg.image_transport} images on {self._image_sub.topic_name}, "
            f"pose method {cfg.pose_method}, "
            f"{'calibrated' if self.calibration.calibrated else 'not calibrated'}")

    def _subscribe(self, cfg: ros_params.NodeConfig) -> None:
        """The image, CameraInfo and reference subscriptions (callback groups: frames and side
        inputs never wait on each other when the node is composed into a multi-threaded executor;
        ficap_node itself spins one thread, ``spin.make_executor``, where every callback is short)."""
        inputs, side = MutuallyExclusiveCallbackGroup(), ReentrantCallbackGroup()
        sensor_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=cfg.qos_depth,
            reliability=(ReliabilityPolicy.BEST_EFFORT if cfg.qos_reliability == "best_effort"
                         else ReliabilityPolicy.RELIABLE),
            durability=qos_profile_sensor_data.durability)
        # CameraInfo before the image: one executor thread takes the ready subscriptions in the order
        # they were created, so a frame's CameraInfo that came with it is in place for the worker.
        self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, sensor_qos,
                                 callback_group=side)
        if cfg.image_transport == "compressed":
            # image_transport's naming: <base topic>/compressed, so remapping `image` moves both.
            self._image_sub = self.create_subscription(
                CompressedImage, self.resolve_topic_name("image") + "/compressed", self._on_image,
                sensor_qos, callback_group=inputs)
        else:
            self._image_sub = self.create_subscription(Image, "image", self._on_image, sensor_qos,
                                                       callback_group=inputs)
        if cfg.calibration_reference_topic:
            ref_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                 reliability=ReliabilityPolicy.BEST_EFFORT)
            self.create_subscription(PoseStamped, cfg.calibration_reference_topic,
                                     self._on_reference, ref_qos, callback_group=side)

    def _advertise(self) -> None:
        """The publishers, the calibration services and the diagnostics timer."""
        pub = self.create_publisher
        # The pose outputs by ros_msgs.pose_outputs' names.
        self._pubs = {"head": pub(PoseStamped, "head_pose", 10),
                      "head_cov": pub(PoseWithCovarianceStamped, "head_pose/with_covariance", 10),
                      "cap": pub(PoseStamped, "cap_pose", 10),
                      "head_frontal": pub(PoseStamped, "head_pose/frontal", 10),
                      "rpy": pub(Vector3Stamped, "head_rpy_deg", 10),
                      "twist": ros_twist.create_publisher(self)}
        self._pub_quality = pub(JointState, "quality", 10)
        self._pub_status = pub(DiagnosticArray, "status", 10)
        self._pub_diag = pub(DiagnosticArray, "/diagnostics", 10)
        self._pub_markers = pub(MarkerArray, "markers", 10)
        # Reliable publishers match both reliable and best-effort subscribers (rviz, rqt).
        self._pub_debug = pub(Image, "debug_image", 2)
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=services)
        self.create_service(Trigger, "~/clear_calibration", self._on_clear_calibration,
                            callback_group=services)
        self.create_timer(1.0, self._on_diagnostics_timer,
                          callback_group=MutuallyExclusiveCallbackGroup())

    # -- parameters ------------------------------------------------------------------------------
    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        reason = ros_params.refusal(self, params)
        return SetParametersResult(successful=not reason, reason=reason)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        self._config = cfg = ros_params.NodeConfig.from_values(ros_params.current_values(self))
        self._mount = cfg.mount
        kept = live.apply_settings(self._processor, cfg)
        if kept:
            self.get_logger().error(kept)
        if any(p.name == "camera_mount" for p in params):
            self._calibration.set_mount(self._mount)  # else the frontal frame stays

    # -- calibration -----------------------------------------------------------------------------
    @property
    def calibration(self) -> HeadCalibration:
        """The calibration in use."""
        return self._calibration.current

    def _run_calibration(self) -> CalibrationResult:
        """What ``~/calibrate`` computes now (``live_calibration.compute_calibration``)."""
        return compute_calibration(self._config, self._recorder, self._calibration.frontal_frame())

    def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._answer(response, *self._calibration.calibrate(
            self._run_calibration, self._config.calibration_file))

    def _on_clear_calibration(self, request: Trigger.Request,
                              response: Trigger.Response) -> Trigger.Response:
        return self._answer(response, *self._calibration.clear_and_save(self._config.calibration_file))

    def _answer(self, response: Trigger.Response, outcome: str, message: str) -> Trigger.Response:
        response.success, response.message = outcome == "ok", message
        # (rclpy refuses two severities from one call site)
        if outcome == "ok":
            self.get_logger().info(message)
        elif outcome == "refused":
            self.get_logger().warning(message)
        else:
            self.get_logger().error(message)
        return response

    # -- inputs ----------------------------------------------------------------------------------
    def _on_image(self, msg: Image | CompressedImage) -> None:
        # An image above the pixel budget is refused from its header, before it is queued.
        if reason := live.refusal_before_queueing(msg):
            self._report_error(msg.header, reason)
            return
        self._mailbox.put((msg, time.monotonic_ns()))

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self._cameras.add(ros_msgs.stamp_to_ns(msg.header.stamp), msg)

    def _on_reference(self, msg: PoseStamped) -> None:
        q = live.reference_q_xyzw(msg)
        if q is None:
            self.get_logger().warning("reference pose with an invalid quaternion ignored",
                                      throttle_duration_sec=self._config.warn_throttle_s)
        else:
            self._recorder.add_reference(ros_msgs.stamp_to_ns(msg.header.stamp), q)

    # -- processing ------------------------------------------------------------------------------
    def _work(self) -> None:
        self._mailbox.serve(lambda item: self._process(*item), self._on_internal_error)

    def _on_internal_error(self, item: tuple[Any, int], err: Exception) -> None:
        self._report_error(item[0].header, f"internal error: {type(err).__name__}: {err}")
        self.get_logger().error(f"processing failed: {err!r}",
                                throttle_duration_sec=self._config.warn_throttle_s)

    def _report_error(self, header: Header, reason: str) -> None:
        self._stats.error(reason)
        self.get_logger().warning(reason, throttle_duration_sec=self._config.warn_throttle_s)
        self._publish_status(header, live.failed_frame(ros_msgs.stamp_to_ns(header.stamp),
                                                       header.frame_id, reason, self.calibration),
                             math.nan)

    def _publish_status(self, header: Header, frame: live.LiveFrame, latency_ms: float) -> None:
        """``quality`` and ``status`` of a frame (``ficap_ros.io.status``'s values, as labels.mcap)."""
        self._pub_quality.publish(messages.named_values(ros_msgs.RCLPY, header,
                                                         frame.quality_values(latency_ms)))
        status = ros_msgs.diagnostic_status(
            STATUS_NAME, bytes([frame.level]), frame.message,
            frame.status_values(latency_ms, self._mailbox.dropped), hardware_id=header.frame_id)
        out = Header(stamp=header.stamp, frame_id=self._config.output_frame or header.frame_id)
        self._pub_status.publish(ros_msgs.diagnostic_array(out, status))

    def _process(self, msg: Image | CompressedImage, received_ns: int) -> None:
        cfg, header = self._config, msg.header
        self._camera_frame = header.frame_id
        # One read of the calibration per frame: the service thread swaps it whole.
        frame = live.process_image(msg, self._processor, self._cameras, self.calibration, cfg)
        if frame.failed:
            self._report_error(header, frame.message)
            return
        rec = frame.record
        if frame.publish_pose:
            for name, out in ros_msgs.pose_outputs(header, rec, cfg.output_frame, cfg.frontal_frame,
                                                   self._mount).items():
                self._pubs[name].publish(out)
        latency_ms = (time.monotonic_ns() - received_ns) / 1e6
        self._publish_status(header, frame, latency_ms)
        self._publish_drawings(header, frame)
        self._stats.frame(rec.tags_detected, latency_ms)
        if rec.pose is not None:
            self._recorder.add_cap(rec.stamp_ns, rec.pose.T_cam_cap.rotation, rec.pose.reliability)

    def _publish_drawings(self, header: Header, frame: live.LiveFrame) -> None:
        """``markers`` and ``debug_image``, while someone subscribes (drawn in camera coordinates:
        the camera's frame)."""
        cam_header = Header(stamp=header.stamp, frame_id=header.frame_id)
        if self._pub_markers.get_subscription_count() > 0:
            self._pub_markers.publish(ros_msgs.markers_msg(cam_header, self._processor.model,
                                                           frame.record))
        if self._pub_debug.get_subscription_count() > 0 and frame.image is not None:
            self._pub_debug.publish(ros_msgs.debug_image_msg(
                frame.image, frame.detections, frame.record.T_cam_head, frame.camera, cam_header))

    # -- diagnostics -----------------------------------------------------------------------------
    def _on_diagnostics_timer(self) -> None:
        level, message, values = self._stats.health(
            self._mailbox.counts(), self.calibration.calibrated, self._calibration.mode)
        status = ros_msgs.diagnostic_status(
            f"{self.get_name()}: pipeline", bytes([level]), message, values,
            hardware_id=self._config.diagnostics_hardware_id or self._camera_frame)
        header = Header(stamp=self.get_clock().now().to_msg())
        self._pub_diag.publish(ros_msgs.diagnostic_array(header, status))

    # -- lifecycle -------------------------------------------------------------------------------
    @property
    def dropped_frames(self) -> int:
        return self._mailbox.dropped

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node."""
        self._mailbox.close()
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout=5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Run ``ficap_node`` (``spin.run_node``: until Ctrl-C or external shutdown)."""
    return run_node(FicapNode, "ficap_node", args)


if __name__ == "__main__":
    raise SystemExit(main())
