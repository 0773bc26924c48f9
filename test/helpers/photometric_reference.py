"""The photometric corner fit in vectorised numpy: the reference the compiled fit
(``ficap_ros.vision.photometric`` with ``photometric_kernels``) is checked against (tests only).

The same model, pixels and steps as the package's fit (its module docstring), laid out per quantity
over all pixels of up to ``_CHUNK_TAGS`` tags at once: the shares along u and v in float32 and
Abramowitz & Stegun's normal CDF, which the compiled fit evaluates in float64; hence the two agree
to a tolerance, not bit for bit.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ficap_ros.geometry.tag36h11 import TAG_CELLS, homography_corners
from ficap_ros.vision.medians import GroupLayout, group_median_nan_propagating
from ficap_ros.vision.tone import srgb_encode_slope, srgb_to_linear_scalar

__all__ = ["fit_tags", "PSF_SIGMA_PX"]

#: Lens PSF sigma, px, assumed when the recording's is unknown: where the per-tag blur scale
#: starts; a typical camera's lens blur, within the range the fit converges from.
PSF_SIGMA_PX = 0.6
#: Cells padded around the 8 x 8 tag (white: quiet zone and beyond) so a 5 x 5 neighbourhood of any
#: face pixel stays inside the table.
_PAD = 3
#: Least grey-level range of a fitted tag's model: below it there is no pattern to fit (as
#: ``decode_tags`` asks of a border).
_MIN_CONTRAST = 10.0
#: Most tags fitted at once (``fit_tags``): a chunk's per-pixel arrays stay in cache and their
#: memory is reused from chunk to chunk.
_CHUNK_TAGS = 12
#: Largest robust residual sd of a fitted tag, as a fraction of its model's contrast: a start a
#: cell or more off settles in a false minimum whose residuals are a large part of the contrast.
_MAX_MISFIT = 0.3
#: Fewest selected pixels a tag needs to be fitted.
_MIN_PIXELS = 40
#: Fewest pixels the start corners call flat black and flat white that set a tag's first levels.
_MIN_LEVEL_PIXELS = 5
#: Levenberg damping on the column-scaled normal equations.
_DAMPING = 1e-3
#: The unit-spaced boundary offsets around a pixel's nearest boundary (k = -2..2: the 4 cells
#: between them each way).
_BOUNDARY_STEPS = np.arange(-2, 3, dtype=np.float32)[:, None]


def _black_tables(cells: np.ndarray) -> np.ndarray:
    """(N, 8 + 2 _PAD, 8 + 2 _PAD) tables of the tags' black cells (float 0/1), cell (i, j) of tag
    t at [t, j + _PAD, i + _PAD]; white (quiet zone and beyond) around them."""
    cells = np.asarray(cells, dtype=bool).reshape(-1, TAG_CELLS, TAG_CELLS)
    t = np.zeros((len(cells), TAG_CELLS + 2 * _PAD, TAG_CELLS + 2 * _PAD))
    t[:, _PAD:_PAD + TAG_CELLS, _PAD:_PAD + TAG_CELLS] = cells
    return t


# ------------------------------------------------------------------------------------------------
# The pixels fitted
# ------------------------------------------------------------------------------------------------
#: Cells a box's side may span where the reach is under a cell (``_mixed_boxes``).
_RUNS = 4


def _select_pixels(shape: tuple[int, int], hom: np.ndarray, tables: np.ndarray, sd_px: float,
                   reach_px: float, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (x, y) within ``reach_px`` (plus 1.5 ``sd_px``) of a black/white boundary of each
    tag's face: (tag of each, x, y) as int arrays, tag after tag; a tag with more than
    ``max_pixels`` is thinned to that many, evenly (a narrower band would lose the flat pixels the
    levels need)."""
    z = np.zeros(0, dtype=np.intp)
    if len(hom) == 0:
        return z, z, z
    use, box, hom_inv, reach = _face_boxes(shape, hom, sd_px, reach_px)
    if len(use) == 0:
        return z, z, z
    sat, mixed = _mixed_boxes(tables)
    tags, cols, rows = [], [], []
    for t in use:
        x0, y0, x1, y1 = box[:, t]
        on, u, v, width = _face_pixels(hom_inv[t], x0, y0, x1, y1)
        if reach[t] < 1.0:
            near = _near_boundary_by_table(mixed, t, u, v, reach[t], tables.shape[1])
        else:
            near = _near_boundary_by_sums(sat[t], u, v, reach[t])
        if len(near) > max_pixels:
            near = near[np.linspace(0, len(near) - 1, max_pixels).astype(np.intp)]
        gy, gx = np.divmod(on.take(near), width)
        tags.append(np.full(len(near), t))
        cols.append(gx + x0)
        rows.append(gy + y0)
    return np.concatenate(tags), np.concatenate(cols), np.concatenate(rows)


def _face_boxes(
    shape: tuple[int, int], hom: np.ndarray, sd_px: float, reach_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each tag's face (10 x 10 cells) box in the image, all tags at once (a stacked matmul, inv
    and norm run the same loops per tag): (tags whose box inside the image's 1-px frame is at least
    3 px each way (K,), box x0, y0, x1, y1 (4, N), inverse homographies (N, 3, 3; zero where not
    used), reach in cell units (N,) from the face's mean px per cell)."""
    h_img, w_img = shape
    face = np.array([[-1, -1, 1], [9, -1, 1], [9, 9, 1], [-1, 9, 1]], float)
    q = face @ hom.transpose(0, 2, 1)  # (N, 4, 3)
    xy = q[..., :2] / q[..., 2:]
    lo, hi = np.floor(xy.min(axis=1)).astype(int), np.ceil(xy.max(axis=1)).astype(int)
    x0, y0 = np.maximum(lo[:, 0], 1), np.maximum(lo[:, 1], 1)
    x1, y1 = np.minimum(hi[:, 0], w_img - 2), np.minimum(hi[:, 1], h_img - 2)
    use = np.flatnonzero((x1 - x0 >= 3) & (y1 - y0 >= 3))
    hom_inv = np.zeros((len(hom), 3, 3))
    if len(use):
        hom_inv[use] = np.linalg.inv(hom[use])
    side = np.linalg.norm(xy[:, [1, 2, 3, 0]] - xy, axis=2).mean(axis=1) / 10.0  # px per cell (face = 10 cells)
    reach = (reach_px + 1.5 * sd_px) / np.maximum(side, 1e-6)
    return use, np.stack([x0, y0, x1, y1]), hom_inv, reach


def _mixed_boxes(tables: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tags' summed-area tables of black cells (N, S + 1, S + 1) int32 (counts: exact), and
    whether each box of cells holds both colours, flattened (N, v0, dv, u0, du): the box of cells
    v0..v0 + dv by u0..u0 + du (clipped to the table), dv and du below ``_RUNS``. Where the reach is
    under a cell a pixel's box spans at most ``_RUNS`` cells a side (floor(u + r) - floor(u - r)
    <= floor(2 r) + 1, one more from rounding), so one lookup here replaces four in the sums."""
    n, size = len(tables), tables.shape[1]
    last, stride = size - 1, size + 1
    sat = np.zeros((n, stride, stride), dtype=np.int32)
    sat[:, 1:, 1:] = tables.cumsum(1).cumsum(2)
    first = np.arange(size)
    end = np.minimum(first[:, None] + np.arange(_RUNS), last) + 1  # (first cell, cells - 1) -> end
    black = (sat[:, end[:, :, None, None], end[None, None]] - sat[:, first[:, None, None, None], end[None, None]]
             - sat[:, end[:, :, None, None], first[None, None, :, None]]
             + sat[:, first[:, None, None, None], first[None, None, :, None]])  # (N, v0, dv, u0, du)
    span = end - first[:, None]
    return sat, ((black > 0) & (black < span[:, :, None, None] * span[None, None])).ravel()


def _face_pixels(
    hom_inv: np.ndarray, x0: int, y0: int, x1: int, y1: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The pixels of the box x0..x1, y0..y1 that lie on the tag's face (within 0.9 cell of the
    tag), through the inverse homography ``hom_inv``: (their flat indices in the box, tag
    coordinates u, v, the box's width). Numerators and denominator are outer sums of a row term and
    a column term (the same sums, in the same order, as per pixel)."""
    xs, ys = np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64)
    H = hom_inv
    u = np.add.outer(H[0, 1] * ys, H[0, 0] * xs).ravel() + H[0, 2]
    v = np.add.outer(H[1, 1] * ys, H[1, 0] * xs).ravel() + H[1, 2]
    den = np.add.outer(H[2, 1] * ys, H[2, 0] * xs).ravel() + H[2, 2]
    u /= den
    v /= den
    on = np.flatnonzero((u > -0.9) & (u < TAG_CELLS + 0.9) & (v > -0.9) & (v < TAG_CELLS + 0.9))
    return on, u.take(on), v.take(on), len(xs)


def _near_boundary_by_table(
    mixed: np.ndarray, t: int, u: np.ndarray, v: np.ndarray, reach: float, size: int
) -> np.ndarray:
    """Which face pixels (u, v) of tag ``t`` have both colours within ``reach`` (< 1 cell) each way:
    one lookup a pixel in ``_mixed_boxes``' table (on the face such a box stays inside the padded
    table: no clipping). The index is built in place, floors taken as floats, then one cast."""
    edges = []
    for c, sgn in ((u, -reach), (u, reach), (v, -reach), (v, reach)):
        e = c + sgn
        np.floor(e, out=e)
        edges.append(e.astype(np.intp))
    lo_u, hi_u, lo_v, hi_v = edges
    hi_u -= lo_u
    hi_v -= lo_v
    lo_v *= _RUNS  # ((v0 runs + dv) size + u0) runs + du, cells counted from the table's
    lo_v += hi_v
    lo_v *= size
    lo_v += lo_u
    lo_v *= _RUNS
    lo_v += hi_u
    lo_v += t * (size * _RUNS * size * _RUNS) + ((_PAD * _RUNS) * size + _PAD) * _RUNS
    return np.flatnonzero(mixed.take(lo_v))


def _near_boundary_by_sums(sat: np.ndarray, u: np.ndarray, v: np.ndarray, reach: float) -> np.ndarray:
    """Which face pixels (u, v) of a tag of a few px have both colours within ``reach`` each way:
    the box's black cells from the tag's summed-area table ``sat`` (S + 1, S + 1), clipped to it
    (``np.take``: cheaper than 2-D fancy indexing)."""
    last = sat.shape[0] - 2
    stride = sat.shape[1]
    flat = sat.ravel()
    lo_u = np.clip(np.floor(u - reach) + _PAD, 0, last).astype(np.intp)
    hi_u = np.clip(np.floor(u + reach) + _PAD, 0, last).astype(np.intp) + 1
    lo_v = np.clip(np.floor(v - reach) + _PAD, 0, last).astype(np.intp) * stride
    hi_v = (np.clip(np.floor(v + reach) + _PAD, 0, last).astype(np.intp) + 1) * stride
    count = (flat.take(hi_v + hi_u) - flat.take(lo_v + hi_u) - flat.take(hi_v + lo_u)
             + flat.take(lo_v + lo_u))
    return np.flatnonzero((count > 0) & (count < (hi_u - lo_u) * ((hi_v - lo_v) // stride)))


# ------------------------------------------------------------------------------------------------
# The model
# ------------------------------------------------------------------------------------------------
def _ndtr32(z: np.ndarray, gauss: np.ndarray) -> np.ndarray:
    """The normal CDF of float32 ``z`` given ``gauss`` = exp(-z^2 / 2): Abramowitz & Stegun 7.1.26
    (erfc to 1.5e-7, i.e. the CDF to 7.5e-8, about float32's rounding of it), reusing the Gaussian
    the fit needs anyway."""
    # t = 1 / (1 + p |z|), tail = t (a1 + t (a2 + t (a3 + t (a4 + t a5)))) / 2: Horner's rule
    # in place, the same operations in the same order.
    t = np.abs(z)
    t *= np.float32(0.3275911 / np.sqrt(2.0))
    t += np.float32(1.0)
    np.divide(np.float32(1.0), t, out=t)
    tail = t * np.float32(0.5 * 1.061405429)
    for a in (0.5 * -1.453152027, 0.5 * 1.421413741, 0.5 * -0.284496736, 0.5 * 0.254829592):
        tail += np.float32(a)
        tail *= t
    tail *= gauss  # ndtr(-|z|)
    return np.subtract(np.float32(1.0), tail, out=tail, where=z > 0.0)


def fit_tags(
    gray: np.ndarray, corners_px: np.ndarray, hom: np.ndarray, cells: np.ndarray,
    psf_sigma_px: float = PSF_SIGMA_PX,
    iterations: int = 3, reach_px: float = 1.0, free_tone: bool = True, max_move_cells: float = 0.35,
    max_pixels: int = 1500,
) -> tuple[np.ndarray, np.ndarray]:
    """Fit each tag's homography and levels to its pixels (module docstring).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) starting corners (the cell-edge fit's; within a few tenths of a px).
        hom: (N, 3, 3) their homographies from tag cell units (``tag36h11.tag_homographies``).
        cells: (N, 8, 8) each tag's cells, True = black (``tag36h11.tag_cells``).
        psf_sigma_px: lens PSF sigma, px (linear light), where the per-tag blur scale starts.
        iterations: Gauss-Newton steps, at least 2 (a tag's misfit, which decides whether it is
            fitted, is measured from the second step on).
        reach_px: pixels used lie within this (plus 1.5 blur sds) of a black/white boundary.
        free_tone: also fit an exponent on the sRGB curve.
        max_move_cells: a tag moving any corner further than this (cells) keeps its input.
        max_pixels: most pixels fitted a tag (a larger tag's are thinned evenly).

    Returns:
        (corners (N, 4, 2), fitted (N,) bool): a tag not fitted keeps its input corners.
    """
    if iterations < 2:
        raise ValueError(f"iterations must be >= 2, got {iterations}")
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    hom = np.asarray(hom, dtype=np.float64).reshape(n, 3, 3)
    cells = np.asarray(cells).reshape(n, TAG_CELLS, TAG_CELLS)
    if n > _CHUNK_TAGS:
        # Every tag's fit is its own, so a frame's tags are fitted a few at a time (the same numbers).
        parts = [fit_tags(gray, c_in[k], hom[k], cells[k], psf_sigma_px, iterations, reach_px,
                          free_tone, max_move_cells, max_pixels)
                 for k in np.array_split(np.arange(n), -(-n // _CHUNK_TAGS))]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    fitted = np.zeros(n, dtype=bool)
    if n == 0:
        return c_in.copy(), fitted
    hom = hom / hom[:, 2:3, 2:3]
    tab = _black_tables(cells)  # (N, S, S)
    sd_px = float(np.sqrt(psf_sigma_px ** 2 + 1.0 / 12.0))  # the PSF and the pixel's area
    tag, xi, yi = _select_pixels(gray.shape[:2], hom, tab, sd_px, reach_px, max_pixels)
    if len(tag) == 0:
        return c_in.copy(), fitted
    fit = _TagFit(gray[yi, xi].astype(np.float64), tag, xi, yi, hom, tab, sd_px, free_tone)
    for it in range(iterations):
        fit.step(it)
    corners = homography_corners(fit.h)
    cell = np.linalg.norm(c_in[:, [1, 2, 3, 0]] - c_in, axis=2).min(axis=1) / TAG_CELLS
    moved = np.linalg.norm(corners - c_in, axis=2).max(axis=1)
    # A tag whose model shows no contrast (a flat region, a blown-out tag) has no pattern to fit:
    # its zero misfit says nothing.
    fitted = (fit.ok_tag & np.isfinite(corners).all(axis=(1, 2)) & (moved <= max_move_cells * cell)
              & (fit.misfit <= _MAX_MISFIT) & (fit.contrast >= _MIN_CONTRAST))
    return np.where(fitted[:, None, None], corners, c_in), fitted


class _TagFit:
    """The Gauss-Newton state of up to ``_CHUNK_TAGS`` tags' fits over their selected pixels.

    Per-pixel arrays are laid out (quantity, pixel), pixels tag after tag: rows are contiguous,
    which keeps numpy's broadcasting and the normal equations' products cheap (the fit's cost is
    all elementwise). Each step's pixel arrays are dropped before the next step makes its own
    (fresh pages cost time: a step's peak memory is part of its cost).

    Parameters per tag: h (8, the homography), theta = (Lb0, Lb_u, Lb_v, Lw0, Lw_u, Lw_v, log blur
    scale[, log tone exponent]).
    """

    def __init__(self, obs: np.ndarray, tag: np.ndarray, xi: np.ndarray, yi: np.ndarray, hom: np.ndarray,
                 tab: np.ndarray, sd_px: float, free_tone: bool) -> None:
        n = len(hom)
        self.obs, self.tag, self.sd_px, self.free_tone = obs, tag, sd_px, free_tone
        self.px, self.py = xi.astype(np.float64), yi.astype(np.float64)
        self.counts = np.bincount(tag, minlength=n)
        self.starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]])
        self.layout = GroupLayout.of_counts(self.counts)  # its groups are ``tag``
        self.h = hom.reshape(n, 9)[:, :8].copy()
        self.n_par = 8 + 7 + (1 if free_tone else 0)
        self.theta = np.zeros((n, self.n_par - 8))
        self.keep = np.ones(len(tag), dtype=bool)
        self.ok_tag = self.counts >= _MIN_PIXELS
        self.misfit = np.full(n, np.inf)
        self.contrast = np.zeros(n)
        # Every 4 x 4 block of each tag's table, row-major ([v, u]): block (r, c) holds cells r..r+3,
        # c..c+3; a pixel's block is one row of this (a 16-value gather instead of 16 gathers).
        self.size = tab.shape[1]
        win = sliding_window_view(tab, (4, 4), axis=(1, 2))  # (N, S - 3, S - 3, 4, 4)
        self.nwin = win.shape[1]
        self.blocks_t = np.ascontiguousarray(win.reshape(-1, 16).T, dtype=np.float32)  # (16, blocks)
        self.J = np.empty((self.n_par, len(tag)))
        self.X = np.empty((2, 3, 4, len(tag)), dtype=np.float32)  # filled anew at each step

    def step(self, it: int) -> None:
        """One Gauss-Newton step (``it`` from 0): model, residuals, Jacobian, solve, update."""
        u, v, m, det, su, sv = self._tag_coordinates()
        if it == 0:
            self._nearest_cells(u, v)
        black, dbu, dbv, dbs = self._black_coverage(u, v, su, sv)
        del su, sv
        C = 1.0 - black
        del black
        uc, vc = (u - 4.0) / 4.0, (v - 4.0) / 4.0
        if it == 0:
            self._start_levels(C)
        lb, lw, model, fp, tone = self._grey_model(C, uc, vc)
        r = self.obs - model
        if it >= 1:
            self._robust_weights(r, model)
        self._jacobian(u, v, m, det, dbu, dbv, dbs, C, uc, vc, lb, lw, model, fp, tone)
        rk = r * self.keep
        # The step's pixel arrays go before the solve.
        del u, v, m, det, dbu, dbv, dbs, C, uc, vc, lb, lw, model, fp, tone, r
        self._solve(rk)

    def _tag_coordinates(self) -> tuple[np.ndarray, ...]:
        """Each pixel's tag coordinates u, v (the inverse of its tag's H), the 2 x 2 matrix M
        (m11, m12, m21, m22) with M (u, v) = (x - a13, y - a23) and its determinant, and the blur's
        sds along u and v in tag units."""
        a11, a12, a13, a21, a22, a23, a31, a32 = np.repeat(self.h.T, self.counts, axis=1)
        px, py = self.px, self.py
        # Solve [a11 - a31 x, a12 - a32 x; a21 - a31 y, a22 - a32 y] (u, v) = (x - a13, y - a23).
        m11, m12, m21, m22 = a11 - a31 * px, a12 - a32 * px, a21 - a31 * py, a22 - a32 * py
        det = m11 * m22 - m12 * m21
        bx, by = px - a13, py - a23
        del a11, a12, a13, a21, a22, a23
        u = (m22 * bx - m12 * by) / det
        v = (-m21 * bx + m11 * by) / det
        den = a31 * u + a32 * v + 1.0
        # Jacobian of H at (u, v): d(x, y)/d(u, v) = M / den; its inverse, (den / det) adj(M), has
        # rows grad u = (m22, -m12) den / det and grad v = (-m21, m11) den / det.
        scale = np.repeat(self.sd_px * np.exp(self.theta[:, 6]), self.counts)  # exp per tag, not per pixel
        gd = scale * np.abs(den / det)
        su = np.hypot(m22, m12) * gd
        sv = np.hypot(m21, m11) * gd
        return u, v, (m11, m12, m21, m22), det, su, sv

    def _nearest_cells(self, u: np.ndarray, v: np.ndarray) -> None:
        """The 4 x 4 cells around the boundary crossing nearest each pixel: boundaries b - 2 .. b + 2
        (b = round(u)) are at least 1.5 cells away on either side, 3 blur sds at half a cell. Kept
        through the steps (a corner moves a few hundredths of a cell; the gather is costly)."""
        self.bu, self.bv = np.round(u), np.round(v)
        ci = np.clip(self.bu.astype(np.intp) + _PAD, 2, self.size - 2)
        cj = np.clip(self.bv.astype(np.intp) + _PAD, 2, self.size - 2)
        # [v, u, p]: the cells b - 2 .. b + 1 along each axis.
        self.patch = self.blocks_t.take((self.tag * self.nwin + cj - 2) * self.nwin + ci - 2,
                                        axis=1).reshape(4, 4, -1)

    def _black_coverage(
        self, u: np.ndarray, v: np.ndarray, su: np.ndarray, sv: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Each pixel's blurred black coverage and its derivatives along u, v and the log blur
        scale (float64).

        The cell shares along u and v are in float32 (half the memory traffic of this, the fit's
        bulk): a share's rounding is about 1e-5 of a grey level. Only boundaries within 9 sds are
        evaluated; the rest count as fully on one side (ndtr(-9) = 1e-19): on a large tag most are
        tens of sds away, and evaluated they would only cost time and send exp() into subnormals,
        which are slow in every later product.
        """
        X = self.X
        # u and v stacked: [0] the boundaries along u, [1] along v (one ufunc call each).
        isd = (1.0 / np.stack([su, sv])).astype(np.float32)[:, None, :]  # (2, 1, P)
        z = np.stack([self.bu - u, self.bv - v]).astype(np.float32)[:, None, :] + _BOUNDARY_STEPS  # (2, 5, P)
        z *= isd
        inner = np.flatnonzero(np.abs(z) < 9.0)  # (indices: cheaper than a boolean mask, used thrice)
        zi = z.take(inner)
        gauss = np.exp(np.float32(-0.5) * zi * zi)
        e = (z > 0.0).astype(np.float32)
        e.ravel()[inner] = _ndtr32(zi, gauss)
        phi = np.zeros_like(z)
        phi.ravel()[inner] = gauss * np.float32(0.3989422804014327)
        del inner, zi, gauss
        # [u / v][share, d share / du (dv), d share / d log(blur scale)][cell][pixel]
        np.subtract(e[:, 1:], e[:, :-1], out=X[:, 0])  # each cell's share along u / v
        del e
        g = phi * isd  # d ndtr(z) / d(boundary - u)
        np.subtract(g[:, :-1], g[:, 1:], out=X[:, 1])
        del g, isd
        hh = np.multiply(phi, z, out=z)  # d ndtr(z) / d log(blur scale) = -phi(z) z
        np.subtract(hh[:, :-1], hh[:, 1:], out=X[:, 2])
        del z, hh, phi
        av, dav, sav = X[1]
        # Each row's share along u (and its derivatives), then summed over rows against v's.
        rows = np.einsum("jkp,ikp->ijp", self.patch, X[0])  # (3, 4, P)
        pa = rows[0]
        black = np.einsum("jp,jp->p", pa, av).astype(np.float64)
        dbu = np.einsum("jp,jp->p", rows[1], av).astype(np.float64)
        dbv = np.einsum("jp,jp->p", pa, dav).astype(np.float64)
        dbs = (np.einsum("jp,jp->p", rows[2], av) + np.einsum("jp,jp->p", pa, sav)).astype(np.float64)
        return black, dbu, dbv, dbs

    def _start_levels(self, C: np.ndarray) -> None:
        """The levels' starts from the pixels the start corners' model calls flat black / flat
        white (each tag's median grey through the inverse sRGB curve; a white near saturation
        starts above 1, where the curve clips)."""
        mb, nb = group_median_nan_propagating(self.obs, self.layout, C < 0.05)
        mw, nw = group_median_nan_propagating(self.obs, self.layout, C > 0.95)
        self.ok_tag &= (nb >= _MIN_LEVEL_PIXELS) & (nw >= _MIN_LEVEL_PIXELS)
        for t in np.flatnonzero(self.ok_tag):
            self.theta[t, 0] = srgb_to_linear_scalar(float(mb[t]) / 255.0)
            self.theta[t, 3] = srgb_to_linear_scalar(float(mw[t]) / 255.0) if mw[t] < 250 else 1.1

    def _grey_model(
        self, C: np.ndarray, uc: np.ndarray, vc: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """Each pixel's black and white levels (linear), model grey and its slope in linear light
        (d grey / d L), and with a free tone exponent kappa (kappa, the encoded value it raises)."""
        th = np.repeat(self.theta[:, :6].T, self.counts, axis=1)
        lb = th[0] + th[1] * uc + th[2] * vc
        lw = th[3] + th[4] * uc + th[5] * vc
        del th
        L = lb + (lw - lb) * C
        enc, slope = srgb_encode_slope(L)
        del L
        if not self.free_tone:
            return lb, lw, 255.0 * enc, 255.0 * slope, None
        kap = np.repeat(np.exp(self.theta[:, 7]), self.counts)
        encp = np.maximum(enc, 1e-4)
        model = 255.0 * encp ** kap
        fp = 255.0 * kap * encp ** (kap - 1.0) * slope
        return lb, lw, model, fp, (kap, encp)

    def _robust_weights(self, r: np.ndarray, model: np.ndarray) -> None:
        """Drop the pixels more than 4 robust sds off their tag's model (glare, a neighbour's
        edge), and measure each tag's misfit: its robust residual sd over its model's range."""
        n = len(self.h)
        ab = np.abs(r)
        mad = group_median_nan_propagating(ab, self.layout)[0]
        self.keep = ab <= np.maximum(4.0 * 1.4826 * mad[self.tag], 3.0)
        del ab
        # Each tag's model range (np.ptp per tag); a tag with no pixels has none.
        some = np.flatnonzero(self.counts)
        contrast = np.zeros(n)
        contrast[some] = (np.maximum.reduceat(model, self.starts[some])
                          - np.minimum.reduceat(model, self.starts[some]))
        self.contrast = contrast
        self.misfit = 1.4826 * mad / np.maximum(contrast, 1.0)

    def _jacobian(
        self, u: np.ndarray, v: np.ndarray, m: tuple[np.ndarray, ...], det: np.ndarray, dbu: np.ndarray,
        dbv: np.ndarray, dbs: np.ndarray, C: np.ndarray, uc: np.ndarray, vc: np.ndarray, lb: np.ndarray,
        lw: np.ndarray, model: np.ndarray, fp: np.ndarray, tone: tuple[np.ndarray, np.ndarray] | None,
    ) -> None:
        """The Jacobian's rows into ``self.J``, zero at dropped pixels (keep is 0/1, so
        J_k^T J_k = J_k^T J).

        d C / d h = g . d(x, y)/d h, g the image gradient of the black coverage: a pattern moved
        by +dx shows each pixel what lay dx to its left (C(x - dx): -dC/dx = +d black/dx). The
        image gradient of the black coverage is J^-T (d/du, d/dv) = adj(M)^T (dbu, dbv) den / det;
        d(x, y)/d h carries a 1 / den.
        """
        J, keep = self.J, self.keep
        m11, m12, m21, m22 = m
        dC = (lw - lb) * fp  # d grey / d C
        w = dC * keep / det
        gx = (m22 * dbu - m21 * dbv) * w
        gy = (m11 * dbv - m12 * dbu) * w
        np.multiply(gx, u, out=J[0])
        np.multiply(gx, v, out=J[1])
        J[2] = gx
        np.multiply(gy, u, out=J[3])
        np.multiply(gy, v, out=J[4])
        J[5] = gy
        gp = gx * self.px + gy * self.py
        np.multiply(gp, -u, out=J[6])
        np.multiply(gp, -v, out=J[7])
        fk = fp * keep
        fw = fk * C
        fb = fk - fw
        J[8] = fb
        np.multiply(fb, uc, out=J[9])
        np.multiply(fb, vc, out=J[10])
        J[11] = fw
        np.multiply(fw, uc, out=J[12])
        np.multiply(fw, vc, out=J[13])
        np.multiply(dbs * dC, keep, out=J[14])
        np.negative(J[14], out=J[14])
        if tone is not None:
            kap, encp = tone
            J[15] = model * np.log(encp) * kap * keep

    def _solve(self, rk: np.ndarray) -> None:
        """Each tag's damped, column-scaled normal equations solved (one batched solve; one by one
        if a tag's system is singular, which drops that tag) and the parameters updated; the blur
        scale is kept within 1/4..4 and the tone exponent within 1/2..2."""
        n, n_par, J, ok_tag = len(self.h), self.n_par, self.J, self.ok_tag
        A = np.tile(np.eye(n_par), (n, 1, 1))
        b = np.zeros((n, n_par))
        for t in np.flatnonzero(ok_tag):
            Js = J[:, self.starts[t]:self.starts[t] + self.counts[t]]
            A[t] = Js @ Js.T
            b[t] = Js @ rk[self.starts[t]:self.starts[t] + self.counts[t]]
        d = np.sqrt(np.maximum(np.diagonal(A, axis1=1, axis2=2), 1e-30))  # (n, n_par)
        As = A / d[:, :, None] / d[:, None, :] + _DAMPING * np.eye(n_par)
        step = np.zeros((n, n_par))
        try:
            step = np.linalg.solve(As, (b / d)[..., None])[..., 0] / d
        except np.linalg.LinAlgError:  # one singular tag: solve them one by one
            for t in np.flatnonzero(ok_tag):
                try:
                    step[t] = np.linalg.solve(As[t], b[t] / d[t]) / d[t]
                except np.linalg.LinAlgError:
                    ok_tag[t] = False
        step[~np.isfinite(step).all(axis=1)] = 0.0
        self.h = self.h + np.where(ok_tag[:, None], step[:, :8], 0.0)
        self.theta = self.theta + np.where(ok_tag[:, None], step[:, 8:], 0.0)
        if self.free_tone:
            self.theta[:, 7] = np.clip(self.theta[:, 7], np.log(0.5), np.log(2.0))
        self.theta[:, 6] = np.clip(self.theta[:, 6], np.log(0.25), np.log(4.0))


# ------------------------------------------------------------------------------------------------
# The moving tag's model (``photometric_kernels.coverage_moving`` / ``model_rows_moving``)
# ------------------------------------------------------------------------------------------------
def moving_model_grey(px: np.ndarray, py: np.ndarray, h: np.ndarray, theta: np.ndarray, table: np.ndarray,
                      warps: np.ndarray, sd_px: float, free_tone: bool) -> np.ndarray:
    """The grey a moving tag's model gives pixels (``px``, ``py``): the white coverage of the
    pattern at homography ``h`` (8,) seen through each of ``warps`` (K, 3, 3), averaged over them,
    mixed between the level planes of ``theta`` at the mean tag coordinates, through the sRGB curve
    (and the tone exponent): per quantity over all pixels, the normal CDF from scipy, in float64."""
    from scipy.special import ndtr

    H = np.append(h, 1.0).reshape(3, 3)
    Hi = np.linalg.inv(H)
    scale = sd_px * np.exp(theta[6])
    white = np.zeros(len(px))
    uv_sum = np.zeros((2, len(px)))
    for W in warps:
        q = W @ np.vstack([px, py, np.ones(len(px))])
        x, y = q[0] / q[2], q[1] / q[2]
        t = Hi @ np.vstack([x, y, np.ones(len(px))])
        u, v = t[0] / t[2], t[1] / t[2]
        uv_sum += (u, v)
        # The sds along u and v: the image Gaussian through the local inverse Jacobian.
        m11, m12, m21, m22 = H[0, 0] - H[2, 0] * x, H[0, 1] - H[2, 1] * x, H[1, 0] - H[2, 0] * y, H[1, 1] - H[2, 1] * y
        det = m11 * m22 - m12 * m21
        gd = scale * np.abs((H[2, 0] * u + H[2, 1] * v + 1.0) / det)
        sd_u, sd_v = np.hypot(m22, m12) * gd, np.hypot(m21, m11) * gd
        bu, bv = np.round(u), np.round(v)
        black = np.zeros(len(px))
        for j in range(4):
            for i in range(4):
                cu, cv = bu - 2 + i, bv - 2 + j  # the cell [cu, cu + 1) x [cv, cv + 1)
                share = ((ndtr((cu + 1 - u) / sd_u) - ndtr((cu - u) / sd_u))
                         * (ndtr((cv + 1 - v) / sd_v) - ndtr((cv - v) / sd_v)))
                ti = np.clip(cu + _PAD, 0, len(table) - 1).astype(int)
                tj = np.clip(cv + _PAD, 0, len(table) - 1).astype(int)
                black += table[tj, ti] * share
        white += 1.0 - black
    C = white / len(warps)
    uc, vc = (uv_sum / len(warps) - 4.0) / 4.0
    lb = theta[0] + theta[1] * uc + theta[2] * vc
    lw = theta[3] + theta[4] * uc + theta[5] * vc
    enc = srgb_encode_slope(lb + (lw - lb) * C)[0]
    if not free_tone:
        return 255.0 * enc
    return 255.0 * np.maximum(enc, 1e-4) ** np.exp(theta[7])
