"""The observations the as-built model is built from: which frames are usable (enough distinct
model tags, a pose from the nominal model), the flat observation arrays of the adjustment, and
whether the frames cover every tag.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.model_build.adjustment import Problem
from ficap_ros.tools.model_build.config import BuildConfig, CoverageError
from ficap_ros.vision.detector import TagDetection

__all__ = ["UsedFrame", "usable_frames", "problem_from", "ids_per_frame", "coverage_problems"]

#: A frame of the adjustment: its position in the input, its camera pose from the nominal model
#: (translation in m) and its pose-inlier detections.
UsedFrame = tuple[int, Transform, list[TagDetection]]


def initial_pose(dets: Sequence[TagDetection], nominal: CapModel, camera: CameraModel,
                  min_tags: int) -> tuple[Transform, tuple[int, ...]] | None:
    """Camera pose from the nominal model and the tags that agree with it (pose inliers)."""
    from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose

    result = estimate_cap_pose(dets, nominal, camera, PoseConfig(method="joint", min_tags=min_tags))
    if result.pose is None:
        return None
    return result.pose.T_cam_cap, result.pose.used_ids


def _candidates(frames: Sequence[Sequence[TagDetection]], nominal: CapModel,
                config: BuildConfig) -> list[tuple[int, list[TagDetection]]]:
    """(position, detections) of the frames with enough distinct model tags (an id seen twice in
    a frame is dropped from it), at most ``max_frames`` of them evenly spaced over the input."""
    candidates = []
    for index, dets in enumerate(frames):
        counts: dict[int, int] = {}
        for d in dets:
            if d.tag_id in nominal:
                counts[d.tag_id] = counts.get(d.tag_id, 0) + 1
        unique = [d for d in dets if counts.get(d.tag_id) == 1]
        if len(unique) >= config.min_tags_per_frame:
            candidates.append((index, unique))
    if len(candidates) > config.max_frames:
        pick = np.unique(np.linspace(0, len(candidates) - 1, config.max_frames).round().astype(int))
        candidates = [candidates[i] for i in pick]
    return candidates


def usable_frames(frames: Sequence[Sequence[TagDetection]], cameras: Sequence[CameraModel],
                  nominal: CapModel, config: BuildConfig,
                  say: Callable[[str], None]) -> list[UsedFrame]:
    """The frames the adjustment uses: enough distinct model tags, and an initial pose from the
    nominal model whose inliers are still enough tags.

    Raises:
        CoverageError: fewer than two such frames.
    """
    candidates = _candidates(frames, nominal, config)
    say(f"{len(candidates)} of {len(frames)} frames see >= {config.min_tags_per_frame} tags")
    used: list[UsedFrame] = []
    for index, dets in candidates:
        start = initial_pose(dets, nominal, cameras[index], config.min_tags_per_frame)
        if start is None:
            continue
        T, inlier_ids = start
        keep = [d for d in dets if d.tag_id in set(inlier_ids)]
        if len(keep) >= config.min_tags_per_frame:
            used.append((index, T, keep))
    if len(used) < 2:
        raise CoverageError(
            f"only {len(used)} frame(s) with a pose from >= {config.min_tags_per_frame} tags; "
            "record the cap from several angles so many tags are seen at once"
        )
    return used


def problem_from(used: Sequence[UsedFrame], cameras: Sequence[CameraModel],
                 nominal: CapModel) -> Problem:
    """The flat observation arrays: undistorted corners and per-observation intrinsics."""
    obs_frame, obs_tag, obs_px, intr = [], [], [], []
    for f, (index, _, dets) in enumerate(used):
        cam = cameras[index]
        k = cam.K
        for d in dets:
            obs_frame.append(f)
            obs_tag.append(nominal.index_of(d.tag_id))
            obs_px.append(cam.undistort_px(d.corners_px))
            intr.append((k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
    return Problem(np.array(obs_frame), np.array(obs_tag), np.array(obs_px), np.array(intr),
                   len(used), len(nominal))


def ids_per_frame(p: Problem, nominal: CapModel) -> list[list[int]]:
    """The tag ids each frame of the problem observes."""
    out: list[list[int]] = [[] for _ in range(p.n_frames)]
    for f, t in zip(p.obs_frame, p.obs_tag):
        out[int(f)].append(nominal.ids[int(t)])
    return out


def coverage_problems(nominal: CapModel, ids_per_frame: list[list[int]], config: BuildConfig) -> list[str]:
    """Every tag seen in enough frames (each with enough tags), all tags linked through frames."""
    counts = {tag_id: 0 for tag_id in nominal.ids}
    parent = {tag_id: tag_id for tag_id in nominal.ids}

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for ids in ids_per_frame:
        if len(ids) < config.min_tags_per_frame:
            continue
        for tag_id in ids:
            counts[tag_id] += 1
            parent[root(tag_id)] = root(ids[0])
    out = []
    short = [f"{t} ({n})" for t, n in counts.items() if n < config.min_frames_per_tag]
    if short:
        out.append(
            f"tag(s) {', '.join(short)} seen in too few frames together with "
            f">= {config.min_tags_per_frame - 1} other tags (need {config.min_frames_per_tag}); "
            "record more views showing them"
        )
    groups = {root(t) for t in nominal.ids}
    if len(groups) > 1:
        out.append(
            f"the tags fall into {len(groups)} groups never seen together in one frame; "
            "record views that show tags of neighbouring groups at once"
        )
    return out
