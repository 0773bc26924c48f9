"""One frame in, what it shows out: the model's tags, how they were found, and the cap pose.

The single code path of the live node, the bag tools, the demo and the benchmarks. The head pose
is ``ficap_ros.io.labels``'s: it composes it from the cap pose and the head calibration.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision import motion_corners
from ficap_ros.vision.detector import DetectorConfig, TagDetection, TagDetector, as_gray
from ficap_ros.vision.motion import MotionPrior, PastPose
from ficap_ros.vision.occlusion import partly_hidden
from ficap_ros.vision.pose import (
    CapPose,
    PoseConfig,
    PoseResult,
    estimate_cap_pose,
)
from ficap_ros.vision.reprojection import TagObservations, undistorted_corners
from ficap_ros.vision.shutter import TimingEvidence, frame_evidence
from ficap_ros.vision.tracking import Search, TrackConfig, TrackedFrame, Tracker
from ficap_ros.vision.uncertainty import UncertaintyConfig

__all__ = ["FrameResult", "FrameSolve", "FrameProcessor", "hidden_tag_ids", "corner_estimator",
           "pose_config_for"]


@dataclass(frozen=True)
class FrameResult:
    """What the pipeline found in one frame.

    Attributes:
        detections: tags of the model detected in the frame (duplicates included).
        pose: the cap pose, or None.
        reason: why there is no pose ("" when there is one).
        search: how the tags were found (``tracking.Search``, a ``str``): ``tracked``, ``region``
            or ``image``.
        detect_ms, pose_ms: time spent finding the tags and solving the pose (with the moving
            tags' refit, ``motion_corners``), ms.
        timing_evidence: what the frame says of the camera's readout when the timing does not
            model one (``shutter.frame_evidence``: a moving cap with a velocity from the frames
            before; ``FrameProcessor(readout_evidence=True)`` only); None otherwise.
            ``shutter.combine_evidence`` turns many into an estimate.
    """

    detections: tuple[TagDetection, ...]
    pose: CapPose | None
    reason: str
    search: Search = Search.IMAGE
    detect_ms: float = 0.0
    pose_ms: float = 0.0
    timing_evidence: TimingEvidence | None = None

    @property
    def detected_ids(self) -> tuple[int, ...]:
        """Ids of the detected tags, sorted, each once."""
        return tuple(sorted({d.tag_id for d in self.detections}))

    @property
    def tags_detected(self) -> int:
        return len(self.detected_ids)


@dataclass(frozen=True)
class FrameSolve:
    """What a frame's pose was solved from (``FrameProcessor.last_solve``), for solving it again
    with the next frame's pose (``FrameProcessor.resolve``, offline).

    Attributes:
        gray: (H, W) uint8 image; camera: its camera.
        detections: the frame's detections before any motion-aware refit.
        tags: the detections the pose was solved from (before any refit).
        prior: the velocity prior from the frames before (None: none).
    """

    gray: np.ndarray
    camera: CameraModel
    detections: tuple[TagDetection, ...]
    tags: tuple[TagDetection, ...]
    prior: MotionPrior | None


def corner_estimator(detector: DetectorConfig) -> str:
    """The corner estimator of a detector setting, as ``UncertaintyConfig.for_corners`` names it:
    ``photometric`` (``edge_photometric``), ``edge`` (the cell-edge fit with its tone-curve
    correction) or ``uncorrected`` (every other ``corner_refine``: corners that keep the tone
    curve's bias)."""
    if detector.edge_photometric:
        return "photometric"
    return "edge" if detector.corner_refine == "edge" else "uncorrected"


def pose_config_for(pose: PoseConfig, detector: DetectorConfig) -> PoseConfig:
    """``pose`` as ``FrameProcessor`` applies it to ``detector``'s corners: an ``uncertainty`` of
    None is the calibrated profile of the corner estimator in use
    (``UncertaintyConfig.for_corners``); an uncertainty that is set is kept as set."""
    if pose.uncertainty is not None:
        return pose
    return replace(pose, uncertainty=UncertaintyConfig.for_corners(corner_estimator(detector)))


def hidden_tag_ids(gray: np.ndarray, detections: tuple[TagDetection, ...]) -> frozenset[int]:
    """Ids of the detections something partly covers (``detection.partly_hidden``): the pose
    drops them at a lower residual than other tags (``PoseConfig.hidden_ratio``)."""
    if not detections:
        return frozenset()
    hidden = partly_hidden(gray, np.stack([d.corners_px for d in detections]),
                           np.array([d.tag_id for d in detections]))
    return frozenset(d.tag_id for d, h in zip(detections, hidden) if h)


class FrameProcessor:
    """Detect tags and estimate the cap pose of frames from one camera.

    Args:
        model, detector, pose: cap model, detector and pose settings. ``pose_config`` may be
            replaced as a whole (the node does when its parameters change): the next frame uses it.
        tracking: follow the cap from frame to frame (``tracking.Tracker``: frames of one camera
            in time order, as the node and the bag tools feed them); ``False``: every frame searched.
        track: tracking settings.
        timing: when the camera's rows see the scene relative to the stamps (exposure, rolling
            shutter readout, stamp offset; ``CameraTiming()``: not known). A rolling shutter's
            poses are solved with the cap's velocity over the readout (``estimate_cap_pose``), the
            tracker's past poses its velocity prior. With an exposure stated, the tags that move
            over it are refitted as moving (``DetectorConfig.motion_corners``,
            ``vision.motion_corners``) and the pose solved again. The cap's velocity (``CapPose.velocity``)
            is reported only when the timing states an exposure or a readout; with neither, the
            outputs are those of an estimator without a motion model. Like ``pose_config`` it may
            be replaced as a whole between frames (the node does when its ``camera.*``
            parameters change; replay sets each recording's).
        readout_evidence: also read each global-shutter frame's evidence of a rolling-shutter
            readout (``FrameResult.timing_evidence``), for a recording's ``timing_estimate``;
            off where nothing collects it (the node), since it costs a residual pass a frame.
    """

    def __init__(self, model: CapModel | None = None, detector: DetectorConfig | None = None,
                 pose: PoseConfig | None = None, tracking: bool = True,
                 track: TrackConfig | None = None, timing: CameraTiming | None = None,
                 readout_evidence: bool = False) -> None:
        self.model = model or nominal_model()
        self.timing = timing or CameraTiming()
        self.readout_evidence = readout_evidence
        self.detector = TagDetector(detector)
        self.pose_config = pose or PoseConfig()
        self.tracker = Tracker(self.model, self.detector, track) if tracking else None
        self._effective: tuple[PoseConfig | None, PoseConfig] = (None, self.pose_config)
        #: What the last ``process`` solved its pose from (None: no pose was solved).
        self.last_solve: FrameSolve | None = None

    @property
    def effective_pose_config(self) -> PoseConfig:
        """``pose_config`` resolved for the detector's corners (``pose_config_for``)."""
        pose = self.pose_config
        if self._effective[0] is not pose:
            self._effective = (pose, pose_config_for(pose, self.detector.config))
        return self._effective[1]

    def reset_tracking(self) -> None:
        """Forget the previous frames: the next frame is searched over the whole image."""
        if self.tracker is not None:
            self.tracker.reset()

    def process(self, image: np.ndarray, camera: CameraModel, stamp_ns: int = 0) -> FrameResult:
        """One frame (raises ``ImageError`` for an invalid image): grey image -> the tracker (or
        a whole-image search without tracking) -> cap pose."""
        pose_config = self.effective_pose_config
        t0 = time.perf_counter()
        gray = as_gray(image)
        solve_started: list[float] = []
        refitted: dict[int, TagDetection] = {}
        solved: list[tuple[tuple[TagDetection, ...], MotionPrior | None]] = []

        def solve(tags: tuple[TagDetection, ...], start: Transform | None,
                  prior: MotionPrior | None = None) -> PoseResult:
            solve_started.append(time.perf_counter())
            solved.append((tags, prior))
            result = self._estimate(gray, camera, pose_config, tags, start, prior)
            if result.pose is None:
                return result
            moved = self._solve_moving(gray, camera, pose_config, tags, result.pose.T_cam_cap,
                                       prior, refitted)
            return result if moved is None else moved

        if self.tracker is not None:
            frame = self.tracker.track(gray, camera, int(stamp_ns), pose_config, solve)
        else:
            detections = tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)
            frame = TrackedFrame(detections, solve(detections, None), Search.IMAGE)
        t1, t2 = solve_started[0], time.perf_counter()
        self.last_solve = (FrameSolve(gray, camera, frame.detections, *solved[-1])
                           if solved and frame.result.pose is not None else None)
        if refitted:
            frame = replace(frame, detections=tuple(refitted.get(id(d), d) for d in frame.detections))
        pose, evidence = frame.result.pose, None
        if self.readout_evidence and pose is not None and not self.timing.rolling:
            evidence = _timing_evidence(pose, frame.detections, self.model, camera)
        if pose is not None and not self.timing.stated:
            pose = replace(pose, velocity=None, velocity_covariance=None)
        return FrameResult(frame.detections, pose, frame.result.reason, frame.search,
                           (t1 - t0) * 1e3, (t2 - t1) * 1e3, evidence)

    def _estimate(self, gray: np.ndarray, camera: CameraModel, pose_config: PoseConfig,
                  tags: tuple[TagDetection, ...], start: Transform | None,
                  prior: MotionPrior | None) -> PoseResult:
        """The cap pose from ``tags`` (the hidden tags read first where the joint solver's
        tag-level outlier step uses them)."""
        cfg = self.detector.config
        find_hidden = cfg.hidden_check and cfg.corner_refine == "edge" and pose_config.method == "joint"
        hidden = hidden_tag_ids(gray, tags) if find_hidden else frozenset()
        return estimate_cap_pose(tags, self.model, camera, pose_config, start=start,
                                 hidden_ids=hidden, timing=self.timing, prior=prior)

    def _solve_moving(self, gray: np.ndarray, camera: CameraModel, pose_config: PoseConfig,
                      tags: tuple[TagDetection, ...], T: Transform, prior: MotionPrior | None,
                      refitted: dict[int, TagDetection]) -> PoseResult | None:
        """Motion-aware corners (``vision.motion_corners``) where they apply: the tags' paths
        through the pose ``T`` and ``prior``'s neighbouring poses, the moving tags refitted
        (recorded in ``refitted`` by the id of the detection they replace) and the pose solved
        again from ``T``; None where they do not apply or nothing moves."""
        if not motion_corners.applies(self.detector.config, self.timing, prior):
            return None
        assert prior is not None
        moved = motion_corners.motion_aware_corners(gray, tags, self.model, camera, self.timing, T,
                                                    prior.neighbours, self.detector.config)
        if all(a is b for a, b in zip(tags, moved)):
            return None
        refitted.update((id(a), b) for a, b in zip(tags, moved) if a is not b)
        return self._estimate(gray, camera, pose_config, moved, T, prior)

    def resolve(self, first: FrameResult, solve: FrameSolve, following: PastPose) -> FrameResult:
        """A frame's result solved again with the next frame's pose (offline, two-sided):
        ``first`` is its ``process`` result and ``solve`` its ``last_solve``; ``following`` the
        next frame's pose (``age_s`` < 0). The rolling-shutter velocity and acceleration and the
        motion-aware corners' paths then interpolate between the frames before and the next one
        (``MotionPrior.two_sided``) instead of extrapolating the frames before. ``first`` as it
        is when the prior is not two-sided (no past pose, the next one too far), the timing
        states neither exposure nor readout, or the second solve finds no pose."""
        if first.pose is None or solve.prior is None or not self.timing.stated:
            return first
        prior = replace(solve.prior, following=(following,))
        if not prior.two_sided:
            return first
        pose_config = self.effective_pose_config
        t0 = time.perf_counter()
        T = first.pose.T_cam_cap
        refitted: dict[int, TagDetection] = {}
        result = self._solve_moving(solve.gray, solve.camera, pose_config, solve.tags, T, prior,
                                    refitted)
        if result is None:
            result = self._estimate(solve.gray, solve.camera, pose_config, solve.tags, T, prior)
        if result.pose is None:
            return first
        detections = tuple(refitted.get(id(d), d) for d in solve.detections)
        return replace(first, detections=detections, pose=result.pose, reason=result.reason,
                       pose_ms=first.pose_ms + (time.perf_counter() - t0) * 1e3)


def _timing_evidence(pose: CapPose, detections: tuple[TagDetection, ...], model: CapModel,
                     camera: CameraModel) -> TimingEvidence | None:
    """A global-shutter pose's evidence of a readout (``shutter.frame_evidence``): its tags'
    corners (each used id seen once) against the pose and its velocity; None without one."""
    if pose.velocity is None:
        return None
    used = [d for d in detections if d.tag_id in pose.used_ids]
    seen = Counter(d.tag_id for d in used)
    once = {d.tag_id: d for d in used if seen[d.tag_id] == 1}
    corners = {i: c[0] for i, c in undistorted_corners(list(once.values()), camera).items()}
    if len(corners) < 4:
        return None
    obs = TagObservations.of(corners, model, camera.K)
    rows = np.concatenate([once[i].corners_px[:, 1] for i in obs.ids])
    return frame_evidence(obs, pose.T_cam_cap, pose.velocity, camera, rows)
