"""Which detected tags something covers in part, read from each tag's white quiet zone.

Every tag is framed by a one-cell white quiet zone. Where hair, the head or a headrest passes in
front of a tag, or the tag runs off the image, a stretch of that margin reads dark. Such a tag's
corners are often off as a whole, not only the hidden one: its line and cell-edge fits may take the
occluder's edge for the tag's and bend every side they share with it. The pose drops such tags at
a lower residual than the others (``PoseConfig.hidden_ratio``); they are still detected and
reported (docs/detection.md, "Partly hidden tags").
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ficap_ros.geometry.tag36h11 import (
    CELL_CENTRES,
    CELL_CENTRES_H,
    TAG_AREA,
    TAG_CELLS,
    tag_cells,
    tag_homographies,
    usable_quads,
)
from ficap_ros.vision.medians import row_lower_median

__all__ = ["partly_hidden"]


def _margin_cycle() -> np.ndarray:
    """Indices into ``CELL_CENTRES`` of the 36 quiet-zone samples in order around the tag (c0, c1, c2,
    c3), so that neighbours along the margin are neighbours in the array (cyclically)."""
    n = TAG_CELLS + 2
    top = [c for c in range(n)]
    right = [r * n + n - 1 for r in range(1, n)]
    bottom = [(n - 1) * n + c for c in range(n - 2, -1, -1)]
    left = [r * n for r in range(n - 2, 0, -1)]
    return np.array(top + right + bottom + left)


_MARGIN_CYCLE = _margin_cycle()
#: A stretch of ``_HIDDEN_MARGIN_RUN`` neighbouring quiet-zone samples (about half a side) whose
#: mean reads at least ``_HIDDEN_MARGIN_DARKNESS`` of the way from the tag's white to its black is
#: covered. 0.5 is where ``read_tag_cells`` calls a cell black; a run of five keeps single noisy or
#: shadowed samples from flagging a whole tag, while a head over one of its corners still darkens
#: that many.
_HIDDEN_MARGIN_DARKNESS = 0.5
_HIDDEN_MARGIN_RUN = 5


@lru_cache(maxsize=None)
def _black_samples(tag_id: int) -> np.ndarray:
    """(100,) which of ``CELL_CENTRES``'s samples of this tag are black (its cells; the margin is white)."""
    black = np.zeros(len(CELL_CENTRES), dtype=bool)
    black[TAG_AREA] = tag_cells(tag_id).ravel()
    black.setflags(write=False)
    return black


@lru_cache(maxsize=256)
def _black_samples_of(ids: tuple[int, ...]) -> np.ndarray:
    """(K, 100) ``_black_samples`` of each id, stacked; cached (a tracked cap shows the same ids
    frame after frame)."""
    out = np.stack([_black_samples(i) for i in ids])
    out.setflags(write=False)
    return out


def partly_hidden(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(K,) which tags something covers in part, read from their white quiet zone.

    Read like ``read_tag_cells``: each of the 36 margin samples (cell centres half a cell outside
    the black border; 0 off the image) against the tag's own levels (the lower median of its white
    cells and margin, of its black cells); a tag is partly hidden when ``_HIDDEN_MARGIN_RUN``
    neighbouring margin samples read on average at least ``_HIDDEN_MARGIN_DARKNESS`` of the way
    from white to black. Uneven light and highlights move the levels smoothly or brighten; a cast
    shadow or a dark background beyond the margin counts only where it darkens half a side's
    margin by half the contrast. Each tag is read on its own.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (K, 4, 2) corners, OpenCV order and pixel convention.
        ids: (K,) their ids (the code says which cells are white).

    Returns:
        (K,) bool; True also for corners that give no usable homography.
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    k = len(c)
    usable = usable_quads(c)
    ids = np.asarray(ids).reshape(-1)
    if not usable.all():  # one bad quadrilateral flags itself only
        out = np.ones(k, dtype=bool)
        if usable.any():
            out[usable] = partly_hidden(gray, c[usable], ids[usable])
        return out
    if k == 0:
        return np.zeros(0, dtype=bool)
    vals, finite = _cell_samples(gray, c)
    black = _black_samples_of(tuple(int(i) for i in ids))
    white_level = row_lower_median(vals, ~black)
    black_level = row_lower_median(vals, black)
    contrast = np.maximum(white_level - black_level, 1.0)
    dark = (white_level[:, None] - vals[:, _MARGIN_CYCLE]) / contrast[:, None]  # 0 white, 1 black
    return ~finite | (_run_means(dark).max(axis=1) >= _HIDDEN_MARGIN_DARKNESS)


def _cell_samples(gray: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image at each tag's 100 ``CELL_CENTRES`` (bilinear, 0 off the image): (values (K, 100)
    float64, finite (K,): every sample point finite)."""
    import cv2

    hom = tag_homographies(corners)
    p = hom @ CELL_CENTRES_H.T  # (K, 3, 100); a matmul, cheaper than einsum here
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (p[:, 0] / p[:, 2]).astype(np.float32)
        y = (p[:, 1] / p[:, 2]).astype(np.float32)
    finite = np.all(np.isfinite(x) & np.isfinite(y), axis=1)
    x = np.where(np.isfinite(x), x, -1.0).astype(np.float32)
    y = np.where(np.isfinite(y), y, -1.0).astype(np.float32)
    vals = cv2.remap(gray, x, y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)  # (K, 100)
    return vals, finite


def _run_means(dark: np.ndarray) -> np.ndarray:
    """(K, 36) mean of ``dark`` over ``_HIDDEN_MARGIN_RUN`` neighbouring samples around each
    margin sample, cyclically: np.roll(dark, j) for j = -half..half summed in that order, taken as
    windows of the cycle padded by half a run at each end (the same sums)."""
    half = _HIDDEN_MARGIN_RUN // 2
    size = dark.shape[1]
    ring = np.concatenate([dark[:, size - half:], dark, dark[:, :half]], axis=1)
    return sum(ring[:, 2 * half - i:2 * half - i + size] for i in range(2 * half + 1)) / (2 * half + 1)
