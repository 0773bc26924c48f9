"""One frame in, one result out: detection, cap pose and head pose.

The single code path shared by the live node, the bag tools, the demo and the benchmarks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.detector import DetectorConfig, TagDetection, TagDetector, as_gray
from ficap_ros.vision.occlusion import partly_hidden
from ficap_ros.vision.pose import (
    CapPose,
    PoseConfig,
    UncertaintyConfig,
    estimate_cap_pose,
)
from ficap_ros.vision.tracking import Search, TrackConfig, Tracker

__all__ = ["FrameResult", "FrameProcessor", "hidden_tag_ids", "corner_estimator", "pose_config_for"]


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
        search: how the tags were found (``tracking.Search``, a ``str``): ``tracked`` (verified
            where the last poses predicted them, no search), ``region`` (searched around the last
            pose) or ``image`` (the whole image searched).
    """

    stamp_ns: int
    detections: tuple[TagDetection, ...]
    pose: CapPose | None
    reason: str
    T_cam_head: Transform | None
    R_frontal_head: Rotation | None
    detect_ms: float
    pose_ms: float
    search: Search = Search.IMAGE

    @property
    def tags_detected(self) -> int:
        return len({d.tag_id for d in self.detections})

    @property
    def tags_used(self) -> int:
        return self.pose.tags_used if self.pose is not None else 0


def corner_estimator(detector: DetectorConfig) -> str:
    """The corner estimator a detector setting uses, as ``UncertaintyConfig.for_corners`` names
    it: ``photometric`` (``edge_photometric``) or ``edge`` (the cell-edge fit; also every other
    ``corner_refine``, whose bounds have no profile of their own)."""
    return "photometric" if detector.edge_photometric else "edge"


def pose_config_for(pose: PoseConfig, detector: DetectorConfig) -> PoseConfig:
    """``pose`` as ``FrameProcessor`` applies it to ``detector``'s corners: when its uncertainty is
    the default ``UncertaintyConfig()``, the synth-calibrated profile of the corner estimator in
    use (``UncertaintyConfig.for_corners``); an uncertainty set to anything else is kept as set.

    The default corners' profile is the default, so with them this is ``pose`` itself (labels and
    fleet fingerprints as before). "Not set" is equality with the defaults, not a sentinel field
    (which would change ``repr(PoseConfig)`` and so every fleet fingerprint): a photometric run
    that passes exactly the defaults gets the photometric profile too.
    """
    if pose.uncertainty != UncertaintyConfig():
        return pose
    profile = UncertaintyConfig.for_corners(corner_estimator(detector))
    return pose if profile == pose.uncertainty else replace(pose, uncertainty=profile)


def hidden_tag_ids(gray: np.ndarray, detections: tuple[TagDetection, ...]) -> frozenset[int]:
    """Ids of the detections something partly covers (``detection.partly_hidden``): the pose
    drops them at a lower residual than other tags (``PoseConfig.hidden_ratio``)."""
    if not detections:
        return frozenset()
    hidden = partly_hidden(gray, np.stack([d.corners_px for d in detections]),
                           np.array([d.tag_id for d in detections]))
    return frozenset(d.tag_id for d, h in zip(detections, hidden) if h)


class FrameProcessor:
    """Detect tags and estimate the cap and head pose of frames from one camera.

    Args:
        model, detector, pose, calibration: cap model, detector, pose and head-calibration settings.
        tracking: follow the cap from frame to frame (``tracking.Tracker``); frames must then come
            from one camera in time order, which is how the node and the bag tools feed it.
            ``False`` makes every frame independent (every frame searched over the whole image).
        track: tracking settings.
    """

    def __init__(
        self,
        model: CapModel | None = None,
        detector: DetectorConfig | None = None,
        pose: PoseConfig | None = None,
        calibration: HeadCalibration | None = None,
        tracking: bool = True,
        track: TrackConfig | None = None,
    ) -> None:
        self.model = model or nominal_model()
        self.detector = TagDetector(detector)
        self.pose_config = pose or PoseConfig()
        #: Replaced as a whole (never mutated) by the node's service thread: ``process`` reads it
        #: once per frame, so a frame never mixes two calibrations.
        self.calibration = calibration or HeadCalibration()
        self.tracker = Tracker(self.model, self.detector, self.pose_config, track) if tracking else None
        self._effective: tuple[PoseConfig | None, PoseConfig] = (None, self.pose_config)

    @property
    def effective_pose_config(self) -> PoseConfig:
        """``pose_config`` with the uncertainty profile of the detector's corners
        (``pose_config_for``); re-derived when ``pose_config`` is replaced (the node does)."""
        pose = self.pose_config
        if self._effective[0] is not pose:
            self._effective = (pose, pose_config_for(pose, self.detector.config))
        return self._effective[1]

    def detect(self, image: np.ndarray) -> tuple[TagDetection, ...]:
        """Detections of the model's tags in the whole image (stateless; raises ``ImageError``)."""
        gray = as_gray(image)
        return tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)

    def reset_tracking(self) -> None:
        """Forget the previous frames: the next frame is searched over the whole image."""
        if self.tracker is not None:
            self.tracker.reset()

    def process(self, image: np.ndarray, camera: CameraModel, stamp_ns: int = 0,
                calibration: HeadCalibration | None = None) -> FrameResult:
        """Process one frame (raises ``ImageError`` for an invalid image): grey image -> tracker
        (or a whole-image search without tracking) -> cap pose -> head pose through
        ``calibration`` (default: ``self.calibration``, read once)."""
        calibration = calibration or self.calibration
        pose_config = self.effective_pose_config
        t0 = time.perf_counter()
        predicted, search = None, Search.IMAGE
        gray = as_gray(image)
        if self.tracker is not None:
            detections, predicted, search = self.tracker.find(gray, camera, int(stamp_ns), pose_config)
        else:
            detections = self.detect(gray)
        t1 = time.perf_counter()
        used = detections if self.tracker is None else \
            self.tracker.pose_tags(detections, predicted, pose_config)
        cfg = self.detector.config
        # Only the joint solver reads it (``paper`` and ``naive`` have no tag-level outlier step).
        hidden = hidden_tag_ids(gray, used) if (cfg.hidden_check and cfg.corner_refine == "edge"
                                                and pose_config.method == "joint") else ()
        result = estimate_cap_pose(used, self.model, camera, pose_config, start=predicted, hidden_ids=hidden)
        t2 = time.perf_counter()
        pose = result.pose
        if pose is not None and pose.tags_detected != len({d.tag_id for d in detections}):
            pose = replace(pose, tags_detected=len({d.tag_id for d in detections}))
        if self.tracker is not None:
            self.tracker.update(None if pose is None else pose.T_cam_cap, int(stamp_ns),
                                detections, camera)
        return FrameResult(
            stamp_ns=int(stamp_ns),
            detections=detections,
            pose=pose,
            reason=result.reason,
            T_cam_head=None if pose is None else calibration.head_in_camera(pose.T_cam_cap),
            R_frontal_head=None if pose is None else calibration.head_in_frontal(pose.T_cam_cap),
            detect_ms=(t1 - t0) * 1e3,
            pose_ms=(t2 - t1) * 1e3,
            search=search,
        )
