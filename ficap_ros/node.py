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
    (Vector3Stamped: x roll, y pitch, z yaw of the head in F, degrees, REP-103), ``quality``
    (JointState: numeric per-frame tag counts, reliability, rms and error bounds by name), ``status``
    (DiagnosticArray, one per frame), ``/diagnostics`` (1 Hz health), ``markers`` (MarkerArray, in the
    camera frame) and ``debug_image`` (Image) only while someone subscribes.
Services:
    ``~/calibrate`` (std_srvs/Trigger), ``~/clear_calibration`` (std_srvs/Trigger).

Frames arrive in a one-slot mailbox and are processed by a worker thread: the newest frame wins,
replaced frames are counted as dropped, and callbacks (services, CameraInfo) never wait for a frame
to be processed. All detection and pose estimation is ``ficap_ros.pipeline.FrameProcessor``.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Vector3Stamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from ficap_ros import ros_msgs
from ficap_ros.calibration import (
    CalibrationRecorder,
    CalibrationResult,
    HeadCalibration,
    calibrated_frontal,
    calibrate_frontal,
    calibrate_reference,
    frontal_from_camera_mount,
    load_calibration,
    save_calibration,
)
from ficap_ros.camera import CameraModel, load_camera_yaml
from ficap_ros.cap_model import load_model, nominal_model
from ficap_ros.detection import DetectorConfig
from ficap_ros.errors import CalibrationError, ConfigError, FicapError, IntrinsicsError
from ficap_ros.native_log import ThrottledStderr
from ficap_ros.metrics import angle_deg, yaw_pitch_roll_deg
from ficap_ros.pipeline import FrameProcessor, FrameResult
from ficap_ros.pose import POSE_METHODS, PoseConfig, UncertaintyConfig
from ficap_ros.report import (
    WARN_RELIABILITY,
    LabelRecord,
    frame_status,
    quality_values,
    record_from_pose,
    record_from_result,
    record_status,
    status_values,
)
from ficap_ros.transform import Transform, rotate_covariance

__all__ = ["FicapNode", "ParamSpec", "PARAMETERS", "NodeConfig", "main"]

NODE_NAME = "ficap_node"
STATUS_NAME = "ficap"


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: declared once from this table, validated on every set.

    Attributes:
        name: dotted parameter name.
        default: default value (its Python type is the parameter type).
        description: one line for ``ros2 param describe``.
        range: inclusive (low, high) for numbers.
        choices: allowed strings.
        read_only: structural (topics, files, detector): fixed after start.
    """

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False


_UNCERTAINTY = UncertaintyConfig()  # the covariance floors' defaults, declared in pose.py

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("image_transport", "raw", "Input transport: 'raw' subscribes to image, 'compressed' "
              "to image/compressed.", choices=("raw", "compressed"), read_only=True),
    ParamSpec("qos.reliability", "best_effort", "Reliability of the image/camera_info "
              "subscriptions (best_effort = sensor-data QoS, matches any publisher).",
              choices=("best_effort", "reliable"), read_only=True),
    ParamSpec("qos.depth", 5, "History depth of the image/camera_info subscriptions.",
              range=(1, 100), read_only=True),
    ParamSpec("camera_info_file", "", "camera_calibration YAML with static intrinsics, used while "
              "no CameraInfo has been received ('' = none).", read_only=True),
    ParamSpec("camera_info_max_stamp_diff_ms", 1.0, "A CameraInfo whose stamp is this close to the "
              "image's is used; otherwise the latest one.", range=(0.0, 1000.0)),
    ParamSpec("image_is_rectified", False, "The image is rectified: use CameraInfo P, no "
              "distortion."),
    ParamSpec("output_frame", "", "frame_id of the pose outputs ('' = the image's frame_id); "
              "needs camera_mount, which moves the poses into it."),
    ParamSpec("camera_mount", [0.0] * 7, "The camera's optical frame (the image's frame_id) in "
              "output_frame, or in frontal_frame when output_frame is '': x y z (m) qx qy qz qw, "
              "static_transform_publisher's order. Its parent's axes are the frontal frame "
              "(x forward, y left, z up). All zeros = not set (the camera looks straight ahead)."),
    ParamSpec("frontal_frame", "ficap_frontal", "frame_id of head_pose/frontal and head_rpy_deg "
              "when output_frame is '' (with output_frame set, the frontal frame is output_frame)."),
    ParamSpec("diagnostics.hardware_id", "", "hardware_id of /diagnostics ('' = the camera's "
              "frame_id, from the images)."),
    ParamSpec("model_file", "", "Cap model YAML/JSON ('' = the nominal 23-tag cap).",
              read_only=True),
    ParamSpec("detector.backend", "opencv", "Tag detector backend.",
              choices=("opencv", "apriltag"), read_only=True),
    ParamSpec("detector.corner_refine", "edge", "Corner refinement.",
              choices=("edge", "subpix", "apriltag", "none"), read_only=True),
    ParamSpec("detector.search_decimate", 1, "Search an image this many times smaller (corners "
              "are refined at full size); 2 pays off at 1080p and above.", range=(1, 4),
              read_only=True),
    ParamSpec("tracking", True, "Follow the cap from frame to frame: verify its tags where the "
              "last poses predict them, search only when that fails.", read_only=True),
    ParamSpec("pose.method", "joint", "Pose estimator: 'joint' (PnP over all corners) or "
              "'paper' (per-tag + Kabsch + outlier trimming).", choices=tuple(POSE_METHODS)),
    ParamSpec("pose.min_tags", 1, "Fewest tags for a pose.", range=(1, 23)),
    ParamSpec("uncertainty.corner_noise_px", _UNCERTAINTY.corner_noise_px,
              "Covariance floor (added to the residual-based term): independent corner noise, px.",
              range=(0.0001, 10.0)),
    ParamSpec("uncertainty.corner_bias_px", _UNCERTAINTY.corner_bias_px,
              "Covariance floor: per-tag radial corner bias, px.", range=(0.0, 10.0)),
    ParamSpec("uncertainty.corner_bias_common_px", _UNCERTAINTY.corner_bias_common_px,
              "Covariance floor: radial corner bias shared by all tags of a frame, px.",
              range=(0.0, 10.0)),
    ParamSpec("uncertainty.model_mm", _UNCERTAINTY.model_mm,
              "Covariance floor: each tag plate's shift against the cap model, mm per axis "
              "(misplaced plates the residuals show come on top).", range=(0.0, 20.0)),
    ParamSpec("uncertainty.model_deg", _UNCERTAINTY.model_deg,
              "Covariance floor: each tag plate's turn against the cap model, deg per axis.",
              range=(0.0, 20.0)),
    ParamSpec("uncertainty.residual_inflation", _UNCERTAINTY.residual_inflation,
              "Covariance: factor on the residual-based sigmas for corner errors neighbouring tags "
              "share (calibrated on ficap synth drives).", range=(1.0, 10.0)),
    ParamSpec("uncertainty.principal_point_px", _UNCERTAINTY.principal_point_px,
              "Covariance: principal point error of the intrinsics, px per axis (0 = exact; a "
              "constant offset that a frontal calibration absorbs in the head angles).",
              range=(0.0, 100.0)),
    ParamSpec("uncertainty.focal_rel", _UNCERTAINTY.focal_rel,
              "Covariance: relative focal length error of the intrinsics (0 = exact).",
              range=(0.0, 0.5)),
    ParamSpec("publish_min_reliability", 0.0, "Poses less reliable than this are not published "
              "(status still is).", range=(0.0, 1.0)),
    ParamSpec("warn_reliability", WARN_RELIABILITY, "Status level is WARN below this reliability.",
              range=(0.0, 1.0)),
    ParamSpec("warn_throttle_s", 5.0, "Least interval between repeated input warnings, s.",
              range=(0.0, 3600.0)),
    ParamSpec("calibration.mode", "auto", "~/calibrate mode: 'frontal', 'reference', or 'auto' "
              "(reference when calibration.reference_topic is set).",
              choices=("auto", "frontal", "reference")),
    ParamSpec("calibration.window_s", 3.0, "Frontal mode uses the reliable frames of the last "
              "window_s seconds (image stamps).", range=(0.2, 120.0)),
    ParamSpec("calibration.min_frames", 30, "Frontal mode: fewest frames.", range=(3, 100000)),
    ParamSpec("calibration.max_spread_deg", 3.0, "Frontal mode: largest RMS residual spread, "
              "deg.", range=(0.1, 45.0)),
    ParamSpec("calibration.min_reliability", 0.5, "Frames less reliable than this are not "
              "buffered for calibration.", range=(0.0, 1.0)),
    ParamSpec("calibration.reference_topic", "", "PoseStamped head-pose reference for reference "
              "mode ('' = none).", read_only=True),
    ParamSpec("calibration.min_pairs", 10, "Reference mode: fewest stamp-matched pairs.",
              range=(3, 100000)),
    ParamSpec("calibration.max_pairs", 0, "Reference mode: use the first max_pairs pairs "
              "(0 = all buffered).", range=(0, 100000)),
    ParamSpec("calibration.pair_tolerance_ms", 5.0, "Reference mode: largest stamp difference of "
              "a pair, ms.", range=(0.0, 1000.0)),
    ParamSpec("calibration.file", "", "Calibration YAML: loaded at start, written by "
              "~/calibrate ('' = not persisted).", read_only=True),
)
_SPECS = {p.name: p for p in PARAMETERS}

#: Parameters that no longer exist, with what replaced them (a params file naming them refuses to
#: start: silently ignoring a camera mount would tilt every head angle).
REMOVED_PARAMETERS: dict[str, str] = {
    name: "replaced by camera_mount (x y z qx qy qz qw of the camera's optical frame in the "
          "vehicle frame, static_transform_publisher order; see README 'Migration')"
    for name in ("frontal.mount_pitch_deg", "frontal.mount_yaw_deg", "frontal.mount_roll_deg")
}


def camera_mount_transform(values: Any) -> Transform | None:
    """The ``camera_mount`` parameter as T_parent_cam, or None when it is all zeros (not set).

    Raises:
        ConfigError: not 7 finite numbers or not a unit quaternion.
    """
    v = np.asarray(list(values), dtype=np.float64)
    if v.size == 7 and not np.any(v):
        return None
    return Transform.from_xyz_q_xyzw(v, "camera_mount")


@dataclass(frozen=True)
class NodeConfig:
    """The parameters, read once per change into one frozen object (names as in ``PARAMETERS``)."""

    values: dict[str, Any]

    def __getitem__(self, name: str) -> Any:
        return self.values[name]


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    d = ParameterDescriptor(name=spec.name, description=spec.description, read_only=spec.read_only)
    if spec.range is not None and isinstance(spec.default, float):
        d.floating_point_range = [FloatingPointRange(
            from_value=float(spec.range[0]), to_value=float(spec.range[1]), step=0.0)]
    elif spec.range is not None and isinstance(spec.default, int) and not isinstance(
            spec.default, bool):
        d.integer_range = [IntegerRange(
            from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=1)]
    if spec.choices is not None:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if isinstance(spec.default, list):
        d.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        d.additional_constraints = "7 numbers x y z qx qy qz qw (unit quaternion), or all zeros"
    return d


def validate_parameter(name: str, value: Any) -> str:
    """The reason ``value`` is not acceptable for parameter ``name``, or '' when it is."""
    spec = _SPECS.get(name)
    if spec is None:
        return ""  # use_sim_time and other rclpy parameters
    want = type(spec.default)
    if want is list:
        try:
            camera_mount_transform(value)
        except (ConfigError, TypeError, ValueError) as err:
            return str(err) if isinstance(err, ConfigError) else f"{name}: {err}"
        return ""
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, want) or (want is int and isinstance(value, bool)):
        return f"{name} must be a {want.__name__}, got {type(value).__name__}"
    if spec.choices is not None and value not in spec.choices:
        return f"{name} must be one of {', '.join(spec.choices)}, got {value!r}"
    if spec.range is not None:
        if isinstance(value, float) and not math.isfinite(value):
            return f"{name} must be finite"
        lo, hi = spec.range
        if not lo <= value <= hi:
            return f"{name} must be within [{lo}, {hi}], got {value}"
    return ""


class FicapNode(Node):
    """Fi-Cap head pose node (see the module docstring for its interface)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        for spec in PARAMETERS:
            try:
                self.declare_parameter(spec.name, spec.default, _descriptor(spec))
            except (ParameterException, InvalidParameterTypeException) as err:
                # An override from a params file or the command line out of range or mistyped.
                raise ConfigError(f"parameter {spec.name}: {err}") from err
        for spec in PARAMETERS:
            reason = validate_parameter(spec.name, self.get_parameter(spec.name).value)
            if reason:
                raise ConfigError(reason)
        removed = sorted(set(self._override_names()) & set(REMOVED_PARAMETERS))
        if removed:
            raise ConfigError(f"parameter {removed[0]} was {REMOVED_PARAMETERS[removed[0]]}")
        reason = _frames_reason({s.name: self.get_parameter(s.name).value for s in PARAMETERS})
        if reason:
            raise ConfigError(reason)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._config = self._read_config()
        cfg = self._config

        # Core objects.
        model = load_model(cfg["model_file"]) if cfg["model_file"] else nominal_model()
        self._processor = FrameProcessor(
            model=model,
            detector=DetectorConfig(backend=cfg["detector.backend"],
                                    corner_refine=cfg["detector.corner_refine"],
                                    search_decimate=cfg["detector.search_decimate"]),
            pose=_pose_config(cfg),
            calibration=HeadCalibration(R_cam_frontal=frontal_from_camera_mount(self._mount)),
            tracking=cfg["tracking"],
        )
        self._static_camera: CameraModel | None = None
        self._static_camera_error = ""
        if cfg["camera_info_file"]:
            try:
                self._static_camera = load_camera_yaml(cfg["camera_info_file"])
            except IntrinsicsError as err:
                self._static_camera_error = str(err)
                self.get_logger().error(str(err))
        self._load_calibration_file()

        # State shared between callbacks and the worker.
        self._lock = threading.Lock()
        self._mailbox_cv = threading.Condition()
        self._mailbox: tuple[Any, int] | None = None
        self._running = True
        self._camera_infos: deque[tuple[int, CameraInfo]] = deque(maxlen=50)
        self._camera_cache: tuple[tuple, CameraModel] | None = None
        self._recorder = CalibrationRecorder(max_frames=20000)
        self._last_calibration: CalibrationResult | None = None
        self._received = 0
        self._dropped = 0
        self._processed = 0
        self._errors = 0
        self._last_error = ""
        self._period = {"received": 0, "dropped": 0, "processed": 0, "tags": 0, "latency_ms": 0.0,
                        "errors": 0}
        self._camera_frame = ""  # the frame_id of the last image (the default hardware_id)

        # Callback groups: frames, side inputs, services and timers never wait on each other.
        self._input_group = MutuallyExclusiveCallbackGroup()
        self._side_group = ReentrantCallbackGroup()
        self._service_group = MutuallyExclusiveCallbackGroup()
        self._timer_group = MutuallyExclusiveCallbackGroup()

        sensor_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=cfg["qos.depth"],
            reliability=(ReliabilityPolicy.BEST_EFFORT if cfg["qos.reliability"] == "best_effort"
                         else ReliabilityPolicy.RELIABLE),
            durability=qos_profile_sensor_data.durability,
        )
        if cfg["image_transport"] == "compressed":
            # image_transport's naming: <base topic>/compressed, so remapping `image` moves both.
            topic = self.resolve_topic_name("image") + "/compressed"
            self._image_sub = self.create_subscription(
                CompressedImage, topic, self._on_image, sensor_qos,
                callback_group=self._input_group)
        else:
            self._image_sub = self.create_subscription(
                Image, "image", self._on_image, sensor_qos, callback_group=self._input_group)
        self._info_sub = self.create_subscription(
            CameraInfo, "camera_info", self._on_camera_info, sensor_qos,
            callback_group=self._side_group)
        self._ref_sub = None
        if cfg["calibration.reference_topic"]:
            ref_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                 reliability=ReliabilityPolicy.BEST_EFFORT)
            self._ref_sub = self.create_subscription(
                PoseStamped, cfg["calibration.reference_topic"], self._on_reference, ref_qos,
                callback_group=self._side_group)

        out_qos = 10
        self._pub_head = self.create_publisher(PoseStamped, "head_pose", out_qos)
        self._pub_head_cov = self.create_publisher(
            PoseWithCovarianceStamped, "head_pose/with_covariance", out_qos)
        self._pub_cap = self.create_publisher(PoseStamped, "cap_pose", out_qos)
        self._pub_head_frontal = self.create_publisher(PoseStamped, "head_pose/frontal", out_qos)
        self._pub_rpy = self.create_publisher(Vector3Stamped, "head_rpy_deg", out_qos)
        self._pub_quality = self.create_publisher(JointState, "quality", out_qos)
        self._pub_status = self.create_publisher(DiagnosticArray, "status", out_qos)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", out_qos)
        self._pub_markers = self.create_publisher(MarkerArray, "markers", out_qos)
        # Reliable publishers match both reliable and best-effort subscribers (rviz, rqt).
        self._pub_debug = self.create_publisher(Image, "debug_image", 2)

        self._srv_calibrate = self.create_service(
            Trigger, "~/calibrate", self._on_calibrate, callback_group=self._service_group)
        self._srv_clear = self.create_service(
            Trigger, "~/clear_calibration", self._on_clear_calibration,
            callback_group=self._service_group)
        self._diag_timer = self.create_timer(1.0, self._on_diagnostics_timer,
                                             callback_group=self._timer_group)
        self._last_diag = time.monotonic()

        self.unknown_parameters = self._warn_unknown_parameters()
        self._worker = threading.Thread(target=self._work, name="ficap_worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"ficap_node ready: {cfg['image_transport']} images on "
            f"{self._image_sub.topic_name}, pose method {cfg['pose.method']}, "
            f"{'calibrated' if self._processor.calibration.calibrated else 'not calibrated'}")

    # -- parameters ------------------------------------------------------------------------------
    def _override_names(self) -> list[str]:
        """Names given to this node by params files (matched by node name, ``/**`` included) and
        ``-p``/``parameter_overrides``. rclpy keeps them in ``_parameter_overrides`` and has no
        public accessor; without it no unknown name could be reported."""
        return list(getattr(self, "_parameter_overrides", {}) or {})

    def _warn_unknown_parameters(self) -> list[str]:
        """Override names the node does not declare (misspelt keys would otherwise be silently
        ignored): one warning naming them. rclpy's own (``use_sim_time``, ``qos_overrides.*``) count
        as known."""
        unknown = sorted(n for n in self._override_names()
                         if not self.has_parameter(n) and not n.startswith("qos_overrides."))
        if unknown:
            self.get_logger().warning(
                f"unknown parameter(s) ignored: {', '.join(unknown)} (ficap_node declares: "
                f"{', '.join(p.name for p in PARAMETERS)})")
        return unknown

    def _read_config(self) -> NodeConfig:
        values = {}
        for spec in PARAMETERS:
            v = self.get_parameter(spec.name).value
            if isinstance(spec.default, float):
                v = float(v)
            elif isinstance(spec.default, list):
                v = [float(x) for x in v]
            values[spec.name] = v
        self._mount = camera_mount_transform(values["camera_mount"])
        return NodeConfig(values)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            reason = validate_parameter(p.name, p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        values = dict(self._config.values)
        values.update({p.name: p.value for p in params})
        reason = _frames_reason(values)
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        self._config = cfg = self._read_config()
        self._processor.pose_config = _pose_config(cfg)
        if not any(p.name == "camera_mount" for p in params):
            return  # the frontal frame (maybe a reference calibration's) stays
        old = self._processor.calibration
        R_cam_frontal = calibrated_frontal(self._last_calibration if old.calibrated else None,
                                           self._mount)
        if angle_deg(old.R_cam_frontal, R_cam_frontal) > 1e-9:
            self._processor.calibration = HeadCalibration(old.R_cap_head, R_cam_frontal,
                                                          old.calibrated)

    # -- calibration state -----------------------------------------------------------------------
    def _load_calibration_file(self) -> None:
        path = self._config["calibration.file"]
        if not path or not Path(path).exists():
            return
        try:
            loaded = load_calibration(path)
        except CalibrationError as err:
            self.get_logger().error(f"{err}; starting uncalibrated")
            return
        # The file's frontal frame (replay --calibration's), unless camera_mount sets one.
        R_cam_frontal = loaded.R_cam_frontal if self._mount is None else \
            frontal_from_camera_mount(self._mount)
        if loaded.calibrated and angle_deg(loaded.R_cam_frontal, R_cam_frontal) > 0.01:
            self.get_logger().warning(
                f"calibration {path} was made with a frontal frame "
                f"{angle_deg(loaded.R_cam_frontal, R_cam_frontal):.2f} deg from the current "
                "camera_mount parameter; head angles keep the current frontal frame")
        self._processor.calibration = HeadCalibration(loaded.R_cap_head, R_cam_frontal,
                                                      loaded.calibrated)
        self.get_logger().info(f"loaded calibration {path} (calibrated: {loaded.calibrated})")

    @property
    def calibration(self) -> HeadCalibration:
        """The calibration in use."""
        return self._processor.calibration

    def _calibration_mode(self) -> str:
        mode = self._config["calibration.mode"]
        if mode == "auto":
            return "reference" if self._config["calibration.reference_topic"] else "frontal"
        return mode

    def _run_calibration(self) -> CalibrationResult:
        cfg = self._config
        mode = self._calibration_mode()
        R_cam_frontal = calibrated_frontal(None, self._mount)  # the frame the result is kept with
        if mode == "frontal":
            return self._recorder.frontal(cfg["calibration.window_s"], R_cam_frontal,
                                          min_frames=cfg["calibration.min_frames"],
                                          max_spread_deg=cfg["calibration.max_spread_deg"],
                                          min_reliability=cfg["calibration.min_reliability"])
        if not cfg["calibration.reference_topic"]:
            raise CalibrationError("reference mode needs calibration.reference_topic")
        return self._recorder.reference(int(cfg["calibration.pair_tolerance_ms"] * 1e6),
                                        min_pairs=cfg["calibration.min_pairs"],
                                        max_pairs=cfg["calibration.max_pairs"])

    def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            result = self._run_calibration()
        except CalibrationError as err:
            response.success = False
            response.message = f"calibration refused: {err}"
            self.get_logger().warning(response.message)
            return response
        calib = HeadCalibration(result.R_cap_head, calibrated_frontal(result, self._mount), True)
        self._processor.calibration = calib
        self._last_calibration = result
        response.success = True
        response.message = (f"calibrated ({result.mode}) from {result.frames_used} frames, "
                            f"spread {result.spread_deg:.2f} deg, uncertainty "
                            f"{result.uncertainty_deg:.2f} deg")
        path = self._config["calibration.file"]
        if path:
            try:
                save_calibration(path, calib, result)
                response.message += f", saved to {path}"
            except (OSError, FicapError) as err:
                # In use, but lost at the next start: the caller must know (success=False).
                response.success = False
                response.message += f"; in use but NOT saved: {err}"
                self.get_logger().error(response.message)
                return response
        self.get_logger().info(response.message)
        return response

    def _on_clear_calibration(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        self._processor.calibration = HeadCalibration(
            R_cam_frontal=self._processor.calibration.R_cam_frontal)
        self._last_calibration = None
        response.success = True
        response.message = "calibration cleared"
        path = self._config["calibration.file"]
        if path:
            try:
                save_calibration(path, self._processor.calibration)
            except (OSError, FicapError) as err:
                # save_calibration never replaces a file that is not a calibration.
                response.success = False
                response.message += f" in memory; {path} NOT updated: {err}"
                self.get_logger().error(response.message)
                return response
        self.get_logger().info(response.message)
        return response

    # -- inputs ----------------------------------------------------------------------------------
    def _on_image(self, msg: Image | CompressedImage) -> None:
        now = time.monotonic_ns()
        with self._mailbox_cv:
            self._received += 1
            self._period["received"] += 1
            if self._mailbox is not None:  # an unprocessed older frame: newest wins
                self._dropped += 1
                self._period["dropped"] += 1
            self._mailbox = (msg, now)
            self._mailbox_cv.notify()

    def _on_camera_info(self, msg: CameraInfo) -> None:
        with self._lock:
            self._camera_infos.append((ros_msgs.stamp_to_ns(msg.header.stamp), msg))

    def _on_reference(self, msg: PoseStamped) -> None:
        o = msg.pose.orientation
        q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
            self.get_logger().warning("reference pose with an invalid quaternion ignored",
                                      throttle_duration_sec=self._config["warn_throttle_s"])
            return
        self._recorder.add_reference(ros_msgs.stamp_to_ns(msg.header.stamp), q / np.linalg.norm(q))

    def _camera_for(self, stamp_ns: int) -> CameraModel:
        """Intrinsics for a frame: the CameraInfo with its stamp, else the latest, else the file."""
        with self._lock:
            infos = list(self._camera_infos)
        if not infos:
            if self._static_camera is not None:
                return self._static_camera
            raise IntrinsicsError(self._static_camera_error or "no CameraInfo received yet and no "
                                  "camera_info_file")
        tol_ns = int(self._config["camera_info_max_stamp_diff_ms"] * 1e6)
        info = min(infos, key=lambda e: abs(e[0] - stamp_ns))
        msg = info[1] if abs(info[0] - stamp_ns) <= tol_ns else infos[-1][1]
        rectified = bool(self._config["image_is_rectified"])
        key = (msg.width, msg.height, tuple(msg.k), tuple(msg.d), msg.distortion_model,
               tuple(msg.p), rectified)
        cache = self._camera_cache
        if cache is not None and cache[0] == key:
            return cache[1]
        camera = ros_msgs.camera_info_to_model(msg, rectified=rectified)
        self._camera_cache = (key, camera)
        return camera

    # -- processing ------------------------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._mailbox_cv:
                self._mailbox_cv.wait_for(lambda: self._mailbox is not None or not self._running,
                                          timeout=0.5)
                if not self._running:
                    return
                item, self._mailbox = self._mailbox, None
            if item is None:
                continue
            try:
                self._process(*item)
            except Exception as err:  # noqa: BLE001 - keep the node alive; report and go on
                self._report_error(item[0].header, f"internal error: {type(err).__name__}: {err}")
                self.get_logger().error(f"processing failed: {err!r}",
                                        throttle_duration_sec=self._config["warn_throttle_s"])

    def _out_header(self, header: Header) -> Header:
        frame = self._config["output_frame"] or header.frame_id
        return Header(stamp=header.stamp, frame_id=frame)

    def _frontal_header(self, header: Header) -> Header:
        frame = self._config["output_frame"] or self._config["frontal_frame"]
        return Header(stamp=header.stamp, frame_id=frame)

    def _T_frontal_cam(self, calibration: HeadCalibration) -> Transform:
        """The camera in the frontal frame F: the mount, or at F's origin looking forward."""
        if self._mount is not None:
            return self._mount
        return Transform(calibration.R_cam_frontal.inv(), np.zeros(3))

    def _report_error(self, header: Header, reason: str) -> None:
        with self._lock:
            self._errors += 1
            self._period["errors"] += 1
            self._last_error = reason
        self.get_logger().warning(reason, throttle_duration_sec=self._config["warn_throttle_s"])
        rec = record_from_pose(0, ros_msgs.stamp_to_ns(header.stamp), header.frame_id, None, (),
                               reason, self._processor.calibration)
        level, message = frame_status(False, math.nan, error=reason)
        self._publish_status(header, rec, level, message, "", math.nan)

    def _publish_status(self, header: Header, rec: LabelRecord, level: int, message: str,
                        search: str, latency_ms: float) -> None:
        """``quality`` and ``status`` of a frame (``ficap_ros.report``'s values, as labels.mcap)."""
        self._pub_quality.publish(ros_msgs.quality_msg(
            header, {**quality_values(rec), "latency_ms": float(latency_ms)}))
        values = {**status_values(rec), "search": search, "latency_ms": latency_ms,
                  "dropped_frames": self._dropped}
        status = ros_msgs.diagnostic_status(STATUS_NAME, bytes([level]), message, values,
                                            hardware_id=header.frame_id)
        self._pub_status.publish(ros_msgs.diagnostic_array(self._out_header(header), status))

    def _process(self, msg: Image | CompressedImage, received_ns: int) -> None:
        cfg = self._config
        header = msg.header
        self._camera_frame = header.frame_id
        stamp_ns = ros_msgs.stamp_to_ns(header.stamp)
        try:
            if isinstance(msg, CompressedImage):
                image = ros_msgs.compressed_to_array(msg)
            else:
                image = ros_msgs.image_to_array(msg)
            camera = self._camera_for(stamp_ns)
            h, w = image.shape[:2]
            if (w, h) != (camera.width_px, camera.height_px):
                raise IntrinsicsError(f"image {w}x{h} does not match the intrinsics "
                                      f"{camera.width_px}x{camera.height_px}")
            # One read of the calibration per frame: the service thread swaps the whole object.
            calibration = self._processor.calibration
            result = self._processor.process(image, camera, stamp_ns, calibration)
        except FicapError as err:
            self._report_error(header, str(err))
            return

        out = self._out_header(header)
        pose = result.pose
        published = (pose is not None and result.T_cam_head is not None
                     and pose.reliability >= cfg["publish_min_reliability"])
        if published:
            assert pose is not None and result.T_cam_head is not None
            # Into output_frame through the mount (identity when the outputs stay in the camera's).
            T_out_cam = self._mount if cfg["output_frame"] else Transform.identity()
            cov = pose.covariance if self._mount is None or not cfg["output_frame"] else \
                rotate_covariance(pose.covariance, T_out_cam.rotation)
            self._pub_head.publish(ros_msgs.pose_stamped(out, T_out_cam * result.T_cam_head))
            self._pub_head_cov.publish(
                ros_msgs.pose_with_covariance_stamped(out, T_out_cam * result.T_cam_head, cov))
            self._pub_cap.publish(ros_msgs.pose_stamped(out, T_out_cam * pose.T_cam_cap))
            frontal = self._frontal_header(header)
            self._pub_head_frontal.publish(
                ros_msgs.pose_stamped(frontal, self._T_frontal_cam(calibration) * result.T_cam_head))
            if result.R_frontal_head is not None:
                self._pub_rpy.publish(ros_msgs.rpy_deg_msg(frontal, result.R_frontal_head))
        latency_ms = (time.monotonic_ns() - received_ns) / 1e6
        rec = record_from_result(result, calibration, frame_id=header.frame_id)
        level, message = record_status(rec, cfg["warn_reliability"])
        self._publish_status(header, rec, level, message, str(result.search), latency_ms)

        # Markers and the debug image are drawn in camera coordinates: the camera's frame.
        cam_header = Header(stamp=header.stamp, frame_id=header.frame_id)
        if self._pub_markers.get_subscription_count() > 0:
            self._pub_markers.publish(ros_msgs.markers_msg(cam_header, self._processor.model, result))
        if self._pub_debug.get_subscription_count() > 0:
            gray = image if image.ndim == 2 else image[:, :, 0]
            self._pub_debug.publish(ros_msgs.debug_image_msg(gray, result, camera, cam_header))

        with self._lock:
            self._processed += 1
            self._period["processed"] += 1
            self._period["tags"] += result.tags_detected
            self._period["latency_ms"] += latency_ms
        if pose is not None:
            self._recorder.add_cap(stamp_ns, pose.T_cam_cap.rotation, pose.reliability)

    # -- diagnostics -----------------------------------------------------------------------------
    def _on_diagnostics_timer(self) -> None:
        now = time.monotonic()
        dt = max(now - self._last_diag, 1e-3)
        self._last_diag = now
        with self._lock, self._mailbox_cv:
            p = dict(self._period)
            self._period = dict.fromkeys(p, 0)
            self._period["latency_ms"] = 0.0
            last_error = self._last_error
        calib = self._processor.calibration
        processed = p["processed"]
        values = {
            "fps": processed / dt,
            "input_fps": p["received"] / dt,
            "drop_rate": p["dropped"] / p["received"] if p["received"] else 0.0,
            "mean_tags": p["tags"] / processed if processed else 0.0,
            "mean_latency_ms": p["latency_ms"] / processed if processed else float("nan"),
            "errors": p["errors"],
            "dropped_frames_total": self._dropped,
            "calibrated": calib.calibrated,
            "calibration_mode": (self._last_calibration.mode if self._last_calibration
                                 else ("loaded" if calib.calibrated else "none")),
        }
        if p["errors"]:
            level, message = ros_msgs.LEVEL_ERROR, f"input errors: {last_error}"
        elif p["received"] == 0:
            level, message = ros_msgs.LEVEL_WARN, "no images"
        elif not calib.calibrated:
            level, message = ros_msgs.LEVEL_OK, "running, not calibrated"
        else:
            level, message = ros_msgs.LEVEL_OK, "running"
        status = ros_msgs.diagnostic_status(
            f"{self.get_name()}: pipeline", level, message, values,
            hardware_id=self._config["diagnostics.hardware_id"] or self._camera_frame)
        header = Header(stamp=self.get_clock().now().to_msg())
        self._pub_diag.publish(ros_msgs.diagnostic_array(header, status))

    # -- lifecycle -------------------------------------------------------------------------------
    @property
    def dropped_frames(self) -> int:
        return self._dropped

    def destroy_node(self) -> None:
        """Stop the worker, then destroy the node."""
        with self._mailbox_cv:
            self._running = False
            self._mailbox_cv.notify_all()
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout=5.0)
        super().destroy_node()


def _pose_config(cfg: NodeConfig) -> PoseConfig:
    """The pose settings of the parameters (estimator and covariance floors)."""
    u = {f: cfg[f"uncertainty.{f}"] for f in ("corner_noise_px", "corner_bias_px",
                                               "corner_bias_common_px", "model_mm", "model_deg",
                                               "principal_point_px", "focal_rel",
                                               "residual_inflation")}
    return PoseConfig(method=cfg["pose.method"], min_tags=cfg["pose.min_tags"],
                      uncertainty=UncertaintyConfig(**u))


def _frames_reason(values: dict[str, Any]) -> str:
    """Why the output_frame / camera_mount combination is refused ('' when it is fine)."""
    if values.get("output_frame") and camera_mount_transform(values["camera_mount"]) is None:
        return (f"output_frame {values['output_frame']!r} needs camera_mount (the camera's optical "
                "frame in it: x y z qx qy qz qw); without it the poses would only be relabelled")
    return ""


def main(args: list[str] | None = None) -> int:
    """Run ``ficap_node`` (Jazzy's idiom: spin until Ctrl-C or external shutdown)."""
    rclpy.init(args=args)
    node: FicapNode | None = None
    code = 0
    try:
        node = FicapNode()
        # Callbacks only fill the mailbox, publish or answer services (the worker thread does the
        # processing), so one executor thread suffices; rclpy's MultiThreadedExecutor spent more
        # of the GIL polling its futures than the callbacks needed (measured: cProfile, 30 Hz).
        log = node.get_logger()
        # libjpeg/FFmpeg print per damaged frame on fd 2: through the logger, throttled.
        with ThrottledStderr(lambda text: log.warning(text)):
            rclpy.spin(node, SingleThreadedExecutor())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FicapError as err:
        print(f"ficap_node: {err}", file=sys.stderr)
        code = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
