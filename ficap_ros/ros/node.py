"""``ficap_node``: live Fi-Cap head pose from a camera stream (a thin ROS 2 skin over the core).

Subscribes (relative names, remappable):
    ``image`` (sensor_msgs/Image) or ``image/compressed`` (sensor_msgs/CompressedImage), chosen by
    ``image_transport``; its CameraInfo (sensor_msgs/CameraInfo), beside the image topic as
    image_transport places it (``ficap_ros.ros.inputs``); the reference head pose
    ``calibration.reference_topic`` (geometry_msgs/PoseStamped) when set.
Publishes (stamp = the image's; poses in the image's frame, or in ``output_frame`` through the
``camera_mount`` transform; ``ficap_ros.ros.outputs`` lists them all):
    ``head_pose``, ``head_pose/with_covariance``, ``cap_pose``, ``head_pose/frontal``,
    ``head_rpy_deg`` and ``head_rpy`` (degrees, radians), ``head_twist``, ``/tf`` and
    ``/tf_static``, ``quality``, ``status``, ``detections``, ``detections/fit``, ``/diagnostics``
    (1 Hz health), ``markers`` and ``debug_image`` (while someone subscribes).
Services:
    ``~/calibrate`` (std_srvs/Trigger), ``~/clear_calibration`` (std_srvs/Trigger).

Frames arrive in a one-slot mailbox and are processed by a worker thread: the newest frame wins,
replaced frames are counted as dropped, and callbacks (services, CameraInfo) never wait for a frame
to be processed. What a frame becomes (decoding, intrinsics, pipeline, status) is
``ficap_ros.ros.live``; all detection and pose estimation is ``ficap_ros.vision.pipeline.FrameProcessor``.
The lifecycle variant (``ficap_ros.ros.lifecycle``) runs the same steps: configure, activate.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from ficap_ros.io.camera_info import CameraInfoCache
from ficap_ros.io.status import PeriodStats
from ficap_ros.ros import inputs, live
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros import params as ros_params
from ficap_ros.ros.live_calibration import LiveCalibration, compute_calibration
from ficap_ros.ros.mailbox import Mailbox
from ficap_ros.ros.outputs import NodeOutputs
from ficap_ros.ros.spin import run_node
from ficap_ros.vision.calibration import CalibrationResult, HeadCalibration

__all__ = ["FicapNodeSteps", "FicapNode", "main", "NODE_NAME"]

NODE_NAME = "ficap_node"


class FicapNodeSteps:
    """What ficap_node does, in the steps a lifecycle node takes them (``configure``: parameters,
    pipeline, calibration, outputs, services and the worker; ``activate``: the subscriptions;
    ``deactivate``; ``cleanup``). Mixed into an rclpy ``Node`` (``FicapNode``) or
    ``LifecycleNode`` (``ficap_ros.ros.lifecycle``)."""

    _inputs: inputs.Inputs | None = None
    _worker: threading.Thread | None = None
    _callbacks_added = False

    # -- the steps -------------------------------------------------------------------------------
    def configure(self: Any) -> None:
        """Declare and read the parameters, build the pipeline, load the calibration, advertise.

        Raises:
            ConfigError: bad parameters (``params.declare``).
        """
        self._config = cfg = ros_params.declare(self)
        self._values = ros_params.current_values(self)
        self._mount = cfg.mount
        if not self._callbacks_added:
            self.add_on_set_parameters_callback(self._on_set_parameters)
            self.add_post_set_parameters_callback(self._after_set_parameters)
            self._callbacks_added = True
        self._processor = live.frame_processor(cfg)
        self.kernels_warm_up_s = self._warm_up_kernels()
        self._cameras = CameraInfoCache.with_file(cfg.camera_info_file)
        if self._cameras.static_error:
            self.get_logger().error(self._cameras.static_error)
        self._calibration = LiveCalibration(self._mount)
        self._recorder = self._calibration.recorder
        for severity, text in self._calibration.start(cfg.calibration_file):
            getattr(self.get_logger(), severity)(text)
        if warning := ros_params.calibration_folder_warning(cfg.calibration_file):
            self.get_logger().warning(warning)
        # State shared between callbacks and the worker.
        self._mailbox, self._stats = Mailbox(), PeriodStats()
        self._camera_frame = ""  # the frame_id of the last image (the default hardware_id)
        self._out = NodeOutputs(self)
        services = MutuallyExclusiveCallbackGroup()
        self._trigger_services = [
            self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=services),
            self.create_service(Trigger, "~/clear_calibration", self._on_clear_calibration,
                                callback_group=services)]
        self._timer = self.create_timer(1.0, self._on_diagnostics_timer,
                                        callback_group=MutuallyExclusiveCallbackGroup())
        self._worker = threading.Thread(target=self._work, name="ficap_worker", daemon=True)
        self._worker.start()

    @staticmethod
    def _warm_up_kernels() -> float:
        """The compiled kernels (``ficap_ros.vision.jit``: the corner stage's, the photometric and
        the moving tags' fits) loaded from their cache, or compiled, now, so no frame waits for
        them: the seconds it took. All of them whatever the parameters say: the corner stage
        always uses its kernels, and a camera_info_file's exposure may switch on the moving tags'
        fit later."""
        from ficap_ros.vision.jit import warm_up

        return warm_up()

    def activate(self: Any) -> None:
        """Subscribe; warn about parameters given but not declared (after the subscriptions'
        ``qos_overrides`` are declared). Raises ``ConfigError`` for a bad ``qos_overrides``."""
        cfg = self._config
        self._inputs = inputs.subscribe(self, cfg, self._on_image, self._on_camera_info,
                                        self._on_reference)
        self._image_sub = self._inputs.image
        self.unknown_parameters = ros_params.unknown_parameters(self)
        if self.unknown_parameters:
            self.get_logger().warning(ros_params.unknown_warning(self.unknown_parameters))
        self.get_logger().info(
            f"ficap_node ready: {cfg.image_transport} images on {self._inputs.image.topic_name}, "
            f"CameraInfo on {self._inputs.camera_info.topic_name}, pose method {cfg.pose_method}, "
            f"{'calibrated' if self.calibration.calibrated else 'not calibrated'}"
            + f", kernels ready in {self.kernels_warm_up_s:.1f} s")

    def deactivate(self: Any) -> None:
        """Unsubscribe (frames in flight still finish)."""
        if self._inputs is not None:
            self._inputs.destroy(self)
            self._inputs = None

    def cleanup(self: Any) -> None:
        """Stop the worker; remove the outputs, services and timer."""
        self._stop_worker()
        self._out.destroy()
        for service in self._trigger_services:
            self.destroy_service(service)
        self.destroy_timer(self._timer)

    def _stop_worker(self: Any) -> None:
        if self._worker is None:
            return
        self._mailbox.close()
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout=5.0)
        self._worker = None

    # -- parameters ------------------------------------------------------------------------------
    def _on_set_parameters(self: Any, params: list[Parameter]) -> SetParametersResult:
        reason = ros_params.refusal(self, params)
        return SetParametersResult(successful=not reason, reason=reason)

    def _after_set_parameters(self: Any, params: list[Parameter]) -> None:
        for line in ros_params.change_lines(self._values, params):
            self.get_logger().info(line)
        self._values = ros_params.current_values(self)
        self._config = cfg = ros_params.NodeConfig.from_values(self._values)
        self._mount = cfg.mount
        kept = live.apply_settings(self._processor, cfg)
        if kept:
            self.get_logger().error(kept)
        if any(p.name == "camera_mount" for p in params):
            self._calibration.set_mount(self._mount)  # else the frontal frame stays

    # -- calibration -----------------------------------------------------------------------------
    @property
    def calibration(self: Any) -> HeadCalibration:
        """The calibration in use."""
        return self._calibration.current

    def _run_calibration(self: Any) -> CalibrationResult:
        """What ``~/calibrate`` computes now (``live_calibration.compute_calibration``)."""
        return compute_calibration(self._config, self._recorder, self._calibration.frontal_frame())

    def _on_calibrate(self: Any, request: Trigger.Request,
                      response: Trigger.Response) -> Trigger.Response:
        return self._answer(response, *self._calibration.calibrate(
            self._run_calibration, self._config.calibration_file))

    def _on_clear_calibration(self: Any, request: Trigger.Request,
                              response: Trigger.Response) -> Trigger.Response:
        return self._answer(response, *self._calibration.clear_and_save(self._config.calibration_file))

    def _answer(self: Any, response: Trigger.Response, outcome: str,
                message: str) -> Trigger.Response:
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
    def _on_image(self: Any, msg: Image | CompressedImage) -> None:
        # An image above the pixel budget is refused from its header, before it is queued.
        if reason := live.refusal_before_queueing(msg):
            self._report_error(msg.header, reason)
            return
        self._mailbox.put((msg, time.monotonic_ns()))

    def _on_camera_info(self: Any, msg: CameraInfo) -> None:
        self._cameras.add(ros_msgs.stamp_to_ns(msg.header.stamp), msg)

    def _on_reference(self: Any, msg: Any) -> None:
        q = live.reference_q_xyzw(msg)
        if q is None:
            self.get_logger().warning("reference pose with an invalid quaternion ignored",
                                      throttle_duration_sec=self._config.warn_throttle_s)
        else:
            self._recorder.add_reference(ros_msgs.stamp_to_ns(msg.header.stamp), q)

    # -- processing ------------------------------------------------------------------------------
    def _work(self: Any) -> None:
        self._mailbox.serve(lambda item: self._process(*item), self._on_internal_error)

    def _on_internal_error(self: Any, item: tuple[Any, int], err: Exception) -> None:
        self._report_error(item[0].header, f"internal error: {type(err).__name__}: {err}")
        self.get_logger().error(f"processing failed: {err!r}",
                                throttle_duration_sec=self._config.warn_throttle_s)

    def _report_error(self: Any, header: Header, reason: str) -> None:
        self._stats.error(reason)
        self.get_logger().warning(reason, throttle_duration_sec=self._config.warn_throttle_s)
        frame = live.failed_frame(ros_msgs.stamp_to_ns(header.stamp), header.frame_id, reason,
                                  self.calibration)
        self._out.status_of(header, frame, math.nan, self._mailbox.dropped,
                            self._config.output_frame)

    def _process(self: Any, msg: Image | CompressedImage, received_ns: int) -> None:
        header = msg.header
        self._camera_frame = header.frame_id
        # One read of the calibration per frame: the service thread swaps it whole.
        frame = live.process_image(msg, self._processor, self._cameras, self.calibration,
                                   self._config)
        if frame.failed:
            self._report_error(header, frame.message)
            return
        rec = frame.record
        # Buffered for ~/calibrate before its outputs go out: a client that saw this frame's
        # status finds it in the next calibration.
        if rec.pose is not None:
            self._recorder.add_cap(rec.stamp_ns, rec.pose.T_cam_cap.rotation, rec.pose.reliability)
        latency_ms = (time.monotonic_ns() - received_ns) / 1e6
        self._stats.frame(rec.tags_detected, latency_ms)
        self._out.frame(header, frame, self._config.frames, self._processor.model, latency_ms,
                        self._mailbox.dropped)

    # -- diagnostics -----------------------------------------------------------------------------
    def _on_diagnostics_timer(self: Any) -> None:
        level, message, values = self._stats.health(
            self._mailbox.counts(), self.calibration.calibrated, self._calibration.mode)
        status = ros_msgs.diagnostic_status(
            f"{self.get_name()}: pipeline", bytes([level]), message, values,
            hardware_id=self._config.diagnostics_hardware_id or self._camera_frame)
        header = Header(stamp=self.get_clock().now().to_msg())
        self._out.diagnostics.publish(ros_msgs.diagnostic_array(header, status))

    @property
    def dropped_frames(self: Any) -> int:
        return self._mailbox.dropped


class FicapNode(FicapNodeSteps, Node):
    """Fi-Cap head pose node (the module docstring says its interface): configured and active
    from its construction."""

    def __init__(self, **kwargs: Any) -> None:
        Node.__init__(self, NODE_NAME, **kwargs)
        self.configure()
        self.activate()

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node."""
        self._stop_worker()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Run ``ficap_node`` (``spin.run_node``: until Ctrl-C or external shutdown; ``--help``
    prints its interface and parameters)."""
    return run_node(FicapNode, NODE_NAME, args, usage=ros_params.usage(__doc__ or ""))


if __name__ == "__main__":
    raise SystemExit(main())
