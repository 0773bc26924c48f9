"""The corner stage's compiled kernels in vectorised numpy: the line pass, its per-side work, the
area step estimator and the cell-edge fit's boundary rows (``cv2.remap``
for the samples): the reference the compiled ones (``ficap_ros.vision.kernels``, used by
``ficap_ros.vision.edges``) are checked against (tests only).

The samples are OpenCV's own; the levels, the normalised profile and its trapezoid integral are
float32 here and float64 in the kernel, and sums run in another order, so the two agree to a
tolerance, not bit for bit.
"""

from __future__ import annotations

import cv2
import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.edges import NEXT, OPPOSITE, PREV
from ficap_ros.vision.medians import row_median


def step_offset(img: np.ndarray, centre: np.ndarray, to_light: np.ndarray, half: np.ndarray,
                samples: int) -> tuple[np.ndarray, np.ndarray]:
    """``edges.step_offset`` in numpy: (offset px along ``to_light`` (P,), contrast (P,))."""
    k = (samples - 1) // 2
    j = np.arange(-k, k + 1, dtype=np.float32)
    step = half / k
    d = (to_light * step[:, None]).astype(np.float32)
    c = centre.astype(np.float32)
    vals = cv2.remap(img, c[:, 0:1] + d[:, 0:1] * j, c[:, 1:2] + d[:, 1:2] * j, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
    dark = 0.5 * (vals[:, 0] + vals[:, 1])
    contrast = 0.5 * (vals[:, -1] + vals[:, -2]) - dark
    frac = np.clip((vals - dark[:, None]) / np.where(contrast > 0, contrast, 1.0)[:, None], 0.0, 1.0)
    area = frac.sum(axis=1) - 0.5 * (frac[:, 0] + frac[:, -1])
    return half - area.astype(np.float64) * step, contrast.astype(np.float64)


def edge_lines(img: np.ndarray, a: np.ndarray, d: np.ndarray, nrm: np.ndarray, half: np.ndarray,
               t: np.ndarray, k: int, check_inside: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``kernels.edge_lines`` in numpy: (unit normal (R, 2), rho (R,), profiles kept (R,))."""
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    step = half / k
    j = np.arange(-k, k + 1, dtype=np.float32)
    dn = (nrm * step[:, None]).astype(np.float32)
    map_x = (a[:, 0:1] + d[:, 0:1] * t).astype(np.float32)[..., None] + dn[:, None, 0:1] * j
    map_y = (a[:, 1:2] + d[:, 1:2] * t).astype(np.float32)[..., None] + dn[:, None, 1:2] * j
    s_len = map_x.shape[-1]
    vals = cv2.remap(img, map_x.reshape(-1, s_len), map_y.reshape(-1, s_len), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(map_x.shape).astype(np.float32)
    dark = 0.5 * (vals[..., 0] + vals[..., 1])
    contrast = 0.5 * (vals[..., -1] + vals[..., -2]) - dark
    frac = np.clip((vals - dark[..., None]) / np.where(contrast > 0, contrast, 1.0)[..., None], 0.0, 1.0)
    trap = np.ones(s_len, dtype=np.float32)
    trap[[0, -1]] = 0.5
    s_edge = half[:, None] - (frac @ trap).astype(np.float64) * step[:, None]
    contrast = contrast.astype(np.float64)
    med_c = row_median(contrast, contrast > 0)
    w = np.where((contrast > 0.3 * med_c[:, None]) & (contrast > 8.0)
                 & (np.abs(s_edge) < half[:, None] - np.maximum(step, 0.25)[:, None]), contrast, 0.0)
    if check_inside:
        h_img, w_img = img.shape
        inside = (map_x >= 0) & (map_y >= 0) & (map_x <= w_img - 1) & (map_y <= h_img - 1)
        w = w * inside.all(axis=2)
    along = t[None, :] * length[:, None]
    alpha, beta, kept = _fit_side_lines(along, s_edge, w)
    along0 = (w * along).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-12)
    point = a + u * along0[:, None] + nrm * alpha[:, None]
    normal = nrm - u * beta[:, None]
    normal /= np.hypot(normal[:, 0], normal[:, 1])[:, None]
    return normal, np.einsum("ij,ij->i", normal, point), kept


def _fit_side_lines(x: np.ndarray, s: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted lines s = alpha + beta (x - x_mean) per row, one round of 3-sigma (MAD) rejection."""
    for round_ in range(2):
        sw = np.maximum(w.sum(axis=1), 1e-12)
        xm = (w * x).sum(axis=1) / sw
        dx = x - xm[:, None]
        alpha = (w * s).sum(axis=1) / sw
        beta = (w * dx * s).sum(axis=1) / np.maximum((w * dx * dx).sum(axis=1), 1e-12)
        if round_ == 1:
            break
        r = np.abs(s - alpha[:, None] - beta[:, None] * dx)
        mad = 1.4826 * row_median(r, w > 0)
        w = np.where(r <= np.maximum(3.0 * mad, 0.05)[:, None], w, 0.0)
    return alpha, beta, (w > 0).sum(axis=1)


def boundary_rows(h: np.ndarray, tag_of: np.ndarray, uv: np.ndarray, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``fit_kernels.boundary_rows`` in numpy: (frames (6, T): x, y, den, normal x, y, cell px;
    rows (T, 10) of the cell-edge fit's linearised model)."""
    u, v = uv[:, 0], uv[:, 1]
    ht = h[tag_of]
    den = ht[:, 6] * u + ht[:, 7] * v + 1.0
    px = (ht[:, 0] * u + ht[:, 1] * v + ht[:, 2]) / den
    py = (ht[:, 3] * u + ht[:, 4] * v + ht[:, 5]) / den
    j11 = (ht[:, 0] - ht[:, 6] * px) / den
    j12 = (ht[:, 1] - ht[:, 7] * px) / den
    j21 = (ht[:, 3] - ht[:, 6] * py) / den
    j22 = (ht[:, 4] - ht[:, 7] * py) / den
    det = j11 * j22 - j12 * j21
    gx = (j22 * nu[:, 0] - j21 * nu[:, 1]) / det
    gy = (-j12 * nu[:, 0] + j11 * nu[:, 1]) / det
    gnorm = np.hypot(gx, gy)
    nx, ny = gx / gnorm, gy / gnorm
    across_x = (np.abs(nu[:, 0]) > 0.5).astype(np.float64)
    jac = np.zeros((len(uv), 10))
    jac[:, 0], jac[:, 1], jac[:, 2] = nx * u / den, nx * v / den, nx / den
    jac[:, 3], jac[:, 4], jac[:, 5] = ny * u / den, ny * v / den, ny / den
    jac[:, 6] = -(nx * px + ny * py) * u / den
    jac[:, 7] = -(nx * px + ny * py) * v / den
    jac[:, 8] = -across_x
    jac[:, 9] = -(1.0 - across_x)
    return np.stack([px, py, den, nx, ny, 1.0 / gnorm]), jac


def outward_sides(corners: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per side (R = 4N rows): start a (R, 2), side vector d (R, 2), length (R,), unit direction
    u (R, 2) and unit normal (R, 2) away from the tag's centre, whatever the handedness."""
    a = corners.reshape(-1, 2)
    d = corners[:, NEXT].reshape(-1, 2) - a
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    nrm = np.column_stack([u[:, 1], -u[:, 0]])
    centre = np.repeat(corners.mean(axis=1), 4, axis=0)
    nrm *= np.where(np.einsum("ij,ij->i", a + 0.5 * d - centre, nrm) < 0, -1.0, 1.0)[:, None]
    return a, d, length, u, nrm


def side_windows(corners: np.ndarray, a: np.ndarray, nrm: np.ndarray, cell_px: np.ndarray,
                 cfg: DetectorConfig) -> np.ndarray:
    """(R,) each side's window half-length, px: the cell across it (the tag's width along the
    side's normal, the mean of its two opposite corners', / 8, at most ``cell_px``)."""
    opp = corners[:, OPPOSITE[0]].reshape(-1, 2) + corners[:, OPPOSITE[1]].reshape(-1, 2) - 2 * a
    width = np.abs(np.einsum("ij,ij->i", opp, nrm)) / 2.0
    cell_side = np.minimum(width / TAG_CELLS, cell_px)
    return np.maximum(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75)


def _corners_of_lines(lines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner k where side k-1's line meets side k's, from (N, 4, 3) lines: (corners, usable)."""
    l_prev = lines[:, PREV]
    a11, a12, r1 = l_prev[..., 0], l_prev[..., 1], l_prev[..., 2]
    a21, a22, r2 = lines[..., 0], lines[..., 1], lines[..., 2]
    det = a11 * a22 - a12 * a21
    good_det = np.abs(det) > 0.2
    det = np.where(good_det, det, 1.0)
    return np.stack([(r1 * a22 - a12 * r2) / det, (a11 * r2 - a21 * r1) / det], axis=-1), good_det


def refine_corners_edge_ok(img: np.ndarray, corners_px: np.ndarray,
                           cfg: DetectorConfig) -> tuple[np.ndarray, np.ndarray]:
    """``edges.refine_corners_edge_ok`` (``kernels.line_pass``) in numpy: (corners, ok)."""
    c_init = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    side_len = np.linalg.norm(c_init[:, NEXT] - c_init, axis=-1)
    cell_px = np.repeat(side_len.mean(axis=1) / TAG_CELLS, 4)
    m, k = cfg.edge_samples_per_side, (cfg.edge_profile_samples - 1) // 2
    t = np.linspace(cfg.edge_corner_skip, 1.0 - cfg.edge_corner_skip, m)
    corners, ok = c_init, np.ones(len(c_init), dtype=bool)
    h_img, w_img = img.shape
    for _ in range(cfg.edge_iterations):
        a, d, _, _, nrm = outward_sides(corners)
        half = side_windows(corners, a, nrm, cell_px, cfg)
        reach = float(half.max()) + 1.0
        near = not (corners.min() >= reach
                    and (corners.max(axis=(0, 1)) <= (w_img - 1 - reach, h_img - 1 - reach)).all())
        normal, rho, kept = edge_lines(img, a, d, nrm, half, t, k, near)
        new, good_det = _corners_of_lines(np.column_stack([normal, rho]).reshape(-1, 4, 3))
        it_ok = good_det.all(axis=1) & (kept.reshape(-1, 4) >= max(3, m // 4)).all(axis=1)
        corners = np.where(it_ok[:, None, None], new, corners)
        ok &= it_ok
    shift = np.linalg.norm(corners - c_init, axis=-1).max(axis=1)
    max_shift = np.minimum(cfg.edge_max_shift_px, 0.25 * side_len.min(axis=1))
    ok &= np.isfinite(corners).all(axis=(1, 2)) & (shift <= max_shift)
    return np.where(ok[:, None, None], corners, c_init), ok
