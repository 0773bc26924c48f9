"""A tag-level photometric corner fit: the printed pattern, blurred in linear light, through a tone curve.

Why (issue 10; docs/detection.md "A tag-level photometric fit"): a lens blurs *light*; the camera's
tone curve comes after the blur, so every black/white edge in the 8-bit image sits toward its black
side by an amount that depends on the edge's own levels. The cell-edge fit (``detection.fit_tag_edges``)
models that as one constant shift per boundary direction and reads each boundary from its own sample
line; on noisy frames its error stops well above what the pixels allow. This fits the whole tag at
once to the same pixels instead:

    grey(x) = 255 f(Lb(u, v) + (Lw(u, v) - Lb(u, v)) C(u, v)),   (u, v) = H^-1(x)

with H the tag's homography (8 parameters, c0 at (0, 0), c2 at (8, 8) in cell units), C the
tag's white coverage blurred by a Gaussian PSF (sigma ``psf_sigma_px`` in image px, plus the
pixel's own area, 1/12 px^2), Lb / Lw the black and white levels in linear light, each a plane over
the tag (shading), and f an assumed sRGB tone curve clipped at 1 (clipped highlights have f' = 0),
optionally raised to a free exponent (``free_tone``: other curves, gamma 1.8 or an S-curve, look
like sRGB to a power near 1 over the grey levels a tag shows).

The blurred pattern is evaluated analytically, no rendering: under the local affine approximation
of H at a pixel, an isotropic image Gaussian of sigma s is a Gaussian in tag units whose marginal
sd along u is s |grad u| (and along v, s |grad v|); a blurred cell is then the product of two
differences of normal CDFs (exact along a straight edge, approximate within a blur radius of a cell
corner, where the Gaussian's u-v correlation under shear is dropped). Only the 4 x 4 cells around
the nearest boundary crossing matter (the blur is at most half a cell at the smallest cells fitted).
The blur's scale is fitted per tag (``psf_sigma_px`` only starts it: a wrong fixed blur moves the
corners by about a fifth of its error, outward for a blur assumed too wide).

Pixels: those within ``reach_px`` plus 1.5 blur sds of a black/white cell boundary (the rest are
flat and say nothing about H), on the tag's 10 x 10-cell face, chosen once at the start corners;
a large tag's thinned evenly to ``max_pixels``. Gauss-Newton (Levenberg-damped) over H, the
levels, a blur scale and the exponent of up to 12 tags at once (per-tag 16 x 16 normal equations),
pixels more than 4 robust sds off dropped after the first step (glare specks, a neighbour's edge).
A tag whose fit fails, that would move a corner more than ``max_move_cells`` of a cell, or whose
residual sd exceeds ``_MAX_MISFIT`` of its contrast keeps its input corners.

Cost: ~0.9 ms of CPU a tag on a tracked 1080p frame, ~0.8 ms at 540p in low light (docs/benchmarks.md),
hence opt-in (``DetectorConfig.edge_photometric``).
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ficap_ros.geometry.tag36h11 import TAG_CELLS

__all__ = ["fit_tags", "PSF_SIGMA_PX"]

#: Default lens PSF sigma, px, assumed when the recording's is unknown: the middle of issue 10's
#: realistic range (0.4-1.0 px); the fit is insensitive to it within that range (docs/detection.md).
PSF_SIGMA_PX = 0.6
#: Cells padded around the 8 x 8 tag (white: quiet zone and beyond) so a 5 x 5 neighbourhood of any
#: face pixel stays inside the table.
_PAD = 3
#: Least grey-level range of a fitted tag's model: below it there is no pattern to fit.
_MIN_CONTRAST = 10.0
#: Most tags fitted at once (``fit_tags``: a chunk's pixel arrays stay in cache).
_CHUNK_TAGS = 12
#: Largest robust residual sd of a fitted tag, as a fraction of its model's contrast.
_MAX_MISFIT = 0.3


def _black_tables(cells: np.ndarray) -> np.ndarray:
    """(N, 8 + 2 _PAD, 8 + 2 _PAD) tables of the tags' black cells (float 0/1), cell (i, j) of tag
    t at [t, j + _PAD, i + _PAD]; white (quiet zone and beyond) around them."""
    cells = np.asarray(cells, dtype=bool).reshape(-1, TAG_CELLS, TAG_CELLS)
    t = np.zeros((len(cells), TAG_CELLS + 2 * _PAD, TAG_CELLS + 2 * _PAD))
    t[:, _PAD:_PAD + TAG_CELLS, _PAD:_PAD + TAG_CELLS] = cells
    return t


def _srgb(lin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sRGB encoding of linear values clipped at 1 (values below 0 stay on its linear toe), and its slope."""
    v = np.minimum(lin, 1.0)
    pos = np.maximum(v, 0.0031308)
    hi = v > 0.0031308
    enc = np.where(hi, 1.055 * pos ** (1.0 / 2.4) - 0.055, 12.92 * v)
    slope = np.where(hi, (1.055 / 2.4) * pos ** (1.0 / 2.4 - 1.0), 12.92)
    return enc, np.where(lin >= 1.0, 0.0, slope)


def _srgb_inv(enc: float) -> float:
    """The linear value of an sRGB-encoded one (clipped to [0, 1]); Python floats: libm's pow, as
    numpy's scalars use (numpy's array pow can round apart)."""
    y = min(max(enc, 0.0), 1.0)
    return y / 12.92 if y <= 0.04045 else ((y + 0.055) / 1.055) ** 2.4


def _select_pixels(shape: tuple[int, int], hom: np.ndarray, tables: np.ndarray, sd_px: float,
                   reach_px: float, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (x, y) within ``reach_px`` of a black/white boundary of each tag's face: (tag of each,
    x, y) as int arrays, tag after tag."""
    h_img, w_img = shape
    n = len(hom)
    z = np.zeros(0, dtype=np.intp)
    if n == 0:
        return z, z, z
    # Each tag's face box, inverse homography and reach, all tags at once (the same values as
    # tag by tag: a stacked matmul, inv and norm run the same loops per tag).
    face = np.array([[-1, -1, 1], [9, -1, 1], [9, 9, 1], [-1, 9, 1]], float)
    q = face @ hom.transpose(0, 2, 1)  # (N, 4, 3)
    xy = q[..., :2] / q[..., 2:]
    lo, hi = np.floor(xy.min(axis=1)).astype(int), np.ceil(xy.max(axis=1)).astype(int)
    x0, y0 = np.maximum(lo[:, 0], 1), np.maximum(lo[:, 1], 1)
    x1, y1 = np.minimum(hi[:, 0], w_img - 2), np.minimum(hi[:, 1], h_img - 2)
    use = np.flatnonzero((x1 - x0 >= 3) & (y1 - y0 >= 3))
    if len(use) == 0:
        return z, z, z
    Hi = np.zeros((n, 3, 3))
    Hi[use] = np.linalg.inv(hom[use])
    # Reach in cell units from the face's mean px per cell (a selection, not the model: an
    # approximation is fine).
    side = np.linalg.norm(xy[:, [1, 2, 3, 0]] - xy, axis=2).mean(axis=1) / 10.0  # px per cell (face = 10 cells)
    r = (reach_px + 1.5 * sd_px) / np.maximum(side, 1e-6)
    # Black cells in the box [u - r, u + r] x [v - r, v + r] by a summed-area table: a pixel is
    # near a boundary when the box holds both colours.
    size = tables.shape[1]
    last = size - 1
    stride = size + 1
    sat = np.zeros((n, stride, stride), dtype=np.int32)  # counts: exact
    sat[:, 1:, 1:] = tables.cumsum(1).cumsum(2)
    # Where the reach is under a cell, a box spans at most 4 cells a side (floor(u + r) - floor(u - r)
    # <= floor(2 r) + 1, one more from rounding), so whether each box (first cell, cells - 1) of each
    # tag holds both colours is a table: one lookup a pixel instead of four.
    runs = 4
    first = np.arange(size)
    end = np.minimum(first[:, None] + np.arange(runs), last) + 1  # (first cell, cells - 1) -> end
    black = (sat[:, end[:, :, None, None], end[None, None]] - sat[:, first[:, None, None, None], end[None, None]]
             - sat[:, end[:, :, None, None], first[None, None, :, None]]
             + sat[:, first[:, None, None, None], first[None, None, :, None]])  # (N, v0, dv, u0, du)
    span = end - first[:, None]
    mixed = ((black > 0) & (black < span[:, :, None, None] * span[None, None])).ravel()
    per_tag = size * runs * size * runs
    tags, cols, rows = [], [], []
    for t in use:
        # Tag coordinates of the box's pixels: numerators and denominator as outer sums of a
        # row term and a column term (the same sums, in the same order, as per pixel).
        xs, ys = np.arange(x0[t], x1[t] + 1, dtype=np.float64), np.arange(y0[t], y1[t] + 1, dtype=np.float64)
        H = Hi[t]
        u = np.add.outer(H[0, 1] * ys, H[0, 0] * xs).ravel() + H[0, 2]
        v = np.add.outer(H[1, 1] * ys, H[1, 0] * xs).ravel() + H[1, 2]
        den = np.add.outer(H[2, 1] * ys, H[2, 0] * xs).ravel() + H[2, 2]
        u /= den
        v /= den
        on = np.flatnonzero((u > -0.9) & (u < TAG_CELLS + 0.9) & (v > -0.9) & (v < TAG_CELLS + 0.9))
        u, v = u.take(on), v.take(on)
        rt = r[t]
        # Box edges as rows / columns of the padded table (floors taken as floats, then one cast).
        if rt < 1.0:  # on the face such a box stays inside the padded table (no clipping): the table
            edges = []
            for c, sgn in ((u, -rt), (u, rt), (v, -rt), (v, rt)):
                e = c + sgn
                np.floor(e, out=e)
                edges.append(e.astype(np.intp))
            lo_u, hi_u, lo_v, hi_v = edges
            hi_u -= lo_u
            hi_v -= lo_v
            lo_v *= runs  # ((v0 runs + dv) size + u0) runs + du, cells counted from the table's
            lo_v += hi_v
            lo_v *= size
            lo_v += lo_u
            lo_v *= runs
            lo_v += hi_u
            lo_v += t * per_tag + ((_PAD * runs) * size + _PAD) * runs
            near = np.flatnonzero(mixed.take(lo_v))
        else:  # a tag of a few px: clipped, by the summed-area table (np.take: cheaper than 2-D fancy indexing)
            flat = sat[t].ravel()
            lo_u = np.clip(np.floor(u - rt) + _PAD, 0, last).astype(np.intp)
            hi_u = np.clip(np.floor(u + rt) + _PAD, 0, last).astype(np.intp) + 1
            lo_v = np.clip(np.floor(v - rt) + _PAD, 0, last).astype(np.intp) * stride
            hi_v = (np.clip(np.floor(v + rt) + _PAD, 0, last).astype(np.intp) + 1) * stride
            count = (flat.take(hi_v + hi_u) - flat.take(lo_v + hi_u) - flat.take(hi_v + lo_u)
                     + flat.take(lo_v + lo_u))
            near = np.flatnonzero((count > 0) & (count < (hi_u - lo_u) * ((hi_v - lo_v) // stride)))
        if len(near) > max_pixels:  # a large tag: every k-th pixel (a narrower band loses the levels)
            near = near[np.linspace(0, len(near) - 1, max_pixels).astype(np.intp)]
        gy, gx = np.divmod(on.take(near), len(xs))
        tags.append(np.full(len(near), t))
        cols.append(gx + x0[t])
        rows.append(gy + y0[t])
    return np.concatenate(tags), np.concatenate(cols), np.concatenate(rows)


def _group_median(x: np.ndarray, group: np.ndarray, pos: np.ndarray, n: int, width: int,
                  mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """np.median of each group's (masked) entries, all groups at once: ((n,) medians, 0 for a group
    with none; (n,) entries counted). ``group``: each entry's group (0..n-1, entries group after
    group); ``pos``: its place in the group's run; ``width``: the longest run. Equal to np.median
    per group bit for bit: the middle one of a sorted run, or the mean of the middle two, (a + b) / 2
    (a run with a NaN: NaN)."""
    pad = np.full((n, width), np.inf)  # runs padded with +inf, sorted to each row's end
    if mask is None:
        pad[group, pos] = x
        cnt = np.bincount(group, minlength=n)
        nan = np.isnan(x)
    else:
        pad[group, pos] = np.where(mask, x, np.inf)
        cnt = np.bincount(group, weights=mask, minlength=n).astype(np.intp)
        nan = np.isnan(x) & mask
    pad.sort(axis=1)
    rows = np.arange(n)
    lo, hi = np.maximum(cnt - 1, 0) // 2, np.minimum(cnt // 2, width - 1)
    med = (pad[rows, lo] + pad[rows, hi]) / 2.0
    if nan.any():  # np.median's answer for a run with a NaN
        med[np.bincount(group[nan], minlength=n) > 0] = np.nan
    return np.where(cnt > 0, med, 0.0), cnt


def _ndtr32(z: np.ndarray, gauss: np.ndarray) -> np.ndarray:
    """The normal CDF of float32 ``z`` given ``gauss`` = exp(-z^2 / 2): Abramowitz & Stegun 7.1.26
    (erfc to 1.5e-7, i.e. the CDF to 7.5e-8, about float32's rounding of it), reusing the Gaussian
    the fit needs anyway: a third of scipy's ndtr's time here."""
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
        reach_px: pixels used lie within this (plus two blur sigmas) of a black/white boundary.
        free_tone: also fit an exponent on the sRGB curve.
        max_move_cells: a tag moving any corner further than this (cells) keeps its input.

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
        # Every tag's fit is its own, so a frame's tags are fitted a few at a time (the same numbers):
        # the per-pixel arrays of ~11 tags stay in cache and their memory is reused from chunk to
        # chunk, where all 21 tags of a 1080p frame at once need ~20 MB, fresh pages each frame
        # when the allocator has given the last frame's back (a fifth of the time, when it has).
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
    obs = gray[yi, xi].astype(np.float64)
    px, py = xi.astype(np.float64), yi.astype(np.float64)
    counts = np.bincount(tag, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(tag)) - starts[tag]  # each pixel's place in its tag's run
    lmax = int(counts.max())
    h = hom.reshape(n, 9)[:, :8].copy()
    n_par = 8 + 7 + (1 if free_tone else 0)
    theta = np.zeros((n, n_par - 8))  # Lb0, Lb_u, Lb_v, Lw0, Lw_u, Lw_v, log blur scale, [log kappa]
    keep = np.ones(len(tag), dtype=bool)
    ks32 = np.arange(-2, 3, dtype=np.float32)[:, None]  # cell boundaries b + k, k = -2..2
    size = tab.shape[1]
    # Every 4 x 4 block of each tag's table, row-major ([v, u]): block (r, c) holds cells r..r+3,
    # c..c+3; a pixel's block is one row of this (a 16-value gather instead of 16 gathers).
    win = sliding_window_view(tab, (4, 4), axis=(1, 2))  # (N, S - 3, S - 3, 4, 4)
    nwin = win.shape[1]
    blocks_t = np.ascontiguousarray(win.reshape(-1, 16).T, dtype=np.float32)  # (16, blocks)
    ok_tag = counts >= 40
    lam = 1e-3
    misfit = np.full(n, np.inf)
    contrast = np.zeros(n)
    # Per-pixel arrays are laid out (quantity, pixel): rows are contiguous, which keeps numpy's
    # broadcasting and the normal equations' products cheap (the fit's cost is all elementwise).
    J = np.empty((n_par, len(tag)))
    X = np.empty((2, 3, 4, len(tag)), dtype=np.float32)  # filled anew at each step
    for it in range(iterations):
        # Each tag's parameters, repeated over its pixels (pixels come tag after tag).
        a11, a12, a13, a21, a22, a23, a31, a32 = np.repeat(h.T, counts, axis=1)
        # Tag coordinates of each pixel: the inverse of H (per pixel: H differs per tag).
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
        scale = np.repeat(sd_px * np.exp(theta[:, 6]), counts)  # exp per tag, not per pixel
        gd = scale * np.abs(den / det)
        su = np.hypot(m22, m12) * gd
        sv = np.hypot(m21, m11) * gd
        if it == 0:
            # The 4 x 4 cells around the boundary crossing nearest the pixel: boundaries b - 2 .. b + 2
            # (b = round(u)) are at least 1.5 cells away on either side, 3 blur sds at half a cell.
            # Kept through the steps (a corner moves a few hundredths of a cell; the gather is costly).
            bu, bv = np.round(u), np.round(v)
            ci = np.clip(bu.astype(np.intp) + _PAD, 2, size - 2)
            cj = np.clip(bv.astype(np.intp) + _PAD, 2, size - 2)
            # [v, u, p]: the cells b - 2 .. b + 1 along each axis.
            patch = blocks_t.take((tag * nwin + cj - 2) * nwin + ci - 2, axis=1).reshape(4, 4, -1)
            del ci, cj
        # u and v stacked: [0] the boundaries along u, [1] along v (one ufunc call each).
        # In float32 (half the memory traffic of this, the fit's bulk): a share's rounding, 6e-8,
        # is 1e-5 of a grey level; with ``_ndtr32``, the corners moved by at most 1.3e-5 px against
        # the float64 version on every blender_dev set.
        isd = (1.0 / np.stack([su, sv])).astype(np.float32)[:, None, :]  # (2, 1, P)
        z = np.stack([bu - u, bv - v]).astype(np.float32)[:, None, :] + ks32  # (2, 5, P)
        z *= isd
        # Only boundaries within 9 sds are evaluated; the rest count as fully on one side (ndtr(-9) =
        # 1e-19, phi(9) = 1e-18). On a large tag most are tens of sds away: evaluated, they cost
        # ndtr's time for nothing and make exp() return subnormals, ~100x slower in every product.
        inner = np.flatnonzero(np.abs(z) < 9.0)  # (indices: cheaper than a boolean mask, used thrice)
        zi = z.take(inner)
        gauss = np.exp(np.float32(-0.5) * zi * zi)
        e = (z > 0.0).astype(np.float32)
        e.ravel()[inner] = _ndtr32(zi, gauss)
        phi = np.zeros_like(z)
        phi.ravel()[inner] = gauss * np.float32(0.3989422804014327)
        del inner, zi, gauss, su, sv, gd, scale, den
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
        rows = np.einsum("jkp,ikp->ijp", patch, X[0])  # (3, 4, P)
        pa = rows[0]
        black = np.einsum("jp,jp->p", pa, av).astype(np.float64)
        dbu = np.einsum("jp,jp->p", rows[1], av).astype(np.float64)
        dbv = np.einsum("jp,jp->p", pa, dav).astype(np.float64)
        dbs = (np.einsum("jp,jp->p", rows[2], av) + np.einsum("jp,jp->p", pa, sav)).astype(np.float64)
        del rows, pa, av, dav, sav
        C = 1.0 - black
        uc, vc = (u - 4.0) / 4.0, (v - 4.0) / 4.0
        if it == 0:
            # Levels from the pixels the model calls flat black / flat white.
            mb, nb = _group_median(obs, tag, pos, n, lmax, C < 0.05)
            mw, nw = _group_median(obs, tag, pos, n, lmax, C > 0.95)
            ok_tag &= (nb >= 5) & (nw >= 5)
            for t in np.flatnonzero(ok_tag):
                theta[t, 0] = _srgb_inv(float(mb[t]) / 255.0)
                theta[t, 3] = _srgb_inv(float(mw[t]) / 255.0) if mw[t] < 250 else 1.1
        th = np.repeat(theta[:, :6].T, counts, axis=1)
        lb = th[0] + th[1] * uc + th[2] * vc
        lw = th[3] + th[4] * uc + th[5] * vc
        del th
        L = lb + (lw - lb) * C
        enc, slope = _srgb(L)
        del L
        if free_tone:
            kap = np.repeat(np.exp(theta[:, 7]), counts)
            encp = np.maximum(enc, 1e-4)
            model = 255.0 * encp ** kap
            fp = 255.0 * kap * encp ** (kap - 1.0) * slope
        else:
            model = 255.0 * enc
            fp = 255.0 * slope
        r = obs - model
        if it >= 1:
            # Robust: pixels more than 4 robust sds off this tag's model (glare, a neighbour's edge).
            ab = np.abs(r)
            mad = _group_median(ab, tag, pos, n, lmax)[0]
            keep = ab <= np.maximum(4.0 * 1.4826 * mad[tag], 3.0)
            del ab
            # Each tag's model range (np.ptp per tag); a tag with no pixels has none.
            some = np.flatnonzero(counts)
            contrast = np.zeros(n)
            contrast[some] = (np.maximum.reduceat(model, starts[some])
                              - np.minimum.reduceat(model, starts[some]))
            misfit = 1.4826 * mad / np.maximum(contrast, 1.0)
        dC = (lw - lb) * fp  # d grey / d C
        # The Jacobian's rows, zero at dropped pixels (keep is 0/1, so J_k^T J_k = J_k^T J).
        # d C / d h = g . d(x, y)/d h, g the image gradient of the black coverage: a pattern moved
        # by +dx shows each pixel what lay dx to its left (C(x - dx): -dC/dx = +d black/dx).
        # The image gradient of the black coverage is J^-T (d/du, d/dv) = adj(M)^T (dbu, dbv) den / det;
        # d(x, y)/d h carries a 1 / den.
        w = dC * keep / det
        gx = (m22 * dbu - m21 * dbv) * w
        gy = (m11 * dbv - m12 * dbu) * w
        np.multiply(gx, u, out=J[0])
        np.multiply(gx, v, out=J[1])
        J[2] = gx
        np.multiply(gy, u, out=J[3])
        np.multiply(gy, v, out=J[4])
        J[5] = gy
        gp = gx * px + gy * py
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
        if free_tone:
            J[15] = model * np.log(encp) * kap * keep
        rk = r * keep
        # The step's pixel arrays go before the next step makes its own (each call's fresh pages
        # are a third of its time at 540p: its peak memory is its cost).
        del a31, a32, m11, m12, m21, m22, det, bx, by, u, v, black, dbu, dbv, dbs, C, uc, vc, lb, lw
        del enc, slope, model, fp, r, dC, w, gx, gy, gp, fk, fw, fb
        if free_tone:
            del kap, encp
        A = np.tile(np.eye(n_par), (n, 1, 1))
        b = np.zeros((n, n_par))
        for t in np.flatnonzero(ok_tag):
            Js = J[:, starts[t]:starts[t] + counts[t]]
            A[t] = Js @ Js.T
            b[t] = Js @ rk[starts[t]:starts[t] + counts[t]]
        d = np.sqrt(np.maximum(np.diagonal(A, axis1=1, axis2=2), 1e-30))  # (n, n_par)
        As = A / d[:, :, None] / d[:, None, :] + lam * np.eye(n_par)
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
        h = h + np.where(ok_tag[:, None], step[:, :8], 0.0)
        theta = theta + np.where(ok_tag[:, None], step[:, 8:], 0.0)
        if free_tone:
            theta[:, 7] = np.clip(theta[:, 7], np.log(0.5), np.log(2.0))
        theta[:, 6] = np.clip(theta[:, 6], np.log(0.25), np.log(4.0))
    full = np.concatenate([h, np.ones((n, 1))], axis=1).reshape(n, 3, 3)
    src = np.array([[0, 0, 1], [TAG_CELLS, 0, 1], [TAG_CELLS, TAG_CELLS, 1], [0, TAG_CELLS, 1]], float)
    p = np.einsum("nij,kj->nki", full, src)
    corners = p[..., :2] / p[..., 2:3]
    cell = np.linalg.norm(c_in[:, [1, 2, 3, 0]] - c_in, axis=2).min(axis=1) / TAG_CELLS
    moved = np.linalg.norm(corners - c_in, axis=2).max(axis=1)
    # A fit whose residual sd is a large part of the tag's contrast is not this pattern where it was
    # placed (a start a cell or more off settles in a false minimum: 0.35-0.6 on synth and
    # blender_dev, against at most 0.25 for right tags at low light, 0.02 in clean frames).
    # A tag whose model shows no contrast (a flat region, a blown-out tag) has no pattern to fit:
    # its zero misfit says nothing (the 10 grey levels ``decode_tags`` asks of a border).
    fitted = (ok_tag & np.isfinite(corners).all(axis=(1, 2)) & (moved <= max_move_cells * cell)
              & (misfit <= _MAX_MISFIT) & (contrast >= _MIN_CONTRAST))
    return np.where(fitted[:, None, None], corners, c_in), fitted
