"""The corner stage's tag-level compiled kernels: the cell-edge fit
(``ficap_ros.vision.corners.fit_tag_edges``) and the border unbias before it
(``ficap_ros.vision.corners.unbias_corners_edge``: ``border_unbias``, the whole step in one call),
and the noise ratio that picks the tags for the photometric fit after it
(``ficap_ros.vision.tag_noise.noise_ratios``: ``tag_noise_ratios``).

``boundary_rows`` places the fit's boundary samples in the image through their tags' homographies,
with the rows of its linearised model; ``grouped_normal_equations``, ``grouped_solve`` and
``grouped_residuals`` are its per-tag weighted least squares: each tag's normal equations
accumulated over its rows, each tag's column-scaled solve (LAPACK's ``gesv``, as
``np.linalg.solve``: the same numbers), and the residuals of each tag's solution;
``robust_grouped_solve`` is the fit's robust step around them; ``edge_fit_round`` one whole
sample-and-solve round: the boundaries placed, their steps measured (``kernels.area_steps``, so
the profiles hold ``cv2.remap``'s values), each tag's clean contrast, the usable samples and the
robust step; ``edge_fit`` the fit's rounds in one call. Kernels divide as numpy does
(``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.kernels import _masked_median, area_steps, frozen

__all__ = ["border_unbias", "boundary_rows", "edge_fit", "edge_fit_round", "tag_noise_ratios",
           "grouped_normal_equations", "grouped_residuals", "grouped_solve",
           "robust_grouped_solve", "tag_homography"]


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
def grouped_normal_equations(jac: np.ndarray, rhs: np.ndarray, w: np.ndarray, starts: np.ndarray,
                             n_dense: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted normal equations per contiguous group of rows.

    The columns from ``n_dense`` on are indicator columns: each row holds at most one nonzero
    among them (the cell-edge fit's edge shifts: -1 in its boundary direction's column), so the
    sums skip their structural zeros. With finite rows, weights and measurements the sums are
    bit for bit those over every column (adding a product with a zero factor leaves a sum
    unchanged); a non-finite row leaves the entries it touches non-finite, as the full sums do.

    Args:
        jac: (T, P) float64 rows of the linear model.
        rhs: (T,) float64 measurements.
        w: (T,) float64 row weights (0: the row is left out).
        starts: (n,) int64 first row of each group, ascending (group g: rows starts[g] to
            starts[g + 1], the last to T).
        n_dense: the leading columns summed in full (P: every column).

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
            tail = -1  # the row's nonzero indicator column
            for i in range(n_dense, p):
                if jac[r, i] != 0.0:
                    tail = i
                    break
            for i in range(n_dense):
                wji = wr * jac[r, i]
                atb[g, i] += wji * rhs[r]
                for j in range(i, n_dense):
                    ata[g, i, j] += wji * jac[r, j]
                if tail >= 0:
                    ata[g, i, tail] += wji * jac[r, tail]
            if tail >= 0:
                wji = wr * jac[r, tail]
                atb[g, tail] += wji * rhs[r]
                ata[g, tail, tail] += wji * jac[r, tail]
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
def grouped_solve(jac: np.ndarray, rhs: np.ndarray, w: np.ndarray, starts: np.ndarray, n_dense: int,
                  min_rows: int, residuals: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least squares per contiguous group of rows (groups as ``grouped_normal_equations``'s).

    Each group's normal equations are scaled by their diagonal's square roots d (the parameters
    differ in size by orders of magnitude), solved by ``np.linalg.solve`` (LAPACK ``gesv``, the
    routine numpy's solve calls, so the same numbers) and unscaled. A group is solved when it has
    ``min_rows`` weighted rows, every parameter is touched by one (a zero diagonal makes the system
    exactly singular) and its solution is finite. A singular system leaves its group unsolved at 0,
    a non-finite one (a non-finite row) at NaN, as numpy's solve leaves them.

    Args:
        jac, rhs, w, starts, n_dense: as ``grouped_normal_equations``'s.
        min_rows: the least weighted rows of a solved group.
        residuals: also return rhs - jac @ solution per row (else an empty array).

    Returns:
        (solutions (n, P), solved (n,) bool, residuals (T,) or (0,)).
    """
    ata, atb, rows = grouped_normal_equations(jac, rhs, w, starts, n_dense)
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
                         ok: np.ndarray, vertical: np.ndarray, starts: np.ndarray, n_dense: int,
                         min_rows: int, min_per_direction: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell-edge fit's robust step per tag: weights
    (contrast / max(tag contrast, 1))^2 on the ``ok`` rows, a solve (``grouped_solve``), the rows
    beyond 3.5 robust sigmas (1.4826 times the median absolute residual of the group's ``ok``
    rows; at least 0.05) dropped, a second solve of the groups that lost a weighted row (the others'
    normal equations are unchanged: their first solution stands). A group is solved when both
    boundary directions keep ``min_per_direction`` weighted rows.

    Args:
        jac: (T, P) rows of the linear model; s: (T,) measured offsets; contrast, top_c: (T,) each
            row's contrast and its tag's clean contrast; ok: (T,) bool usable rows.
        vertical: (T,) bool rows of vertical boundaries (tag x direction).
        starts: (n,) int64 each group's first row (groups as ``grouped_normal_equations``'s).
        n_dense: the columns before the indicator columns (``grouped_normal_equations``).
        min_rows, min_per_direction: the least weighted rows in all and per direction.

    Returns:
        (solutions (n, P), solved (n,) bool, the rows kept (T,) bool).
    """
    t_rows, n = len(s), len(starts)
    w = np.empty(t_rows)
    for r in range(t_rows):
        q = contrast[r] / max(top_c[r], 1.0)
        w[r] = q * q if ok[r] else 0.0
    first, first_solved, resid = grouped_solve(jac, s, w, starts, n_dense, min_rows, True)
    keep = np.empty(t_rows, np.bool_)
    scratch = np.empty(t_rows)
    again = np.zeros(n, np.bool_)  # groups that lost a weighted row
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        m = _gather_finite(resid, ok, starts[g], end, scratch)
        for i in range(m):  # |resid| is finite where resid is
            scratch[i] = abs(scratch[i])
        med = _median_of_sorted(np.sort(scratch[:m])) if m else 0.0
        limit = max(3.5 * (1.4826 * med), 0.05)
        for r in range(starts[g], end):
            keep[r] = ok[r] and abs(resid[r]) <= limit
            if not keep[r]:
                again[g] = again[g] or w[r] > 0
                w[r] = 0.0
    # A group that kept every weighted row has the same normal equations again: its first
    # solution is the second's, so only the others are solved again.
    w_again = np.empty(t_rows)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        for r in range(starts[g], end):
            w_again[r] = w[r] if again[g] else 0.0
    sol, solved, _ = grouped_solve(jac, s, w_again, starts, n_dense, min_rows, False)
    for g in range(n):
        if not again[g]:
            sol[g] = first[g]
            solved[g] = first_solved[g]
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t_rows
        n_vertical = n_used = 0
        for r in range(starts[g], end):
            if w[r] > 0:
                n_used += 1
                n_vertical += vertical[r]
        solved[g] = solved[g] and n_vertical >= min_per_direction and n_used - n_vertical >= min_per_direction
    return sol, solved, keep


@njit(inline="always", error_model="numpy")
def _gather_finite(values: np.ndarray, mask: np.ndarray, lo: int, hi: int, out: np.ndarray) -> int:
    """Copies the finite ``values[lo:hi]`` where ``mask`` is set to the start of ``out``; their
    count."""
    m = 0
    for r in range(lo, hi):
        if mask[r] and math.isfinite(values[r]):
            out[m] = values[r]
            m += 1
    return m


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
    robust step (``robust_grouped_solve``; the two edge-shift columns are indicator columns, each
    row holding -1 in its boundary direction's only).

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
        m = _gather_finite(contrast, keep, starts[g], end, scratch)
        top = 0.0
        if m:
            top = np.sort(scratch[:m])[max(int(np.rint(0.9 * (m - 1))), 0)]
        for r in range(starts[g], end):
            top_c[r] = top
    ok = np.empty(t_rows, np.bool_)
    for r in range(t_rows):
        ok[r] = (keep[r] and frames[5, r] >= min_cell_px and math.isfinite(s[r]) and abs(s[r]) < half[r] - step[r]
                 and contrast[r] > 8.0 and contrast[r] >= min_contrast_ratio * top_c[r])
    return robust_grouped_solve(jac, s, contrast, top_c, ok, vertical, starts, 8, min_rows, min_per_direction)


@njit(error_model="numpy")
def edge_fit(img: np.ndarray, h: np.ndarray, tag_of: np.ndarray, uv: np.ndarray, nu: np.ndarray,
             starts: np.ndarray, iterations: int, search_px: float, k: int, min_cell_px: float,
             min_contrast_ratio: float, min_rows: int, min_per_direction: int) -> tuple[np.ndarray, np.ndarray]:
    """The cell-edge fit's rounds (``corners.fit_tag_edges``): ``iterations`` rounds of
    ``edge_fit_round`` from homographies ``h`` (N, 8), updated in place where a round solved a
    tag, the last round on the samples the one before it trusted.

    Returns:
        (solved (N,) bool: the last round solved the tag; delta (N,): its two directions' mean
        edge shift, px, NaN where not solved).
    """
    n, t_rows = len(h), len(tag_of)
    keep = np.ones(t_rows, np.bool_)
    vertical = np.empty(t_rows, np.bool_)
    for r in range(t_rows):
        vertical[r] = abs(nu[r, 0]) > 0.5
    delta = np.full(n, np.nan)
    fitted = np.zeros(n, np.bool_)
    for it in range(iterations):
        sol, solved, ok = edge_fit_round(img, h, tag_of, uv, nu, vertical, keep, starts, search_px, k,
                                         min_cell_px, min_contrast_ratio, min_rows, min_per_direction)
        for g in range(n):
            for j in range(8):
                h[g, j] = h[g, j] + (sol[g, j] if solved[g] else 0.0)
            delta[g] = (sol[g, 8] + sol[g, 9]) / 2.0 if solved[g] else np.nan
        fitted = solved
        if it == iterations - 2:
            keep = ok
    return fitted, delta


@njit(inline="always", error_model="numpy")
def _cell_px(c: np.ndarray) -> float:
    """A tag's cell width, px: its shortest side (corners ``c`` (4, 2)) over the 8 cells across."""
    cell = np.inf
    for j in range(4):
        e = (j + 1) % 4
        ex, ey = c[e, 0] - c[j, 0], c[e, 1] - c[j, 1]
        cell = min(cell, math.sqrt(ex * ex + ey * ey))
    return cell / 8.0


#: Side k's previous side (the line it meets at corner k).
_PREV = (3, 0, 1, 2)


@njit(inline="always", error_model="numpy")
def tag_homography(c: np.ndarray, out: np.ndarray) -> bool:
    """``geometry.tag36h11.tag_homographies`` of one tag's corners (4, 2) into ``out`` (3, 3), the
    same arithmetic; False (``out`` unset) for a degenerate quadrilateral."""
    x0, y0, x1, y1 = c[0, 0], c[0, 1], c[1, 0], c[1, 1]
    x2, y2, x3, y3 = c[2, 0], c[2, 1], c[3, 0], c[3, 1]
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    den = dx1 * dy2 - dx2 * dy1
    if not (math.isfinite(den) and den != 0.0):
        return False
    g = (dx3 * dy2 - dx2 * dy3) / den
    h = (dx1 * dy3 - dx3 * dy1) / den
    inv = 1.0 / 8.0
    out[0, 0], out[0, 1], out[0, 2] = (x1 - x0 + g * x1) * inv, (x3 - x0 + h * x3) * inv, x0
    out[1, 0], out[1, 1], out[1, 2] = (y1 - y0 + g * y1) * inv, (y3 - y0 + h * y3) * inv, y0
    out[2, 0], out[2, 1], out[2, 2] = g * inv, h * inv, 1.0
    return True


@njit(inline="always", error_model="numpy")
def _through(hm: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """Tag point (u, v) through homography ``hm`` (3, 3) (``tag36h11.apply_homographies``)."""
    x = hm[0, 0] * u + hm[0, 1] * v + hm[0, 2]
    y = hm[1, 0] * u + hm[1, 1] * v + hm[1, 2]
    w = hm[2, 0] * u + hm[2, 1] * v + hm[2, 2]
    return x / w, y / w


@njit(inline="always", error_model="numpy")
def _median_of_sorted(srt: np.ndarray) -> float:
    """``np.median`` of a sorted non-empty array ((a + b) / 2 of the middle two)."""
    m = len(srt)
    return 0.5 * (srt[(m - 1) // 2] + srt[m // 2])


@njit(error_model="numpy")
def _border_midlines(img: np.ndarray, p_in: np.ndarray, p_out: np.ndarray, nk: np.ndarray, search_px: float,
                     window_cells: float, k: int, min_cell_px: float,
                     min_contrast_ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The border unbias's measurement across each white data cell: (midline (T,), valid (T,),
    width0 (T,)) (the tests' numpy reference: ``_border_midlines_numpy``)."""
    t = len(p_in)
    width0, half, step = np.empty(t), np.empty(t), np.empty(t)
    cx, cy = np.empty(2 * t, np.float32), np.empty(2 * t, np.float32)
    dx, dy = np.empty(2 * t, np.float32), np.empty(2 * t, np.float32)
    for r in range(t):
        width0[r] = nk[r, 0] * (p_out[r, 0] - p_in[r, 0]) + nk[r, 1] * (p_out[r, 1] - p_in[r, 1])
        w = window_cells * width0[r]
        w = search_px if search_px < w else w  # NaN stays NaN
        half[r] = 0.75 if 0.75 > w else w
        step[r] = half[r] / k
        for j, (px, py, sign) in enumerate(((p_in[r, 0], p_in[r, 1], -1.0), (p_out[r, 0], p_out[r, 1], 1.0))):
            q = r + j * t
            cx[q], cy[q] = np.float32(px), np.float32(py)
            dx[q], dy[q] = np.float32(sign * nk[r, 0] * step[r]), np.float32(sign * nk[r, 1] * step[r])
    half2, step2 = np.concatenate((half, half)), np.concatenate((step, step))
    first, first_c, _ = area_steps(img, cx, cy, dx, dy, k, half2, step2)
    s1 = np.empty(t)
    for r in range(t):
        v = first[r]
        s1[r] = -half[r] if v < -half[r] else (half[r] if v > half[r] else v)
        cx[r] = np.float32(p_in[r, 0] - nk[r, 0] * s1[r])
        cy[r] = np.float32(p_in[r, 1] - nk[r, 1] * s1[r])
    s2, c_inner, _ = area_steps(img, cx[:t], cy[:t], dx[:t], dy[:t], k, half, step)
    midline, valid = np.empty(t), np.empty(t, np.bool_)
    for r in range(t):
        o1, c_outer = first[t + r], first_c[t + r]
        inner = (nk[r, 0] * p_in[r, 0] + nk[r, 1] * p_in[r, 1]) - s1[r] - s2[r]
        outer = (nk[r, 0] * p_out[r, 0] + nk[r, 1] * p_out[r, 1]) + o1
        limit = half[r] - step[r]
        valid[r] = (math.isfinite(inner) and math.isfinite(outer) and width0[r] >= min_cell_px
                    and abs(s2[r]) < limit and abs(o1) < limit and c_outer > 8.0
                    and c_inner[r] >= min_contrast_ratio * c_outer)
        midline[r] = 0.5 * (inner + outer)
    return midline, valid, width0


@njit(error_model="numpy")
def _border_inliers(d: np.ndarray, valid: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """The border unbias's inliers: the valid finite samples within 3 MAD (at least 0.1 px) of
    their tag's median (medians of each tag's finite valid samples, 0 without any)."""
    t, n = len(d), len(starts)
    keep = np.zeros(t, np.bool_)
    scratch = np.empty(t)
    for g in range(n):
        end = starts[g + 1] if g + 1 < n else t
        m = _gather_finite(d, valid, starts[g], end, scratch)
        med = _median_of_sorted(np.sort(scratch[:m])) if m else 0.0
        for i in range(m):  # the same samples: |d - med| is finite where d is
            scratch[i] = abs(scratch[i] - med)
        mad = 1.4826 * (_median_of_sorted(np.sort(scratch[:m])) if m else 0.0)
        limit = max(3.0 * mad, 0.1)
        for r in range(starts[g], end):
            keep[r] = valid[r] and math.isfinite(d[r]) and abs(d[r] - med) <= limit
    return keep


@njit(error_model="numpy")
def _pooled_corners(d: np.ndarray, keep: np.ndarray, tag_of: np.ndarray, side: np.ndarray, nrm: np.ndarray,
                    rho: np.ndarray, prior: float) -> tuple[np.ndarray, np.ndarray]:
    """Each side's offset (its mean kept sample, shrunk toward its tag's mean)
    and the corners where the moved sides meet (``edges.intersect_sides``): (delta (N, 4),
    corners (N, 4, 2))."""
    n = len(nrm)
    side_sum, side_cnt = np.zeros((n, 4)), np.zeros((n, 4))
    for r in range(len(d)):
        side_sum[tag_of[r], side[r]] += d[r] if keep[r] else 0.0
        side_cnt[tag_of[r], side[r]] += 1.0 if keep[r] else 0.0
    delta, corners = np.empty((n, 4)), np.empty((n, 4, 2))
    moved = np.empty(4)
    for g in range(n):
        # As numpy sums a row of four: the first, plus the other three added in turn.
        tag_sum = side_sum[g, 0] + ((side_sum[g, 1] + side_sum[g, 2]) + side_sum[g, 3])
        tag_cnt = side_cnt[g, 0] + ((side_cnt[g, 1] + side_cnt[g, 2]) + side_cnt[g, 3])
        tag_mean = tag_sum / max(tag_cnt, 1e-12) if tag_cnt > 0 else 0.0
        for j in range(4):
            delta[g, j] = (side_sum[g, j] + prior * tag_mean) / (side_cnt[g, j] + prior)
            moved[j] = rho[g, j] + delta[g, j]
        for j in range(4):
            p = _PREV[j]
            det = nrm[g, p, 0] * nrm[g, j, 1] - nrm[g, p, 1] * nrm[g, j, 0]
            det = det if abs(det) > 1e-9 else 1e-9
            corners[g, j, 0] = (moved[p] * nrm[g, j, 1] - nrm[g, p, 1] * moved[j]) / det
            corners[g, j, 1] = (nrm[g, p, 0] * moved[j] - moved[p] * nrm[g, j, 0]) / det
    return delta, corners


@njit(error_model="numpy")
def border_unbias(img: np.ndarray, c_in: np.ndarray, nrm: np.ndarray, rho: np.ndarray, hom: np.ndarray,
                  tag_of: np.ndarray, side: np.ndarray, uv: np.ndarray, side_out: np.ndarray, starts: np.ndarray,
                  search_px: float, window_cells: float, k: int, min_cell_px: float, min_contrast_ratio: float,
                  prior: float) -> np.ndarray:
    """The border unbias of ``corners.unbias_corners_edge`` (its docstring has the model), every tag
    in one call: each inner-edge sample and the outer-edge point one cell out through the tag's
    homography, both edges measured with the same window, the outliers (from the first round), then
    two rounds of each side's delta and the corners re-intersected, the cell width re-read from
    the corrected corners in the second. A tag whose correction exceeds a third of a cell (or 2 px),
    or whose corners are not finite or degenerate, keeps its input corners.

    Args:
        img: (H, W) uint8 image (read-only view: ``kernels.frozen``).
        c_in: (N, 4, 2) the line pass's corners; nrm, rho: their side lines (``edges.side_lines``);
            hom: (N, 3, 3) their homographies (``tag36h11.tag_homographies``).
        tag_of, side, uv: (T,) each sample's tag and side, (T, 2) its place in tag cell units, tag
            after tag (``starts`` (N,): each tag's first sample).
        side_out: (4, 2) the tag-unit step from each side's inner edge to its outer edge.
        search_px, window_cells, k: the window (at most ``search_px``, ``window_cells`` of a cell,
            at least 0.75 px; 2 k + 1 samples).
        min_cell_px, min_contrast_ratio: a sample's least cell width and inner/outer contrast.
        prior: samples' worth of prior weight of a tag's mean delta on each side.

    Returns:
        (N, 4, 2) the corrected corners.
    """
    t, n = len(tag_of), len(c_in)
    nk, p_in, p_out = np.empty((t, 2)), np.empty((t, 2)), np.empty((t, 2))
    for r in range(t):
        g, j = tag_of[r], side[r]
        nk[r, 0], nk[r, 1] = nrm[g, j, 0], nrm[g, j, 1]
        p_in[r, 0], p_in[r, 1] = _through(hom[g], uv[r, 0], uv[r, 1])
        p_out[r, 0], p_out[r, 1] = _through(hom[g], uv[r, 0] + side_out[j, 0], uv[r, 1] + side_out[j, 1])
    midline, valid, width0 = _border_midlines(img, p_in, p_out, nk, search_px, window_cells, k, min_cell_px,
                                              min_contrast_ratio)
    d = np.empty(t)
    for r in range(t):
        d[r] = midline[r] + 0.5 * width0[r] - rho[tag_of[r], side[r]]
    keep = _border_inliers(d, valid, starts)
    delta, corners = _pooled_corners(d, keep, tag_of, side, nrm, rho, prior)
    hom2 = np.empty((n, 3, 3))
    usable = np.empty(n, np.bool_)
    for g in range(n):
        usable[g] = tag_homography(corners[g], hom2[g])
    for r in range(t):
        g, j = tag_of[r], side[r]
        width = np.nan
        if usable[g]:
            xi, yi = _through(hom2[g], uv[r, 0], uv[r, 1])
            xo, yo = _through(hom2[g], uv[r, 0] + side_out[j, 0], uv[r, 1] + side_out[j, 1])
            width = nk[r, 0] * (xo - xi) + nk[r, 1] * (yo - yi)
        d[r] = midline[r] + 0.5 * width - rho[g, j]
    delta, corners = _pooled_corners(d, keep, tag_of, side, nrm, rho, prior)
    out = c_in.copy()
    for g in range(n):
        cell = _cell_px(c_in[g])
        limit = min(cell / 3.0, 2.0)
        sane = usable[g]
        for j in range(4):
            sane = (sane and abs(delta[g, j]) <= limit and math.isfinite(corners[g, j, 0])
                    and math.isfinite(corners[g, j, 1]))
        if sane:
            out[g] = corners[g]
    return out


@njit(error_model="numpy")
def tag_noise_ratios(img: np.ndarray, corners: np.ndarray, hom: np.ndarray, black: np.ndarray,
                     centres_h: np.ndarray, mad_sd: float, min_contrast: float) -> np.ndarray:
    """Each tag's noise ratio (``tag_noise``'s module docstring): noise sd / (contrast sqrt(px per
    cell)), from the grey at the nearest pixel to each of its 64 cells' centres (the image's edge
    pixel for a centre outside it).

    Args:
        img: (H, W) uint8 image.
        corners: (N, 4, 2) the tags' corners; hom: (N, 3, 3) their homographies.
        black: (N, 64) bool each tag's cells, row-major [v, u] (True = black).
        centres_h: (64, 3) the cells' centres in tag cell units, homogeneous.
        mad_sd: MAD -> sd of a normal distribution; min_contrast: the least contrast divided by.

    Returns:
        (N,) ratios; infinite for a tag without a neighbouring pair of same-coloured cells.
    """
    n, (h_img, w_img) = len(corners), img.shape
    out = np.empty(n)
    grey, black_g = np.empty(64), np.empty(64, np.bool_)
    steps, same = np.empty(112), np.empty(112, np.bool_)
    scratch, dev = np.empty(112), np.empty(112)
    for g in range(n):
        for c in range(64):
            q0 = hom[g, 0, 0] * centres_h[c, 0] + hom[g, 0, 1] * centres_h[c, 1] + hom[g, 0, 2] * centres_h[c, 2]
            q1 = hom[g, 1, 0] * centres_h[c, 0] + hom[g, 1, 1] * centres_h[c, 1] + hom[g, 1, 2] * centres_h[c, 2]
            q2 = hom[g, 2, 0] * centres_h[c, 0] + hom[g, 2, 1] * centres_h[c, 1] + hom[g, 2, 2] * centres_h[c, 2]
            x = min(max(np.rint(q0 / q2), 0.0), w_img - 1.0)
            y = min(max(np.rint(q1 / q2), 0.0), h_img - 1.0)
            grey[c] = float(img[int(y), int(x)])
            black_g[c] = black[g, c]
        contrast = _masked_median(grey, ~black_g, scratch) - _masked_median(grey, black_g, scratch)
        i = 0
        for v in range(8):  # along u, then along v (row-major), as the numpy differences run
            for u in range(7):
                steps[i] = grey[8 * v + u + 1] - grey[8 * v + u]
                same[i] = black_g[8 * v + u + 1] == black_g[8 * v + u]
                i += 1
        for v in range(7):
            for u in range(8):
                steps[i] = grey[8 * (v + 1) + u] - grey[8 * v + u]
                same[i] = black_g[8 * (v + 1) + u] == black_g[8 * v + u]
                i += 1
        med = _masked_median(steps, same, scratch)
        for j in range(112):
            dev[j] = abs(steps[j] - med)
        noise_sd = mad_sd * _masked_median(dev, same, scratch) / math.sqrt(2.0)
        cell = _cell_px(corners[g])
        ratio = noise_sd / (max(contrast, min_contrast) * math.sqrt(max(cell, 1e-6)))
        out[g] = ratio if same.any() else np.inf
    return out


@register_warm_up
def _warm_up() -> None:
    """Every kernel once on a tiny input of the pipeline's argument types."""
    tag_of = frozen(np.array([0, 0, 1, 1], np.int64))
    uv = frozen(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))
    nu = frozen(np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]))
    boundary_rows(np.tile([10.0, 0.0, 5.0, 0.0, 10.0, 5.0, 0.0, 0.0], (2, 1)), tag_of, uv, nu)
    jac, starts = np.eye(4, 10), frozen(np.array([0, 2], np.int64))
    grouped_normal_equations(jac, np.ones(4), np.ones(4), starts, 8)
    grouped_residuals(jac, np.ones(4), np.zeros((2, 10)), starts)
    grouped_solve(jac, np.ones(4), np.ones(4), starts, 8, 1, True)
    flags = np.ones(4, np.bool_)
    robust_grouped_solve(jac, np.ones(4), np.ones(4), np.ones(4), flags, flags, starts, 8, 1, 1)
    img = np.zeros((16, 16), np.uint8)
    img[:, 8:] = 200
    h = np.tile([1.0, 0.0, 4.0, 0.0, 1.0, 4.0, 0.0, 0.0], (2, 1))
    edge_fit_round(frozen(img), h, tag_of, uv, nu, flags, flags.copy(), starts, 3.0, 5, 2.0, 0.7, 1, 1)
    corners = np.array([[[4.0, 4.0], [12.0, 4.0], [12.0, 12.0], [4.0, 12.0]]] * 2)
    edge_fit(frozen(img), h.copy(), tag_of, uv, nu, starts, 2, 3.0, 5, 2.0, 0.7, 1, 1)
    nrm = np.tile(np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]), (2, 1, 1))
    rho = np.einsum("nkd,nkd->nk", nrm, corners)
    hom = np.tile(np.eye(3), (2, 1, 1))
    side, side_out = frozen(np.array([0, 1, 2, 3], np.int64)), frozen(nrm[0].copy())
    border_unbias(frozen(img), corners, nrm, rho, hom, tag_of, side, uv, side_out, starts, 4.0, 0.6, 8, 2.0, 0.7, 3.0)
    cells = frozen(np.zeros((2, 64), np.bool_))
    tag_noise_ratios(frozen(img), corners, hom, cells, frozen(np.ones((64, 3))), 1.4826, 1.0)
