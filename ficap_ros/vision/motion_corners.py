"""Motion-aware corners: the corners of tags smeared by the cap's motion over the exposure.

A tag that moves several pixels while the shutter is open is recorded as the mean of its pattern
over the exposure, in linear light, and only then bent by the camera's tone curve. An edge fit
that models a still edge reads such a tag as smaller along its motion (the tone curve moves each
smeared edge toward its black side by a share of the smear) and reads its corners with the noise
of a long, shallow edge. The photometric fit with the motion in its model
(``photometric.fit_tags`` with ``motion_px``) fits the mid-exposure homography to the smeared
pixels instead.

The motion is each corner's path through the frame's own pose and its neighbouring poses
(``corner_paths_px``: their projections interpolated in time; ``MotionPrior.neighbours``: the
poses before it, and offline the next frame's too), over the exposure centred on the corner's row
time (``CameraTiming.row_time_s``): the pipeline solves the pose from the tags' corners first,
refits the moving tags along the paths through it and solves again. A motion predicted before the
pose is known lags a glance's acceleration by a fifth of the motion and more; a path through the
frame's own pose does not, and its bend (the glance speeding up or slowing down within the
exposure) moves each smear's centre of light off the mid-exposure corner by up to a fifth of a
pixel at a glance's peak acceleration. Through the poses before alone the bend is extrapolated and
lags the glance's changing acceleration; with the next frame's pose it is interpolated
(``vision.two_sided``). The refit runs only where the
camera's exposure is stated, a past pose gives the paths, and a tag's corner motion reaches
``DetectorConfig.motion_corners_min_px``; everything else keeps its corners, so a frame without a
stated exposure is untouched. Its cost is the moving fit's, per refitted tag (docs/benchmarks.md).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.corners import fit_tags_photometric
from ficap_ros.vision.detector import DetectorConfig, TagDetection
from ficap_ros.vision.motion import MotionPrior, PastPose

__all__ = ["applies", "corner_paths_px", "motion_aware_corners"]

#: Farthest a moving tag's refit may move a corner, in cells (``photometric.fit_tags``'
#: ``max_move_cells``): the cell-edge corners of a smeared tag are off along its motion by up to
#: half a cell, further than a still tag's.
_MAX_MOVE_CELLS = 0.5
#: The most Gauss-Newton steps a moving tag's fit takes, and the corner move, px, below which it
#: stops (``photometric.fit_tags``' ``iterations`` and ``converged_px``): the cell-edge corners
#: of a smeared tag start up to a pixel off, beyond one linearised step's reach. A step of a
#: fiftieth of a pixel leaves the corners within a few hundredths of where further steps settle,
#: well within their noise.
MAX_STEPS = 12
CONVERGED_PX = 0.02
#: The moving fit's Levenberg damping (``photometric.fit_tags``' ``damping``): on a smeared tag the
#: tone exponent, the levels and the blur scale trade against each other along a weakly determined
#: direction that the still fit's damping (``photometric.DAMPING``) walks a small share a step, so
#: its corners creep for the whole step budget; a third of it reaches them in a few steps.
DAMPING = 3e-4
#: Most a corner moves between the instants a moving tag's light is averaged over, in blur sds
#: (``photometric.fit_tags``' ``instant_spacing_sds``): the fit's cost grows with the instants, and
#: Gaussians three sds apart still sum close to their box-blurred one; the rest of the difference
#: (a short smear averaged over two instants is narrower than its box) the fitted blur scale takes
#: up, leaving the corners a bias far under their noise.
INSTANT_SPACING_SDS = 3.0


def corner_paths_px(corners_m: np.ndarray, rows_px: np.ndarray, T_cam_cap: Transform,
                    past: tuple[PastPose, ...], camera: CameraModel,
                    timing: CameraTiming) -> tuple[np.ndarray, np.ndarray]:
    """Each corner's path over the exposure, from the frame's pose and its neighbouring poses.

    The corners' image positions at the poses (this frame's at its stamp, the others at theirs)
    are interpolated in time, corner by corner, by the polynomial through them (a line through
    two poses, a cubic through four): at each corner's row time ``t`` (``CameraTiming.row_time_s``)
    and at ``t`` -+ half the exposure. A glance speeds up and slows down within an exposure:
    the path's bend moves the smear's centre of light off the mid-exposure corner.

    Args:
        corners_m: (N, 4, 3) the tags' corners, cap frame, m.
        rows_px: (N, 4) the image rows the corners are seen in.
        T_cam_cap: the cap's pose at the stamp.
        past: the neighbouring poses (``MotionPrior.neighbours``: the poses before, newest first,
            then offline the next frame's, ``age_s`` < 0; at least one).
        camera: the camera (its distortion applies).
        timing: the exposure and readout.

    Returns:
        (motion (N, 4, 2): each corner's motion over the exposure, end minus start, px; bend
        (N, 4, 2): how far the mean of the path's ends lies from its middle, px, as
        ``photometric.motion_warps`` takes them).
    """
    n = len(corners_m)
    pts = corners_m.reshape(-1, 3)
    times = np.array([0.0] + [-p.age_s for p in past])
    at = np.stack([camera.project(T.apply(pts)) for T in [T_cam_cap] + [p.T_cam_cap for p in past]])
    middle = timing.row_time_s(rows_px, camera.height_px).reshape(-1)
    half = 0.5e-3 * timing.exposure_ms
    start, mid, end = (np.einsum("jc,jcd->cd", _lagrange(times, middle + s), at) for s in (-half, 0.0, half))
    return (end - start).reshape(n, 4, 2), (0.5 * (start + end) - mid).reshape(n, 4, 2)


def _lagrange(nodes: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(len(nodes), len(x)) the Lagrange basis of ``nodes`` at the points ``x``: row j weighs the
    value at node j."""
    w = np.ones((len(nodes), len(x)))
    for j, tj in enumerate(nodes):
        for m, tm in enumerate(nodes):
            if m != j:
                w[j] *= (x - tm) / (tj - tm)
    return w


def applies(config: DetectorConfig, timing: CameraTiming, prior: MotionPrior | None) -> bool:
    """Whether a frame's moving tags are refitted: motion corners on, ``edge`` refine, the
    exposure stated, and a velocity prior from past poses."""
    return (config.motion_corners and config.corner_refine == "edge" and timing.exposure_ms > 0.0
            and prior is not None and prior.from_past)


def motion_aware_corners(
    gray: np.ndarray, tags: tuple[TagDetection, ...], model: CapModel, camera: CameraModel,
    timing: CameraTiming, T_cam_cap: Transform, past: tuple[PastPose, ...], config: DetectorConfig,
) -> tuple[TagDetection, ...]:
    """``tags`` with the corners of those that move over the exposure refitted (module docstring).

    Args:
        gray: (H, W) uint8 image.
        tags: the frame's detections (model tags).
        model, camera, timing: the cap model, the camera and its timing (its exposure stated).
        T_cam_cap: the cap's pose at the stamp; past: the neighbouring poses
            (``MotionPrior.neighbours``).
        config: the detector's settings (``motion_corners_min_px``).

    Returns:
        The detections in order; a refitted tag's with its new corners (one the fit refuses keeps
        its own), the same objects where nothing moved.
    """
    if not tags or not past:
        return tags
    corners_px = np.stack([t.corners_px for t in tags])
    corners_m = 1e-3 * np.stack([model.corners_of(t.tag_id) for t in tags])
    motion, bend = corner_paths_px(corners_m, corners_px[:, :, 1], T_cam_cap, past, camera, timing)
    moving = np.flatnonzero(np.linalg.norm(motion, axis=2).max(axis=1) >= config.motion_corners_min_px)
    if len(moving) == 0:
        return tags
    ids = np.array([tags[i].tag_id for i in moving])
    refit, fitted = fit_tags_photometric(gray, corners_px[moving], ids, motion_px=motion[moving],
                                         bend_px=bend[moving], max_move_cells=_MAX_MOVE_CELLS,
                                         iterations=MAX_STEPS, converged_px=CONVERGED_PX, damping=DAMPING,
                                         instant_spacing_sds=INSTANT_SPACING_SDS)
    out = list(tags)
    for k, i in enumerate(moving):
        if fitted[k]:
            out[i] = replace(tags[i], corners_px=refit[k])
    return tuple(out)
