"""Corners from straight-line fits to a tag's four outer border edges (``DetectorConfig``'s ``edge``
corner refinement), and the step estimator and side-line geometry the corner stage builds on.

For every side of every tag, points along the side (leaving out ``edge_corner_skip`` at each end)
are searched along the side's outward normal for the dark-to-light step between the black border
and the white quiet zone. The step's position is its *area* location: with dark level d and light
level l at the ends of the window, the edge sits at s_out - integral((I - d) / (l - d)) ds, which is
exact for an area-sampled step under any blur that fits in the window, and is the 50 % crossing
for a symmetric one. A line is fitted per side (weights = local contrast; samples beyond 3 robust
sigmas dropped and the line refitted) and adjacent lines are intersected. The pass is compiled
(``ficap_ros.vision.kernels.line_pass``).

Corner order and pixel convention are OpenCV's (``ficap_ros.vision.detector``). Side k runs from
corner k to corner k + 1; corner k joins sides k - 1 and k.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.kernels import area_steps, frozen, line_pass

__all__ = [
    "NEXT",
    "PREV",
    "OPPOSITE",
    "refine_corners_edge",
    "refine_corners_edge_ok",
    "refine_corners_edge_wide",
    "side_lines",
    "intersect_sides",
    "line_windows",
    "step_offset",
    "vector_norm",
]

#: Corner/side index tables: side k runs from corner k to corner NEXT[k]; corner k joins sides
#: PREV[k] and k; OPPOSITE[0][k], OPPOSITE[1][k] are the two corners not on side k.
NEXT = np.array([1, 2, 3, 0])
PREV = np.array([3, 0, 1, 2])
OPPOSITE = (np.array([2, 3, 0, 1]), np.array([3, 0, 1, 2]))


def vector_norm(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1)`` of a float array, bit for bit (the same sum of squares and
    square root), without its argument checks, which dominate on the corner stage's small arrays."""
    return np.sqrt(np.add.reduce(x * x, axis=-1, keepdims=keepdims))


def refine_corners_edge(
    gray: np.ndarray, corners_px: np.ndarray, config: DetectorConfig | None = None
) -> np.ndarray:
    """Sub-pixel corners from line fits to the tag's four outer border edges (module docstring).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) initial corners, OpenCV order and pixel convention.
        config: search settings (``edge_*`` fields); None: the defaults.

    Returns:
        (N, 4, 2) float64 refined corners; a tag whose fit is implausible keeps its input corners.
    """
    return refine_corners_edge_ok(gray, corners_px, config)[0]


def refine_corners_edge_ok(
    gray: np.ndarray, corners_px: np.ndarray, config: DetectorConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``refine_corners_edge`` that also says which tags were refined: (corners (N,4,2), ok (N,)).

    ``edge_iterations`` passes, each from the previous pass's corners; a tag is refined when every
    pass fitted its four sides and no corner moved further than ``edge_max_shift_px`` (or a
    quarter of the tag's shortest side) from its input.
    """
    cfg = config or DetectorConfig()
    c_init = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c_init) == 0:
        return c_init.copy(), np.zeros(0, dtype=bool)
    m = cfg.edge_samples_per_side
    # Every side's window [-half, half] holds the same number of samples, so their spacing
    # follows the window: the same relative resolution on every side.
    return line_pass(frozen(gray), c_init, cfg.edge_iterations, float(cfg.edge_search_px),
                     float(cfg.edge_window_cells), _side_positions(cfg.edge_corner_skip, m),
                     (cfg.edge_profile_samples - 1) // 2, max(3, m // 4), float(cfg.edge_max_shift_px))


def refine_corners_edge_wide(gray: np.ndarray, corners: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """Line-fit corners from starts up to 8 px off (a decimated search's polygon, a corner rebuilt
    from the other three): one wide coarse pass (8 px each way, 12 x 9 samples a side), then the
    passes of ``cfg``; a tag either stage fails keeps its input corners."""
    coarse = replace(cfg, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                     edge_samples_per_side=12, edge_profile_samples=9)
    c, ok1 = refine_corners_edge_ok(gray, corners, coarse)
    c, ok2 = refine_corners_edge_ok(gray, c, cfg)
    return np.where((ok1 & ok2)[:, None, None], c, corners)


@lru_cache(maxsize=8)
def _side_positions(corner_skip: float, m: int) -> np.ndarray:
    """The line pass's positions along a side (M,), fractions of its length, built once per
    setting."""
    t = np.linspace(corner_skip, 1.0 - corner_skip, m)
    t.setflags(write=False)
    return t


def side_lines(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (N, 4, 2) and offsets rho (N, 4) of the lines through corners k, k+1
    (a point p is on side k's line when normal . p = rho; larger = further out)."""
    d = corners[:, NEXT] - corners
    u = d / np.maximum(vector_norm(d, keepdims=True), 1e-12)
    nrm = np.stack([u[..., 1], -u[..., 0]], axis=-1)
    centre = corners.mean(axis=1, keepdims=True)
    flip = np.einsum("nkd,nkd->nk", corners + 0.5 * d - centre, nrm) < 0
    nrm = np.where(flip[..., None], -nrm, nrm)
    return nrm, np.einsum("nkd,nkd->nk", nrm, corners)


def intersect_sides(nrm: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2) where side k-1's line meets side k's (lines as ``side_lines`` gives)."""
    n1, r1 = nrm[:, PREV], rho[:, PREV]
    det = n1[..., 0] * nrm[..., 1] - n1[..., 1] * nrm[..., 0]
    det = np.where(np.abs(det) > 1e-9, det, 1e-9)
    x = (r1 * nrm[..., 1] - n1[..., 1] * rho) / det
    y = (n1[..., 0] * rho - r1 * nrm[..., 0]) / det
    return np.stack([x, y], axis=-1)


def line_windows(corners: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """(N, 4) half-length, px, of the line pass's window across each side of these corners, from
    the corners' own side lines: the line pass's windows (``kernels.line_pass``), except that the
    tag's width across a side is taken at its farther opposite corner, where the line pass takes
    the mean of the two (the same on a parallelogram, at least as wide otherwise)."""
    side_len = np.linalg.norm(corners[:, NEXT] - corners, axis=2)
    cell_px = side_len.mean(axis=1, keepdims=True) / TAG_CELLS
    nrm, rho = side_lines(corners)
    width = (rho[:, :, None] - np.einsum("nkd,njd->nkj", nrm, corners)).max(axis=2)
    cell_side = np.minimum(width / TAG_CELLS, cell_px)
    return np.clip(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75, None)


def step_offset(
    img: np.ndarray, centre: np.ndarray, to_light: np.ndarray, half: np.ndarray, samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """Area location of a dark-to-light step along ``to_light`` (unit, (P, 2)) in the window
    [-half, half] around ``centre``: (offset px along ``to_light`` (P,), contrast (P,)).

    The line pass's estimator for single points: levels from the window's two end samples, the
    edge where the trapezoid integral of the normalised profile puts it (exact for any blur of a
    step in linear light; under a tone curve, shifted toward the dark side by the same amount for
    every edge of the same blur and contrast).
    """
    k = (samples - 1) // 2
    step = half / k
    d = (to_light * step[:, None]).astype(np.float32)
    c = centre.astype(np.float32)
    offset, contrast, _ = area_steps(frozen(img), c[:, 0].copy(), c[:, 1].copy(), d[:, 0].copy(), d[:, 1].copy(), k,
                                     np.asarray(half, dtype=np.float64), step)
    return offset, contrast
