"""Tracking: find the cap's tags where the previous poses say they are, without a search.

Between consecutive frames of a 30-60 fps camera the cap moves little, and it is rigid, so its
pose (extrapolated at constant velocity from the last two) predicts every tag's corners to a few
pixels. The edge refinement (``detection.refine_corners_edge_ok``) pulls the predicted corners
onto the tag's border, the tag-aware corner stage removes the tone-curve bias; then each tag is *verified* by reading its 8x8 cells (black border and
6x6 data bits) through the homography of its refined corners and comparing them with the code
of the id it is expected to be. A tag36h11 code is at least 11 bits from any other, and a wrong
image patch matches one given 64-cell pattern within 2 cells with a chance of about 1e-16 (for
random cells), so a verified tag is as trustworthy as a searched one.

This replaces ArUco's search (the costliest step: adaptive thresholds, contours, candidate
decoding over the whole image) on every tracked frame; the tracker falls back to the search when
tracking cannot verify enough tags (``Tracker`` below, which ``pipeline.FrameProcessor`` runs one
call a frame: ``Tracker.track``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import Enum
from typing import Callable

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.tag36h11 import (
    stacked_tag_cells,
    tag_cells,
    tag_homographies,
)
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.cell_reads import read_cells
from ficap_ros.vision.corners import refine_tag_corners
from ficap_ros.vision.detector import TagDetection, TagDetector
from ficap_ros.vision.edges import PREV, refine_corners_edge_ok
from ficap_ros.vision.motion import MotionPrior, PastPose
from ficap_ros.vision.pose import CapPose, PoseConfig, PoseResult, estimate_cap_pose

__all__ = ["TrackConfig", "Tracker", "TrackedFrame", "PoseSolver", "Search", "extrapolate_pose",
           "predict_tags", "verify_tags", "tag_cells", "view_angles_deg"]

@dataclass(frozen=True)
class TrackConfig:
    """Tracking settings.

    Attributes:
        max_view_angle_deg: tags seen more obliquely than this (angle between the tag's normal
            and the line of sight) are not looked for.
        pose_max_view_angle_deg: tags seen more obliquely than this at the predicted pose are
            reported but left out of the pose (their corners are the least accurate), as long as
            ``min_tags`` others remain.
        min_side_px: tags whose predicted shortest side is below this are not looked for (cells
            under about 1 px cannot be read).
        border_px: nor tags with a predicted corner closer than this to the image border.
        max_cell_errors: a tag is verified when at most this many of its 64 cells (border and
            data) read differently from its id's code.
        min_contrast: ... and when its white margin is at least this many grey levels brighter
            than its black border.
        min_tags: fewest verified tags for a tracked frame; with fewer the frame is searched.
    """

    max_view_angle_deg: float = 86.0
    pose_max_view_angle_deg: float = 78.0
    min_side_px: float = 8.0
    border_px: float = 4.0
    max_cell_errors: int = 2
    min_contrast: float = 20.0
    min_tags: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.max_view_angle_deg < 90.0:
            raise ConfigError(f"max_view_angle_deg must be in (0, 90), got {self.max_view_angle_deg}")
        if not 0.0 < self.pose_max_view_angle_deg <= 90.0:
            raise ConfigError(f"pose_max_view_angle_deg must be in (0, 90], got {self.pose_max_view_angle_deg}")
        if not self.min_side_px >= 4.0:
            raise ConfigError(f"min_side_px must be >= 4, got {self.min_side_px}")
        if not 0 <= self.max_cell_errors <= 4:
            raise ConfigError(f"max_cell_errors must be in [0, 4], got {self.max_cell_errors}")
        if self.min_tags < 1:
            raise ConfigError(f"min_tags must be >= 1, got {self.min_tags}")


def extrapolate_pose(
    T_prev: Transform, T_prev2: Transform | None, dt_ratio: float = 1.0
) -> Transform:
    """The cap pose one step on at constant velocity.

    Args:
        T_prev: T_cam_cap of the last frame.
        T_prev2: T_cam_cap of the frame before it (None: assume no motion).
        dt_ratio: (t_now - t_prev) / (t_prev - t_prev2); 1 for evenly spaced frames.

    Returns:
        Predicted T_cam_cap: rotation continued about the camera's axes, cap origin continued along
        a straight line.
    """
    if T_prev2 is None:
        return T_prev
    step = (T_prev * T_prev2.inv()).rvec * dt_ratio
    t = T_prev.translation_m + (T_prev.translation_m - T_prev2.translation_m) * dt_ratio
    return T_prev.turned(step, t)


def view_angles_deg(model: CapModel, T_cam_cap: Transform) -> np.ndarray:
    """Angle (model.ids order) between each tag's outward normal and its line of sight to the
    camera, deg: 0 = seen head-on, 90 = edge-on, above 90 = facing away."""
    centres_cam = T_cam_cap.apply(model.centres_mm / 1000.0)
    normals_cam = model.normals @ T_cam_cap.rotation_matrix.T
    dist = np.maximum(np.linalg.norm(centres_cam, axis=1), 1e-9)
    return np.degrees(np.arccos(np.clip(-np.einsum("ij,ij->i", normals_cam, centres_cam) / dist, -1.0, 1.0)))


def predict_tags(
    model: CapModel, camera: CameraModel, T_cam_cap: Transform, config: TrackConfig | None = None,
    angles_deg: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Ids (K,) and distorted-image corners (K, 4, 2) of the tags worth looking for at a pose.

    A tag is worth it when it faces the camera within ``max_view_angle_deg``, lies in front of it,
    has every corner inside the image (``border_px`` in) and a shortest side of ``min_side_px``.
    ``angles_deg``: ``view_angles_deg(model, T_cam_cap)`` when the caller has it already.
    """
    cfg = config or TrackConfig()
    if angles_deg is None:
        angles_deg = view_angles_deg(model, T_cam_cap)
    facing = (angles_deg < cfg.max_view_angle_deg) & (
        T_cam_cap.apply(model.centres_mm / 1000.0)[:, 2] > 0.05)
    if not facing.any():
        return np.zeros(0, dtype=int), np.zeros((0, 4, 2))
    ids = np.asarray(model.ids)[facing]
    px = camera.project(T_cam_cap.apply(model.corners_mm[facing].reshape(-1, 3) / 1000.0)).reshape(-1, 4, 2)
    side = np.linalg.norm(px - px[:, PREV], axis=2).min(axis=1)
    b = cfg.border_px
    inside = (
        np.all(np.isfinite(px), axis=(1, 2))
        & np.all(px[..., 0] >= b, axis=1) & np.all(px[..., 0] <= camera.width_px - 1 - b, axis=1)
        & np.all(px[..., 1] >= b, axis=1) & np.all(px[..., 1] <= camera.height_px - 1 - b, axis=1)
    )
    keep = inside & (side >= cfg.min_side_px)
    return ids[keep], px[keep]


def verify_tags(
    gray: np.ndarray, ids: np.ndarray, corners_px: np.ndarray, config: TrackConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read each tag's cells at its corners and compare them with its id's code.

    Args:
        gray: (H, W) uint8 image.
        ids: (K,) expected ids.
        corners_px: (K, 4, 2) corners, OpenCV order and pixel convention.
        config: acceptance thresholds.

    Returns:
        (verified (K,) bool, cell_errors (K,) int, contrast (K,) grey levels white - black).
    """
    cfg = config or TrackConfig()
    k = len(ids)
    if k == 0:
        return np.zeros(0, dtype=bool), np.zeros(0, dtype=int), np.zeros(0)
    try:
        hom = tag_homographies(np.asarray(corners_px, dtype=np.float64))
    except np.linalg.LinAlgError:
        return np.zeros(k, dtype=bool), np.full(k, 64), np.zeros(k)
    read_black, white, black, finite = read_cells(gray, hom)
    expected = stacked_tag_cells(tuple(int(i) for i in ids)).reshape(k, -1)  # (K, 64) True = black
    errors = (read_black != expected).sum(axis=1)
    contrast = white - black
    ok = (errors <= cfg.max_cell_errors) & (contrast >= cfg.min_contrast) & finite
    return ok, errors, contrast


# -- the tracker ----------------------------------------------------------------------------------
#: Frames further apart than this are searched over the whole image.
_TRACK_MAX_GAP_NS = 500_000_000
#: Margin around the predicted tags (region search): this fraction of the region's size plus pixels.
_TRACK_MARGIN_FRACTION = 0.25
_TRACK_MARGIN_PX = 24
#: A predicted region larger than this share of the image is searched as a whole.
_TRACK_MAX_AREA = 0.6
#: Second look: a tag not verified at the extrapolated pose is looked for again at the pose of the
#: verified tags when that moves its predicted corners by more than this.
_TRACK_RETRY_PX = 0.5
#: A refinement pass that moves no corner by more than this started close enough to the edges for
#: its result to be final (smaller thresholds give the same pose error and cost a second pass).
_TRACK_CONVERGED_PX = 0.2
#: A search completion's tag whose refined corners lie further than this from where the searched
#: tags' pose put them is fitted again from that prediction (``Tracker._refit_astray``): a pose of
#: several tags of the same frame predicts a tag's corners to a few tenths of a px, so a corner this
#: far off is the line pass's, latched onto a neighbouring edge (at low light, on oblique tags).
_LOCATED_AGREE_PX = 1.0
#: ... and the fit from the prediction is taken when it moves no corner further than this from it
#: (it confirms the prediction; a prediction that far off, e.g. of a cap built unlike its model,
#: leaves the line pass's corners).
_LOCATED_CONFIRM_PX = 0.5


class Search(str, Enum):
    """How a frame's tags were found (``TrackedFrame.search``, ``FrameResult.search``; a ``str``
    so it prints and compares as its value)."""

    TRACKED = "tracked"  # verified where the last poses predicted them, no search
    REGION = "region"  # searched around the last pose
    IMAGE = "image"  # the whole image searched

    def __str__(self) -> str:
        return self.value


#: How the pipeline solves a frame's pose: (the tags the pose uses, the pose they were predicted
#: at or None, the velocity prior of the frames before or None) -> the pose result.
#: ``Tracker.track`` calls it once a frame.
PoseSolver = Callable[[tuple[TagDetection, ...], "Transform | None", "MotionPrior | None"],
                      PoseResult]


@dataclass(frozen=True)
class TrackedFrame:
    """One frame through the tracker.

    Attributes:
        detections: the model's tags found in the frame (duplicates included).
        result: the frame's pose, solved by the pipeline's ``PoseSolver`` from the detections the
            pose should use (without tags seen too obliquely at the predicted pose).
        search: how the tags were found.
    """

    detections: tuple[TagDetection, ...]
    result: PoseResult
    search: Search


@dataclass(frozen=True)
class _TrackState:
    T_cam_cap: Transform
    T_prev: Transform | None  # the pose one frame earlier, for the velocity
    stamp_ns: int
    dt_prev_ns: int  # stamp_ns minus the earlier frame's stamp (0: unknown)
    n_tags: int
    camera: CameraModel
    # The last three posed frames' (stamp_ns, pose, covariance), newest first, while
    # consecutive: the velocity prior of the next frame (``Tracker.motion_prior``).
    history: tuple[tuple[int, Transform, np.ndarray], ...] = ()


class Tracker:
    """Follows the cap from frame to frame of one camera (frames in time order).

    A frame that follows one with a pose is not searched: the cap pose is extrapolated from the
    last two frames and its tags are refined and verified (their cells read as their ids) where it
    puts them. When fewer than ``TrackConfig.min_tags`` verify, the region around the last pose is
    searched, and when that finds fewer tags than the last frame had, the whole image. A search
    uses the whole image's settings and refines on the whole image, so a tag gets the same corners
    however it was found; the tags a search missed are read where the searched ones put them.

    The pose settings come with each frame (``track``), so settings the node replaces apply to
    the next frame.

    Args:
        model: the cap model.
        detector: the tag detector (searches and the corner settings of tracked tags).
        config: tracking settings.
    """

    def __init__(self, model: CapModel, detector: TagDetector,
                 config: TrackConfig | None = None) -> None:
        self.model = model
        self.detector = detector
        self.config = config or TrackConfig()
        # Tracked tags start from extrapolated corners: usually within a tenth of a pixel, so one
        # refinement pass converges; after a sudden head movement a few px off, out of the fine
        # pass's reach, so those get a coarse pass with a wide reach (capped at 0.6 cell) first.
        base = detector.config
        self._fine_pass = replace(base, edge_iterations=1)
        self._tracked_corners = replace(base, edge_fit_iterations=1)
        self._coarse_passes = (
            replace(base, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                    edge_samples_per_side=12, edge_profile_samples=9),
            replace(base, edge_iterations=2),
        )
        # Search-free tracking rests on the edge refinement (it pulls predicted corners onto the
        # border); with another corner refinement tracked frames are searched in the region.
        self._verify = base.corner_refine == "edge"
        # The naive pose a search's completion locates the cap with, for the last settings given.
        self._locate: tuple[PoseConfig, PoseConfig] | None = None
        self._track: _TrackState | None = None
        # The view angles at the last pose asked for (``_view_angles``): a tracked frame's
        # prediction and its pose's choice of tags both want them at the predicted pose.
        self._angles_at: Transform | None = None
        self._angles_deg = np.zeros(0)
        self.tracked_frames = 0  # frames whose tags were verified where the cap was predicted
        self.second_looks = 0  # tracked frames that looked again at the verified tags' pose
        self.roi_searches = 0  # frames searched in the predicted region only
        self.full_searches = 0  # frames searched over the whole image
        self.search_completions = 0  # searches whose pose found more of the model's tags

    def reset(self) -> None:
        """Forget the previous frames: the next frame is searched over the whole image."""
        self._track = None

    # -- prediction ---------------------------------------------------------------------------
    def _usable_track(self, camera: CameraModel, stamp_ns: int) -> _TrackState | None:
        """The last posed frame's state if a frame at ``stamp_ns`` can follow it (same camera;
        stamps in order and at most ``_TRACK_MAX_GAP_NS`` apart, or unknown), else None."""
        tr = self._track
        if tr is None or tr.camera != camera:
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

    # -- refine and verify --------------------------------------------------------------------
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

    def _verified(
        self, gray: np.ndarray, ids: np.ndarray, corners: np.ndarray, located: bool = False,
    ) -> tuple[list[TagDetection], float]:
        """Refine predicted corners and keep the tags whose cells read as their ids; also the
        largest distance, px, a verified tag's corner moved from its prediction. ``located``: the
        corners were predicted by the pose of tags found in this frame (a search's completion),
        so a tag refined far from them is fitted again from them (``_refit_astray``)."""
        refined, ok = self._refine_predicted(gray, corners)
        # The tone-curve bias and the cell-edge fit, as on searched tags (one corner estimator),
        # after the edge refinement: corners fitted straight from the prediction keep a pull toward
        # the model's projection, which shrinks the residuals and so the error bounds.
        shift = np.full(len(ids), np.nan)
        refined[ok], shift[ok] = refine_tag_corners(gray, refined[ok], ids[ok], self._tracked_corners)
        if located:
            self._refit_astray(gray, ids, corners, refined, ok, shift)
        ver, errors, contrast = verify_tags(gray, ids[ok], refined[ok], self.config)
        kept = np.flatnonzero(ok)[ver]
        moved = np.linalg.norm(refined[kept] - corners[kept], axis=2)
        # Python numbers (tolist) for the per-tag fields: cheaper than numpy scalars one by one.
        return ([TagDetection(i, c, e, m, x)
                 for i, c, e, m, x in zip(ids[kept].tolist(), refined[kept], errors[ver].tolist(),
                                          contrast[ver].tolist(), shift[kept].tolist())],
                float(moved.max()) if moved.size else 0.0)

    def _refit_astray(
        self, gray: np.ndarray, ids: np.ndarray, predicted: np.ndarray, refined: np.ndarray,
        ok: np.ndarray, shift: np.ndarray,
    ) -> None:
        """Fit again, in place (``refined``, ``shift``), the refined tags (``ok``) with a corner
        further than ``_LOCATED_AGREE_PX`` from its ``predicted`` place, this time from the
        prediction itself (no line pass): a line side pulled onto a neighbouring edge leaves the
        cell-edge fit a start it converges from to a wrong place whose cells still read right. The
        new corners are taken where that fit succeeds, moves no corner further than
        ``_LOCATED_CONFIRM_PX`` from the prediction (it confirms it) and its cells verify."""
        far = np.flatnonzero(ok & (np.linalg.norm(refined - predicted, axis=2).max(axis=1) > _LOCATED_AGREE_PX))
        if not len(far):
            return
        c, d = refine_tag_corners(gray, predicted[far], ids[far], self._tracked_corners)
        take = np.isfinite(d) & (np.linalg.norm(c - predicted[far], axis=2).max(axis=1) <= _LOCATED_CONFIRM_PX)
        take[take] = verify_tags(gray, ids[far][take], c[take], self.config)[0]
        refined[far[take]], shift[far[take]] = c[take], d[take]

    def _view_angles(self, T_cam_cap: Transform) -> np.ndarray:
        """``view_angles_deg(self.model, T_cam_cap)``, remembered for the last pose object."""
        if self._angles_at is not T_cam_cap:
            self._angles_at, self._angles_deg = T_cam_cap, view_angles_deg(self.model, T_cam_cap)
        return self._angles_deg

    def _track_tags(
        self, gray: np.ndarray, camera: CameraModel, predicted: Transform, pose: PoseConfig
    ) -> tuple[TagDetection, ...] | None:
        """The model's tags verified where ``predicted`` puts them; None when too few verify."""
        cfg = self.config
        ids, corners = predict_tags(self.model, camera, predicted, cfg, self._view_angles(predicted))
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
            # Only its T_cam_cap is wanted: no uncertainty (the frame's final pose has it).
            first = estimate_cap_pose(found, self.model, camera, pose, start=predicted, with_uncertainty=False)
            if first.pose is not None:
                ids2, corners2 = predict_tags(self.model, camera, first.pose.T_cam_cap, cfg)
                before = dict(zip(ids[missing].tolist(), corners[missing]))
                retry = np.array([int(i) in before and np.abs(c - before[int(i)]).max() > _TRACK_RETRY_PX
                                  for i, c in zip(ids2, corners2)], dtype=bool)
                if retry.any():
                    found += self._verified(gray, ids2[retry], corners2[retry])[0]
        return tuple(found)

    def _locate_pose(self, pose: PoseConfig) -> PoseConfig:
        """``pose`` with the ``naive`` method: the locating pose of a search's completion."""
        if self._locate is None or self._locate[0] is not pose:
            self._locate = (pose, replace(pose, method="naive"))
        return self._locate[1]

    def _complete_search(
        self, gray: np.ndarray, camera: CameraModel, found: tuple[TagDetection, ...],
        predicted: Transform | None, pose: PoseConfig,
    ) -> tuple[tuple[TagDetection, ...], Transform | None, bool]:
        """A search's tags plus the model's other tags read where the searched ones put them.

        The search (decimated on large frames) loses the smallest and most oblique tags; the cap
        is rigid, so the pose of the tags it found predicts the rest, which are edge-refined and
        verified as tracked tags are (a tag refined far from that prediction is fitted again from
        it: ``_refit_astray``). Returns the tags, the pose they were looked for at
        (the search's pose, or ``predicted`` when too few tags were found to pose the cap) and
        whether the search's pose was found (the completion ran).
        """
        if not self._verify or len({d.tag_id for d in found}) < self.config.min_tags:
            return found, predicted, False
        # One SQPnP + LM is enough to place the others: a wrong prediction verifies no tag, and
        # the final pose only starts from it if every tag agrees with it. Only its T_cam_cap is
        # wanted: no uncertainty (the frame's final pose has it).
        first = estimate_cap_pose(found, self.model, camera, self._locate_pose(pose),
                                  with_uncertainty=False)
        if first.pose is None:
            return found, predicted, False
        ids, corners = predict_tags(self.model, camera, first.pose.T_cam_cap, self.config)
        have = {d.tag_id for d in found}
        missing = np.array([int(i) not in have for i in ids], dtype=bool)
        if missing.any():
            self.search_completions += 1
            found = found + tuple(self._verified(gray, ids[missing], corners[missing], located=True)[0])
        return found, first.pose.T_cam_cap, True

    # -- one frame ----------------------------------------------------------------------------
    def track(self, gray: np.ndarray, camera: CameraModel, stamp_ns: int, pose: PoseConfig,
              solve: PoseSolver) -> TrackedFrame:
        """One frame: its tags, its pose (``solve``) and how the tags were found; the pose is
        remembered for the next frame (None: lost, the next frame is searched).

        Args:
            gray: (H, W) uint8 image.
            camera: its intrinsics (a frame of another camera is searched).
            stamp_ns: its stamp (0: unknown; frames further apart than a gap are searched).
            pose: the current pose settings (second looks, search completion, the pose's tags).
            solve: the pipeline's solver of the frame's final pose.
        """
        prior = self.motion_prior(camera, stamp_ns, pose)
        detections, predicted, search = self._find(gray, camera, stamp_ns, pose)
        result = solve(self._pose_tags(detections, predicted, pose), predicted, prior)
        self._remember(result.pose, stamp_ns, detections, camera)
        return TrackedFrame(detections, result, search)

    def motion_prior(self, camera: CameraModel, stamp_ns: int,
                     pose: PoseConfig) -> MotionPrior | None:
        """The velocity prior of a frame at ``stamp_ns``: the last posed frames' poses (at most
        three, consecutive and stamped), or None when no frame before can inform it."""
        tr = self._usable_track(camera, stamp_ns)
        if tr is None or not stamp_ns or not tr.history:
            return None
        past = tuple(PastPose((stamp_ns - s) * 1e-9, T, cov) for s, T, cov in tr.history
                     if s and stamp_ns > s)
        return MotionPrior(past, pose.motion) if past else None

    def _find(
        self, gray: np.ndarray, camera: CameraModel, stamp_ns: int, pose: PoseConfig
    ) -> tuple[tuple[TagDetection, ...], Transform | None, Search]:
        """Tags of a frame, the pose they were predicted at (None: none) and how they were found.

        First the tags are looked for where the extrapolated pose puts them (no search); if too
        few verify, the region around the last pose is searched; if that finds fewer tags than
        the last frame had, the whole image.
        """
        predicted = self._predict_pose(camera, stamp_ns)
        if predicted is not None and self._verify:
            found = self._track_tags(gray, camera, predicted, pose)
            if found is not None:
                self.tracked_frames += 1
                return found, predicted, Search.TRACKED
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
                found, seen_at, _ = self._complete_search(gray, camera, found, predicted, pose)
                return found, seen_at, Search.REGION
        self.full_searches += 1
        # A decimated search skips its second reading of rejected quads once it found enough of
        # the model's tags for the completion, which reads the rest at their pose (the same
        # tags, cheaper); should that pose fail, the frame is searched again with the second
        # reading.
        enough = self.config.min_tags if self._verify else 0
        found = tuple(d for d in self.detector.detect(gray, wanted_ids=self.model, enough_tags=enough)
                      if d.tag_id in self.model)
        found, seen_at, located = self._complete_search(gray, camera, found, predicted, pose)
        if enough and not located and len({d.tag_id for d in found}) >= enough:
            found = tuple(d for d in self.detector.detect(gray) if d.tag_id in self.model)
            found, seen_at, _ = self._complete_search(gray, camera, found, predicted, pose)
        return found, seen_at, Search.IMAGE

    def _pose_tags(
        self, detections: tuple[TagDetection, ...], predicted: Transform | None, pose: PoseConfig
    ) -> tuple[TagDetection, ...]:
        """The detections the pose should use: without the tags seen too obliquely at the
        predicted pose (``TrackConfig.pose_max_view_angle_deg``) while enough others remain."""
        limit = self.config.pose_max_view_angle_deg
        if predicted is None or limit >= 90.0 or not self._verify:
            return detections
        angles = dict(zip(self.model.ids, self._view_angles(predicted)))
        kept = tuple(d for d in detections if angles[d.tag_id] <= limit)
        if len({d.tag_id for d in kept}) < max(self.config.min_tags, pose.min_tags):
            return detections
        return kept

    def _remember(self, cap_pose: CapPose | None, stamp_ns: int,
                  detections: tuple[TagDetection, ...], camera: CameraModel) -> None:
        """Remember a frame's pose (None: lost, the next frame is searched over the whole image)."""
        if cap_pose is None:
            self._track = None
            return
        T_cam_cap = cap_pose.T_cam_cap
        # The velocity needs the previous posed frame to be the one just before, at another stamp.
        prev = self._usable_track(camera, stamp_ns)
        timed = prev is not None and bool(stamp_ns and prev.stamp_ns)
        if timed and stamp_ns == prev.stamp_ns:  # type: ignore[union-attr]
            prev = None
        history = ((stamp_ns, T_cam_cap, cap_pose.covariance),)
        if prev is not None and timed:
            history += prev.history[:2]
        self._track = _TrackState(
            T_cam_cap, None if prev is None else prev.T_cam_cap, stamp_ns,
            stamp_ns - prev.stamp_ns if prev is not None and timed else 0,
            len({d.tag_id for d in detections}), camera, history)
