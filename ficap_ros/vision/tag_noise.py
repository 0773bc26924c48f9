"""How far noise limits a tag's cell-edge corners: its noise ratio, from its cell centres.

The cell-edge fit (``corners.fit_tag_edges``) reads each cell boundary from a few samples across
it, so where the image is noisy against the tag's contrast its corners scatter; the tag-level
photometric fit (``ficap_ros.vision.photometric``) uses every pixel near the boundaries and scatters
less, at a higher CPU cost per tag. The quantity that says where the second pays is

    ratio = noise sd / (contrast * sqrt(px per cell))

(grey levels over grey levels, per sqrt(px)): a boundary's position error from n samples of
noise sd s across an edge of step c goes as s / (c sqrt(n)), and the samples along a tag's
boundaries grow with its cell size. Measured on the tag's own pixels, nothing else:

* contrast: the median grey of its white cells' centres minus that of its black cells' centres;
* noise sd: from the differences between the centres of neighbouring cells of the same colour
  (along u and v): a robust sd (MAD) over sqrt(2), so the light's slow change over a tag and a
  few glints do not count as noise;
* px per cell: the tag's shortest side over its 8 cells.

At cells of 2-3 px a centre pixel sees a few percent of its neighbouring cells through the blur,
which the noise estimate counts as noise: the ratio then errs toward the photometric fit, where
the cell-edge fit is weakest anyway.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.tag36h11 import (
    CELL_CENTRES_H,
    TAG_AREA,
    TAG_CELLS,
    stacked_tag_cells,
    tag_homographies,
)
from ficap_ros.vision.medians import row_median

__all__ = ["noise_ratios"]

#: MAD -> sd of a normal distribution.
_MAD_SD = 1.4826
#: Least contrast a ratio is taken over, grey levels (a tag without contrast: a large ratio).
_MIN_CONTRAST = 1.0


def _cell_centres_grey(gray: np.ndarray, hom: np.ndarray) -> np.ndarray:
    """(N, 8, 8) float grey at the nearest pixel to each cell's centre, [tag, v, u] (the
    ``tag36h11`` cells' layout), the image's edge pixel for a centre outside it."""
    q = hom @ CELL_CENTRES_H[TAG_AREA].T  # (N, 3, 64), the tag's own cells row-major
    x = np.clip(np.rint(q[:, 0] / q[:, 2]), 0, gray.shape[1] - 1).astype(np.intp)
    y = np.clip(np.rint(q[:, 1] / q[:, 2]), 0, gray.shape[0] - 1).astype(np.intp)
    return gray[y, x].astype(np.float64).reshape(-1, TAG_CELLS, TAG_CELLS)


def noise_ratios(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Each tag's noise ratio (module docstring): noise sd / (contrast sqrt(px per cell)).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) the tags' corners, px (usable quadrilaterals: ``usable_quads``).
        ids: (N,) their ids.

    Returns:
        (N,) ratios, >= 0; infinite for a tag without a neighbouring pair of same-coloured cells
        (no tag of tag36h11 lacks one).
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0:
        return np.zeros(0)
    grey = _cell_centres_grey(gray, tag_homographies(c)).reshape(len(c), -1)
    black = stacked_tag_cells(tuple(int(i) for i in np.asarray(ids).reshape(-1))).reshape(len(c), TAG_CELLS, TAG_CELLS)
    black = black.astype(bool)
    # A tag of one colour would have no contrast (row_median gives 0 for an empty row).
    flat = black.reshape(len(c), -1)
    contrast = row_median(grey, ~flat) - row_median(grey, flat)
    g = grey.reshape(black.shape)
    steps = np.concatenate([(g[:, :, 1:] - g[:, :, :-1]).reshape(len(c), -1),
                            (g[:, 1:, :] - g[:, :-1, :]).reshape(len(c), -1)], axis=1)
    same = np.concatenate([(black[:, :, 1:] == black[:, :, :-1]).reshape(len(c), -1),
                           (black[:, 1:, :] == black[:, :-1, :]).reshape(len(c), -1)], axis=1)
    mad = row_median(np.abs(steps - row_median(steps, same)[:, None]), same)
    noise_sd = _MAD_SD * mad / np.sqrt(2.0)
    cell_px = np.linalg.norm(c[:, [1, 2, 3, 0]] - c, axis=2).min(axis=1) / TAG_CELLS
    ratio = noise_sd / (np.maximum(contrast, _MIN_CONTRAST) * np.sqrt(np.maximum(cell_px, 1e-6)))
    return np.where(same.any(axis=1), ratio, np.inf)
