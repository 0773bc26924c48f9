"""The line pass's per-side work and the area step estimator in vectorised numpy (``cv2.remap``
for the samples): the reference the compiled ones (``ficap_ros.vision.kernels``, used by
``ficap_ros.vision.edges``) are checked against (tests only).

The samples are OpenCV's own; the levels, the normalised profile and its trapezoid integral are
float32 here and float64 in the kernel, and sums run in another order, so the two agree to a
tolerance, not bit for bit.
"""

from __future__ import annotations

import cv2
import numpy as np

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
    """``kernels.boundary_rows`` in numpy: (frames (6, T): x, y, den, normal x, y, cell px;
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
