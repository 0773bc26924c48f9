"""Motion blur's shared corner errors: each tag's image motion over the exposure and the modes it
moves the tags' corners in alike.

A tag smeared along its motion over the exposure and then bent by the tone curve has its edges
across the motion pulled toward the black, in every tag alike, and edges fitted on a smeared tag
settle off their mid-exposure place along the motion: errors the pose absorbs without residuals.
``blur_modes`` states them per px of each tag's motion (``blur_px``), for the covariance's terms
``blur`` and ``blur_shift`` (``uncertainty_terms``' ``shared_modes``, scaled by
``UncertaintyConfig.motion_blur_gain`` and ``motion_blur_shift_gain``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.reprojection import TagObservations, moving_points_m, project_px

if TYPE_CHECKING:
    from ficap_ros.vision.motion import MotionPrior

__all__ = ["blur_px", "blur_modes", "prior_blur_modes"]


def blur_px(obs: TagObservations, T: Transform, velocity: np.ndarray, exposure_s: float) -> np.ndarray:
    """(tags, 2) each tag's image motion over the exposure, px: where its corners' centre is at
    the end of the exposure minus where it is at its start (a cap at pose ``T`` at the stamp
    moving at ``velocity``; each corner's exposure centred on its row's time, ``obs.time_s``)."""
    n = len(obs)
    times = np.zeros((n, 4)) if obs.time_s is None else obs.time_s
    ends = []
    for half in (-0.5 * exposure_s, 0.5 * exposure_s):
        p = moving_points_m(T.rotation_matrix, T.translation_m, velocity, obs.model_m, times + half)
        ends.append(project_px(obs.K, Transform.identity(), p).reshape(n, 4, 2).mean(axis=1))
    return ends[1] - ends[0]


def blur_modes(corners_px: np.ndarray, blur: np.ndarray) -> dict[str, np.ndarray]:
    """The corner errors motion blur shares among the tags (``uncertainty_terms``'
    ``shared_modes``), per px of each tag's motion ``blur`` (tags, 2: ``blur_px``), for the
    tags' corners ``corners_px`` (tags, 4, 2): ``blur``, each tag's corners moved toward its
    centre along its motion by its length times the cosine between the motion and the
    centre-to-corner direction (an edge across the motion moves by the full length, one along it
    not at all); ``blur_shift``, each tag's corners moved along its motion by its length."""
    lever = corners_px - corners_px.mean(axis=1, keepdims=True)
    unit = lever / np.maximum(np.linalg.norm(lever, axis=2, keepdims=True), 1e-9)
    length = np.linalg.norm(blur, axis=1)
    direction = blur / np.maximum(length, 1e-12)[:, None]
    along = np.einsum("tkj,tj->tk", unit, direction)  # cosines (tags, 4)
    shrink = -(along * length[:, None])[:, :, None] * direction[:, None, :]
    shift = np.repeat(blur[:, None, :], 4, axis=1)
    return {"blur": shrink.reshape(-1), "blur_shift": shift.reshape(-1)}


def prior_blur_modes(prior: MotionPrior | None, obs: TagObservations, T: Transform,
                     timing: CameraTiming | None) -> dict[str, np.ndarray] | None:
    """A global-shutter frame's ``blur_modes`` at the prior's velocity at pose ``T``; None when
    the exposure or the velocity (a past pose) is not known."""
    if prior is None or not prior.from_past or timing is None or timing.exposure_ms <= 0.0:
        return None
    return blur_modes(obs.image_px, blur_px(obs, T, prior.at(T).mean, timing.exposure_ms * 1e-3))
