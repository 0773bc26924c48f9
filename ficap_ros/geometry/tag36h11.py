"""The tag36h11 family as this package uses it: a tag's 8 x 8 cells, the 10 x 10 grid of cell centres
with the white quiet zone around it, the map from cell units to the image, and reading a tag's cells
and id from an image.

Cell units: c0 at (0, 0), c1 at (8, 0), c2 at (8, 8), c3 at (0, 8); the black border is the outer
ring of the 8 x 8 cells and the 6 x 6 data cells are inside it. Corner order c0..c3 is OpenCV's
drawing (``cv2.aruco.generateImageMarker``), which the cap model's corners follow.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

__all__ = ["TAG_CELLS", "CELL_CENTRES", "CELL_CENTRES_H", "QUIET_ZONE", "TAG_AREA", "BORDER", "tag_cells",
           "stacked_tag_cells", "tag_homographies", "homography_corners", "usable_quads",
           "apply_homographies", "read_tag_cells", "cell_errors", "decode_tags"]

#: Cells across a tag36h11 tag, its black border included (6 x 6 data cells inside).
TAG_CELLS = 8


@lru_cache(maxsize=None)
def tag_cells(tag_id: int) -> np.ndarray:
    """The 8x8 cells of a tag36h11 tag (True = black), in OpenCV's drawing (corner order c0..c3)."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    img = cv2.aruco.generateImageMarker(dictionary, int(tag_id), TAG_CELLS, borderBits=1)
    cells = img == 0
    cells.setflags(write=False)
    return cells


@lru_cache(maxsize=256)
def stacked_tag_cells(ids: tuple[int, ...]) -> np.ndarray:
    """(K, 8, 8) ``tag_cells`` of each id, stacked (read-only); cached: a tracked cap shows the
    same ids frame after frame."""
    out = (np.stack([tag_cells(i) for i in ids]) if ids
           else np.zeros((0, TAG_CELLS, TAG_CELLS), dtype=bool))
    out.setflags(write=False)
    return out


def tag_homographies(corners_px: np.ndarray) -> np.ndarray:
    """(K, 3, 3) maps from tag cell units (c0 at (0, 0), c1 at (8, 0), c2 at (8, 8)) to the image.

    The square-to-quadrilateral homography in closed form (Heckbert 1989), vectorised over the
    tags: no linear solve. Raises ``np.linalg.LinAlgError`` for a degenerate quadrilateral (three
    corners on a line), as a solve would.
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    x0, y0 = c[:, 0, 0], c[:, 0, 1]
    x1, y1 = c[:, 1, 0], c[:, 1, 1]
    x2, y2 = c[:, 2, 0], c[:, 2, 1]
    x3, y3 = c[:, 3, 0], c[:, 3, 1]
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    den = dx1 * dy2 - dx2 * dy1
    if not (np.isfinite(den) & (den != 0.0)).all():
        raise np.linalg.LinAlgError("degenerate tag quadrilateral")
    g = (dx3 * dy2 - dx2 * dy3) / den
    h = (dx1 * dy3 - dx3 * dy1) / den
    out = np.empty((len(c), 3, 3))
    inv = 1.0 / TAG_CELLS  # the unit square's homography, scaled to 8 cells
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = (x1 - x0 + g * x1) * inv, (x3 - x0 + h * x3) * inv, x0
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = (y1 - y0 + g * y1) * inv, (y3 - y0 + h * y3) * inv, y0
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = g * inv, h * inv, 1.0
    return out


def homography_corners(h8: np.ndarray) -> np.ndarray:
    """(N, 4, 2) the corners c0..c3 that homographies from tag cell units put in the image, from
    their first 8 entries (N, 8) row-major (the ninth is 1): the inverse of ``tag_homographies``."""
    n = len(h8)
    full = np.concatenate([h8, np.ones((n, 1))], axis=1).reshape(n, 3, 3)
    src = np.array([[0, 0, 1], [TAG_CELLS, 0, 1], [TAG_CELLS, TAG_CELLS, 1], [0, TAG_CELLS, 1]], float)
    p = np.einsum("nij,kj->nki", full, src)
    return p[..., :2] / p[..., 2:3]


def usable_quads(corners_px: np.ndarray) -> np.ndarray:
    """(K,) which quadrilaterals (K, 4, 2) ``tag_homographies`` maps to: finite corners, c1, c2 and
    c3 not on a line (``tag_homographies`` raises for a batch holding one that is not)."""
    c = corners_px
    d1, d2 = c[:, 1] - c[:, 2], c[:, 3] - c[:, 2]
    with np.errstate(invalid="ignore", over="ignore"):
        den = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    return np.isfinite(c).all(axis=(1, 2)) & np.isfinite(den) & (den != 0.0)


def apply_homographies(hom: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Points (P, 2) through homographies (P, 3, 3), one per point."""
    p = np.einsum("pij,pj->pi", hom[:, :, :2], uv) + hom[:, :, 2]
    return p[:, :2] / p[:, 2:3]


def _cell_grid() -> np.ndarray:
    """Centres (100, 2) of the 10x10 cells (white margin ring + 8x8 tag), in cell units from c0."""
    c = np.arange(-1, TAG_CELLS + 1) + 0.5
    gx, gy = np.meshgrid(c, c)
    return np.column_stack([gx.ravel(), gy.ravel()])


#: (100, 2) centres of the 10 x 10 cells (quiet-zone ring + 8 x 8 tag), cell units from c0.
CELL_CENTRES = _cell_grid()
#: ``CELL_CENTRES`` in homogeneous coordinates (100, 3).
CELL_CENTRES_H = np.concatenate([CELL_CENTRES, np.ones((len(CELL_CENTRES), 1))], axis=1)
#: (100,) which of ``CELL_CENTRES`` lie in the white quiet zone around the tag.
QUIET_ZONE = ((CELL_CENTRES < 0) | (CELL_CENTRES > TAG_CELLS)).any(axis=1)
#: (100,) which of ``CELL_CENTRES`` are the tag's own 8 x 8 cells (row-major).
TAG_AREA = ~QUIET_ZONE
#: (64,) which of the tag's own cells form its black border.
BORDER = ((CELL_CENTRES[TAG_AREA] < 1) | (CELL_CENTRES[TAG_AREA] > TAG_CELLS - 1)).any(axis=1)


def read_tag_cells(gray: np.ndarray, hom: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read the 8x8 cells of tags through their homographies (cell units from c0 -> pixels).

    Each cell is sampled at its centre and read against the tag's own levels, taken from the cells
    every tag shares: its black border and the white quiet zone around it.

    Returns:
        (read_black (K, 64) bool row-major, white (K,), black (K,) grey levels, finite (K,): every
        sample point finite, i.e. the homography is usable).
    """
    import cv2

    p = np.einsum("kij,gj->kgi", hom, CELL_CENTRES_H)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = (p[..., :2] / p[..., 2:3]).astype(np.float32)  # (K, 100, 2)
    finite = np.all(np.isfinite(xy), axis=(1, 2))
    xy = np.where(np.isfinite(xy), xy, -1.0)
    vals = cv2.remap(gray, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)  # (K, 100)
    inner = vals[:, TAG_AREA]  # (K, 64)
    white = vals[:, QUIET_ZONE].mean(axis=1)
    black = inner[:, BORDER].mean(axis=1)
    return inner < 0.5 * (white + black)[:, None], white, black, finite


def cell_errors(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray,
                read: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, ...]] | None = None) -> np.ndarray:
    """(K,) how many of each tag's 64 cells, read at ``corners_px`` (K, 4, 2) by ``read``
    (``read_tag_cells``'s signature and results; itself by default), differ from its id's code
    (64 where the corners give no usable homography)."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0:
        return np.zeros(0, dtype=int)
    try:
        hom = tag_homographies(c)
    except np.linalg.LinAlgError:
        return np.full(len(c), 64)
    read_black, _, _, finite = (read or read_tag_cells)(gray, hom)
    expected = stacked_tag_cells(tuple(int(i) for i in ids)).reshape(len(c), -1)
    return np.where(finite, (read_black != expected).sum(axis=1), 64)


@lru_cache(maxsize=1)
def _all_codes() -> np.ndarray:
    """(587, 36) the 6x6 data cells of every tag36h11 id (True = black), OpenCV's drawing."""
    import cv2

    n = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11).bytesList.shape[0]
    codes = np.stack([tag_cells(i)[1:-1, 1:-1].ravel() for i in range(n)])
    codes.setflags(write=False)
    return codes


def _pack36(bits: np.ndarray) -> np.ndarray:
    """(N, 36) bool -> (N,) uint64 words."""
    return (bits.astype(np.uint64) << np.arange(36, dtype=np.uint64)).sum(axis=1, dtype=np.uint64)


@lru_cache(maxsize=1)
def _all_words() -> np.ndarray:
    return _pack36(_all_codes())


def decode_tags(
    gray: np.ndarray, corners_px: np.ndarray, max_bit_errors: int = 2, min_contrast: float = 10.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read quads of unknown id as tag36h11 tags (the search's second chance).

    Each quad's cells are read by ``read_tag_cells`` (as tracking verifies a tag), in its four
    corner orders; the order and id whose 36 data cells are nearest (Hamming) win. A quad is a tag when at most
    ``max_bit_errors`` data cells and 2 of the 28 border cells disagree and the border is at
    least ``min_contrast`` grey levels darker than the white margin. tag36h11 codes are 11 bits
    apart, so 2 errors are corrected with room to spare (AprilTag 3 corrects 2 by default).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (K, 4, 2) quads (any corner order), refined on ``gray``.

    Returns:
        (ok (K,) bool, ids (K,), bit errors (K,), corners (K, 4, 2) in the id's OpenCV order).
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    k = len(c)
    if k == 0:
        return np.zeros(0, bool), np.zeros(0, int), np.zeros(0, int), c.copy()
    rolled = np.stack([np.roll(c, -r, axis=1) for r in range(4)], axis=1).reshape(-1, 4, 2)  # (4K,)
    try:
        hom = tag_homographies(rolled)
    except np.linalg.LinAlgError:
        return np.zeros(k, bool), np.zeros(k, int), np.full(k, 36), c.copy()
    read_black, white, black, finite = read_tag_cells(gray, hom)
    border_errors = (~read_black[:, BORDER]).sum(axis=1)
    data = read_black.reshape(-1, TAG_CELLS, TAG_CELLS)[:, 1:-1, 1:-1].reshape(-1, 36)
    # Hamming distances to every code as popcounts of 36-bit words: (4K, 587) in one pass.
    dist = np.bitwise_count(_pack36(data)[:, None] ^ _all_words()[None, :])
    best_id, best_err = dist.argmin(axis=1), dist.min(axis=1)
    good = finite & (border_errors <= 2) & (white - black >= min_contrast)
    score = np.where(good, best_err, 99).reshape(k, 4)
    order = score.argmin(axis=1)
    rows = np.arange(k) * 4 + order
    errors = score[np.arange(k), order]
    ok = errors <= max_bit_errors
    return ok, best_id[rows].astype(int), errors.astype(int), rolled[rows]
