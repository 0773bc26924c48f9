"""The corner stage's per-pixel kernel, compiled: image profiles across an edge and the area
location of the step on each (``ficap_ros.vision.edges``: the line pass, ``step_offset``; through it
the border unbias and the cell-edge fit of ``ficap_ros.vision.corners``).

A profile is ``2 k + 1`` samples at ``c + j d`` (j = -k..k) of an 8-bit grey image, sampled as
``cv2.remap`` samples it with ``INTER_LINEAR`` and ``BORDER_REPLICATE`` (positions rounded to 1/32
px, fixed-point weights, values rounded to a grey level), so a profile holds the same values as
OpenCV's. Positions are float32, computed as ``c + d * j`` in float32, as the callers' sample maps
are. Every kernel divides as numpy does (``error_model="numpy"``): a degenerate input gives inf or
NaN, which the callers' checks refuse, never an exception.

The step's area location: dark level d from the profile's two inner samples, light level l from its
two outer ones, the edge at ``half`` minus the trapezoid integral of the clipped normalised profile
(I - d) / (l - d) times the sample spacing (``edges``' module docstring).

``edge_lines`` is the line pass's per-side work on top of it: a side's profiles, their weights and
the robust straight-line fit through their steps; ``line_pass`` the whole line pass of
``edges.refine_corners_edge_ok`` around it (each side's outward normal and window, the corners
where adjacent lines meet, the passes and the plausibility checks).

The cell-edge fit's kernels, built on ``area_steps``, are ``ficap_ros.vision.fit_kernels``.
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up

__all__ = ["area_steps", "edge_lines", "frozen", "line_pass"]

#: ``cv2.remap``'s sub-pixel positions per px (``INTER_TAB_SIZE``) and its weights' scale bits
#: (``INTER_REMAP_COEF_BITS``).
_TAB_SIZE = 32
_COEF_BITS = 15
#: Cells across a tag, border included (``geometry.tag36h11.TAG_CELLS``).
_TAG_CELLS = 8.0


def frozen(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a``: the kernels take their images and tables read-only, so one
    compiled version serves writable and read-only arrays alike (numba compiles one per flag)."""
    view = a.view()
    view.setflags(write=False)
    return view


@njit(inline="always", error_model="numpy")
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


@njit(inline="always", error_model="numpy")
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


@njit(error_model="numpy")
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


@njit(error_model="numpy")
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


@njit(inline="always", error_model="numpy")
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


@njit(inline="always", error_model="numpy")
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


@njit(inline="always", error_model="numpy")
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


@njit(error_model="numpy")
def line_pass(img: np.ndarray, c_init: np.ndarray, iterations: int, search_px: float, window_cells: float,
              t: np.ndarray, k: int, min_kept: int, max_shift_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The line pass (``edges.refine_corners_edge_ok``, the rules in ``edges``' module docstring).

    Args:
        img: (H, W) uint8 image.
        c_init: (N, 4, 2) float64 starting corners.
        iterations: search-and-fit passes, each from the previous pass's corners.
        search_px, window_cells: a side's window half-length is at most ``search_px`` and at most
            ``window_cells`` of the cell across it (at least 0.75 px).
        t: (M,) the profiles' places along a side, fractions of its length.
        k: samples each way across a side (2 k + 1).
        min_kept: profiles each side's fit must keep.
        max_shift_px: the furthest a refined corner may move (and a quarter of the shortest side).

    Returns:
        (corners (N, 4, 2), ok (N,)): a tag not refined keeps its starting corners.
    """
    n = c_init.shape[0]
    cell_px = np.empty(n)
    max_shift = np.empty(n)
    for g in range(n):
        total, shortest = 0.0, np.inf
        for s in range(4):
            e = (s + 1) % 4
            side = math.sqrt((c_init[g, e, 0] - c_init[g, s, 0]) ** 2 + (c_init[g, e, 1] - c_init[g, s, 1]) ** 2)
            total += side
            shortest = min(shortest, side)
        cell_px[g] = total / 4.0 / _TAG_CELLS
        max_shift[g] = min(max_shift_px, 0.25 * shortest)
    corners = c_init.copy()
    ok = np.ones(n, np.bool_)
    for _ in range(iterations):
        corners = _one_line_pass(img, corners, cell_px, search_px, window_cells, t, k, min_kept, ok)
    out = np.empty_like(c_init)
    for g in range(n):
        shift = 0.0
        finite = True
        for c in range(4):
            dx, dy = corners[g, c, 0] - c_init[g, c, 0], corners[g, c, 1] - c_init[g, c, 1]
            shift = max(shift, math.sqrt(dx * dx + dy * dy))
            finite = finite and math.isfinite(corners[g, c, 0]) and math.isfinite(corners[g, c, 1])
        ok[g] = ok[g] and finite and shift <= max_shift[g]
        out[g] = corners[g] if ok[g] else c_init[g]
    return out, ok


@njit(error_model="numpy")
def _one_line_pass(img: np.ndarray, corners: np.ndarray, cell_px: np.ndarray, search_px: float,
                   window_cells: float, t: np.ndarray, k: int, min_kept: int, ok: np.ndarray) -> np.ndarray:
    """One search-and-fit pass over the tags' 4N sides: each side's outward normal (away from the
    tag's centre, either handedness) and window (the cell across it: the tag's width along the
    normal / 8, at most ``cell_px``), a line per side (``edge_lines``), corners where adjacent
    lines meet. A tag whose lines meet at under ~12 degrees or keep fewer than ``min_kept``
    profiles keeps its corners and is marked not ``ok`` (in place)."""
    n = corners.shape[0]
    a = np.empty((4 * n, 2))
    d = np.empty((4 * n, 2))
    nrm = np.empty((4 * n, 2))
    half = np.empty(4 * n)
    h_img, w_img = img.shape
    lo, hi_x, hi_y = np.inf, -np.inf, -np.inf
    for g in range(n):
        mx = 0.25 * (corners[g, 0, 0] + corners[g, 1, 0] + corners[g, 2, 0] + corners[g, 3, 0])
        my = 0.25 * (corners[g, 0, 1] + corners[g, 1, 1] + corners[g, 2, 1] + corners[g, 3, 1])
        for s in range(4):
            r = 4 * g + s
            e, o1, o2 = (s + 1) % 4, (s + 2) % 4, (s + 3) % 4
            ax, ay = corners[g, s, 0], corners[g, s, 1]
            dx, dy = corners[g, e, 0] - ax, corners[g, e, 1] - ay
            length = max(math.hypot(dx, dy), 1e-9)
            nx, ny = dy / length, -dx / length
            if (ax + 0.5 * dx - mx) * nx + (ay + 0.5 * dy - my) * ny < 0:
                nx, ny = -nx, -ny
            ox = corners[g, o1, 0] + corners[g, o2, 0] - 2 * ax
            oy = corners[g, o1, 1] + corners[g, o2, 1] - 2 * ay
            width = abs(ox * nx + oy * ny) / 2.0
            cell_side = min(width / _TAG_CELLS, cell_px[g])
            half[r] = max(min(search_px, window_cells * cell_side), 0.75)
            a[r, 0], a[r, 1], d[r, 0], d[r, 1], nrm[r, 0], nrm[r, 1] = ax, ay, dx, dy, nx, ny
            lo = min(lo, ax, ay)
            hi_x, hi_y = max(hi_x, ax), max(hi_y, ay)
    # Profiles may reach off the image only when some corner lies within a window of its border.
    reach = half.max() + 1.0 if n else 1.0
    near = not (lo >= reach and hi_x <= w_img - 1 - reach and hi_y <= h_img - 1 - reach)
    normal, rho, kept = edge_lines(img, a, d, nrm, half, t, k, near)
    new = corners.copy()
    cs = np.empty((4, 2))  # every entry written before new[g] copies it
    for g in range(n):
        good = True
        for c in range(4):
            p, q = 4 * g + (c + 3) % 4, 4 * g + c
            a11, a12, r1 = normal[p, 0], normal[p, 1], rho[p]
            a21, a22, r2 = normal[q, 0], normal[q, 1], rho[q]
            det = a11 * a22 - a12 * a21
            if not abs(det) > 0.2 or kept[q] < min_kept:
                good = False
                det = 1.0
            cs[c, 0], cs[c, 1] = (r1 * a22 - a12 * r2) / det, (a11 * r2 - a21 * r1) / det
        if good:
            new[g] = cs
        else:
            ok[g] = False
    return new


@register_warm_up
def _warm_up() -> None:
    """``area_steps``, ``edge_lines`` and ``line_pass`` once on a small step image (the pipeline's
    argument types)."""
    img = np.zeros((16, 16), np.uint8)
    img[:, 8:] = 200
    img = frozen(img)
    one = np.ones(2, np.float32)
    area_steps(img, 8 * one, 8 * one, 0.25 * one, 0 * one, 8, np.full(2, 2.0), np.full(2, 0.25))
    corners = np.array([[4.0, 4.0], [12.0, 4.0], [12.0, 12.0], [4.0, 12.0]])
    a, d = corners, np.roll(corners, -1, axis=0) - corners
    nrm = np.column_stack([d[:, 1], -d[:, 0]]) / 8.0
    edge_lines(img, a, d, nrm, np.full(4, 1.0), frozen(np.linspace(0.15, 0.85, 6)), 4, True)
    line_pass(img, corners[None], 2, 3.0, 0.5, frozen(np.linspace(0.15, 0.85, 6)), 4, 3, 2.0)
