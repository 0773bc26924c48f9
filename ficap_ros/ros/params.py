"""``ficap_node``'s parameters: declared once from one table, validated on every set, read into
one frozen, typed ``NodeConfig`` (imports rclpy's parameter types). What the node builds from them
is beside it: the pipeline in ``ficap_ros.ros.live``, calibrations in
``ficap_ros.ros.live_calibration``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from enum import Enum
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import ROW_ORDERS, CameraTiming
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.camera_info import CAMERA_INFO_MAX_STAMP_DIFF_NS
from ficap_ros.io.frames import OutputFrames, camera_mount_transform
from ficap_ros.io.frames import frames_reason as _frames_reason
from ficap_ros.io.status import WARN_RELIABILITY
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pose import POSE_METHODS, PoseConfig
from ficap_ros.vision.uncertainty import UncertaintyConfig

__all__ = ["ParamSpec", "PARAMETERS", "REMOVED_PARAMETERS", "CalibrationMode", "NodeConfig",
           "camera_mount_transform", "descriptor", "validate_parameter", "frames_reason",
           "calibration_folder_warning", "change_lines", "usage"]


class CalibrationMode(str, Enum):
    """``calibration.mode``: what ``~/calibrate`` does."""

    AUTO = "auto"  # reference when calibration.reference_topic is set, else frontal
    FRONTAL = "frontal"
    REFERENCE = "reference"

    def __str__(self) -> str:
        return self.value


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
              "subscriptions (best_effort = sensor-data QoS, matches any publisher); "
              "qos_overrides.<topic>.subscription.* override it per topic.",
              choices=("best_effort", "reliable"), read_only=True),
    ParamSpec("qos.depth", 5, "History depth of the image/camera_info subscriptions; "
              "qos_overrides.<topic>.subscription.depth overrides it per topic.",
              range=(1, 100), read_only=True),
    ParamSpec("camera_info_topic", "", "CameraInfo topic ('' = beside the image topic, "
              "image_transport's rule: <the image topic's namespace>/camera_info, remaps of image "
              "included; a remap of camera_info is honoured too).", read_only=True),
    ParamSpec("camera_info_file", "", "camera_calibration YAML with static intrinsics, used while "
              "no CameraInfo has been received ('' = none).", read_only=True),
    ParamSpec("camera_info_max_stamp_diff_ms", CAMERA_INFO_MAX_STAMP_DIFF_NS / 1e6, "A CameraInfo "
              "whose stamp is this close to the image's is used (the nearest); otherwise the last "
              "one at or before the image (bags: the same rule).", range=(0.0, 1000.0)),
    ParamSpec("image_is_rectified", False, "The image is rectified: use CameraInfo P, no "
              "distortion."),
    ParamSpec("camera.exposure_ms", 0.0, "Each row's exposure time, ms (0 = not known: no motion "
              "blur modelled). While every camera.* parameter is at its default, the camera_timing "
              "mapping of camera_info_file applies, if it has one.", range=(0.0, 1000.0)),
    ParamSpec("camera.readout_ms", 0.0, "Rolling shutter: time between the first and the last "
              "row's exposure centres, ms (0 = a global shutter).", range=(0.0, 1000.0)),
    ParamSpec("camera.row_order", "top_to_bottom", "Order in which a rolling shutter reads its "
              "rows.", choices=ROW_ORDERS),
    ParamSpec("camera.stamp_offset_ms", 0.0, "Added to an image's stamp to reach the middle row's "
              "mid-exposure (the instant the poses are reported at), ms: 0 for drivers that stamp "
              "it, (exposure + readout) / 2 for a stamp at the start of the first row's exposure, "
              "negative for one at the end of the frame.", range=(-1000.0, 1000.0)),
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
    ParamSpec("detector.photometric", False, "Corners' last step: fit each tag's pattern, blurred in "
              "linear light and through a tone curve, to its pixels: more accurate where noise limits "
              "the corners (dim frames), at more CPU a frame than all the rest of the processing, "
              "which a live camera's frame rate may not leave (costs in docs/benchmarks.md). While "
              "every uncertainty.* parameter is at its default, its corners get their own "
              "covariance profile.", read_only=True),
    ParamSpec("detector.photometric_auto", True, "With detector.photometric false: that fit on the "
              "tags whose corners noise limits only (noise sd over contrast times sqrt(px per cell), "
              "from each tag's cell centres, above DetectorConfig.edge_photometric_noise_ratio: dim "
              "or small tags); the rest keep the cell-edge fit's corners. false: the cell-edge "
              "fit's corners everywhere.", read_only=True),
    ParamSpec("detector.motion_corners", True, "With camera.exposure_ms given: refit each tag that "
              "moves over the exposure with its pattern moving along its corners' paths, so its "
              "corners are the mid-exposure ones (blurred edges otherwise settle off them); more CPU "
              "in fast frames (costs in docs/benchmarks.md).", read_only=True),
    ParamSpec("detector.search_decimate", 0, "Search an image this many times smaller (corners "
              "are refined at full size); 0 = auto, as ficap replay: 2 from 1920 px wide up, else 1.",
              range=(0, 4),
              read_only=True),
    ParamSpec("tracking", True, "Follow the cap from frame to frame: verify its tags where the "
              "last poses predict them, search only when that fails.", read_only=True),
    ParamSpec("pose.method", "joint", "Pose estimator: 'joint' (PnP over all corners, tag-level "
              "outlier rejection), 'paper' (per-tag + Kabsch + outlier trimming) or 'naive' (one "
              "PnP over all corners, no outlier handling: the baseline).",
              choices=tuple(POSE_METHODS)),
    ParamSpec("pose.min_tags", 1, "Fewest tags for a pose.", range=(1, 23)),
    ParamSpec("uncertainty.corner_noise_px", _UNCERTAINTY.corner_noise_px,
              "Covariance floor (added to the residual-based term): independent corner noise, px.",
              range=(0.0001, 10.0)),
    ParamSpec("uncertainty.corner_bias_px", _UNCERTAINTY.corner_bias_px,
              "Covariance floor: per-tag radial corner bias, px.", range=(0.0, 10.0)),
    ParamSpec("uncertainty.corner_bias_common_px", _UNCERTAINTY.corner_bias_common_px,
              "Covariance floor: radial corner bias shared by all tags of a frame, px.",
              range=(0.0, 10.0)),
    ParamSpec("uncertainty.shared_bias_gain", _UNCERTAINTY.shared_bias_gain,
              "Covariance: the edge corners' radial offset shared by all tags of a frame (the depth "
              "takes it), px per unit of the frame's corner noise over its cell width (0 = not "
              "used: common_offset_gain states the offset).", range=(0.0, 10.0)),
    ParamSpec("uncertainty.common_offset_gain", _UNCERTAINTY.common_offset_gain,
              "Covariance: factor on the tags' common radial offset the residuals show, a measured "
              "mean error the depth takes (calibrated on path-traced renders; 0 = not used).",
              range=(0.0, 10.0)),
    ParamSpec("uncertainty.common_offset_se_gain", _UNCERTAINTY.common_offset_se_gain,
              "Covariance: factor on the standard error of that measured offset, a spread along the "
              "same mode (0 = not used).", range=(0.0, 10.0)),
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
    ParamSpec("uncertainty.light_gradient_gain", _UNCERTAINTY.light_gradient_gain,
              "Covariance: corner noise the pose absorbs per px of the frame's light gradient "
              "(spread of the tags' edge shifts; calibrated on ficap synth drives).",
              range=(0.0, 10.0)),
    ParamSpec("uncertainty.light_gradient_tilt_gain", _UNCERTAINTY.light_gradient_tilt_gain,
              "Covariance: shared shift of the tags along their foreshortening per px of the "
              "frame's light gradient (the mode that moves the depth).", range=(0.0, 10.0)),
    ParamSpec("uncertainty.edge_shift_tilt_gain", _UNCERTAINTY.edge_shift_tilt_gain,
              "Covariance: that shared shift, px edge-on, per px of the tags' mean edge shift (the "
              "light's strength), beyond what the other terms state along it.", range=(0.0, 10.0)),
    ParamSpec("uncertainty.tilt_shift_px", _UNCERTAINTY.tilt_shift_px,
              "Covariance floor: that shared shift, px at a tag seen edge-on (0 = none; values for "
              "small blurred tags in docs/benchmarks.md).", range=(0.0, 10.0)),
    ParamSpec("uncertainty.motion_blur_gain", _UNCERTAINTY.motion_blur_gain,
              "Covariance: shared shrink of the tags across their image motion over the exposure, "
              "per px of it (only with camera.exposure_ms given).", range=(0.0, 10.0)),
    ParamSpec("uncertainty.motion_blur_shift_gain", _UNCERTAINTY.motion_blur_shift_gain,
              "Covariance: shared shift of the tags along their image motion over the exposure, "
              "per px of it (only with camera.exposure_ms given).", range=(0.0, 10.0)),
    ParamSpec("uncertainty.weight_tags", _UNCERTAINTY.weight_tags,
              "Joint pose: weight each tag by its own corner noise (one weighted Gauss-Newton "
              "step from the unweighted optimum)."),
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
              "~/calibrate ('' = not persisted) into its folder, which must exist.",
              read_only=True),
)
_SPECS = {p.name: p for p in PARAMETERS}

#: Parameters that no longer exist, with what replaced them (a params file naming them refuses to
#: start: silently ignoring a camera mount would tilt every head angle).
REMOVED_PARAMETERS: dict[str, str] = {
    name: "replaced by camera_mount (x y z qx qy qz qw of the camera's optical frame in the "
          "vehicle frame, static_transform_publisher order; see README 'Migration')"
    for name in ("frontal.mount_pitch_deg", "frontal.mount_yaw_deg", "frontal.mount_roll_deg")
}


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
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


def frames_reason(values: dict[str, Any]) -> str:
    """Why the output_frame / camera_mount combination is refused ('' when it is fine)."""
    return _frames_reason(values.get("output_frame", ""),
                          camera_mount_transform(values.get("camera_mount", [0.0] * 7)))


def calibration_folder_warning(path: str) -> str:
    """The start-up warning for a ``calibration.file`` whose folder does not exist ('' when it
    does): ~/calibrate will not save into it until it is made (never a new folder tree from a
    typo in the path)."""
    if path and not Path(path).parent.is_dir():
        return (f"calibration.file {path}: folder {Path(path).parent} does not exist; "
                "~/calibrate cannot save until it does")
    return ""


def change_lines(old: dict[str, Any], params: list[Any]) -> list[str]:
    """One log line per parameter of ficap_node's whose value a set changed: ``name: old -> new``."""
    out = []
    for p in params:
        if p.name in _SPECS and p.name in old and old[p.name] != p.value:
            out.append(f"parameter {p.name}: {old[p.name]!r} -> {p.value!r}")
    return out


@dataclass(frozen=True)
class NodeConfig:
    """The parameters, read once per change into one frozen, typed object (a parameter's name with
    its dots as underscores: ``calibration.window_s`` is ``calibration_window_s``)."""

    image_transport: str
    qos_reliability: str
    qos_depth: int
    camera_info_topic: str
    camera_info_file: str
    camera_info_max_stamp_diff_ms: float
    image_is_rectified: bool
    camera_exposure_ms: float
    camera_readout_ms: float
    camera_row_order: str
    camera_stamp_offset_ms: float
    output_frame: str
    camera_mount: tuple[float, ...]
    frontal_frame: str
    diagnostics_hardware_id: str
    model_file: str
    detector_backend: str
    detector_corner_refine: str
    detector_search_decimate: int
    detector_photometric: bool
    detector_photometric_auto: bool
    detector_motion_corners: bool
    tracking: bool
    pose_method: str
    pose_min_tags: int
    uncertainty_corner_noise_px: float
    uncertainty_corner_bias_px: float
    uncertainty_corner_bias_common_px: float
    uncertainty_shared_bias_gain: float
    uncertainty_common_offset_gain: float
    uncertainty_common_offset_se_gain: float
    uncertainty_model_mm: float
    uncertainty_model_deg: float
    uncertainty_residual_inflation: float
    uncertainty_principal_point_px: float
    uncertainty_focal_rel: float
    uncertainty_light_gradient_gain: float
    uncertainty_light_gradient_tilt_gain: float
    uncertainty_edge_shift_tilt_gain: float
    uncertainty_tilt_shift_px: float
    uncertainty_motion_blur_gain: float
    uncertainty_motion_blur_shift_gain: float
    uncertainty_weight_tags: bool
    publish_min_reliability: float
    warn_reliability: float
    warn_throttle_s: float
    calibration_mode: CalibrationMode
    calibration_window_s: float
    calibration_min_frames: int
    calibration_max_spread_deg: float
    calibration_min_reliability: float
    calibration_reference_topic: str
    calibration_min_pairs: int
    calibration_max_pairs: int
    calibration_pair_tolerance_ms: float
    calibration_file: str

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> NodeConfig:
        """From parameter values by name (validated by ``validate_parameter``)."""
        kw: dict[str, Any] = {}
        for spec in PARAMETERS:
            v = values[spec.name]
            if isinstance(spec.default, float):
                v = float(v)
            elif isinstance(spec.default, list):
                v = tuple(float(x) for x in v)
            kw[spec.name.replace(".", "_")] = v
        kw["calibration_mode"] = CalibrationMode(kw["calibration_mode"])
        return cls(**kw)

    @property
    def mount(self) -> Transform | None:
        """``camera_mount`` as T_parent_cam (None: not set)."""
        return camera_mount_transform(self.camera_mount)

    @property
    def frames(self) -> OutputFrames:
        """The output frames (``output_frame``, ``camera_mount``, ``frontal_frame``)."""
        return OutputFrames(self.output_frame, self.mount, self.frontal_frame)

    @property
    def camera_timing(self) -> CameraTiming | None:
        """The ``camera.*`` parameters as the camera's timing, or None while every one is at its
        default (a parameter cannot be unset: "not set", so a camera_info_file's timing may
        apply, ``live.camera_timing``)."""
        timing = CameraTiming(self.camera_exposure_ms, self.camera_readout_ms,
                              self.camera_row_order, self.camera_stamp_offset_ms)
        return None if timing == CameraTiming() else timing

    @property
    def effective_calibration_mode(self) -> CalibrationMode:
        """``auto`` resolved: reference when a reference topic is set."""
        if self.calibration_mode is CalibrationMode.AUTO:
            return CalibrationMode.REFERENCE if self.calibration_reference_topic else \
                CalibrationMode.FRONTAL
        return self.calibration_mode

    @property
    def detector_config(self) -> DetectorConfig:
        """The detector settings."""
        return DetectorConfig(backend=self.detector_backend, corner_refine=self.detector_corner_refine,
                              search_decimate=self.detector_search_decimate,
                              edge_photometric=self.detector_photometric,
                              edge_photometric_auto=self.detector_photometric_auto,
                              motion_corners=self.detector_motion_corners)

    @property
    def pose_config(self) -> PoseConfig:
        """The pose settings (estimator and covariance floors). A parameter cannot be unset, so
        ``uncertainty.*`` all at their defaults is "not set": the uncertainty profile of the
        detector's corner estimator (``PoseConfig.uncertainty`` None)."""
        u = {f.name: getattr(self, f"uncertainty_{f.name}") for f in fields(UncertaintyConfig)
             if hasattr(self, f"uncertainty_{f.name}")}
        unset = u == {k: v for k, v in asdict(_UNCERTAINTY).items() if k in u}
        return PoseConfig(method=self.pose_method, min_tags=self.pose_min_tags,
                          uncertainty=None if unset else UncertaintyConfig(**u))


assert {f.name for f in fields(NodeConfig)} == {s.name.replace(".", "_") for s in PARAMETERS}


def declare(node: Any) -> NodeConfig:
    """Declare every parameter on ``node`` and read them (validated, the frame rules checked).

    Raises:
        ConfigError: an override out of range or mistyped, a removed parameter, or output_frame
            without camera_mount.
    """
    from rclpy.exceptions import InvalidParameterTypeException, ParameterException

    for spec in PARAMETERS:
        if node.has_parameter(spec.name):
            continue  # declared by an earlier configure (a lifecycle node's)
        try:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except (ParameterException, InvalidParameterTypeException) as err:
            # An override from a params file or the command line out of range or mistyped.
            raise ConfigError(f"parameter {spec.name}: {err}") from err
    values = current_values(node)
    for name, value in values.items():
        if reason := validate_parameter(name, value):
            raise ConfigError(reason)
    removed = sorted(set(override_names(node)) & set(REMOVED_PARAMETERS))
    if removed:
        raise ConfigError(f"parameter {removed[0]} was {REMOVED_PARAMETERS[removed[0]]}")
    if reason := frames_reason(values):
        raise ConfigError(reason)
    return NodeConfig.from_values(values)


def current_values(node: Any) -> dict[str, Any]:
    return {s.name: node.get_parameter(s.name).value for s in PARAMETERS}


def refusal(node: Any, params: list[Any]) -> str:
    """Why a set of new parameter values is refused ('' when it is accepted)."""
    values = {**current_values(node), **{p.name: p.value for p in params}}
    reason = next(filter(None, (validate_parameter(p.name, p.value) for p in params)), "")
    return reason or frames_reason(values)


def override_names(node: Any) -> list[str]:
    """Names given to ``node`` by params files (matched by node name, ``/**`` included) and
    ``-p``/``parameter_overrides``. rclpy keeps them in ``_parameter_overrides`` and has no
    public accessor; without it no unknown name could be reported."""
    return list(getattr(node, "_parameter_overrides", {}) or {})


def unknown_parameters(node: Any) -> list[str]:
    """Override names the node does not declare (misspelt keys would otherwise be silently
    ignored). rclpy's own (``use_sim_time``) and the ``qos_overrides.*`` of the node's
    subscriptions are declared once it has subscribed; a ``qos_overrides`` key of any other topic
    is unknown."""
    return sorted(n for n in override_names(node) if not node.has_parameter(n))


def usage(doc: str) -> str:
    """``ficap_node --help``: how to run it, ``doc`` (the node's interface) and every parameter
    with its default and description."""
    lines = [f"usage: {doc.split(':', 1)[0].strip('`') or 'ficap_node'} [--ros-args "
             "[-r FROM:=TO] [-p NAME:=VALUE] [--params-file FILE]]", "", doc.strip(), "",
             "Parameters (-p NAME:=VALUE, or a params file; ros2 param describe for ranges):"]
    for spec in PARAMETERS:
        lines.append(f"  {spec.name} (default {spec.default!r}"
                     f"{', read-only' if spec.read_only else ''}): {spec.description}")
    return "\n".join(lines) + "\n"


def unknown_warning(names: list[str]) -> str:
    """The start-up warning naming parameters the node does not declare, and those it does."""
    return (f"unknown parameter(s) ignored: {', '.join(names)} (ficap_node declares: "
            f"{', '.join(p.name for p in PARAMETERS)})")
