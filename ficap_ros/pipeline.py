"""One frame in, one result out: detection, cap pose and head pose.

The single code path shared by the live node, the bag tools, the demo and the benchmarks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import CapModel, nominal_model
from ficap_ros.detection import DetectorConfig, TagDetection, TagDetector, as_gray
from ficap_ros.pose import CapPose, PoseConfig, estimate_cap_pose
from ficap_ros.transform import CAM_FROM_FORWARD, Transform

__all__ = ["HeadCalibration", "FrameResult", "FrameProcessor"]


@dataclass(frozen=True)
class HeadCalibration:
    """How the cap sits on the head, and how the head's zero pose sits in the camera.

    Attributes:
        R_cap_head: orientation of the head frame H (x forward, y left, z up) in the cap frame C.
            Identity until calibrated.
        R_cam_frontal: orientation of the frontal frame F (the head's zero pose: x forward, y left,
            z up, usually the vehicle's axes) in the camera optical frame. Default: the camera looks
            straight forward, so F's x is the optical axis.
        calibrated: whether ``R_cap_head`` came from a calibration.
    """

    R_cap_head: Rotation = field(default_factory=Rotation.identity)
    R_cam_frontal: Rotation = field(default_factory=lambda: CAM_FROM_FORWARD)
    calibrated: bool = False

    def head_in_camera(self, T_cam_cap: Transform) -> Transform:
        """T_cam_head: the cap pose composed with R_cap_head (head origin = cap origin)."""
        return Transform(T_cam_cap.rotation * self.R_cap_head, T_cam_cap.translation_m)

    def head_in_frontal(self, T_cam_cap: Transform) -> Rotation:
        """R_frontal_head: the head orientation in the frontal frame (identity when frontal)."""
        return self.R_cam_frontal.inv() * T_cam_cap.rotation * self.R_cap_head


@dataclass(frozen=True)
class FrameResult:
    """Everything known about one frame.

    Attributes:
        stamp_ns: the image's stamp, ns.
        detections: tags of the model detected in the frame (duplicates included).
        pose: the cap pose, or None.
        reason: why there is no pose ("" when there is one).
        T_cam_head: head pose in the camera optical frame (None without a pose).
        R_frontal_head: head orientation in the frontal frame (None without a pose).
        detect_ms, pose_ms: time spent, ms.
    """

    stamp_ns: int
    detections: tuple[TagDetection, ...]
    pose: CapPose | None
    reason: str
    T_cam_head: Transform | None
    R_frontal_head: Rotation | None
    detect_ms: float
    pose_ms: float

    @property
    def tags_detected(self) -> int:
        return len({d.tag_id for d in self.detections})

    @property
    def tags_used(self) -> int:
        return self.pose.tags_used if self.pose is not None else 0


class FrameProcessor:
    """Detect tags and estimate the cap and head pose of frames from one camera."""

    def __init__(
        self,
        model: CapModel | None = None,
        detector: DetectorConfig | None = None,
        pose: PoseConfig | None = None,
        calibration: HeadCalibration | None = None,
    ) -> None:
        self.model = model or nominal_model()
        self.detector = TagDetector(detector)
        self.pose_config = pose or PoseConfig()
        self.calibration = calibration or HeadCalibration()

    def detect(self, image: np.ndarray) -> tuple[TagDetection, ...]:
        """Detections of the model's tags (validates the image; raises ``ImageError``)."""
        gray = as_gray(image)
        return tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)

    def process(self, image: np.ndarray, camera: CameraModel, stamp_ns: int = 0) -> FrameResult:
        """Process one frame (raises ``ImageError`` for an invalid image)."""
        t0 = time.perf_counter()
        detections = self.detect(image)
        t1 = time.perf_counter()
        result = estimate_cap_pose(detections, self.model, camera, self.pose_config)
        t2 = time.perf_counter()
        pose = result.pose
        return FrameResult(
            stamp_ns=int(stamp_ns),
            detections=detections,
            pose=pose,
            reason=result.reason,
            T_cam_head=None if pose is None else self.calibration.head_in_camera(pose.T_cam_cap),
            R_frontal_head=None if pose is None else self.calibration.head_in_frontal(pose.T_cam_cap),
            detect_ms=(t1 - t0) * 1e3,
            pose_ms=(t2 - t1) * 1e3,
        )
