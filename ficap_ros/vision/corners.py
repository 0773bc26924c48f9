"""The corner stage after the line fit: corners free of the camera's tone-curve bias.

A lens blurs *linear* light; the camera's tone curve (sRGB, gamma, an S-curve) and clipping then
move the grey-level midpoint of every black/white edge toward the black, by an amount delta that
depends on the curve, the blur and the contrast, none of which is known. The line fit of the outer
border edges (``ficap_ros.vision.edges``) therefore puts a tag's sides delta inside the tag. The
stage (``refine_tag_corners``) removes that bias with the tag's own pattern:

1. ``unbias_corners_edge``: the border's inner edge is biased the other way, so the measured border
   is 2 delta thinner than one cell; each side moves out by half the difference.
2. ``fit_tag_edges``: the tag's homography fitted to every black/white cell boundary at once,
   with one free shift per boundary direction.
3. Tags the fit refused, or whose cells then read wrong, are fitted again from other starts.
4. The photometric fit of the whole pattern (``fit_tags_photometric``,
   ``ficap_ros.vision.photometric``): of every tag (``DetectorConfig.edge_photometric``), or of
   the tags whose corners noise limits (``edge_photometric_auto``, ``tag_noise.noise_ratios``).
5. Tags too small or oblique to measure their own shift take the line estimator's bias measured
   on the fitted tags of the same call (``_line_bias``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from ficap_ros.geometry.tag36h11 import (
    TAG_CELLS,
    homography_corners,
    stacked_tag_cells,
    tag_cells,
    tag_homographies,
    usable_quads,
)
from ficap_ros.vision.cell_reads import cell_errors
from ficap_ros.vision.detector import DetectorConfig, as_gray
from ficap_ros.vision.edges import (
    NEXT,
    OPPOSITE,
    PREV,
    intersect_sides,
    line_windows,
    refine_corners_edge_ok,
    refine_corners_edge_wide,
    side_lines,
    step_offset,
    vector_norm,
)
from ficap_ros.vision.fit_kernels import border_unbias, edge_fit
from ficap_ros.vision.kernels import frozen
from ficap_ros.vision.medians import (
    row_median,
)
from ficap_ros.vision.tag_noise import noise_ratios

__all__ = [
    "refine_tag_corners",
    "unbias_corners_edge",
    "shift_tag_edges",
    "fit_tag_edges",
    "fit_tags_photometric",
]

#: Fewest px a cell must span across an edge for the edge to be measured next to its neighbours:
#: a window of half a cell each way must hold the blurred step and stay off the next edge.
_MIN_CELL_PX = 2.0
#: ... and a tag is fitted on its own when its cells span this much across both axes.
_MIN_TAG_CELL_PX = 2.0
#: A sample's contrast must be at least this share of a clean reference (the quiet zone across
#: the border; a tag's 90th percentile): darker means its window saw a neighbouring cell.
_MIN_CONTRAST_RATIO = 0.7
#: Cells of its own code (of 64) a fitted tag may read wrong at its fitted corners (noise at
#: low light); more, and a corner is off by about a cell.
_MAX_FIT_CELL_ERRORS = 1
#: Where the inner edge of the border is sampled across a white data cell (fractions of the cell
#: along the side): away from the cell's ends, where the neighbouring black cells blur in.
_INNER_FRACTIONS = (0.35, 0.5, 0.65)
#: Tag-unit step from a side's inner edge to its outer edge (sides 0..3: top, right, bottom, left).
_SIDE_OUT = frozen(np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]))
#: Samples' worth of prior weight of a tag's mean delta on each side (three samples = one cell).
_SIDE_PRIOR_SAMPLES = 3.0
#: Where each cell boundary is sampled (fractions of its length: away from the cell corners, where
#: the blur mixes in the cells diagonally across). The fit's error is mostly the pixels' noise, so
#: three profiles a boundary (more of its pixels) give lower-scatter corners than two.
_EDGE_FRACTIONS = (0.25, 0.5, 0.75)
#: Samples across each boundary's window (half a cell each way; nine resolve the step as well as
#: more do, for less time).
_FIT_PROFILE_SAMPLES = 9
#: Fewest trusted profiles (the fit's rows) a tag's cell-edge fit needs in all and per boundary
#: direction; fewer leave the tag its border-line corners.
_MIN_FIT_ROWS, _MIN_FIT_ROWS_PER_DIRECTION = 24, 12
#: Points per side of a fitted tag where ``_line_bias`` measures its outer edge, and the most
#: fitted tags it uses (spread over the call's order).
_BIAS_POINTS = np.linspace(0.2, 0.8, 7)
_BIAS_TAGS = 8


# --- Where each tag's edges are, in tag cell units (c0 at (0, 0), x right, y down) ----------
@lru_cache(maxsize=None)
def _inner_edge_samples(tag_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points on the inner edge of the black border, where a white data cell borders it.

    Returns (side (S,) int, uv (S, 2) in tag cell units). Side k runs from corner k to corner
    k + 1: 0 top (inner edge y = 1), 1 right (x = 7), 2 bottom (y = 7), 3 left (x = 1).
    """
    cells = tag_cells(tag_id)
    sides, uv = [], []
    for j in range(1, TAG_CELLS - 1):
        for f in _INNER_FRACTIONS:
            t = j + f
            for side, white, point in (
                (0, not cells[1, j], (t, 1.0)),
                (1, not cells[j, TAG_CELLS - 2], (TAG_CELLS - 1.0, t)),
                (2, not cells[TAG_CELLS - 2, j], (t, TAG_CELLS - 1.0)),
                (3, not cells[j, 1], (1.0, t)),
            ):
                if white:
                    sides.append(side)
                    uv.append(point)
    out = np.array(sides, dtype=np.int64), np.array(uv, dtype=np.float64).reshape(-1, 2)
    for a in out:
        a.setflags(write=False)
    return out


@lru_cache(maxsize=None)
def _cell_edge_samples(tag_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points on every black/white cell boundary of a tag and its white quiet zone.

    Returns (uv (S, 2) in tag cell units; nu (S, 2) the boundary's unit normal in tag units,
    pointing from the black cell to the white one). Each boundary is one cell long and sampled at
    ``_EDGE_FRACTIONS`` of its length.
    """
    cells = np.ones((TAG_CELLS + 2, TAG_CELLS + 2), dtype=bool)  # True = white, with the quiet zone
    cells[1:-1, 1:-1] = ~tag_cells(tag_id)
    uv, nu = [], []
    size = TAG_CELLS + 2
    for r in range(size):
        for c in range(size):
            for dr, dc in ((0, 1), (1, 0)):
                r2, c2 = r + dr, c + dc
                if r2 >= size or c2 >= size or cells[r, c] == cells[r2, c2]:
                    continue
                # Boundary between cell (r, c) and its right (dc) or lower (dr) neighbour, in tag
                # units where the tag's cell (0, 0) spans [0, 1]: grid index i -> i - 1.
                sign = 1.0 if cells[r2, c2] else -1.0  # +: the neighbour is the white one
                for f in _EDGE_FRACTIONS:
                    if dc:
                        uv.append((c2 - 1.0, r - 1.0 + f))
                        nu.append((sign, 0.0))
                    else:
                        uv.append((c - 1.0 + f, r2 - 1.0))
                        nu.append((0.0, sign))
    out = np.array(uv, dtype=np.float64), np.array(nu, dtype=np.float64)
    for a in out:
        a.setflags(write=False)
    return out


@lru_cache(maxsize=256)
def _stacked(
    table: Callable[[int], tuple[np.ndarray, ...]], ids: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The per-tag sample ``table`` of each id stacked tag after tag: (tag of each sample (T,),
    first sample of each tag (N,), the tables' columns concatenated). Cached: a tracked cap shows
    the same ids frame after frame."""
    tables = [table(i) for i in ids]
    counts = np.array([len(t[0]) for t in tables])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    columns = [np.concatenate([t[k] for t in tables]) for k in range(len(tables[0]))]
    out = np.repeat(np.arange(len(tables)), counts), starts, columns
    for a in (*out[:2], *columns):
        a.setflags(write=False)
    return out


# --- The stage ------------------------------------------------------------------------------
def _fittable(corners: np.ndarray, lines: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(N,) which tags' cells span ``_MIN_TAG_CELL_PX`` both ways (those ``refine_tag_corners``
    unbiases and fits with their own cells); ``lines``: ``side_lines(corners)``."""
    nrm, rho = lines
    # Width of the tag across each side (opposite corners from the side's line), in cells.
    across = rho[:, :, None] - np.einsum("nkd,njd->nkj", nrm, corners)
    return across.max(axis=2).min(axis=1) / TAG_CELLS >= _MIN_TAG_CELL_PX


def refine_tag_corners(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    retry_px: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The tag-aware stage after the line fit (module docstring), as ``config`` enables its steps.

    Tags whose cells span ``_MIN_TAG_CELL_PX`` both ways are unbiased and fitted with their own
    cells; their corners depend on their own pixels only (a region search gives the full frame's
    corners). A smaller (or oblique) tag keeps its line-fit corners, each side moved out by the
    bias the line estimator has with that side's window, measured on the outer edges of the tags
    fitted in the same call (``_line_bias``); without a fitted tag it keeps its line corners.
    With ``retry_px``, a fittable tag the fit refused, or whose 64 cells read at its fitted
    corners disagree with its code in more than ``_MAX_FIT_CELL_ERRORS`` (a corner about a cell
    off, which the fit, moving at most a third of a cell, cannot undo), is fitted again from other
    starts (``_refit``); where none reads right it keeps its corners (and its fit's shift).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) corners from ``refine_corners_edge``.
        ids: (N,) their ids.
        config: detector settings; None: the defaults.
        retry_px: (N, 4, 2) other starting corners (the search's; rows of NaN = none), or None:
            no second look (the tracker, whose tags are verified by their cells afterwards).

    Returns:
        (corners (N, 4, 2), edge shift px (N,): ``fit_tag_edges``'s delta, NaN where not fitted:
        a small tag's correction was measured on other tags, not on it).
    """
    cfg = config or DetectorConfig()
    corners = np.array(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    delta = np.full(len(corners), np.nan)
    if len(corners) == 0 or cfg.corner_refine != "edge" or not (cfg.edge_unbias or cfg.edge_fit):
        return corners, delta
    ids = np.asarray(ids).reshape(-1)
    nrm, rho = side_lines(corners)
    good = _fittable(corners, (nrm, rho))
    corners_in = corners.copy()
    if good.any():
        c = corners[good]
        if cfg.edge_unbias:
            # The fittable tags' lines are rows of these (each row's arithmetic is its own).
            c = unbias_corners_edge(gray, c, ids[good], cfg, lines=(nrm[good], rho[good]))
        if cfg.edge_fit:
            c, delta[good] = fit_tag_edges(gray, c, ids[good], cfg, cfg.edge_fit_iterations)
        corners[good] = c
    if cfg.edge_fit and retry_px is not None:
        _retry_misfits(gray, corners, delta, good, ids, retry_px, cfg)
    if cfg.edge_fit and (cfg.edge_photometric or cfg.edge_photometric_auto) and np.isfinite(delta).any():
        done = np.flatnonzero(np.isfinite(delta))
        if not cfg.edge_photometric:  # only the tags whose corners noise limits (tag_noise)
            done = done[noise_ratios(gray, corners[done], ids[done]) > cfg.edge_photometric_noise_ratio]
        if len(done):
            corners[done] = fit_tags_photometric(gray, corners[done], ids[done])[0]
    fitted = np.isfinite(delta)
    # Line-fit corners only (too small to unbias or fit, or both failed): no tone-curve correction yet.
    line_only = ~fitted & np.all(corners == corners_in, axis=(1, 2))
    if cfg.edge_fit and fitted.any() and line_only.any():
        _shift_line_only(gray, corners, fitted, line_only, nrm, rho, cfg)
    return corners, delta


def _retry_misfits(
    gray: np.ndarray, corners: np.ndarray, delta: np.ndarray, good: np.ndarray, ids: np.ndarray,
    retry_px: np.ndarray, cfg: DetectorConfig,
) -> None:
    """Fit again, in place (``corners``, ``delta``), the fittable tags the cell-edge fit refused
    (it would move a corner beyond a third of a cell: the start was off) and those whose cells read
    wrong at their fitted corners (converged from a corner a cell off), from the other starts of
    ``_refit``. Where no other start reads right either, a fitted tag keeps its fit (small cells
    under glare may read a few cells wrong at the right corners)."""
    done = np.flatnonzero(np.isfinite(delta))
    wrong = np.zeros(len(corners), dtype=bool)
    wrong[done] = cell_errors(gray, corners[done], ids[done]) > _MAX_FIT_CELL_ERRORS
    again = np.flatnonzero(good & (~np.isfinite(delta) | wrong))
    if len(again):
        c, d = _refit(gray, corners[again], retry_px[again], ids[again], cfg)
        corners[again], delta[again] = c, np.where(np.isfinite(d), d, delta[again])


def _shift_line_only(
    gray: np.ndarray, corners: np.ndarray, fitted: np.ndarray, line_only: np.ndarray, nrm: np.ndarray,
    rho: np.ndarray, cfg: DetectorConfig,
) -> None:
    """Move out, in place, each side of the ``line_only`` tags by the line estimator's bias with
    that side's window, measured on the ``fitted`` tags' outer edges (whose true place is now
    known). A small tag's window is a fraction of a px, and a window that cuts the blurred step's
    tails sees less of the shift than the fit's delta on larger tags: hence the estimator's own
    bias, not the fitted tags' delta. The bias changes slowly with the window: it is measured on a
    1/8 px grid of the windows needed, on at most ``_BIAS_TAGS`` of the fitted tags."""
    halves = np.round(line_windows(corners[line_only], cfg) * 8.0) / 8.0
    grid, where = np.unique(halves, return_inverse=True)
    ref = np.flatnonzero(fitted)
    ref = ref[np.linspace(0, len(ref) - 1, min(len(ref), _BIAS_TAGS)).round().astype(int)]
    bias = _line_bias(gray, corners[ref], grid, cfg)[where.reshape(halves.shape)]
    ok = np.isfinite(bias).all(axis=1)
    todo = np.flatnonzero(line_only)[ok]
    if len(todo):
        corners[todo] = intersect_sides(nrm[todo], rho[todo] + bias[ok])


def _refit(
    gray: np.ndarray, corners: np.ndarray, other: np.ndarray, ids: np.ndarray, cfg: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Tags whose cell-edge fit failed from ``corners`` (M, 4, 2), fitted from other starts: ``other``
    (M, 4, 2, rows of NaN = none) and ``corners`` and ``other`` with each corner k replaced by the
    parallelogram c[k-1] + c[k+1] - c[k+2] (one corner led astray is how a search or a line pass
    fails: a side pulled onto a neighbouring edge in a dark corner); each start line-refined,
    unbiased and fitted. A tag takes the start whose fit succeeds, reads its cells right and moves
    least (its corners and delta, NaN where none did; such tags keep ``corners``)."""
    m = len(corners)
    bases = [corners, np.asarray(other, dtype=np.float64).reshape(m, 4, 2)]
    starts = [bases[1]]
    for base in bases:
        for k in range(4):
            c = base.copy()
            c[:, k] = base[:, PREV[k]] + base[:, NEXT[k]] - base[:, OPPOSITE[0][k]]
            starts.append(c)
    cand = np.concatenate(starts)  # (S * M, 4, 2), start after start
    tag = np.tile(np.arange(m), len(starts))
    usable = np.isfinite(cand).all(axis=(1, 2))
    best_c, best_d = corners.copy(), np.full(m, np.nan)
    if not usable.any():
        return best_c, best_d
    cand, tag = cand[usable], tag[usable]
    lines, ok = refine_corners_edge_ok(gray, cand, cfg)
    if not ok.all():
        lines[~ok] = refine_corners_edge_wide(gray, cand[~ok], cfg)
    c = unbias_corners_edge(gray, lines, ids[tag], cfg) if cfg.edge_unbias else lines
    fitted, d = fit_tag_edges(gray, c, ids[tag], cfg, cfg.edge_fit_iterations + 1)
    right = np.isfinite(d)
    right[right] = cell_errors(gray, fitted[right], ids[tag][right]) <= _MAX_FIT_CELL_ERRORS
    moved = np.where(right, np.linalg.norm(fitted - c, axis=2).max(axis=1), np.inf)
    for j in range(m):
        mine = np.flatnonzero((tag == j) & np.isfinite(moved))
        if len(mine):
            k = mine[np.argmin(moved[mine])]
            best_c[j], best_d[j] = fitted[k], d[k]
    return best_c, best_d


def _line_bias(gray: np.ndarray, fitted_px: np.ndarray, halves: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """How far inside a true black/white edge the line pass's estimator puts it, px, with each
    window half-length of ``halves`` (any shape): the median over the outer border edges of the
    tags with fitted (true) corners ``fitted_px`` (NaN where too few edges were clean)."""
    nrm, _ = side_lines(fitted_px)
    a, d = fitted_px, fitted_px[:, NEXT] - fitted_px
    pts = (a[:, :, None, :] + d[:, :, None, :] * _BIAS_POINTS[None, None, :, None]).reshape(-1, 2)
    out_n = np.repeat(nrm.reshape(-1, 2), len(_BIAS_POINTS), axis=0)
    h = np.asarray(halves, dtype=np.float64).ravel()
    p_n, h_n = len(pts), len(h)
    s, contrast = step_offset(gray, np.tile(pts, (h_n, 1)), np.tile(out_n, (h_n, 1)), np.repeat(h, p_n),
                              cfg.edge_profile_samples)
    s, contrast = s.reshape(h_n, p_n), contrast.reshape(h_n, p_n)
    # As the line pass weighs its samples: weak or inverted profiles and edges at the window's end out.
    med_c = row_median(contrast, contrast > 0)
    step = h / ((cfg.edge_profile_samples - 1) // 2)
    use = ((contrast > 0.3 * med_c[:, None]) & (contrast > 8.0)
           & (np.abs(s) < (h - np.maximum(step, 0.25))[:, None]))
    bias = -row_median(s, use)
    return np.where(use.sum(axis=1) >= 8, bias, np.nan).reshape(np.shape(halves))


def shift_tag_edges(corners_px: np.ndarray, shift_px: float) -> np.ndarray:
    """Line-fit corners (N, 4, 2) with every side moved out by ``shift_px``: the frame's tone-curve
    shift applied to tags too small or oblique to measure their own (the shift is the camera's
    blur and tone curve, so it is shared by the tags of a frame)."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0 or not np.isfinite(shift_px):
        return c.copy()
    nrm, rho = side_lines(c)
    return intersect_sides(nrm, rho + float(shift_px))


# --- Step 1: the black border's two edges ---------------------------------------------------
def unbias_corners_edge(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    lines: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Remove the tone-curve bias from edge-fitted corners, using each tag's own black border.

    The fitted outer edge of the border sits delta *inside* the tag (module docstring). The
    border's inner edge, where a white data cell meets it, has black on its outer side, so the same
    estimator puts it delta *outside* its true place: the measured border is 2 delta thinner than
    one cell. The tag's homography says how wide one cell is at each point, so

        delta = (cell width - measured border width) / 2

    per side, from the samples across the white cells of the first data ring (known from the id),
    with no model of the camera's response. Each side's line is then moved out by its delta and
    the corners re-intersected; the cell width is re-read from the corrected corners (two rounds).
    A side with few samples leans on its tag's mean; a tag with none is left as it is. Samples
    where the two edges are too close to resolve (cells under ``_MIN_CELL_PX`` across) are not used.
    The step is one compiled call (``fit_kernels.border_unbias``).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) corners from ``refine_corners_edge`` (OpenCV order and convention).
        ids: (N,) the tags' ids (their data cells say where the border's inner edge is).
        config: window settings (``edge_search_px``, ``edge_window_cells``, ``edge_profile_samples``).
        lines: ``side_lines(corners_px)`` when the caller has them.

    Returns:
        (N, 4, 2) corrected corners (a tag keeps its input corners when no estimate is possible
        or the correction is implausibly large).
    """
    cfg = config or DetectorConfig()
    c_in = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c_in) == 0:
        return c_in.copy()
    tag_of, starts, (side, uv) = _stacked(_inner_edge_samples, tuple(int(i) for i in ids))
    nrm, rho = side_lines(c_in) if lines is None else lines
    try:
        hom = tag_homographies(c_in)
    except np.linalg.LinAlgError:
        return c_in.copy()
    return border_unbias(frozen(gray), c_in, np.ascontiguousarray(nrm), np.ascontiguousarray(rho), hom, tag_of,
                         side, uv, _SIDE_OUT, starts, cfg.edge_search_px, cfg.edge_window_cells,
                         (cfg.edge_profile_samples - 1) // 2, _MIN_CELL_PX, _MIN_CONTRAST_RATIO, _SIDE_PRIOR_SAMPLES)


# --- Step 2: every cell edge of the tag at once ---------------------------------------------
def fit_tag_edges(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Corners from every cell edge of each tag at once, free of the tone-curve bias.

    The tag is a known pattern: every boundary between a black and a white cell (its border's
    two edges, the data cells', the quiet zone's) lies where the tag's homography H maps it. The
    tone curve moves each measured boundary toward its black side by an unknown delta (one blur,
    one contrast, one curve per tag); what the estimator sees of it also depends on its window
    (half a cell across the boundary, narrower along an oblique tag's foreshortened axis), so there
    is one delta per boundary direction (tag x, tag y). Boundaries of both polarities are spread
    over the tag in both directions, so H (8 parameters) and the deltas are separable: each
    sample's measured offset s along the image normal (toward the white cell) is modelled as
    n . J_H dh - delta_dir, and one weighted least-squares step per iteration updates H and the
    deltas together (re-sampling the image each time); samples beyond 3.5 robust sigmas are
    dropped. The fit reads every cell boundary, not only the four outer lines, and extrapolates
    no line to a corner. The rounds are one compiled call (``fit_kernels.edge_fit``; each round
    ``fit_kernels.edge_fit_round``, which says which samples are used).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) starting corners (``refine_corners_edge``; within a third of a cell).
        ids: (N,) tag ids (their cells say where the boundaries are).
        config: ``edge_search_px`` (the longest window).
        iterations: sample-and-solve rounds.

    Returns:
        (corners (N, 4, 2), delta_px (N,)): corrected corners (a tag keeps its input corners when
        its cells are too small to resolve or the fit is implausible) and each tag's fitted edge
        shift toward black, px, the mean of its two directions' (NaN where not fitted).
    """
    cfg = config or DetectorConfig()
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    if n == 0:
        return c_in.copy(), np.full(0, np.nan)
    tag_of, starts, (uv, nu) = _stacked(_cell_edge_samples, tuple(int(i) for i in ids))
    try:
        h = tag_homographies(c_in).reshape(n, 9)[:, :8].copy()
    except np.linalg.LinAlgError:
        return c_in.copy(), np.full(n, np.nan)
    fitted, delta = edge_fit(frozen(gray), h, tag_of, uv, nu, starts, int(iterations), cfg.edge_search_px,
                             (_FIT_PROFILE_SAMPLES - 1) // 2, _MIN_CELL_PX, _MIN_CONTRAST_RATIO, _MIN_FIT_ROWS,
                             _MIN_FIT_ROWS_PER_DIRECTION)
    corners = homography_corners(h)
    cell = vector_norm(c_in[:, NEXT] - c_in).min(axis=1) / TAG_CELLS
    moved = vector_norm(corners - c_in).max(axis=1)
    good = fitted & np.isfinite(corners).all(axis=(1, 2)) & (moved <= np.minimum(0.35 * cell, 2.5))
    return np.where(good[:, None, None], corners, c_in), np.where(good, delta, np.nan)


# --- Step 4 (optional): the photometric fit -------------------------------------------------
def fit_tags_photometric(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, **kwargs: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """The tag-level photometric fit (``ficap_ros.vision.photometric.fit_tags``, keyword arguments
    as there) of tags given by their corners and ids: (corners (N, 4, 2), fitted (N,) bool; a tag
    not fitted keeps its corners). ``gray`` may be any image ``as_gray`` takes (else ImageError).
    Each tag's fit is its own: a quadrilateral without a homography stays unfitted alone."""
    gray = as_gray(gray)  # no copy for the pipeline's uint8 grey frames
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    ids = np.asarray(ids).reshape(-1)
    usable = usable_quads(c)
    if not usable.all():
        out, fitted = c.copy(), np.zeros(len(c), dtype=bool)
        if usable.any():
            out[usable], fitted[usable] = fit_tags_photometric(gray, c[usable], ids[usable], **kwargs)
        return out, fitted
    if len(c) == 0:
        return c.copy(), np.zeros(0, dtype=bool)
    # Imported here: the fit's compiled kernels (numba) load only where photometric corners are on.
    from ficap_ros.vision.photometric import fit_tags

    cells = stacked_tag_cells(tuple(int(i) for i in ids))
    return fit_tags(gray, c, tag_homographies(c), cells, **kwargs)
