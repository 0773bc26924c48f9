"""One frame in, one result out: detection, cap pose and head pose.

The single code path shared by the live node, the bag tools, the demo and the benchmarks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.calibration import HeadCalibration
from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import CapModel, nominal_model
from ficap_ros.detection import (
    DetectorConfig,
    TagDetection,
    TagDetector,
    as_gray,
    refine_corners_edge_ok,
    refine_tag_corners,
    with_frame_edge_shift,
)
from ficap_ros.pose import CapPose, PoseConfig, estimate_cap_pose
from ficap_ros.tracking import TrackConfig, extrapolate_pose, predict_tags, verify_tags, view_angles_deg
from ficap_ros.transform import Transform

__all__ = ["FrameResult", "FrameProcessor"]


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
        search: how the tags were found: ``tracked`` (verified where the last poses predicted
            them, no search), ``region`` (searched around the last pose) or ``image`` (the whole
            image searched).
    """

    stamp_ns: int
    detections: tuple[TagDetection, ...]
    pose: CapPose | None
    reason: str
    T_cam_head: Transform | None
    R_frontal_head: Rotation | None
    detect_ms: float
    pose_ms: float
    search: str = "image"

    @property
    def tags_detected(self) -> int:
        return len({d.tag_id for d in self.detections})

    @property
    def tags_used(self) -> int:
        return self.pose.tags_used if self.pose is not None else 0


#: Tracking: frames further apart than this are searched over the whole image.
_TRACK_MAX_GAP_NS = 500_000_000
#: Tracking margin around the predicted tags (region search): this fraction of the region's size
#: plus pixels.
_TRACK_MARGIN_FRACTION = 0.25
_TRACK_MARGIN_PX = 24
#: Tracking: a predicted region larger than this share of the image is searched as a whole.
_TRACK_MAX_AREA = 0.6
#: Tracking, second look: a tag not verified at the extrapolated pose is looked for again at the
#: pose of the verified tags when that moves its predicted corners by more than this.
_TRACK_RETRY_PX = 0.5
#: Tracking: a refinement pass that moves no corner by more than this started close enough to the
#: edges for its result to be final (0.05, 0.1, 0.2 and 0.5 px gave the same pose error on the
#: rendered glance sequence; a second pass is a fifth of a tracked frame's time).
_TRACK_CONVERGED_PX = 0.2


@dataclass(frozen=True)
class _TrackState:
    T_cam_cap: Transform
    T_prev: Transform | None  # the pose one frame earlier, for the velocity
    stamp_ns: int
    dt_prev_ns: int  # stamp_ns minus the earlier frame's stamp (0: unknown)
    n_tags: int
    camera_key: tuple


def _camera_key(camera: CameraModel) -> tuple:
    return (camera.width_px, camera.height_px, camera.K.tobytes(), camera.D.tobytes(),
            camera.distortion_model)


class FrameProcessor:
    """Detect tags and estimate the cap and head pose of frames from one camera.

    Args:
        model, detector, pose, calibration: cap model, detector, pose and head-calibration settings.
        tracking: follow the cap from frame to frame (see ``process``); frames must then come from
            one camera in time order, which is how the node and the bag tools feed it. ``False``
            makes every frame independent (every frame searched over the whole image).
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
        self.calibration = calibration or HeadCalibration()
        self.tracking = bool(tracking)
        self.track_config = track or TrackConfig()
        # Tracked tags start from extrapolated corners: usually within a tenth of a pixel, so one
        # refinement pass converges; after a sudden head movement a few px off, out of the fine
        # pass's reach, so those get a coarse pass with a wide reach (capped at 0.6 cell) first.
        base = self.detector.config
        self._fine_pass = replace(base, edge_iterations=1)
        self._tracked_corners = replace(base, edge_fit_iterations=1)
        self._coarse_passes = (
            replace(base, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                    edge_samples_per_side=12, edge_profile_samples=9),
            replace(base, edge_iterations=2),
        )
        # Search-free tracking rests on the edge refinement (it pulls predicted corners onto the
        # border); with another corner refinement tracked frames are searched in the region.
        self._verify_tracking = self.tracking and base.corner_refine == "edge"
        self._locate_pose = replace(self.pose_config, method="naive")
        self._track: _TrackState | None = None
        self.tracked_frames = 0  # frames whose tags were verified where the cap was predicted
        self.second_looks = 0  # tracked frames that looked again at the verified tags' pose
        self.roi_searches = 0  # frames searched in the predicted region only
        self.full_searches = 0  # frames searched over the whole image
        self.search_completions = 0  # searches whose pose found more of the model's tags

    def detect(self, image: np.ndarray) -> tuple[TagDetection, ...]:
        """Detections of the model's tags in the whole image (stateless; raises ``ImageError``)."""
        gray = as_gray(image)
        return tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)

    def reset_tracking(self) -> None:
        """Forget the previous frames: the next frame is searched over the whole image."""
        self._track = None

    def _usable_track(self, camera: CameraModel, stamp_ns: int) -> _TrackState | None:
        """The last posed frame's state if a frame at ``stamp_ns`` can follow it (same camera;
        stamps in order and at most ``_TRACK_MAX_GAP_NS`` apart, or unknown), else None."""
        tr = self._track
        if tr is None or tr.camera_key != _camera_key(camera):
            return None
        if stamp_ns and tr.stamp_ns and not 0 <= stamp_ns - tr.stamp_ns <= _TRACK_MAX_GAP_NS:
            return None
        return tr

    def _predict_pose(self, camera: CameraModel, stamp_ns: int) -> Transform | None:
        """The cap pose at ``stamp_ns`` extrapolated from the last two frames, or None."""
        tr = self._usable_track(camera, stamp_ns)
        if tr is None:
            return None
        timed = bool(stamp_ns and tr.stamp_ns and tr.dt_prev_ns > 0)
        ratio = (stamp_ns - tr.stamp_ns) / tr.dt_prev_ns if timed else 1.0
        return extrapolate_pose(tr.T_cam_cap, tr.T_prev, min(ratio, 3.0))

    def _refine_predicted(self, gray: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Edge-refine predicted corners: one pass, a second where the first moved a corner by more
        than ``_TRACK_CONVERGED_PX``, and coarse-then-fine passes where the first failed."""
        refined, ok = refine_corners_edge_ok(gray, corners, self._fine_pass)
        moved = np.linalg.norm(refined - corners, axis=2).max(axis=1)
        again = ok & (moved > _TRACK_CONVERGED_PX)
        if again.any():
            refined[again], ok[again] = refine_corners_edge_ok(gray, refined[again], self._fine_pass)
        if not ok.all():
            lost = ~ok
            c = corners[lost]
            ok_lost = np.ones(len(c), dtype=bool)
            for config in self._coarse_passes:
                c, ok_pass = refine_corners_edge_ok(gray, c, config)
                ok_lost &= ok_pass
            refined[lost], ok[lost] = c, ok_lost
        return refined, ok

    def _verified(self, gray: np.ndarray, ids: np.ndarray, corners: np.ndarray) -> tuple[list[TagDetection], float]:
        """Refine predicted corners and keep the tags whose cells read as their ids; also the
        largest distance, px, a verified tag's corner moved from its prediction."""
        refined, ok = self._refine_predicted(gray, corners)
        # The tone-curve bias and the cell-edge fit, as on searched tags (one corner estimator).
        shift = np.full(len(ids), np.nan)
        refined[ok], shift[ok] = refine_tag_corners(gray, refined[ok], ids[ok], self._tracked_corners)
        ver, errors, contrast = verify_tags(gray, ids[ok], refined[ok], self.track_config)
        moved = np.linalg.norm(refined[ok][ver] - corners[ok][ver], axis=2)
        return ([TagDetection(int(i), c, int(e), float(m), float(x))
                 for i, c, e, m, x in zip(ids[ok][ver], refined[ok][ver], errors[ver], contrast[ver],
                                          shift[ok][ver])],
                float(moved.max()) if moved.size else 0.0)

    def _track_tags(
        self, gray: np.ndarray, camera: CameraModel, predicted: Transform
    ) -> tuple[TagDetection, ...] | None:
        """The model's tags verified where ``predicted`` puts them; None when too few verify."""
        cfg = self.track_config
        ids, corners = predict_tags(self.model, camera, predicted, cfg)
        found, moved_px = self._verified(gray, ids, corners)
        if len(found) < cfg.min_tags:
            return None
        found_ids = {d.tag_id for d in found}
        missing = np.array([i not in found_ids for i in ids], dtype=bool)
        if missing.any() and moved_px > _TRACK_RETRY_PX:
            # Second look: the verified tags moved from their predicted corners, so the
            # extrapolation was off; they pin the pose down, and where that pose moves a missing
            # tag's predicted corners, that tag is refined again from there.
            self.second_looks += 1
            first = estimate_cap_pose(found, self.model, camera, self.pose_config, start=predicted)
            if first.pose is not None:
                ids2, corners2 = predict_tags(self.model, camera, first.pose.T_cam_cap, cfg)
                before = dict(zip(ids[missing].tolist(), corners[missing]))
                retry = np.array([int(i) in before and np.abs(c - before[int(i)]).max() > _TRACK_RETRY_PX
                                  for i, c in zip(ids2, corners2)], dtype=bool)
                if retry.any():
                    found += self._verified(gray, ids2[retry], corners2[retry])[0]
        return tuple(found)

    def _detect_tracked(
        self, gray: np.ndarray, camera: CameraModel, stamp_ns: int
    ) -> tuple[tuple[TagDetection, ...], Transform | None, str]:
        """Tags of a frame, the predicted pose (None: none) and how the tags were found
        (``FrameResult.search``).

        First the tags are looked for where the extrapolated pose puts them (no search); if too
        few verify, the region around the last pose is searched; if that finds fewer tags than
        the last frame had, the whole image.
        """
        predicted = self._predict_pose(camera, stamp_ns)
        if predicted is not None and self._verify_tracking:
            found = self._track_tags(gray, camera, predicted)
            if found is not None:
                self.tracked_frames += 1
                return found, predicted, "tracked"
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
                found, seen_at = self._complete_search(gray, camera, found, predicted)
                return found, seen_at, "region"
        self.full_searches += 1
        found = tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)
        found, seen_at = self._complete_search(gray, camera, found, predicted)
        return found, seen_at, "image"

    def _complete_search(
        self, gray: np.ndarray, camera: CameraModel, found: tuple[TagDetection, ...],
        predicted: Transform | None,
    ) -> tuple[tuple[TagDetection, ...], Transform | None]:
        """A search's tags plus the model's other tags read where the searched ones put them.

        The search (decimated on large frames) loses the smallest and most oblique tags; the cap
        is rigid, so the pose of the tags it found predicts the rest, which are edge-refined and
        verified exactly as tracked tags are. Returns the tags and the pose they were looked for
        at (the search's pose, or ``predicted`` when too few tags were found to pose the cap).
        """
        if not self._verify_tracking or len({d.tag_id for d in found}) < self.track_config.min_tags:
            return found, predicted
        # One SQPnP + LM is enough to place the others: a wrong prediction verifies no tag, and
        # the final pose only starts from it if every tag agrees with it.
        first = estimate_cap_pose(found, self.model, camera, self._locate_pose)
        if first.pose is None:
            return found, predicted
        ids, corners = predict_tags(self.model, camera, first.pose.T_cam_cap, self.track_config)
        have = {d.tag_id for d in found}
        missing = np.array([int(i) not in have for i in ids], dtype=bool)
        if missing.any():
            self.search_completions += 1
            found = found + tuple(self._verified(gray, ids[missing], corners[missing])[0])
        return found, first.pose.T_cam_cap

    def _predict_roi(
        self, camera: CameraModel, stamp_ns: int, shape: tuple[int, ...]
    ) -> tuple[int, int, int, int] | None:
        """(x, y, w, h) around every front-facing tag at the last pose, with a motion margin."""
        tr = self._usable_track(camera, stamp_ns)
        if tr is None:
            return None
        T = tr.T_cam_cap
        front = view_angles_deg(self.model, T) < 90.0
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

    def _pose_grade(
        self, detections: tuple[TagDetection, ...], predicted: Transform | None
    ) -> tuple[TagDetection, ...]:
        """The detections the pose should use: without the tags seen too obliquely at the
        predicted pose (``TrackConfig.pose_max_view_angle_deg``) while enough others remain."""
        limit = self.track_config.pose_max_view_angle_deg
        if predicted is None or limit >= 90.0 or not self._verify_tracking:
            return detections
        angles = dict(zip(self.model.ids, view_angles_deg(self.model, predicted)))
        kept = tuple(d for d in detections if angles[d.tag_id] <= limit)
        if len({d.tag_id for d in kept}) < max(self.track_config.min_tags, self.pose_config.min_tags):
            return detections
        return kept

    def _next_track(
        self, T_cam_cap: Transform, stamp_ns: int, detections: tuple[TagDetection, ...], camera: CameraModel
    ) -> _TrackState:
        # The velocity needs the previous posed frame to be the one just before, at another stamp.
        prev = self._usable_track(camera, stamp_ns)
        timed = prev is not None and bool(stamp_ns and prev.stamp_ns)
        if timed and stamp_ns == prev.stamp_ns:  # type: ignore[union-attr]
            prev = None
        return _TrackState(
            T_cam_cap, None if prev is None else prev.T_cam_cap, stamp_ns,
            stamp_ns - prev.stamp_ns if prev is not None and timed else 0,
            len({d.tag_id for d in detections}), _camera_key(camera))

    def process(self, image: np.ndarray, camera: CameraModel, stamp_ns: int = 0) -> FrameResult:
        """Process one frame (raises ``ImageError`` for an invalid image).

        With ``tracking``, a frame that follows one with a pose is not searched: the cap pose is
        extrapolated from the last two frames and its tags are refined and verified (their cells
        read as their ids) where it puts them (``ficap_ros.tracking``). When fewer than
        ``TrackConfig.min_tags`` verify, the region around the last pose is searched, and when that
        finds fewer tags than the last frame had, the whole image. A search uses the whole
        image's settings and refines on the whole image, so a tag gets the same corners however
        it was found. Frames without a recent predecessor are searched over the whole image.
        """
        t0 = time.perf_counter()
        predicted, search = None, "image"
        if self.tracking:
            gray = as_gray(image)
            detections, predicted, search = self._detect_tracked(gray, camera, int(stamp_ns))
        else:
            detections = self.detect(image)
        # Tags too small or oblique to measure their own tone-curve shift take the frame's.
        detections = with_frame_edge_shift(detections)
        t1 = time.perf_counter()
        result = estimate_cap_pose(self._pose_grade(detections, predicted), self.model, camera,
                                   self.pose_config, start=predicted)
        t2 = time.perf_counter()
        pose = result.pose
        if pose is not None and pose.tags_detected != len({d.tag_id for d in detections}):
            pose = replace(pose, tags_detected=len({d.tag_id for d in detections}))
        if self.tracking:
            self._track = None if pose is None else self._next_track(pose.T_cam_cap, int(stamp_ns), detections, camera)
        return FrameResult(
            stamp_ns=int(stamp_ns),
            detections=detections,
            pose=pose,
            reason=result.reason,
            T_cam_head=None if pose is None else self.calibration.head_in_camera(pose.T_cam_cap),
            R_frontal_head=None if pose is None else self.calibration.head_in_frontal(pose.T_cam_cap),
            detect_ms=(t1 - t0) * 1e3,
            pose_ms=(t2 - t1) * 1e3,
            search=search,
        )
