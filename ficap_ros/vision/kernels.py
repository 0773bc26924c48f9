"""The corner stage's per-pixel kernel, compiled: image profiles across an edge and the area
location of the step on each (``ficap_ros.vision.edges``: the line pass, ``step_offset``; through it
the border unbias and the cell-edge fit of ``ficap_ros.vision.corners``).

A profile is ``2 k + 1`` samples at ``c + j d`` (j = -k..k) of an 8-bit grey image, sampled as
``cv2.remap`` samples it with ``INTER_LINEAR`` and ``BORDER_REPLICATE`` (positions rounded to 1/32
px, fixed-point weights, values rounded to a grey level), so a profile holds the same values as
OpenCV's. Positions are float32, computed as ``c + d * j`` in float32, as the callers' sample maps
are.

The step's area location: dark level d from the profile's two inner samples, light level l from its
two outer ones, the edge at ``half`` minus the trapezoid integral of the clipped normalised profile
(I - d) / (l - d) times the sample spacing (``edges``' module docstring).

``edge_lines`` is the line pass's per-side work on top of it: a side's profiles, their weights and
the robust straight-line fit through their steps (``edges._edge_pass``).

``boundary_rows`` places the cell-edge fit's boundary samples in the image through their tags'
homographies, with the rows of its linearised model; ``grouped_normal_equations`` and
``grouped_residuals`` are its per-tag weighted
least squares (``corners._solve_grouped``): each tag's normal equations accumulated over its rows,
and the residuals of each tag's solution.
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up

__all__ = ["area_steps", "edge_lines", "boundary_rows", "frozen", "grouped_normal_equations", "grouped_residuals"]

#: ``cv2.remap``'s sub-pixel positions per px (``INTER_TAB_SIZE``) and its weights' scale bits
#: (``INTER_REMAP_COEF_BITS``).
_TAB_SIZE = 32
_COEF_BITS = 15


def frozen(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a``: the kernels take their images and tables read-only, so one
    compiled version serves writable and read-only arrays alike (numba compiles one per flag)."""
    view = a.view()
    view.setflags(write=False)
    return view


@njit(inline="always")
def _remap_sample(img: np.ndarray, x: np.float32, y: np.float32, clamp: bool) -> int:
    """One ``cv2.remap`` INTER_LINEAR, BORDER_REPLICATE sample of the uint8 image at (x, y).

    The position is rounded to 1/32 px (half to even); the weights of the four pixels are the
    products of (32 - f, f) along each axis times 32, which sum to 2^15 exactly, and the value is
    their sum rounded (+2^14, >> 15). Pixels beyond the image are its nearest edge pixel's (with
    ``clamp``; without, the caller knows all four lie inside)."""
    sx = int(np.rint(x * np.float32(_TAB_SIZE)))
    sy = int(np.rint(y * np.float32(_TAB_SIZE)))
    fx, fy = sx & (_TAB_SIZE - 1), sy & (_TAB_SIZE - 1)
    x0, y0 = sx >> 5, sy >> 5
    xa, xb, ya, yb = x0, x0 + 1, y0, y0 + 1
    if clamp:
        h, w = img.shape
        xa, xb = min(max(xa, 0), w - 1), min(max(xb, 0), w - 1)
        ya, yb = min(max(ya, 0), h - 1), min(max(yb, 0), h - 1)
    gx, gy = _TAB_SIZE - fx, _TAB_SIZE - fy
    total = ((int(img[ya, xa]) * gx + int(img[ya, xb]) * fx) * gy
             + (int(img[yb, xa]) * gx + int(img[yb, xb]) * fx) * fy) * _TAB_SIZE
    return (total + (1 << (_COEF_BITS - 1))) >> _COEF_BITS


@njit(inline="always")
def _area_step(img: np.ndarray, cx: np.float32, cy: np.float32, dx: np.float32, dy: np.float32, k: int,
               half: float, step: float, vals: np.ndarray) -> tuple[float, float, bool]:
    """One profile's step (``area_steps``): (offset, contrast, inside); ``vals`` (2 k + 1,) scratch."""
    s_len = 2 * k + 1
    h, w = img.shape
    # The samples lie on a segment: its ends say whether every sample and its 2 x 2 pixels do.
    x_lo, y_lo = cx - dx * np.float32(k), cy - dy * np.float32(k)
    x_hi, y_hi = cx + dx * np.float32(k), cy + dy * np.float32(k)
    inside = (min(x_lo, x_hi) >= 0 and min(y_lo, y_hi) >= 0 and max(x_lo, x_hi) <= w - 1
              and max(y_lo, y_hi) <= h - 1)
    clamp = not (min(x_lo, x_hi) >= 1 and min(y_lo, y_hi) >= 1 and max(x_lo, x_hi) <= w - 3
                 and max(y_lo, y_hi) <= h - 3)
    for j in range(s_len):
        vals[j] = _remap_sample(img, cx + dx * np.float32(j - k), cy + dy * np.float32(j - k), clamp)
    dark = 0.5 * (vals[0] + vals[1])
    contrast = 0.5 * (vals[s_len - 1] + vals[s_len - 2]) - dark
    scale = contrast if contrast > 0 else 1.0
    area = 0.0
    for j in range(s_len):
        f = min(max((vals[j] - dark) / scale, 0.0), 1.0)
        area += 0.5 * f if j == 0 or j == s_len - 1 else f
    return half - area * step, contrast, inside


@njit
def area_steps(img: np.ndarray, cx: np.ndarray, cy: np.ndarray, dx: np.ndarray, dy: np.ndarray, k: int,
               half: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The step on each profile: its area location and contrast.

    Args:
        img: (H, W) uint8 image.
        cx, cy: (P,) float32 each profile's centre.
        dx, dy: (P,) float32 one sample step along the profile, toward the light side.
        k: samples each way from the centre (2 k + 1 in all).
        half, step: (P,) float64 the window's half-length and the sample spacing, px
            (``half = k step``).

    Returns:
        (offset (P,): the step's place, px from the centre toward the light side; contrast (P,):
        light minus dark level, grey levels; inside (P,) bool: every sample within the image's
        pixel centres).
    """
    n = len(cx)
    offset = np.empty(n)
    contrast = np.empty(n)
    inside = np.empty(n, np.bool_)
    vals = np.empty(2 * k + 1)
    for p in range(n):
        offset[p], contrast[p], inside[p] = _area_step(img, cx[p], cy[p], dx[p], dy[p], k, half[p], step[p], vals)
    return offset, contrast, inside


@njit
def edge_lines(img: np.ndarray, a: np.ndarray, d: np.ndarray, nrm: np.ndarray, half: np.ndarray, t: np.ndarray,
               k: int, check_inside: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The line pass on every side: profiles across it, their weights, a robust line through their
    steps (``edges._edge_pass``; the rules in ``_profile_weights`` and ``_robust_line``).

    Args:
        img: (H, W) uint8 image.
        a, d, nrm: (R, 2) each side's start, vector to its end and outward unit normal.
        half: (R,) each side's window half-length, px (the samples ``half / k`` apart).
        t: (M,) the profiles' places along a side, fractions of its length.
        k: samples each way across (2 k + 1).
        check_inside: drop profiles reaching off the image (False when no side comes near its
            border).

    Returns:
        (normal (R, 2): unit normal of each fitted line, rho (R,): its offset, normal . p = rho
        on it; kept (R,): profiles the fit kept).
    """
    n_r, m = len(a), len(t)
    normal = np.empty((n_r, 2))
    rho = np.empty(n_r)
    kept = np.empty(n_r, np.int64)
    vals = np.empty(2 * k + 1)
    s = np.empty(m)
    c = np.empty(m)
    w = np.empty(m)
    along = np.empty(m)
    resid = np.empty(m)
    scratch = np.empty(m)
    for r in range(n_r):
        step = half[r] / k
        length = max(math.sqrt(d[r, 0] * d[r, 0] + d[r, 1] * d[r, 1]), 1e-9)
        dx, dy = np.float32(nrm[r, 0] * step), np.float32(nrm[r, 1] * step)
        for i in range(m):
            cx, cy = np.float32(a[r, 0] + d[r, 0] * t[i]), np.float32(a[r, 1] + d[r, 1] * t[i])
            s[i], c[i], inside = _area_step(img, cx, cy, dx, dy, k, half[r], step, vals)
            w[i] = 0.0 if check_inside and not inside else 1.0
            along[i] = t[i] * length
        _profile_weights(s, c, w, half[r], step, scratch)
        # The line's point is placed at the weighted mean place of the profiles before the
        # rejection, with the refitted line's offset there.
        sw = swx = 0.0
        for i in range(m):
            sw += w[i]
            swx += w[i] * along[i]
        along0 = swx / max(sw, 1e-12)
        alpha, beta, kept[r] = _robust_line(along, s, w, resid, scratch)
        ux, uy = d[r, 0] / length, d[r, 1] / length
        px = a[r, 0] + ux * along0 + nrm[r, 0] * alpha
        py = a[r, 1] + uy * along0 + nrm[r, 1] * alpha
        nx, ny = nrm[r, 0] - ux * beta, nrm[r, 1] - uy * beta
        norm = math.sqrt(nx * nx + ny * ny)
        normal[r, 0], normal[r, 1] = nx / norm, ny / norm
        rho[r] = normal[r, 0] * px + normal[r, 1] * py
    return normal, rho, kept


@njit(inline="always")
def _masked_median(x: np.ndarray, mask: np.ndarray, scratch: np.ndarray) -> float:
    """``np.median`` of the entries of ``x`` where ``mask`` (the middle one, or the mean of the
    middle two); 0.0 where there are none. ``scratch``: as long as ``x`` (an insertion sort: a
    side has a few dozen profiles)."""
    n = 0
    for i in range(len(x)):
        if mask[i]:
            v = x[i]
            j = n
            while j > 0 and scratch[j - 1] > v:
                scratch[j] = scratch[j - 1]
                j -= 1
            scratch[j] = v
            n += 1
    if n == 0:
        return 0.0
    return 0.5 * (scratch[(n - 1) // 2] + scratch[n // 2])


@njit(inline="always")
def _profile_weights(s: np.ndarray, c: np.ndarray, w: np.ndarray, half: float, step: float,
                     scratch: np.ndarray) -> None:
    """Each profile's weight in its side's fit, in place on ``w`` (1 or 0 on entry: inside the
    image): its contrast; 0 for weak or inverted profiles (under 0.3 of the side's median positive
    contrast or 8 grey levels) and for an edge at the window's end."""
    med_c = _masked_median(c, c > 0, scratch)
    limit = half - max(step, 0.25)
    for i in range(len(s)):
        good = c[i] > 0.3 * med_c and c[i] > 8.0 and abs(s[i]) < limit
        w[i] = c[i] * w[i] if good else 0.0


@njit(inline="always")
def _robust_line(x: np.ndarray, s: np.ndarray, w: np.ndarray, resid: np.ndarray,
                 scratch: np.ndarray) -> tuple[float, float, int]:
    """Weighted line s = alpha + beta (x - x_mean), one round of 3-sigma (MAD, at least 0.05 px)
    rejection, refitted: (alpha, beta, profiles kept); ``w`` updated in place, ``resid`` and
    ``scratch`` scratch."""
    m = len(x)
    alpha = beta = 0.0
    for round_ in range(2):
        sw = swx = sws = 0.0
        for i in range(m):
            sw += w[i]
            swx += w[i] * x[i]
            sws += w[i] * s[i]
        sw = max(sw, 1e-12)
        xm, alpha = swx / sw, sws / sw
        num = den = 0.0
        for i in range(m):
            dx = x[i] - xm
            num += w[i] * dx * s[i]
            den += w[i] * dx * dx
        beta = num / max(den, 1e-12)
        if round_ == 1:
            break
        for i in range(m):
            resid[i] = abs(s[i] - alpha - beta * (x[i] - xm))
        limit = max(3.0 * 1.4826 * _masked_median(resid, w > 0, scratch), 0.05)
        for i in range(m):
            if resid[i] > limit:
                w[i] = 0.0
    kept = 0
    for i in range(m):
        kept += w[i] > 0
    return alpha, beta, kept


@njit
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


@njit
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


@njit
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


@register_warm_up
def _warm_up() -> None:
    """``area_steps`` once on a small step image (the pipeline's argument types)."""
    img = np.zeros((16, 16), np.uint8)
    img[:, 8:] = 200
    img = frozen(img)
    one = np.ones(2, np.float32)
    area_steps(img, 8 * one, 8 * one, 0.25 * one, 0 * one, 8, np.full(2, 2.0), np.full(2, 0.25))
    corners = np.array([[4.0, 4.0], [12.0, 4.0], [12.0, 12.0], [4.0, 12.0]])
    a, d = corners, np.roll(corners, -1, axis=0) - corners
    nrm = np.column_stack([d[:, 1], -d[:, 0]]) / 8.0
    edge_lines(img, a, d, nrm, np.full(4, 1.0), frozen(np.linspace(0.15, 0.85, 6)), 4, True)
    tag_of = frozen(np.array([0, 0, 1, 1], np.int64))
    uv = frozen(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))
    nu = frozen(np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]))
    boundary_rows(np.tile([10.0, 0.0, 5.0, 0.0, 10.0, 5.0, 0.0, 0.0], (2, 1)), tag_of, uv, nu)
    jac, starts = np.eye(4, 10), frozen(np.array([0, 2], np.int64))
    grouped_normal_equations(jac, np.ones(4), np.ones(4), starts)
    grouped_residuals(jac, np.ones(4), np.zeros((2, 10)), starts)
