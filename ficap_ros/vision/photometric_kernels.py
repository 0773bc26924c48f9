"""The photometric corner fit's per-pixel work, compiled: which pixels it fits, and each tag's
Gauss-Newton steps (``ficap_ros.vision.photometric`` holds the model, its settings and the per-frame
set-up; this module only its loops).

The model, per pixel x of a tag with homography H (tag cell units -> image px), in its three steps:

1. the tag's pattern at (u, v) = H^-1(x): the black cells of the tag's padded table;
2. blurred in linear light: the coverage C of white, from the blurred cell shares along u and v
   (differences of normal CDFs with sds ``s |grad u|``, ``s |grad v|``; ``_black_coverage``), with
   black and white levels Lb, Lw planes over the tag: L = Lb + (Lw - Lb) C;
3. through the tone curve: grey = 255 f(L)^kappa, f the clipped sRGB curve (``_srgb_encode``),
   kappa a free exponent (``free_tone``).

Parameters per tag, as ``photometric``'s docstring: h (8, the homography), theta = (Lb0, Lb_u,
Lb_v, Lw0, Lw_u, Lw_v, log blur scale[, log tone exponent]). Every tag's fit is its own: the
kernel runs the tags one after the other, each through all its steps.
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.tone import SRGB_ENCODED_KNEE, SRGB_LINEAR_KNEE

__all__ = ["PAD", "select_pixels", "fit_steps", "fit_steps_moving", "coverage_moving", "model_rows_moving"]

#: Cells padded around the 8 x 8 tag in a tag's table (white: quiet zone and beyond), so the
#: 4 x 4 cells around any face pixel's nearest boundary stay inside it.
PAD = 3
#: Tag side in cells.
_CELLS = 8
#: Robust residual sds beyond which a pixel is dropped, and the least threshold (grey levels).
_OUTLIER_SDS = 4.0
_MIN_OUTLIER_GREY = 3.0
#: MAD -> sd of a normal distribution.
_MAD_SD = 1.4826
#: Boundaries further than this many blur sds count as fully on one side (ndtr(-9) = 1e-19).
_FAR_SDS = 9.0
#: 1 / sqrt(2 pi).
_INV_SQRT_2PI = 0.3989422804014327


@njit
def select_pixels(hom_inv: np.ndarray, boxes: np.ndarray, use: np.ndarray, reach: np.ndarray,
                  sat: np.ndarray, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of each used tag's face box within ``reach`` cells of a black/white cell boundary.

    Args:
        hom_inv: (N, 3, 3) inverse homographies (image px -> tag cells).
        boxes: (4, N) int64 face boxes x0, y0, x1, y1 (inclusive), inside the image.
        use: (K,) int64 the tags to select for, in order.
        reach: (N,) reach in cells (both colours within it, each way).
        sat: (N, S + 1, S + 1) int32 summed-area tables of each tag's padded black cells.
        max_pixels: most pixels a tag; more are thinned evenly (as ``np.linspace`` indices).

    Returns:
        (tag of each pixel, x, y) int64 arrays, tag after tag, each tag's pixels row by row.
    """
    cap = 0
    widest = 0
    for t in use:
        area = (boxes[2, t] - boxes[0, t] + 1) * (boxes[3, t] - boxes[1, t] + 1)
        cap += area
        widest = max(widest, area)
    tag = np.empty(cap, np.int64)
    xs = np.empty(cap, np.int64)
    ys = np.empty(cap, np.int64)
    near = np.empty(widest, np.int64)
    last = sat.shape[1] - 2
    n = 0
    for t in use:
        x0, y0, x1, y1 = boxes[0, t], boxes[1, t], boxes[2, t], boxes[3, t]
        width = x1 - x0 + 1
        count = _near_boundary(hom_inv[t], sat[t], x0, y0, x1, y1, reach[t], last, near)
        if count > max_pixels:
            step = (count - 1) / (max_pixels - 1)
            for k in range(max_pixels - 1):
                near[k] = near[int(k * step)]
            near[max_pixels - 1] = near[count - 1]
            count = max_pixels
        for k in range(count):
            tag[n] = t
            ys[n] = near[k] // width + y0
            xs[n] = near[k] % width + x0
            n += 1
    return tag[:n], xs[:n], ys[:n]


@njit
def _near_boundary(H: np.ndarray, sat: np.ndarray, x0: int, y0: int, x1: int, y1: int, reach: float,
                   last: int, out: np.ndarray) -> int:
    """The box's pixels on the tag's face (within 0.9 cell of the tag) whose cells within ``reach``
    each way hold both colours, as flat indices in the box into ``out``; returns how many."""
    width = x1 - x0 + 1
    count = 0
    for gy in range(y1 - y0 + 1):
        y = float(y0 + gy)
        for gx in range(width):
            x = float(x0 + gx)
            den = (H[2, 1] * y + H[2, 0] * x) + H[2, 2]
            u = ((H[0, 1] * y + H[0, 0] * x) + H[0, 2]) / den
            v = ((H[1, 1] * y + H[1, 0] * x) + H[1, 2]) / den
            if not (u > -0.9 and u < _CELLS + 0.9 and v > -0.9 and v < _CELLS + 0.9):
                continue
            lo_u = min(max(int(math.floor(u - reach)) + PAD, 0), last)
            hi_u = min(max(int(math.floor(u + reach)) + PAD, 0), last) + 1
            lo_v = min(max(int(math.floor(v - reach)) + PAD, 0), last)
            hi_v = min(max(int(math.floor(v + reach)) + PAD, 0), last) + 1
            black = sat[hi_v, hi_u] - sat[lo_v, hi_u] - sat[hi_v, lo_u] + sat[lo_v, lo_u]
            if 0 < black < (hi_u - lo_u) * (hi_v - lo_v):
                out[count] = gy * width + gx
                count += 1
    return count


@njit
def fit_steps(obs: np.ndarray, px: np.ndarray, py: np.ndarray, starts: np.ndarray, counts: np.ndarray,
              h: np.ndarray, theta: np.ndarray, tables: np.ndarray, sd_px: float, free_tone: bool,
              iterations: int, min_pixels: int, min_level_pixels: int,
              damping: float, converged_px: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every tag's Gauss-Newton steps, in place on ``h`` (N, 8) and ``theta`` (N, 7 or 8).

    Args:
        obs, px, py: (P,) float64 grey level and position of each selected pixel, tag after tag.
        starts, counts: (N,) int64 each tag's first pixel and pixel count.
        h, theta: (N, 8), (N, 7 + free_tone) the start (theta zero: the levels start from the
            pixels), updated in place.
        tables: (N, S, S) float64 each tag's padded black cells (1 black, 0 white), [v, u].
        sd_px: the blur's sd in px at blur scale 1 (the PSF and the pixel's area).
        free_tone: fit the tone exponent (theta[:, 7]).
        iterations: steps (the misfit is measured from the second on).
        min_pixels, min_level_pixels: fewest pixels a tag needs, and fewest flat black and flat
            white pixels that start its levels.
        damping: Levenberg damping on the column-scaled normal equations.
        converged_px: a tag stops once a step (from the second on) moves no corner further than
            this, px (0: only a step that moves nothing stops it).

    Returns:
        (fitted (N,) bool: pixels enough, levels started, every system solved; misfit (N,): robust
        residual sd over the model's range; contrast (N,): the model's range, grey levels).
    """
    n = h.shape[0]
    ok = counts >= min_pixels
    misfit = np.full(n, np.inf)
    contrast = np.zeros(n)
    for t in range(n):
        if not ok[t]:
            continue
        a, b = starts[t], starts[t] + counts[t]
        ok[t], misfit[t], contrast[t] = _fit_tag(obs[a:b], px[a:b], py[a:b], h[t], theta[t], tables[t],
                                                 sd_px, free_tone, iterations, min_level_pixels, damping,
                                                 converged_px)
    return ok, misfit, contrast


@njit
def _fit_tag(obs: np.ndarray, px: np.ndarray, py: np.ndarray, h: np.ndarray, theta: np.ndarray,
             table: np.ndarray, sd_px: float, free_tone: bool, iterations: int, min_level_pixels: int,
             damping: float, converged_px: float) -> tuple[bool, float, float]:
    """One tag's steps (``fit_steps``), ``h`` and ``theta`` in place: (fitted, misfit, contrast)."""
    p_n = len(obs)
    n_par = 8 + len(theta)
    bu = np.empty(p_n, np.int64)
    bv = np.empty(p_n, np.int64)
    geo = np.empty((p_n, 7))  # u, v, m11, m12, m21, m22, det
    cov = np.empty((p_n, 4))  # C, d black / du, d black / dv, d black / d log(blur scale)
    jac = np.empty((p_n, n_par))
    r = np.empty(p_n)
    shares = np.empty((2, 3, 4))  # scratch: [along u / v][share, d / d coordinate, d / d log scale][cell]
    misfit, contrast = np.inf, 0.0
    for it in range(iterations):
        scale = sd_px * math.exp(theta[6])
        _coverage(px, py, h, scale, table, it == 0, bu, bv, geo, cov, shares)
        if it == 0 and not _start_levels(obs, cov[:, 0], theta, min_level_pixels):
            return False, misfit, contrast
        lo, hi = _model_rows(obs, px, py, theta, geo, cov, free_tone, jac, r)
        state, misfit, contrast = _step(jac, r, lo, hi, h, theta, damping, free_tone, it, converged_px,
                                        misfit, contrast)
        if state == _REFUSED:
            return False, misfit, contrast
        if state == _SETTLED:
            break
    return True, misfit, contrast


@njit
def fit_steps_moving(obs: np.ndarray, px: np.ndarray, py: np.ndarray, starts: np.ndarray, counts: np.ndarray,
                     h: np.ndarray, theta: np.ndarray, tables: np.ndarray, warps: np.ndarray,
                     instants: np.ndarray, sd_px: float, free_tone: bool, iterations: int, min_pixels: int,
                     min_level_pixels: int, damping: float,
                     converged_px: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``fit_steps`` with each tag's pattern moving over the exposure (motion blur).

    A pixel's linear light is the mean over ``instants[t]`` instants of the light the tag's
    pattern sends it at each: the mid-exposure pattern (``h``) seen at the pixel mapped through
    the instant's warp (``warps[t, k]``: image px at instant k -> image px at mid-exposure). The
    levels, the lens blur and the tone curve are as ``fit_steps``'; ``h`` is the mid-exposure
    homography.

    Args:
        warps: (N, K, 3, 3) each tag's warps, the first ``instants[t]`` of them used.
        instants: (N,) int64 each tag's instant count (at least 1).
        iterations: the most steps a tag takes (at least 2).
        converged_px: a tag stops once a step (from the second on) moves no corner further
            than this, px: a smeared edge's start can lie beyond the reach of one linearised
            step (its model's slope lives within a blur sd of the smear's two ends), so such a
            tag needs more steps than a still one, and a tag already there needs none.
        The rest: as ``fit_steps``.
    """
    n = h.shape[0]
    ok = counts >= min_pixels
    misfit = np.full(n, np.inf)
    contrast = np.zeros(n)
    for t in range(n):
        if not ok[t]:
            continue
        a, b = starts[t], starts[t] + counts[t]
        ok[t], misfit[t], contrast[t] = _fit_tag_moving(
            obs[a:b], px[a:b], py[a:b], h[t], theta[t], tables[t], warps[t, :instants[t]], sd_px,
            free_tone, iterations, min_level_pixels, damping, converged_px)
    return ok, misfit, contrast


@njit
def _fit_tag_moving(obs: np.ndarray, px: np.ndarray, py: np.ndarray, h: np.ndarray, theta: np.ndarray,
                    table: np.ndarray, warps: np.ndarray, sd_px: float, free_tone: bool, iterations: int,
                    min_level_pixels: int, damping: float, converged_px: float) -> tuple[bool, float, float]:
    """One moving tag's steps (``fit_steps_moving``; ``_fit_tag``'s steps over the instants'
    mean), ``h`` and ``theta`` in place: (fitted, misfit, contrast)."""
    p_n = len(obs)
    n_par = 8 + len(theta)
    bu = np.empty((p_n, len(warps)), np.int64)
    bv = np.empty((p_n, len(warps)), np.int64)
    mean = np.empty((p_n, 12))  # C, d black / d log scale, u, v, 8 geometric rows of d C / d h
    jac = np.empty((p_n, n_par))
    r = np.empty(p_n)
    shares = np.empty((2, 3, 4))
    misfit, contrast = np.inf, 0.0
    for it in range(iterations):
        scale = sd_px * math.exp(theta[6])
        coverage_moving(px, py, h, scale, table, warps, it == 0, bu, bv, mean, shares)
        if it == 0 and not _start_levels(obs, mean[:, 0], theta, min_level_pixels):
            return False, misfit, contrast
        lo, hi = model_rows_moving(obs, theta, mean, free_tone, jac, r)
        state, misfit, contrast = _step(jac, r, lo, hi, h, theta, damping, free_tone, it, converged_px,
                                        misfit, contrast)
        if state == _REFUSED:
            return False, misfit, contrast
        if state == _SETTLED:
            break
    return True, misfit, contrast


#: ``_step``'s outcomes: the update was refused, the tag goes on, its corners settled.
_REFUSED, _GOING, _SETTLED = 0, 1, 2


@njit
def _step(jac: np.ndarray, r: np.ndarray, lo: float, hi: float, h: np.ndarray, theta: np.ndarray,
          damping: float, free_tone: bool, it: int, converged_px: float, misfit: float,
          contrast: float) -> tuple[int, float, float]:
    """One Gauss-Newton step of a tag's fit from its model rows (``jac``, ``r``; ``h`` and
    ``theta`` in place), shared by the still and the moving fit: from the second step on the
    outliers are dropped first (which gives the misfit and contrast); the tag settles once a step
    from the second on moves no corner further than ``converged_px``. Returns (outcome,
    misfit, contrast)."""
    if it >= 1:
        misfit, contrast = _drop_outliers(jac, r, lo, hi)
    before = h.copy()
    if not _gauss_newton_update(jac, r, h, theta, damping, free_tone):
        return _REFUSED, misfit, contrast
    if it >= 1 and _largest_corner_move(before, h) <= converged_px:
        return _SETTLED, misfit, contrast
    return _GOING, misfit, contrast


@njit
def _largest_corner_move(h0: np.ndarray, h1: np.ndarray) -> float:
    """The farthest any of the tag's corners (cell units (0, 0), (8, 0), (8, 8), (0, 8)) lies
    under homography ``h1`` from where it lies under ``h0``, px."""
    most = 0.0
    for k in range(4):
        u = float(_CELLS) if k == 1 or k == 2 else 0.0
        v = float(_CELLS) if k >= 2 else 0.0
        d0 = h0[6] * u + h0[7] * v + 1.0
        d1 = h1[6] * u + h1[7] * v + 1.0
        dx = (h1[0] * u + h1[1] * v + h1[2]) / d1 - (h0[0] * u + h0[1] * v + h0[2]) / d0
        dy = (h1[3] * u + h1[4] * v + h1[5]) / d1 - (h0[3] * u + h0[4] * v + h0[5]) / d0
        most = max(most, math.sqrt(dx * dx + dy * dy))
    return most


@njit
def coverage_moving(px: np.ndarray, py: np.ndarray, h: np.ndarray, scale: float, table: np.ndarray,
                    warps: np.ndarray, first: bool, bu: np.ndarray, bv: np.ndarray, mean: np.ndarray,
                    shares: np.ndarray) -> None:
    """Every pixel's white coverage averaged over the instants of ``warps`` (K, 3, 3), with what
    the steps need, into ``mean`` (P, 12): C, d black / d log(blur scale), the mean tag
    coordinates u, v (the levels' planes), and the 8 rows of d C / d h per unit d grey / d C (each
    instant's ``_model_rows`` geometry at the pixel it maps to). ``bu``, ``bv`` (P, K): each
    instant's nearest boundary crossing, set on the ``first`` step."""
    a11, a12, a13, a21, a22, a23, a31, a32 = h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7]
    n_k = len(warps)
    inv_k = 1.0 / n_k
    for p in range(len(px)):
        for c in range(12):
            mean[p, c] = 0.0
        for k in range(n_k):
            W = warps[k]
            wd = W[2, 0] * px[p] + W[2, 1] * py[p] + W[2, 2]
            x = (W[0, 0] * px[p] + W[0, 1] * py[p] + W[0, 2]) / wd
            y = (W[1, 0] * px[p] + W[1, 1] * py[p] + W[1, 2]) / wd
            m11, m12, m21, m22 = a11 - a31 * x, a12 - a32 * x, a21 - a31 * y, a22 - a32 * y
            det = m11 * m22 - m12 * m21
            bx, by = x - a13, y - a23
            u = (m22 * bx - m12 * by) / det
            v = (-m21 * bx + m11 * by) / det
            gd = scale * abs((a31 * u + a32 * v + 1.0) / det)
            if first:
                bu[p, k] = _round_half_even(u)
                bv[p, k] = _round_half_even(v)
            _shares(shares, 0, bu[p, k] - u, math.sqrt(m22 * m22 + m12 * m12) * gd)
            _shares(shares, 1, bv[p, k] - v, math.sqrt(m21 * m21 + m11 * m11) * gd)
            black, dbu, dbv, dbs = _blurred_cells(table, shares, bu[p, k], bv[p, k])
            gx = (m22 * dbu - m21 * dbv) / det
            gy = (m11 * dbv - m12 * dbu) / det
            gp = gx * x + gy * y
            mean[p, 0] += 1.0 - black
            mean[p, 1] += dbs
            mean[p, 2] += u
            mean[p, 3] += v
            mean[p, 4] += gx * u
            mean[p, 5] += gx * v
            mean[p, 6] += gx
            mean[p, 7] += gy * u
            mean[p, 8] += gy * v
            mean[p, 9] += gy
            mean[p, 10] -= gp * u
            mean[p, 11] -= gp * v
        for c in range(12):
            mean[p, c] *= inv_k


@njit
def model_rows_moving(obs: np.ndarray, theta: np.ndarray, mean: np.ndarray, free_tone: bool, jac: np.ndarray,
                      r: np.ndarray) -> tuple[float, float]:
    """``_model_rows`` from the instants' means (``coverage_moving``): each pixel's residual into
    ``r`` and Jacobian row into ``jac``; returns the model's (least, greatest) grey."""
    lo, hi = np.inf, -np.inf
    kap = math.exp(theta[7]) if free_tone else 1.0
    for p in range(len(obs)):
        C, dbs = mean[p, 0], mean[p, 1]
        uc, vc = (mean[p, 2] - 4.0) / 4.0, (mean[p, 3] - 4.0) / 4.0
        lb, lw, model, fp, d_kappa = _grey(C, uc, vc, theta, kap, free_tone)
        if free_tone:
            jac[p, 15] = d_kappa
        r[p] = obs[p] - model
        lo, hi = min(lo, model), max(hi, model)
        dC = (lw - lb) * fp  # d grey / d C
        for i in range(8):
            jac[p, i] = mean[p, 4 + i] * dC
        fw = fp * C
        fb = fp - fw
        jac[p, 8], jac[p, 9], jac[p, 10] = fb, fb * uc, fb * vc
        jac[p, 11], jac[p, 12], jac[p, 13] = fw, fw * uc, fw * vc
        jac[p, 14] = -(dbs * dC)
    return lo, hi


@njit
def _coverage(px: np.ndarray, py: np.ndarray, h: np.ndarray, scale: float, table: np.ndarray, first: bool,
              bu: np.ndarray, bv: np.ndarray, geo: np.ndarray, cov: np.ndarray, shares: np.ndarray) -> None:
    """Every pixel (``px``, ``py``): its tag coordinates and the local geometry into ``geo``, its
    white coverage and the black coverage's derivatives into ``cov``; on the ``first`` step also
    the boundary crossing nearest it into ``bu``, ``bv`` (kept through the steps: a corner moves a
    few hundredths of a cell). ``shares``: (2, 3, 4) scratch (``_shares``). One loop whose helpers
    are inlined (``_shares``, ``_blurred_cells``): the loop is the fit's bulk."""
    a11, a12, a13, a21, a22, a23, a31, a32 = h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7]
    for p in range(len(px)):
        x, y = px[p], py[p]
        # Solve [a11 - a31 x, a12 - a32 x; a21 - a31 y, a22 - a32 y] (u, v) = (x - a13, y - a23).
        m11, m12, m21, m22 = a11 - a31 * x, a12 - a32 * x, a21 - a31 * y, a22 - a32 * y
        det = m11 * m22 - m12 * m21
        bx, by = x - a13, y - a23
        u = (m22 * bx - m12 * by) / det
        v = (-m21 * bx + m11 * by) / det
        den = a31 * u + a32 * v + 1.0
        # grad u = (m22, -m12) den / det, grad v = (-m21, m11) den / det: the blur's sds in tag units.
        gd = scale * abs(den / det)
        if first:
            bu[p] = _round_half_even(u)
            bv[p] = _round_half_even(v)
        geo[p, 0], geo[p, 1], geo[p, 2], geo[p, 3], geo[p, 4], geo[p, 5], geo[p, 6] = u, v, m11, m12, m21, m22, det
        _shares(shares, 0, bu[p] - u, math.sqrt(m22 * m22 + m12 * m12) * gd)
        _shares(shares, 1, bv[p] - v, math.sqrt(m21 * m21 + m11 * m11) * gd)
        black, dbu, dbv, dbs = _blurred_cells(table, shares, bu[p], bv[p])
        cov[p, 0], cov[p, 1], cov[p, 2], cov[p, 3] = 1.0 - black, dbu, dbv, dbs


@njit(inline="always")
def _blurred_cells(table: np.ndarray, shares: np.ndarray, bu: int, bv: int) -> tuple[float, float, float, float]:
    """The black coverage a pixel gets from the 4 x 4 cells around its nearest boundary crossing
    (``bu``, ``bv``; the table padded by ``PAD``) under the blurred shares (``_shares``), and its
    derivatives along the pixel's u and v and the log of the blur's scale."""
    size = table.shape[0]
    ci = min(max(bu + PAD, 2), size - 2) - 2
    cj = min(max(bv + PAD, 2), size - 2) - 2
    black, dbu, dbv, dbs = 0.0, 0.0, 0.0, 0.0
    for j in range(4):
        r0, r1, r2 = 0.0, 0.0, 0.0
        for i in range(4):
            cell = table[cj + j, ci + i]
            r0 += cell * shares[0, 0, i]
            r1 += cell * shares[0, 1, i]
            r2 += cell * shares[0, 2, i]
        av = shares[1, 0, j]
        black += r0 * av
        dbu += r1 * av
        dbv += r0 * shares[1, 1, j]
        dbs += r2 * av + r0 * shares[1, 2, j]
    return black, dbu, dbv, dbs


@njit(inline="always")
def _shares(out: np.ndarray, axis: int, offset: float, sd: float) -> None:
    """The blurred shares of the 4 cells between the boundaries ``offset`` - 2 .. ``offset`` + 2
    (tag units from the pixel) under a Gaussian of ``sd``, into ``out[axis]`` (3, 4): the shares,
    their derivatives along the pixel's coordinate, and along the log of the blur's scale."""
    isd = 1.0 / sd
    e_prev, phi_prev, hz_prev = 0.0, 0.0, 0.0
    for k in range(5):
        z = (offset + (k - 2)) * isd
        e, phi = _cdf_pdf(z)
        hz = phi * z
        if k > 0:
            out[axis, 0, k - 1] = e - e_prev
            out[axis, 1, k - 1] = (phi_prev - phi) * isd
            out[axis, 2, k - 1] = hz_prev - hz
        e_prev, phi_prev, hz_prev = e, phi, hz


@njit
def _cdf_pdf(z: float) -> tuple[float, float]:
    """The normal CDF and density at ``z``; beyond ``_FAR_SDS`` (0 or 1, 0): on a large tag most
    boundaries are tens of sds away."""
    if abs(z) >= _FAR_SDS:
        return (1.0 if z > 0.0 else 0.0), 0.0
    g = math.exp(-0.5 * z * z)
    return _ndtr(z, g), g * _INV_SQRT_2PI


@njit
def _ndtr(z: float, gauss: float) -> float:
    """The normal CDF of ``z`` given ``gauss`` = exp(-z^2 / 2): Abramowitz & Stegun 7.1.26 (the
    CDF to 7.5e-8), reusing the Gaussian the fit needs anyway."""
    t = 1.0 / (1.0 + (0.3275911 / math.sqrt(2.0)) * abs(z))
    tail = t * (0.5 * 0.254829592 + t * (0.5 * -0.284496736 + t * (
        0.5 * 1.421413741 + t * (0.5 * -1.453152027 + t * (0.5 * 1.061405429))))) * gauss
    return 1.0 - tail if z > 0.0 else tail


@njit
def _round_half_even(x: float) -> int:
    """``np.round`` of one value (halves to even), as an int."""
    r = math.floor(x + 0.5)
    if r - x == 0.5 and r % 2.0 != 0.0:
        r -= 1.0
    return int(r)


@njit
def _srgb_to_linear(value: float) -> float:
    """``tone.srgb_to_linear_scalar``: the inverse sRGB curve of one value clipped to [0, 1]."""
    y = min(max(value, 0.0), 1.0)
    return y / 12.92 if y <= SRGB_ENCODED_KNEE else ((y + 0.055) / 1.055) ** 2.4


@njit
def _start_levels(obs: np.ndarray, white: np.ndarray, theta: np.ndarray, min_level_pixels: int) -> bool:
    """The levels' starts (``theta[0]``, ``theta[3]``) from the pixels the start corners' model calls
    flat black (white coverage under 0.05) and flat white (over 0.95): each set's median grey
    through the inverse sRGB curve (a white near saturation starts above 1, where the curve
    clips). False when either set has fewer than ``min_level_pixels``."""
    black = obs[white < 0.05]
    bright = obs[white > 0.95]
    if len(black) < min_level_pixels or len(bright) < min_level_pixels:
        return False
    mb, mw = np.median(black), np.median(bright)
    theta[0] = _srgb_to_linear(mb / 255.0)
    theta[3] = _srgb_to_linear(mw / 255.0) if mw < 250.0 else 1.1
    return True


@njit
def _model_rows(obs: np.ndarray, px: np.ndarray, py: np.ndarray, theta: np.ndarray, geo: np.ndarray,
                cov: np.ndarray, free_tone: bool, jac: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """Each pixel's residual (grey - model) into ``r`` and its Jacobian row into ``jac``; returns the
    model's (least, greatest) grey.

    d C / d h = g . d(x, y)/d h, g the image gradient of the black coverage: a pattern moved by +dx
    shows each pixel what lay dx to its left. That gradient is adj(M)^T (dC/du, dC/dv) den / det,
    and d(x, y)/d h carries a 1 / den.
    """
    lo, hi = np.inf, -np.inf
    kap = math.exp(theta[7]) if free_tone else 1.0
    for p in range(len(obs)):
        u, v, m11, m12, m21, m22, det = geo[p, 0], geo[p, 1], geo[p, 2], geo[p, 3], geo[p, 4], geo[p, 5], geo[p, 6]
        C, dbu, dbv, dbs = cov[p, 0], cov[p, 1], cov[p, 2], cov[p, 3]
        uc, vc = (u - 4.0) / 4.0, (v - 4.0) / 4.0
        lb, lw, model, fp, d_kappa = _grey(C, uc, vc, theta, kap, free_tone)
        if free_tone:
            jac[p, 15] = d_kappa
        r[p] = obs[p] - model
        lo, hi = min(lo, model), max(hi, model)
        dC = (lw - lb) * fp  # d grey / d C
        w = dC / det
        gx = (m22 * dbu - m21 * dbv) * w
        gy = (m11 * dbv - m12 * dbu) * w
        gp = gx * px[p] + gy * py[p]
        jac[p, 0], jac[p, 1], jac[p, 2] = gx * u, gx * v, gx
        jac[p, 3], jac[p, 4], jac[p, 5] = gy * u, gy * v, gy
        jac[p, 6], jac[p, 7] = -gp * u, -gp * v
        fw = fp * C
        fb = fp - fw
        jac[p, 8], jac[p, 9], jac[p, 10] = fb, fb * uc, fb * vc
        jac[p, 11], jac[p, 12], jac[p, 13] = fw, fw * uc, fw * vc
        jac[p, 14] = -(dbs * dC)
    return lo, hi


@njit
def _grey(C: float, uc: float, vc: float, theta: np.ndarray, kap: float,
          free_tone: bool) -> tuple[float, float, float, float, float]:
    """The model at a pixel whose white coverage is ``C``, at tag position (``uc``, ``vc``) from the
    centre (half-tags): (black level, white level, grey, d grey / d linear light, d grey / d log
    tone exponent (0 without ``free_tone``)); ``kap`` the tone exponent."""
    lb = theta[0] + theta[1] * uc + theta[2] * vc
    lw = theta[3] + theta[4] * uc + theta[5] * vc
    enc, slope = _srgb_encode(lb + (lw - lb) * C)
    if free_tone:
        encp = max(enc, 1e-4)
        log_enc = math.log(encp)
        powered = math.exp(kap * log_enc)
        model = 255.0 * powered
        return lb, lw, model, 255.0 * kap * (powered / encp) * slope, model * log_enc * kap
    return lb, lw, 255.0 * enc, 255.0 * slope, 0.0


@njit
def _drop_outliers(jac: np.ndarray, r: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """Zero the rows of pixels more than ``_OUTLIER_SDS`` robust sds off (glare specks, a
    neighbour's edge) in ``jac`` and ``r``; returns (misfit: the robust residual sd over the
    model's grey range ``hi - lo``, that range)."""
    mad = np.median(np.abs(r))
    limit = max(_OUTLIER_SDS * _MAD_SD * mad, _MIN_OUTLIER_GREY)
    contrast = hi - lo
    for p in range(len(r)):
        if abs(r[p]) > limit:
            jac[p, :] = 0.0
            r[p] = 0.0
    return _MAD_SD * mad / max(contrast, 1.0), contrast


@njit
def _srgb_encode(linear: float) -> tuple[float, float]:
    """``tone.srgb_encode_slope`` of one value: (encoded, d encoded / d linear); 1 and above
    encode as 1 does, with slope 0; below 0 the linear toe continues."""
    v = min(linear, 1.0)
    if v > SRGB_LINEAR_KNEE:
        root = v ** (1.0 / 2.4)
        enc, slope = 1.055 * root - 0.055, (1.055 / 2.4) * root / v
    else:
        enc, slope = 12.92 * v, 12.92
    return enc, 0.0 if linear >= 1.0 else slope


@njit
def _gauss_newton_update(jac: np.ndarray, r: np.ndarray, h: np.ndarray, theta: np.ndarray, damping: float,
                         free_tone: bool) -> bool:
    """Solve the damped, column-scaled normal equations of ``jac`` (P, n_par) and ``r`` and update
    ``h`` and ``theta`` in place (the blur scale kept within 1/4..4, the tone exponent within
    1/2..2). False for a singular system; a step that is not finite is not taken."""
    n_par = jac.shape[1]
    A = jac.T @ jac
    b = jac.T @ r
    d = np.sqrt(np.maximum(np.diag(A), 1e-30))
    for i in range(n_par):
        for j in range(n_par):
            A[i, j] /= d[i] * d[j]
        A[i, i] += damping
        b[i] /= d[i]
    solved, step = _solve(A, b)
    if not solved:
        return False
    step = step / d
    if not np.isfinite(step).all():
        return True
    for i in range(8):
        h[i] += step[i]
    for i in range(n_par - 8):
        theta[i] += step[8 + i]
    if free_tone:
        theta[7] = min(max(theta[7], math.log(0.5)), math.log(2.0))
    theta[6] = min(max(theta[6], math.log(0.25)), math.log(4.0))
    return True


@njit
def _solve(A: np.ndarray, b: np.ndarray) -> tuple[bool, np.ndarray]:
    """(solved, x) with A x = b by Gaussian elimination with partial pivoting (A and b
    overwritten); not solved when a pivot is exactly zero (singular, as LAPACK's getrf reports it)."""
    n = len(b)
    x = np.zeros(n)
    for c in range(n):
        piv = c
        for i in range(c + 1, n):
            if abs(A[i, c]) > abs(A[piv, c]):
                piv = i
        if A[piv, c] == 0.0:
            return False, x
        if piv != c:
            for j in range(n):
                A[c, j], A[piv, j] = A[piv, j], A[c, j]
            b[c], b[piv] = b[piv], b[c]
        for i in range(c + 1, n):
            f = A[i, c] / A[c, c]
            for j in range(c, n):
                A[i, j] -= f * A[c, j]
            b[i] -= f * b[c]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, n):
            s -= A[i, j] * x[j]
        x[i] = s / A[i, i]
    return True, x


@register_warm_up
def _warm_up() -> None:
    """The kernels once on one small synthetic tag (the pipeline's argument types), still and moving."""
    size = _CELLS + 2 * PAD
    table = np.zeros((size, size))
    table[PAD:PAD + _CELLS, PAD:PAD + _CELLS] = 1.0  # a black border around white cells
    table[PAD + 1:PAD + _CELLS - 1, PAD + 1:PAD + _CELLS - 1] = 0.0
    sat = np.zeros((1, len(table) + 1, len(table) + 1), np.int32)
    sat[0, 1:, 1:] = table.cumsum(0).cumsum(1)
    hom = np.array([[[4.0, 0.0, 20.0], [0.0, 4.0, 20.0], [0.0, 0.0, 1.0]]])
    boxes = np.array([[16], [16], [56], [56]], np.int64)
    tag, xs, ys = select_pixels(np.linalg.inv(hom), boxes, np.zeros(1, np.int64), np.full(1, 0.5), sat, 1500)
    # The pattern's grey at each pixel (4 px a cell from (20, 20)).
    obs = 30.0 + 170.0 * (1.0 - table[(ys - 20) // 4 + PAD, (xs - 20) // 4 + PAD])
    theta = np.zeros((1, 8))
    fit_steps(obs, xs.astype(np.float64), ys.astype(np.float64), np.zeros(1, np.int64),
              np.array([len(tag)], np.int64), hom.reshape(1, 9)[:, :8].copy(), theta, table[None], 0.66,
              True, 2, 40, 5, 1e-3, 0.02)  # the stop as the fit passes it (a float)
    theta = np.zeros((1, 8))
    fit_steps_moving(obs, xs.astype(np.float64), ys.astype(np.float64), np.zeros(1, np.int64),
                     np.array([len(tag)], np.int64), hom.reshape(1, 9)[:, :8].copy(), theta, table[None],
                     np.tile(np.eye(3), (1, 2, 1, 1)), np.array([2], np.int64), 0.66, True, 2, 40, 5, 1e-3,
                     0.02)
