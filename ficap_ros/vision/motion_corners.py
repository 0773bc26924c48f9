"""Motion-aware corners: the corners of tags smeared by the cap's motion over the exposure.

A tag that moves several pixels while the shutter is open is recorded as the mean of its pattern
over the exposure, in linear light, and only then bent by the camera's tone curve. An edge fit
that models a still edge reads such a tag as smaller along its motion (the tone curve moves each
smeared edge toward its black side by a share of the smear) and reads its corners with the noise
of a long, shallow edge. The photometric fit with the motion in its model
(``photometric.fit_tags`` with ``motion_px``) fits the mid-exposure homography to the smeared
pixels instead.

The motion is the cap's velocity at the frame's own pose, projected per corner, each corner's
exposure centred on its row's time (``CameraTiming.row_time_s``): the pipeline solves the pose
from the tags' corners first, takes the velocity the frames before give at that pose (the velocity
prior's finite difference through it, or a rolling shutter's solved velocity), refits the moving
tags and solves again. A velocity predicted before the pose is known lags a glance's acceleration
by a fifth of the motion and more; one through the frame's own pose does not. The refit runs only
where the camera's exposure is stated, a past pose gives the velocity, and a tag's corner motion
reaches ``DetectorConfig.motion_corners_min_px``; everything else keeps its corners, so a frame
without a stated exposure is untouched.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.corners import fit_tags_photometric
from ficap_ros.vision.detector import DetectorConfig, TagDetection
from ficap_ros.vision.motion import MotionPrior
from ficap_ros.vision.reprojection import moving_points_m

__all__ = ["applies", "corner_motion_px", "motion_aware_corners"]

#: Farthest a moving tag's refit may move a corner, in cells (``photometric.fit_tags``'
#: ``max_move_cells``): the cell-edge corners of a smeared tag are off along its motion by up to
#: half a cell, further than a still tag's.
_MAX_MOVE_CELLS = 0.5


def corner_motion_px(corners_m: np.ndarray, rows_px: np.ndarray, T_cam_cap: Transform,
                     velocity: np.ndarray, camera: CameraModel, timing: CameraTiming) -> np.ndarray:
    """(N, 4, 2) each corner's image motion over the exposure, px (end minus start; distorted
    image).

    Args:
        corners_m: (N, 4, 3) the tags' corners, cap frame, m.
        rows_px: (N, 4) the image rows the corners are seen in (their row times).
        T_cam_cap: the cap's pose at the stamp.
        velocity: (6,) the cap's twist, ROS order, camera axes (m/s, rad/s).
        camera: the camera (its distortion applies).
        timing: the exposure and readout (each corner's exposure centred on its row's time).
    """
    n = len(corners_m)
    times = timing.row_time_s(rows_px, camera.height_px)
    half = 0.5e-3 * timing.exposure_ms
    ends = [camera.project(moving_points_m(T_cam_cap.rotation_matrix, T_cam_cap.translation_m,
                                           velocity, corners_m, times + s)).reshape(n, 4, 2)
            for s in (-half, half)]
    return ends[1] - ends[0]


def applies(config: DetectorConfig, timing: CameraTiming, prior: MotionPrior | None) -> bool:
    """Whether a frame's moving tags are refitted: motion corners on, ``edge`` refine, the
    exposure stated, and a velocity prior from past poses."""
    return (config.motion_corners and config.corner_refine == "edge" and timing.exposure_ms > 0.0
            and prior is not None and prior.from_past)


def motion_aware_corners(
    gray: np.ndarray, tags: tuple[TagDetection, ...], model: CapModel, camera: CameraModel,
    timing: CameraTiming, T_cam_cap: Transform, velocity: np.ndarray, config: DetectorConfig,
) -> tuple[TagDetection, ...]:
    """``tags`` with the corners of those that move over the exposure refitted (module docstring).

    Args:
        gray: (H, W) uint8 image.
        tags: the frame's detections (model tags).
        model, camera, timing: the cap model, the camera and its timing (its exposure stated).
        T_cam_cap: the cap's pose at the stamp; velocity: its twist (6,), ROS order, camera axes.
        config: the detector's settings (``motion_corners_min_px``).

    Returns:
        The detections in order; a refitted tag's with its new corners (one the fit refuses keeps
        its own), the same objects where nothing moved.
    """
    if not tags:
        return tags
    corners_px = np.stack([t.corners_px for t in tags])
    corners_m = 1e-3 * np.stack([model.corners_of(t.tag_id) for t in tags])
    motion = corner_motion_px(corners_m, corners_px[:, :, 1], T_cam_cap, velocity, camera, timing)
    moving = np.flatnonzero(np.linalg.norm(motion, axis=2).max(axis=1) >= config.motion_corners_min_px)
    if len(moving) == 0:
        return tags
    ids = np.array([tags[i].tag_id for i in moving])
    refit, fitted = fit_tags_photometric(gray, corners_px[moving], ids, motion_px=motion[moving],
                                         max_move_cells=_MAX_MOVE_CELLS)
    out = list(tags)
    for k, i in enumerate(moving):
        if fitted[k]:
            out[i] = replace(tags[i], corners_px=refit[k])
    return tuple(out)
