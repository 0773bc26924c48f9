"""A tag-level photometric corner fit: the printed pattern, blurred in linear light, through a tone curve.

A lens blurs *light*; the camera's tone curve comes after the blur, so every black/white edge in the
8-bit image sits toward its black side by an amount that depends on the edge's own levels. The
cell-edge fit (``corners.fit_tag_edges``) models that as one constant shift per boundary direction
and reads each boundary from its own sample line, so noise limits it. This fits the whole tag at
once to the same pixels instead (docs/detection.md, "A tag-level photometric fit"):

    grey(x) = 255 f(Lb(u, v) + (Lw(u, v) - Lb(u, v)) C(u, v)),   (u, v) = H^-1(x)

with H the tag's homography (8 parameters, c0 at (0, 0), c2 at (8, 8) in cell units), C the
tag's white coverage blurred by a Gaussian PSF (sigma ``psf_sigma_px`` in image px, plus the
pixel's own area, 1/12 px^2), Lb / Lw the black and white levels in linear light, each a plane over
the tag (shading), and f the sRGB tone curve clipped at 1 (clipped highlights have f' = 0),
optionally raised to a free exponent (``free_tone``: other curves, gamma 1.8 or an S-curve, look
like sRGB to a power near 1 over the grey levels a tag shows).

The blurred pattern is evaluated analytically, no rendering: under the local affine approximation
of H at a pixel, an isotropic image Gaussian of sigma s is a Gaussian in tag units whose marginal
sd along u is s |grad u| (and along v, s |grad v|); a blurred cell is then the product of two
differences of normal CDFs (exact along a straight edge, approximate within a blur radius of a cell
corner, where the Gaussian's u-v correlation under shear is dropped). Only the 4 x 4 cells around
the nearest boundary crossing matter (the blur is at most half a cell at the smallest cells fitted).
The blur's scale is fitted per tag (``psf_sigma_px`` only starts it: a wrong fixed blur would move
the corners outward for a blur assumed too wide, inward for one too narrow).

Pixels: those within ``reach_px`` plus 1.5 blur sds of a black/white cell boundary (the rest are
flat and say nothing about H), on the tag's 10 x 10-cell face, chosen once at the start corners;
a large tag's thinned evenly to ``max_pixels``. Gauss-Newton
(Levenberg-damped) over H, the levels, a blur scale and the exponent, tag by tag (16 x 16 normal
equations), pixels more than 4 robust sds off dropped after the first step (glare specks, a
neighbour's edge); a tag stops once a step from the second on moves no corner further than
``converged_px``. A tag whose fit fails, that would move a corner more than ``max_move_cells`` of
a cell, or whose residual sd exceeds ``_MAX_MISFIT`` of its contrast keeps its input corners.

This module sets a frame's fit up (the tags' tables, face boxes and inverse homographies) and
judges its outcome; the per-pixel work (the pixels' selection, the model, its Jacobian and the
steps) is compiled (``ficap_ros.vision.photometric_kernels``, numba). The fit costs more CPU per tag
than the cell-edge fit (docs/benchmarks.md), so by default it runs on the tags whose corners noise
limits (``DetectorConfig.edge_photometric_auto``, ``ficap_ros.vision.tag_noise``), on every tag with
``DetectorConfig.edge_photometric``; this module (and numba) is imported only when it runs
(``corners.fit_tags_photometric``).
"""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS, homography_corners, tag_homographies
from ficap_ros.vision.photometric_kernels import PAD as _PAD
from ficap_ros.vision.photometric_kernels import (
    fit_steps,
    fit_steps_moving,
    select_pixels,
)

__all__ = ["fit_tags", "motion_warps", "PSF_SIGMA_PX"]

#: Lens PSF sigma, px, assumed when the recording's is unknown: where the per-tag blur scale
#: starts; a typical camera's lens blur, within the range the fit converges from.
PSF_SIGMA_PX = 0.6
#: Least grey-level range of a fitted tag's model: below it there is no pattern to fit (as
#: ``decode_tags`` asks of a border).
_MIN_CONTRAST = 10.0
#: Largest robust residual sd of a fitted tag, as a fraction of its model's contrast: a start a
#: cell or more off settles in a false minimum whose residuals are a large part of the contrast.
_MAX_MISFIT = 0.3
#: Fewest selected pixels a tag needs to be fitted.
_MIN_PIXELS = 40
#: Fewest pixels the start corners call flat black and flat white that set a tag's first levels.
_MIN_LEVEL_PIXELS = 5
#: Levenberg damping on the column-scaled normal equations (``fit_tags``' ``damping``).
DAMPING = 1e-3
#: A still tag stops once a step (from the second on) moves no corner further than this, px
#: (``fit_tags``' ``converged_px``): far below the corners' noise, so the steps after it move
#: nothing that matters.
STILL_CONVERGED_PX = 0.02
#: Most a moving tag's corners move between the instants its light is averaged over, in blur sds
#: (``motion_warps``; ``fit_tags``' ``instant_spacing_sds``): Gaussians two sds apart sum to their
#: box-blurred one within exp(-pi^2 / 2), under 1 % of the step (Poisson summation:
#: exp(-2 pi^2 / spacing^2)), a ripple symmetric about each instant that moves no corner; the
#: fit's cost grows with the instants.
INSTANT_SPACING_SDS = 2.0


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
def _select_pixels(shape: tuple[int, int], hom: np.ndarray, tables: np.ndarray, sd_px: float,
                   reach_px: float | np.ndarray, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (x, y) within ``reach_px`` (plus 1.5 ``sd_px``) of a black/white boundary of each
    tag's face: (tag of each, x, y) as int arrays, tag after tag, each tag's row by row; a tag with
    more than ``max_pixels`` is thinned to that many, evenly (a narrower band would lose the flat
    pixels the levels need). A pixel is near a boundary when the cells within the reach each way
    hold both colours (``photometric_kernels.select_pixels``)."""
    z = np.zeros(0, dtype=np.int64)
    if len(hom) == 0:
        return z, z, z
    use, box, hom_inv, reach = _face_boxes(shape, hom, sd_px, reach_px)
    if len(use) == 0:
        return z, z, z
    sat = np.zeros((len(tables), tables.shape[1] + 1, tables.shape[2] + 1), dtype=np.int32)
    sat[:, 1:, 1:] = tables.cumsum(1).cumsum(2)
    return select_pixels(hom_inv, np.ascontiguousarray(box, dtype=np.int64), use.astype(np.int64), reach,
                         sat, int(max_pixels))


def _face_boxes(
    shape: tuple[int, int], hom: np.ndarray, sd_px: float, reach_px: float | np.ndarray
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


# ------------------------------------------------------------------------------------------------
# Motion over the exposure
# ------------------------------------------------------------------------------------------------
def motion_warps(corners_px: np.ndarray, motion_px: np.ndarray, spacing_px: float,
                 bend_px: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The instants a moving tag is averaged over, as image warps (``fit_steps_moving``).

    Each tag's corners move by ``motion_px`` over the exposure: at instant s (-1/2 .. 1/2 of the
    exposure from its middle) corner j is at ``corners_px[j] + s motion_px[j] + 4 s^2
    bend_px[j]`` (``bend_px``: how far the path's ends lie beyond the straight line through the
    mid-exposure corner, a motion that speeds up or slows down over the exposure: 1/8 of the
    acceleration times the exposure squared; None: constant velocity). The instants are the midpoints of K equal parts of the exposure, K such that
    no corner moves more than ``spacing_px`` from one to the next (a sum of Gaussian-blurred
    patterns this close is their box-blurred one to well under a grey level); a tag that does not
    move has one, the identity.

    Args:
        corners_px: (N, 4, 2) mid-exposure corners.
        motion_px: (N, 4, 2) each corner's motion over the exposure (end minus start), px.
        spacing_px: the most a corner moves between instants, px.
        bend_px: (N, 4, 2) the path's bend, px, or None.

    Returns:
        (warps (N, K, 3, 3): image px at each instant -> image px at mid-exposure (the identity
        beyond a tag's own count), instants (N,) int64 each tag's count K_t, K the largest).
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    m = np.asarray(motion_px, dtype=np.float64).reshape(-1, 4, 2)
    length = np.linalg.norm(m, axis=2).max(axis=1)
    instants = np.maximum(np.ceil(length / spacing_px), 1).astype(np.int64)
    k_max = int(instants.max()) if len(instants) else 1
    warps = np.tile(np.eye(3), (len(c), k_max, 1, 1))
    if k_max == 1:
        return warps, instants
    h_mid = tag_homographies(c)
    for t in np.flatnonzero(instants > 1):
        s = (np.arange(instants[t]) + 0.5) / instants[t] - 0.5
        at = c[t][None] + s[:, None, None] * m[t][None]
        if bend_px is not None:
            at = at + (4.0 * s * s)[:, None, None] * np.asarray(bend_px, dtype=np.float64).reshape(-1, 4, 2)[t][None]
        h_k = tag_homographies(at)
        warps[t, :instants[t]] = h_mid[t] @ np.linalg.inv(h_k)
    return warps, instants


# ------------------------------------------------------------------------------------------------
# The model
# ------------------------------------------------------------------------------------------------
def fit_tags(
    gray: np.ndarray, corners_px: np.ndarray, hom: np.ndarray, cells: np.ndarray,
    psf_sigma_px: float = PSF_SIGMA_PX,
    iterations: int = 3, reach_px: float = 1.0, free_tone: bool = True, max_move_cells: float = 0.35,
    max_pixels: int = 1500, motion_px: np.ndarray | None = None, converged_px: float | None = None,
    bend_px: np.ndarray | None = None, damping: float = DAMPING,
    instant_spacing_sds: float = INSTANT_SPACING_SDS,
) -> tuple[np.ndarray, np.ndarray]:
    """Fit each tag's homography and levels to its pixels (module docstring).

    With ``motion_px`` the pattern moves over the exposure (motion blur): each pixel's light is
    the mean over the exposure's instants (``motion_warps``), in linear light before the tone
    curve, and the fitted corners are the mid-exposure ones; the pixels fitted reach half the
    tag's motion further from a boundary.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) starting corners (the cell-edge fit's; within a few tenths of a px).
        hom: (N, 3, 3) their homographies from tag cell units (``tag36h11.tag_homographies``).
        cells: (N, 8, 8) each tag's cells, True = black (``tag36h11.tag_cells``).
        psf_sigma_px: lens PSF sigma, px (linear light), where the per-tag blur scale starts.
        iterations: the most Gauss-Newton steps, at least 2 (a tag's misfit, which decides
            whether it is fitted, is measured from the second step on).
        reach_px: pixels used lie within this (plus 1.5 blur sds) of a black/white boundary.
        free_tone: also fit an exponent on the sRGB curve.
        max_move_cells: a tag moving any corner further than this (cells) keeps its input.
        max_pixels: most pixels fitted a tag (a larger tag's are thinned evenly).
        motion_px: (N, 4, 2) each corner's image motion over the exposure (end minus start), px;
            None: the tags are still.
        converged_px: a tag stops once a step (from the second on) moves no corner further
            than this, px; None: ``STILL_CONVERGED_PX`` for still tags, 0 (every step) with
            ``motion_px``.
        bend_px: with ``motion_px``, (N, 4, 2) how each corner's path bends over the exposure
            (``motion_warps``), or None: constant velocity.
        damping: Levenberg damping on the column-scaled normal equations: less damping walks
            along the parameters' weakly determined combinations (the tone exponent against the
            levels and the blur) in fewer steps.
        instant_spacing_sds: with ``motion_px``, the most a corner moves between the instants
            averaged, in blur sds (``motion_warps``); the moving fit's cost grows with the instants.

    Returns:
        (corners (N, 4, 2), fitted (N,) bool): a tag not fitted keeps its input corners.
    """
    if iterations < 2:
        raise ValueError(f"iterations must be >= 2, got {iterations}")
    if not (damping > 0.0 and instant_spacing_sds > 0.0):
        raise ValueError(f"damping and instant_spacing_sds must be > 0, got {damping}, {instant_spacing_sds}")
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    hom = np.asarray(hom, dtype=np.float64).reshape(n, 3, 3)
    cells = np.asarray(cells).reshape(n, TAG_CELLS, TAG_CELLS)
    fitted = np.zeros(n, dtype=bool)
    if n == 0:
        return c_in.copy(), fitted
    hom = hom / hom[:, 2:3, 2:3]
    tab = _black_tables(cells)  # (N, S, S)
    sd_px = float(np.sqrt(psf_sigma_px ** 2 + 1.0 / 12.0))  # the PSF and the pixel's area
    still = motion_px is None
    if converged_px is None:
        converged_px = STILL_CONVERGED_PX if still else 0.0
    reach: float | np.ndarray = reach_px
    if motion_px is not None:
        motion_px = np.asarray(motion_px, dtype=np.float64).reshape(n, 4, 2)
        reach = reach_px + 0.5 * np.linalg.norm(motion_px, axis=2).max(axis=1)
    tag, xi, yi = _select_pixels(gray.shape[:2], hom, tab, sd_px, reach, max_pixels)
    if len(tag) == 0:
        return c_in.copy(), fitted
    counts = np.bincount(tag, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    h = hom.reshape(n, 9)[:, :8].copy()
    theta = np.zeros((n, 8 if free_tone else 7))  # levels (2 planes), log blur scale, log tone exponent
    args = (gray[yi, xi].astype(np.float64), xi.astype(np.float64), yi.astype(np.float64), starts, counts,
            h, theta, tab)
    settings = (sd_px, bool(free_tone), int(iterations), _MIN_PIXELS, _MIN_LEVEL_PIXELS,
                float(damping))
    if motion_px is None:
        ok, misfit, contrast = fit_steps(*args, *settings, float(converged_px))
    else:
        warps, instants = motion_warps(c_in, motion_px, instant_spacing_sds * sd_px, bend_px)
        ok, misfit, contrast = fit_steps_moving(*args, warps, instants, *settings, float(converged_px))
    corners = homography_corners(h)
    cell = np.linalg.norm(c_in[:, [1, 2, 3, 0]] - c_in, axis=2).min(axis=1) / TAG_CELLS
    moved = np.linalg.norm(corners - c_in, axis=2).max(axis=1)
    # A tag whose model shows no contrast (a flat region, a blown-out tag) has no pattern to fit:
    # its zero misfit says nothing.
    fitted = (ok & np.isfinite(corners).all(axis=(1, 2)) & (moved <= max_move_cells * cell)
              & (misfit <= _MAX_MISFIT) & (contrast >= _MIN_CONTRAST))
    return np.where(fitted[:, None, None], corners, c_in), fitted
