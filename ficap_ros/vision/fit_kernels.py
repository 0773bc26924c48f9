"""The cell-edge fit's compiled kernels (``ficap_ros.vision.corners.fit_tag_edges``).

``boundary_rows`` places the fit's boundary samples in the image through their tags' homographies,
with the rows of its linearised model; ``grouped_normal_equations``, ``grouped_solve`` and
``grouped_residuals`` are its per-tag weighted least squares: each tag's normal equations
accumulated over its rows, each tag's column-scaled solve (LAPACK's ``gesv``, as
``np.linalg.solve``: the same numbers), and the residuals of each tag's solution;
``robust_grouped_solve`` is the fit's robust step around them; ``edge_fit_round`` one whole
sample-and-solve round: the boundaries placed, their steps measured (``kernels.area_steps``, so
the profiles hold ``cv2.remap``'s values), each tag's clean contrast, the usable samples and the
robust step. Kernels divide as numpy does (``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.kernels import area_steps, frozen

__all__ = ["boundary_rows", "edge_fit_round", "grouped_normal_equations", "grouped_residuals", "grouped_solve",
           "robust_grouped_solve"]


@njit(error_model="numpy")
def boundary_rows(h: np.ndarray, tag_of: np.ndarray, uv: np.ndarray,
                  nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each cell-boundary sample through its tag's homography, and its row of the cell-edge fit's
    linearised model (``corners.fit_tag_edges``).

    Args:
        h: (N, 8) each tag's homography, tag (u, v) to image px (h33 = 1).
        tag_of: (T,) int64 the tag of each sample.
        uv: (T, 2) each sample's place on its tag, tag units.
        nu: (T, 2) the boundary's unit normal on the tag, toward its white cell.

    Returns:
        (frames (6, T): image x, y px, the homography's denominator, the boundary's unit image
        normal x, y (toward the white cell: J^-T nu, J = d(x, y)/d(u, v)) and one cell across it,
        px; rows (T, 10): d(offset along the normal)/d(h) (8), then -1 in the column of the
        boundary's direction (tag x: column 8, tag y: column 9)).
    """
    t_rows = len(tag_of)
    frames = np.empty((6, t_rows))
    rows = np.zeros((t_rows, 10))
    for r in range(t_rows):
        g = tag_of[r]
        u, v = uv[r, 0], uv[r, 1]
        den = h[g, 6] * u + h[g, 7] * v + 1.0
        px = (h[g, 0] * u + h[g, 1] * v + h[g, 2]) / den
        py = (h[g, 3] * u + h[g, 4] * v + h[g, 5]) / den
        j11 = (h[g, 0] - h[g, 6] * px) / den
        j12 = (h[g, 1] - h[g, 7] * px) / den
        j21 = (h[g, 3] - h[g, 6] * py) / den
        j22 = (h[g, 4] - h[g, 7] * py) / den
        det = j11 * j22 - j12 * j21
        gx = (j22 * nu[r, 0] - j21 * nu[r, 1]) / det
        gy = (-j12 * nu[r, 0] + j11 * nu[r, 1]) / det
        gnorm = math.hypot(gx, gy)
        nx, ny = gx / gnorm, gy / gnorm
        frames[0, r], frames[1, r], frames[2, r] = px, py, den
        frames[3, r], frames[4, r], frames[5, r] = nx, ny, 1.0 / gnorm
        rows[r, 0], rows[r, 1], rows[r, 2] = nx * u / den, nx * v / den, nx / den
        rows[r, 3], rows[r, 4], rows[r, 5] = ny * u / den, ny * v / den, ny / den
        along = nx * px + ny * py
        rows[r, 6] = -along * u / den
        rows[r, 7] = -along * v / den
        if abs(nu[r, 0]) > 0.5:
            rows[r, 8] = -1.0
        else:
            rows[r, 9] = -1.0
    return frames, rows


@njit(error_model="numpy")
def grouped_normal_equations(jac: np.ndarray, rhs: np.ndarray, w: np.ndarray,
                             starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted normal equations per contiguous group of rows.

    Args:
        jac: (T, P) float64 rows of the linear model.
        rhs: (T,) float64 measurements.
        w: (T,) float64 row weights (0: the row is left out).
        starts: (n,) int64 first row of each group, ascending (group g: rows starts[g] to
            starts[g + 1], the last to T).

    Returns:
        (A^T W A (n, P, P), A^T W b (n, P), weighted rows (n,) float64: rows with w > 0).
    """
    n, t_rows, p = len(starts), len(rhs), jac.shape[1]
    ata = np.zeros((n, p, p))
    atb = np.zeros((n, p))
    rows = np.zeros(n)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        for r in range(starts[g], end):
            wr = w[r]
            if wr > 0:
                rows[g] += 1.0
            elif wr == 0:
                continue
            for i in range(p):
                wji = wr * jac[r, i]
                atb[g, i] += wji * rhs[r]
                for j in range(i, p):
                    ata[g, i, j] += wji * jac[r, j]
        for i in range(p):
            for j in range(i):
                ata[g, i, j] = ata[g, j, i]
    return ata, atb, rows


@njit(error_model="numpy")
def grouped_residuals(jac: np.ndarray, rhs: np.ndarray, sol: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(T,) rhs - jac @ sol[g] for the rows of each group g (groups as ``grouped_normal_equations``'s;
    ``sol`` (n, P))."""
    n, t_rows, p = len(starts), len(rhs), jac.shape[1]
    resid = np.empty(t_rows)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        for r in range(starts[g], end):
            acc = 0.0
            for i in range(p):
                acc += jac[r, i] * sol[g, i]
            resid[r] = rhs[r] - acc
    return resid


@njit(error_model="numpy")
def grouped_solve(jac: np.ndarray, rhs: np.ndarray, w: np.ndarray, starts: np.ndarray, min_rows: int,
                  residuals: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least squares per contiguous group of rows (groups as ``grouped_normal_equations``'s).

    Each group's normal equations are scaled by their diagonal's square roots d (the parameters
    differ in size by orders of magnitude), solved by ``np.linalg.solve`` (LAPACK ``gesv``, the
    routine numpy's solve calls, so the same numbers) and unscaled. A group is solved when it has
    ``min_rows`` weighted rows, every parameter is touched by one (a zero diagonal makes the system
    exactly singular) and its solution is finite. A singular system leaves its group unsolved at 0,
    a non-finite one (a non-finite row) at NaN, as numpy's solve leaves them.

    Args:
        jac, rhs, w, starts: as ``grouped_normal_equations``'s.
        min_rows: the least weighted rows of a solved group.
        residuals: also return rhs - jac @ solution per row (else an empty array).

    Returns:
        (solutions (n, P), solved (n,) bool, residuals (T,) or (0,)).
    """
    ata, atb, rows = grouped_normal_equations(jac, rhs, w, starts)
    n, p = ata.shape[0], ata.shape[1]
    sol = np.zeros((n, p))
    solved = np.zeros(n, np.bool_)
    d = np.empty(p)
    a_s = np.empty((p, p))
    b_s = np.empty(p)
    for g in range(n):
        usable = rows[g] >= min_rows
        for i in range(p):
            usable = usable and ata[g, i, i] > 0.0
        if not usable:
            continue
        finite = True
        for i in range(p):
            d[i] = math.sqrt(max(ata[g, i, i], 1e-30))
        for i in range(p):
            b_s[i] = atb[g, i] / d[i]
            finite = finite and math.isfinite(b_s[i])
            for j in range(p):
                a_s[i, j] = ata[g, i, j] / d[i] / d[j]
                finite = finite and math.isfinite(a_s[i, j])
        if not finite:
            sol[g] = np.nan
            continue
        try:
            x = np.linalg.solve(a_s, b_s)
        except Exception:  # singular to machine precision: unsolved
            continue
        for i in range(p):
            sol[g, i] = x[i] / d[i]
            finite = finite and math.isfinite(sol[g, i])
        solved[g] = finite
    resid = grouped_residuals(jac, rhs, sol, starts) if residuals else np.empty(0)
    return sol, solved, resid


@njit(error_model="numpy")
def robust_grouped_solve(jac: np.ndarray, s: np.ndarray, contrast: np.ndarray, top_c: np.ndarray,
                         ok: np.ndarray, vertical: np.ndarray, starts: np.ndarray, min_rows: int,
                         min_per_direction: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell-edge fit's robust step per tag (``corners._solve_edges``): weights
    (contrast / max(tag contrast, 1))^2 on the ``ok`` rows, a solve (``grouped_solve``), the rows
    beyond 3.5 robust sigmas (1.4826 times the median absolute residual of the group's ``ok``
    rows; at least 0.05) dropped, a second solve. A group is solved when both boundary directions
    keep ``min_per_direction`` weighted rows.

    Args:
        jac: (T, P) rows of the linear model; s: (T,) measured offsets; contrast, top_c: (T,) each
            row's contrast and its tag's clean contrast; ok: (T,) bool usable rows.
        vertical: (T,) bool rows of vertical boundaries (tag x direction).
        starts: (n,) int64 each group's first row (groups as ``grouped_normal_equations``'s).
        min_rows, min_per_direction: the least weighted rows in all and per direction.

    Returns:
        (solutions (n, P), solved (n,) bool, the rows kept (T,) bool).
    """
    t_rows, n = len(s), len(starts)
    w = np.empty(t_rows)
    for r in range(t_rows):
        q = contrast[r] / max(top_c[r], 1.0)
        w[r] = q * q if ok[r] else 0.0
    _, _, resid = grouped_solve(jac, s, w, starts, min_rows, True)
    keep = np.empty(t_rows, np.bool_)
    scratch = np.empty(t_rows)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        m = 0
        for r in range(starts[g], end):
            a = abs(resid[r])
            if ok[r] and math.isfinite(a):
                scratch[m] = a
                m += 1
        med = 0.0
        if m:
            srt = np.sort(scratch[:m])
            med = 0.5 * (srt[(m - 1) // 2] + srt[m // 2])
        limit = max(3.5 * (1.4826 * med), 0.05)
        for r in range(starts[g], end):
            keep[r] = ok[r] and abs(resid[r]) <= limit
            if not keep[r]:
                w[r] = 0.0
    sol, solved, _ = grouped_solve(jac, s, w, starts, min_rows, False)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        n_vertical = n_used = 0
        for r in range(starts[g], end):
            if w[r] > 0:
                n_used += 1
                n_vertical += vertical[r]
        solved[g] = solved[g] and n_vertical >= min_per_direction and n_used - n_vertical >= min_per_direction
    return sol, solved, keep


@njit(error_model="numpy")
def edge_fit_round(img: np.ndarray, h: np.ndarray, tag_of: np.ndarray, uv: np.ndarray, nu: np.ndarray,
                   vertical: np.ndarray, keep: np.ndarray, starts: np.ndarray, search_px: float, k: int,
                   min_cell_px: float, min_contrast_ratio: float, min_rows: int,
                   min_per_direction: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One sample-and-solve round of the cell-edge fit, every tag at once.

    Each boundary sample is placed through its tag's homography (``boundary_rows``); its step is
    measured across the boundary (``area_steps``, 2 k + 1 samples over a window of half a cell
    each way, at most ``search_px``); each tag's clean contrast is the nearest-rank 90th percentile
    of the finite contrasts of its ``keep`` samples; a sample is usable where it is kept, its
    cell spans ``min_cell_px``, its step lies finite and inside the window less one sample step,
    and its contrast exceeds 8 grey levels and ``min_contrast_ratio`` of its tag's (a window whose
    ends a neighbouring black cell darkens, or a white one lightens, is not a clean step); then the
    robust step (``robust_grouped_solve``).

    Args:
        img: (H, W) uint8 image (read-only view: ``kernels.frozen``).
        h: (N, 8) each tag's homography, tag (u, v) to image px (h33 = 1).
        tag_of, uv, nu: the samples' tags, places on them and boundary normals (``boundary_rows``).
        vertical: (T,) bool samples on vertical boundaries (tag x direction).
        keep: (T,) bool samples this round may use.
        starts: (N,) int64 each tag's first sample (samples tag after tag).
        search_px, k, min_cell_px, min_contrast_ratio: as above.
        min_rows, min_per_direction: ``robust_grouped_solve``'s.

    Returns:
        (solutions (N, 10): the homography's update (8) and the two directions' edge shifts,
        solved (N,) bool, the samples kept (T,) bool).
    """
    frames, jac = boundary_rows(h, tag_of, uv, nu)
    t_rows, n = len(tag_of), len(starts)
    half, step = np.empty(t_rows), np.empty(t_rows)
    cx, cy = np.empty(t_rows, np.float32), np.empty(t_rows, np.float32)
    dx, dy = np.empty(t_rows, np.float32), np.empty(t_rows, np.float32)
    for r in range(t_rows):
        half_cell = 0.5 * frames[5, r]
        half[r] = search_px if search_px < half_cell else half_cell  # NaN stays NaN
        step[r] = half[r] / k
        cx[r], cy[r] = np.float32(frames[0, r]), np.float32(frames[1, r])
        dx[r], dy[r] = np.float32(frames[3, r] * step[r]), np.float32(frames[4, r] * step[r])
    s, contrast, _ = area_steps(img, cx, cy, dx, dy, k, half, step)
    top_c = np.empty(t_rows)
    scratch = np.empty(t_rows)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        m = 0
        for r in range(starts[g], end):
            if keep[r] and math.isfinite(contrast[r]):
                scratch[m] = contrast[r]
                m += 1
        top = 0.0
        if m:
            top = np.sort(scratch[:m])[max(int(np.rint(0.9 * (m - 1))), 0)]
        for r in range(starts[g], end):
            top_c[r] = top
    ok = np.empty(t_rows, np.bool_)
    for r in range(t_rows):
        ok[r] = (keep[r] and frames[5, r] >= min_cell_px and math.isfinite(s[r]) and abs(s[r]) < half[r] - step[r]
                 and contrast[r] > 8.0 and contrast[r] >= min_contrast_ratio * top_c[r])
    return robust_grouped_solve(jac, s, contrast, top_c, ok, vertical, starts, min_rows, min_per_direction)


@register_warm_up
def _warm_up() -> None:
    """Every kernel once on a tiny input of the pipeline's argument types."""
    tag_of = frozen(np.array([0, 0, 1, 1], np.int64))
    uv = frozen(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))
    nu = frozen(np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]))
    boundary_rows(np.tile([10.0, 0.0, 5.0, 0.0, 10.0, 5.0, 0.0, 0.0], (2, 1)), tag_of, uv, nu)
    jac, starts = np.eye(4, 10), frozen(np.array([0, 2], np.int64))
    grouped_normal_equations(jac, np.ones(4), np.ones(4), starts)
    grouped_residuals(jac, np.ones(4), np.zeros((2, 10)), starts)
    grouped_solve(jac, np.ones(4), np.ones(4), starts, 1, True)
    flags = np.ones(4, np.bool_)
    robust_grouped_solve(jac, np.ones(4), np.ones(4), np.ones(4), flags, flags, starts, 1, 1)
    img = np.zeros((16, 16), np.uint8)
    img[:, 8:] = 200
    h = np.tile([1.0, 0.0, 4.0, 0.0, 1.0, 4.0, 0.0, 0.0], (2, 1))
    edge_fit_round(frozen(img), h, tag_of, uv, nu, flags, flags.copy(), starts, 3.0, 5, 2.0, 0.7, 1, 1)
