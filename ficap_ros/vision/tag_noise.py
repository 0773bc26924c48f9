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
    stacked_tag_cells,
    tag_homographies,
)
from ficap_ros.vision.fit_kernels import tag_noise_ratios
from ficap_ros.vision.kernels import frozen

__all__ = ["noise_ratios"]

#: MAD -> sd of a normal distribution.
_MAD_SD = 1.4826
#: Least contrast a ratio is taken over, grey levels (a tag without contrast: a large ratio).
_MIN_CONTRAST = 1.0
#: (64, 3) the tag's own cells' centres (row-major), homogeneous tag cell units.
_CENTRES_H = frozen(np.ascontiguousarray(CELL_CENTRES_H[TAG_AREA]))


def noise_ratios(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Each tag's noise ratio (module docstring): noise sd / (contrast sqrt(px per cell)), from the
    grey at the nearest pixel to each cell's centre (the image's edge pixel for a centre outside
    it). Compiled: ``fit_kernels.tag_noise_ratios``.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) the tags' corners, px (usable quadrilaterals: ``usable_quads``).
        ids: (N,) their ids.

    Returns:
        (N,) ratios, >= 0; infinite for a tag without a neighbouring pair of same-coloured cells
        (no tag of tag36h11 lacks one).
    """
    c = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0:
        return np.zeros(0)
    black = stacked_tag_cells(tuple(int(i) for i in np.asarray(ids).reshape(-1))).reshape(len(c), -1)
    return tag_noise_ratios(frozen(gray), c, tag_homographies(c), black, _CENTRES_H, _MAD_SD, _MIN_CONTRAST)
