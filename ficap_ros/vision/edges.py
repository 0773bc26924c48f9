"""Corners from straight-line fits to a tag's four outer border edges (``DetectorConfig``'s ``edge``
corner refinement), and the step estimator and side-line geometry the corner stage builds on.

For every side of every tag, points along the side (leaving out ``edge_corner_skip`` at each end)
are searched along the side's outward normal for the dark-to-light step between the black border
and the white quiet zone. The step's position is its *area* location: with dark level d and light
level l at the ends of the window, the edge sits at s_out - integral((I - d) / (l - d)) ds, which is
exact for an area-sampled step under any blur that fits in the window, and is the 50 % crossing
for a symmetric one. A line is fitted per side (weights = local contrast; samples beyond 3 robust
sigmas dropped and the line refitted) and adjacent lines are intersected. The per-side work (the
profiles, their steps and weights, the line fit) is compiled (``ficap_ros.vision.kernels``); the
rest is vectorised across the tags' 4N sides.

Corner order and pixel convention are OpenCV's (``ficap_ros.vision.detector``). Side k runs from
corner k to corner k + 1; corner k joins sides k - 1 and k.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.kernels import area_steps, edge_lines, frozen

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
    c_init = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c_init) == 0:
        return c_init.copy(), np.zeros(0, dtype=bool)
    side_len = vector_norm(c_init[:, NEXT] - c_init)  # (N, 4)
    cell_px = np.repeat(side_len.mean(axis=1) / TAG_CELLS, 4)  # (4N,) one per side
    corners = c_init
    ok = np.ones(len(c_init), dtype=bool)
    for _ in range(cfg.edge_iterations):
        corners, it_ok = _edge_pass(gray, corners, cell_px, cfg)
        ok &= it_ok
    shift = vector_norm(corners - c_init).max(axis=1)
    max_shift = np.minimum(cfg.edge_max_shift_px, 0.25 * side_len.min(axis=1))
    ok &= np.isfinite(corners).all(axis=(1, 2)) & (shift <= max_shift)
    return np.where(ok[:, None, None], corners, c_init), ok


def refine_corners_edge_wide(gray: np.ndarray, corners: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """Line-fit corners from starts up to 8 px off (a decimated search's polygon, a corner rebuilt
    from the other three): one wide coarse pass (8 px each way, 12 x 9 samples a side), then the
    passes of ``cfg``; a tag either stage fails keeps its input corners."""
    coarse = replace(cfg, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                     edge_samples_per_side=12, edge_profile_samples=9)
    c, ok1 = refine_corners_edge_ok(gray, corners, coarse)
    c, ok2 = refine_corners_edge_ok(gray, c, cfg)
    return np.where((ok1 & ok2)[:, None, None], c, corners)


def _edge_pass(
    img: np.ndarray, corners: np.ndarray, cell_px: np.ndarray, cfg: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """One search-and-fit pass over the 4N sides (rows r of every per-side array): sample each
    side's profiles, locate the step on each, fit a line per side (``kernels.edge_lines``, the
    module docstring's rules side by side, compiled), intersect adjacent lines.

    Returns:
        (corners (N,4,2), ok (N,)): a tag is ok when its four lines meet at usable angles and each
        kept at least a quarter of its samples (at least 3).
    """
    n, m = len(corners), cfg.edge_samples_per_side
    a, d, _, _, nrm = _outward_sides(corners)
    half = _side_windows(corners, a, nrm, cell_px, cfg)
    # Every side's window [-half, half] holds the same number of samples, so their spacing
    # follows the window: the same relative resolution on every side and one array shape for all.
    k = (cfg.edge_profile_samples - 1) // 2
    normal, rho, keep_n = edge_lines(frozen(img), a, d, nrm, half, _side_positions(cfg.edge_corner_skip, m), k,
                                     _near_border(img, corners, half))
    new, good_det = _corners_of_lines(np.column_stack([normal, rho]).reshape(n, 4, 3))
    ok = good_det.all(axis=1) & (keep_n.reshape(n, 4) >= max(3, m // 4)).all(axis=1)
    return np.where(ok[:, None, None], new, corners), ok


def _near_border(img: np.ndarray, corners: np.ndarray, half: np.ndarray) -> bool:
    """Whether a profile of these corners' sides may reach off the image (then each profile is
    checked)."""
    h_img, w_img = img.shape
    reach = float(half.max()) + 1.0
    return not (corners.min() >= reach and (corners.max(axis=(0, 1)) <= (w_img - 1 - reach, h_img - 1 - reach)).all())


def _outward_sides(corners: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per side (R = 4N rows): start point a (R, 2), side vector d (R, 2), length (R,), unit
    direction u (R, 2) and unit normal (R, 2) pointing away from the tag's centre, whatever the
    corner order's handedness."""
    a = corners.reshape(-1, 2)
    d = corners[:, NEXT].reshape(-1, 2) - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    nrm = np.column_stack([u[:, 1], -u[:, 0]])
    centre = np.repeat(corners.mean(axis=1), 4, axis=0)
    nrm *= np.where(np.einsum("ij,ij->i", a + 0.5 * d - centre, nrm) < 0, -1.0, 1.0)[:, None]
    return a, d, length, u, nrm


def _side_windows(
    corners: np.ndarray, a: np.ndarray, nrm: np.ndarray, cell_px: np.ndarray, cfg: DetectorConfig
) -> np.ndarray:
    """(R,) half-length, px, of each side's search window across it.

    The window must stay between the data cells (one cell inside) and whatever lies beyond the
    white quiet zone (one cell outside). The cell that matters is the one across this side, which
    on an obliquely seen tag is much narrower than the mean side / 8: the tag's width along the
    side's normal (distance of the two opposite corners from the side's line) gives it.
    """
    opp = corners[:, OPPOSITE[0]].reshape(-1, 2) + corners[:, OPPOSITE[1]].reshape(-1, 2) - 2 * a
    width = np.abs(np.einsum("ij,ij->i", opp, nrm)) / 2.0
    cell_side = np.minimum(width / TAG_CELLS, cell_px)
    return np.maximum(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75)


def _corners_of_lines(lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner k where side k-1's line meets side k's, from ``lines`` (N, 4, 3) = (normal x,
    normal y, rho): (corners (N, 4, 2), usable (N, 4): the two sides at least ~12 deg apart)."""
    l_prev = lines[:, PREV]
    a11, a12, r1 = l_prev[..., 0], l_prev[..., 1], l_prev[..., 2]
    a21, a22, r2 = lines[..., 0], lines[..., 1], lines[..., 2]
    det = a11 * a22 - a12 * a21
    good_det = np.abs(det) > 0.2
    det = np.where(good_det, det, 1.0)
    return np.stack([(r1 * a22 - a12 * r2) / det, (a11 * r2 - a21 * r1) / det], axis=-1), good_det


@lru_cache(maxsize=8)
def _side_positions(corner_skip: float, m: int) -> np.ndarray:
    """``_edge_pass``'s positions along a side (M,), fractions of its length, built once per
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
    the corners' own side lines: ``_side_windows``, except that the tag's width across a side is
    taken at its farther opposite corner, where the line pass takes the mean of the two (the
    same on a parallelogram, at least as wide otherwise)."""
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
