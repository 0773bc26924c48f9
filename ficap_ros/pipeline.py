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


#: Tracking: frames further apart than this are searched over the whole image.
_TRACK_MAX_GAP_NS = 500_000_000
#: Tracking margin around the predicted tags: this fraction of the region's size plus pixels.
_TRACK_MARGIN_FRACTION = 0.25
_TRACK_MARGIN_PX = 24
#: Tracking: a predicted region larger than this share of the image is searched as a whole.
_TRACK_MAX_AREA = 0.6


@dataclass(frozen=True)
class _TrackState:
    T_cam_cap: Transform
    stamp_ns: int
    n_tags: int
    camera_key: tuple


def _camera_key(camera: CameraModel) -> tuple:
    return (camera.width_px, camera.height_px, camera.K.tobytes(), camera.D.tobytes(),
            camera.distortion_model)


class FrameProcessor:
    """Detect tags and estimate the cap and head pose of frames from one camera.

    Args:
        model, detector, pose, calibration: cap model, detector, pose and head-calibration settings.
        tracking: search the region predicted from the previous frame's pose first (see
            ``process``); frames must then come from one camera in time order, which is how the
            node and the bag tools feed it. ``False`` makes every frame independent.
    """

    def __init__(
        self,
        model: CapModel | None = None,
        detector: DetectorConfig | None = None,
        pose: PoseConfig | None = None,
        calibration: HeadCalibration | None = None,
        tracking: bool = True,
    ) -> None:
        self.model = model or nominal_model()
        self.detector = TagDetector(detector)
        self.pose_config = pose or PoseConfig()
        self.calibration = calibration or HeadCalibration()
        self.tracking = bool(tracking)
        self._track: _TrackState | None = None
        self.roi_searches = 0  # frames searched in the predicted region only
        self.full_searches = 0  # frames searched over the whole image

    def detect(self, image: np.ndarray) -> tuple[TagDetection, ...]:
        """Detections of the model's tags in the whole image (stateless; raises ``ImageError``)."""
        gray = as_gray(image)
        return tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)

    def reset_tracking(self) -> None:
        """Forget the previous frame: the next frame is searched over the whole image."""
        self._track = None

    def _detect_tracked(self, gray: np.ndarray, camera: CameraModel, stamp_ns: int) -> tuple[TagDetection, ...]:
        """Search the region predicted from the last pose; the whole image if that finds fewer tags."""
        roi = self._predict_roi(camera, stamp_ns, gray.shape)
        if roi is not None:
            found = tuple(d for d in self.detector.detect(gray, roi=roi) if d.tag_id in self.model)
            assert self._track is not None
            # Fewer tags than last frame: search everything, unless the found tags all sit well
            # inside the region (then the cap did not run out of it: the lost tag turned away or
            # got too dark, and the whole image would give the same tags).
            x, y, w, h = roi
            inner = 0.5 * _TRACK_MARGIN_FRACTION * max(w, h) / (1 + 2 * _TRACK_MARGIN_FRACTION)
            inside = bool(found) and all(
                d.corners_px[:, 0].min() >= x + inner and d.corners_px[:, 0].max() <= x + w - inner
                and d.corners_px[:, 1].min() >= y + inner and d.corners_px[:, 1].max() <= y + h - inner
                for d in found)
            if inside or len({d.tag_id for d in found}) >= self._track.n_tags:
                self.roi_searches += 1
                return found
        self.full_searches += 1
        return tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)

    def _predict_roi(
        self, camera: CameraModel, stamp_ns: int, shape: tuple[int, ...]
    ) -> tuple[int, int, int, int] | None:
        """(x, y, w, h) around every front-facing tag at the last pose, with a motion margin."""
        tr = self._track
        if tr is None or tr.camera_key != _camera_key(camera) or tr.n_tags == 0:
            return None
        if stamp_ns and tr.stamp_ns and not 0 <= stamp_ns - tr.stamp_ns <= _TRACK_MAX_GAP_NS:
            return None
        T = tr.T_cam_cap
        normals_cam = T.rotation.apply(self.model.normals)
        centres_cam = T.apply(self.model.centres_mm / 1000.0)
        front = np.einsum("ij,ij->i", normals_cam, centres_cam) < 0.0
        if not front.any():
            return None
        pts = T.apply(self.model.corners_mm[front].reshape(-1, 3) / 1000.0)
        if np.any(pts[:, 2] <= 0.05):
            return None
        px = camera.project(pts)
        if not np.all(np.isfinite(px)):
            return None
        lo, hi = px.min(axis=0), px.max(axis=0)
        # Margin for the motion until the next frame (a fast 150 deg/s glance moves the cap by
        # about a tenth of its size per 30 fps frame) plus the white quiet zone and ArUco's border.
        margin = _TRACK_MARGIN_FRACTION * float(np.max(hi - lo)) + _TRACK_MARGIN_PX
        x0, y0 = np.floor(lo - margin).astype(int)
        x1, y1 = np.ceil(hi + margin).astype(int)
        x0, y0 = max(int(x0), 0), max(int(y0), 0)
        x1, y1 = min(int(x1), shape[1]), min(int(y1), shape[0])
        if x1 - x0 < 16 or y1 - y0 < 16 or (x1 - x0) * (y1 - y0) > _TRACK_MAX_AREA * shape[0] * shape[1]:
            return None  # off the image, or a region nearly as big as the frame
        return x0, y0, x1 - x0, y1 - y0

    def process(self, image: np.ndarray, camera: CameraModel, stamp_ns: int = 0) -> FrameResult:
        """Process one frame (raises ``ImageError`` for an invalid image).

        With ``tracking`` the tags are searched first in the region around the cap's last pose
        (the whole image when there was none, when the frames are far apart in time, or when the
        region gives fewer tags than the last frame had), with the whole image's search settings
        and the refinement on the whole image, so a tag found there gets the same corners.
        """
        t0 = time.perf_counter()
        if self.tracking:
            gray = as_gray(image)
            detections = self._detect_tracked(gray, camera, int(stamp_ns))
        else:
            detections = self.detect(image)
        t1 = time.perf_counter()
        result = estimate_cap_pose(detections, self.model, camera, self.pose_config)
        t2 = time.perf_counter()
        pose = result.pose
        if self.tracking:
            self._track = None if pose is None else _TrackState(
                pose.T_cam_cap, int(stamp_ns), len({d.tag_id for d in detections}), _camera_key(camera))
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
