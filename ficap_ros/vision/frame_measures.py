"""What a frame shows of the corner errors its tags share, which the pose absorbs without
residuals (``ficap_ros.vision.uncertainty`` sizes its covariance terms by them): how unevenly the
light moves the tags' edges across the cap (``light_gradient_px``), how strongly it moves them
(``edge_shift_mean_px``) and the frame's corner noise over its cell width (``shared_bias_ratio``).
Each from the tags' measured edge shifts (``TagDetection.edge_shift_px``, px), image positions and
corner noise; nothing else.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.vision.edges import NEXT
from ficap_ros.vision.reprojection import median

__all__ = ["light_gradient_px", "edge_shift_mean_px", "shared_bias_ratio"]


def light_gradient_px(edge_shift_px: np.ndarray, centres_px: np.ndarray) -> float:
    """How unevenly the light moves the tags' edges across the cap, px: the spread (standard
    deviation over the tags) of a plane fitted to the tags' measured edge shifts
    (``TagDetection.edge_shift_px``) over their image positions. The smooth part only: a tag's own
    edge shift scatters with its noise and view angle, a spotlight's gradient is shared by its
    neighbours. 0 with fewer than six fitted tags (too few to tell a gradient from scatter)."""
    es = np.asarray(edge_shift_px, dtype=float)
    ok = np.isfinite(es)
    if ok.sum() < 6:
        return 0.0
    c = np.asarray(centres_px, dtype=float)[ok]
    c = (c - c.mean(axis=0)) / max(float(np.ptp(c, axis=0).max()), 1e-9)
    X = np.column_stack([np.ones(len(c)), c])
    # The normal equations (3 x 3; the columns are centred and scaled to about 1, so they are
    # as well conditioned as X), not lstsq's SVD; a degenerate layout (tags on a line) as lstsq.
    try:
        coef = np.linalg.solve(X.T @ X, X.T @ es[ok])
    except np.linalg.LinAlgError:
        coef, *_ = np.linalg.lstsq(X, es[ok], rcond=None)
    return float(np.std(X @ coef))


def edge_shift_mean_px(edge_shift_px: np.ndarray | None) -> float:
    """The fitted tags' mean edge shift (``TagDetection.edge_shift_px``), px: how strongly the
    light and the tone curve move the edges, the size of the shared tilt they leave
    (``UncertaintyConfig.edge_shift_tilt_gain``). 0 without edge shifts or without a fitted tag."""
    if edge_shift_px is None:
        return 0.0
    es = np.asarray(edge_shift_px, dtype=float)
    es = es[np.isfinite(es)]
    return float(es.mean()) if es.size else 0.0


def shared_bias_ratio(corners_px: np.ndarray, tag_sigma_px: np.ndarray) -> float:
    """The frame's corner noise over its cell width (dimensionless): the median of the tags'
    corner noise (``tag_noise_px``, px) over the median tag's cell width (its mean side over the
    ``TAG_CELLS`` cells across, px). What sets the edge corners' shared bias
    (``UncertaintyConfig.shared_bias_gain``): the corner stage measures the tone curve's edge
    shift across one cell, and its error grows with the blur and noise of the edges (the corner
    noise) against the cell they are measured over.

    Args:
        corners_px: (tags, 4, 2) the tags' corners, px.
        tag_sigma_px: (tags,) each tag's corner noise, px.
    """
    c = np.asarray(corners_px, dtype=float)
    side_px = np.linalg.norm(c - c[:, NEXT], axis=2).mean(axis=1)
    cell_px = max(median(side_px) / TAG_CELLS, 1e-6)
    return median(tag_sigma_px) / cell_px
