"""Reading tags' cells at given corners, compiled: ``geometry.tag36h11.read_tag_cells``'s numbers
in one kernel call, for the corner stage's checks (``corners``: a fitted tag whose cells read
wrong is fitted again) and the tracker's verification (``tracking.verify_tags``).

Each of the 10 x 10 cell centres (the tag's 8 x 8 cells and the white quiet-zone ring around
them, ``tag36h11.CELL_CENTRES``) goes through the tag's homography in float64, is rounded to
float32 and sampled as ``cv2.remap`` samples it with ``INTER_LINEAR`` and ``BORDER_CONSTANT`` 0
(positions rounded to 1/32 px, fixed-point weights, values rounded to a grey level). The tag's
white level is the mean of its quiet-zone samples, its black level the mean of its border cells',
and a cell reads black below their midpoint. The samples are whole grey levels, so the means are
exact in any order of summation and every number equals ``read_tag_cells``'s.
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.geometry import tag36h11
from ficap_ros.geometry.tag36h11 import BORDER, CELL_CENTRES, QUIET_ZONE, TAG_AREA
from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.kernels import frozen

__all__ = ["read_cells", "cell_errors", "tag_cell_reads"]

#: ``cv2.remap``'s sub-pixel positions per px (``INTER_TAB_SIZE``) and its weights' scale bits.
_TAB_SIZE = 32
_COEF_BITS = 15
#: Each tag's 100 samples: which are quiet zone (white reference), tag cells, and border cells
#: among the tag cells (row-major, as ``tag36h11``'s masks).
_CENTRES = frozen(np.ascontiguousarray(CELL_CENTRES, dtype=np.float64))
_QUIET = frozen(np.ascontiguousarray(QUIET_ZONE))
_TAG = frozen(np.ascontiguousarray(TAG_AREA))
_BORDER = frozen(np.ascontiguousarray(BORDER))


@njit(inline="always", error_model="numpy")
def _remap_constant(img: np.ndarray, x: np.float32, y: np.float32) -> int:
    """One ``cv2.remap`` INTER_LINEAR, BORDER_CONSTANT (0) sample of the uint8 image at (x, y):
    the position rounded to 1/32 px (half to even), the four pixels' fixed-point weights (products
    of (32 - f, f) along each axis times 32, summing to 2^15), pixels beyond the image 0, and a
    sample whose four pixels all lie beyond it 0."""
    h, w = img.shape
    sx = int(np.rint(x * np.float32(_TAB_SIZE)))
    sy = int(np.rint(y * np.float32(_TAB_SIZE)))
    fx, fy = sx & (_TAB_SIZE - 1), sy & (_TAB_SIZE - 1)
    x0, y0 = sx >> 5, sy >> 5
    if x0 >= w or x0 + 1 < 0 or y0 >= h or y0 + 1 < 0:
        return 0
    p00 = int(img[y0, x0]) if 0 <= x0 < w and 0 <= y0 < h else 0
    p01 = int(img[y0, x0 + 1]) if 0 <= x0 + 1 < w and 0 <= y0 < h else 0
    p10 = int(img[y0 + 1, x0]) if 0 <= x0 < w and 0 <= y0 + 1 < h else 0
    p11 = int(img[y0 + 1, x0 + 1]) if 0 <= x0 + 1 < w and 0 <= y0 + 1 < h else 0
    gx, gy = _TAB_SIZE - fx, _TAB_SIZE - fy
    total = ((p00 * gx + p01 * fx) * gy + (p10 * gx + p11 * fx) * fy) * _TAB_SIZE
    return (total + (1 << (_COEF_BITS - 1))) >> _COEF_BITS


@njit(error_model="numpy")
def tag_cell_reads(img: np.ndarray, hom: np.ndarray, centres: np.ndarray, quiet: np.ndarray, tag_area: np.ndarray,
                   border: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every tag's cells read through its homography (module docstring).

    Args:
        img: (H, W) uint8 image (read-only view: ``kernels.frozen``).
        hom: (K, 3, 3) tag cell units -> image px.
        centres: (G, 2) the cell centres in tag cell units; quiet, tag_area: (G,) bool which of
            them are quiet zone and tag cells; border: (C,) bool which tag cells are border.

    Returns:
        (read_black (K, C) bool, white (K,), black (K,) grey levels, finite (K,) bool: every
        centre mapped to a finite point; a centre that did not is sampled at (-1, -1)).
    """
    k_n, g_n = hom.shape[0], centres.shape[0]
    c_n = 0
    for g in range(g_n):
        c_n += tag_area[g]
    read_black = np.empty((k_n, c_n), np.bool_)
    white = np.empty(k_n)
    black = np.empty(k_n)
    finite = np.ones(k_n, np.bool_)
    vals = np.empty(g_n)
    for t in range(k_n):
        hm = hom[t]
        for g in range(g_n):
            u, v = centres[g, 0], centres[g, 1]
            pw = hm[2, 0] * u + hm[2, 1] * v + hm[2, 2]
            x = np.float32((hm[0, 0] * u + hm[0, 1] * v + hm[0, 2]) / pw)
            y = np.float32((hm[1, 0] * u + hm[1, 1] * v + hm[1, 2]) / pw)
            if not (math.isfinite(x) and math.isfinite(y)):
                finite[t] = False
                x = x if math.isfinite(x) else np.float32(-1.0)
                y = y if math.isfinite(y) else np.float32(-1.0)
            vals[g] = _remap_constant(img, x, y)
        w_sum, w_n, b_sum, b_n, c = 0.0, 0, 0.0, 0, 0
        for g in range(g_n):
            if quiet[g]:
                w_sum += vals[g]
                w_n += 1
            if tag_area[g]:
                if border[c]:
                    b_sum += vals[g]
                    b_n += 1
                c += 1
        white[t], black[t] = w_sum / w_n, b_sum / b_n
        mid = 0.5 * (white[t] + black[t])
        c = 0
        for g in range(g_n):
            if tag_area[g]:
                read_black[t, c] = vals[g] < mid
                c += 1
    return read_black, white, black, finite


def read_cells(gray: np.ndarray, hom: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``tag36h11.read_tag_cells(gray, hom)`` compiled, the same numbers: (read_black (K, 64) bool
    row-major, white (K,), black (K,) grey levels, finite (K,)) of uint8 ``gray`` (H, W) and the
    tags' homographies ``hom`` (K, 3, 3) from tag cell units to px."""
    h = np.ascontiguousarray(hom, dtype=np.float64).reshape(-1, 3, 3)
    return tag_cell_reads(frozen(gray), h, _CENTRES, _QUIET, _TAG, _BORDER)


def cell_errors(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``tag36h11.cell_errors`` compiled, the same numbers: (K,) how many of each tag's 64 cells,
    read at ``corners_px`` (K, 4, 2), differ from its id's code (64 where the corners give no
    usable homography)."""
    return tag36h11.cell_errors(gray, corners_px, ids, read=read_cells)


@register_warm_up
def _warm_up() -> None:
    """``tag_cell_reads`` once on a small image (the pipeline's argument types)."""
    hom = np.array([[[2.0, 0.0, 4.0], [0.0, 2.0, 4.0], [0.0, 0.0, 1.0]]])
    read_cells(np.zeros((24, 24), np.uint8), hom)
