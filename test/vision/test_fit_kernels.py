"""The cell-edge fit's compiled kernels against numpy: the boundary rows and per-tag normal
equations and residuals to 1e-12 relative; the solves, the robust step and a whole round (the
boundaries' steps, each tag's clean contrast, the usable samples, the robust step) bit for bit,
numpy's batched ``np.linalg.solve`` and the group medians of ``medians`` as the reference."""

from __future__ import annotations

import numpy as np
import pytest
from edges_reference import boundary_rows as boundary_rows_numpy
from tag_images import two_tag_scene

from ficap_ros.geometry.tag36h11 import (
    CELL_CENTRES_H,
    TAG_AREA,
    TAG_CELLS,
    apply_homographies,
    stacked_tag_cells,
    tag_homographies,
)
from ficap_ros.vision import corners as corners_mod
from ficap_ros.vision import edges, tag_noise
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.edges import (
    NEXT,
    intersect_sides,
    side_lines,
    step_offset,
    vector_norm,
)
from ficap_ros.vision.fit_kernels import (
    boundary_rows,
    edge_fit,
    edge_fit_round,
    grouped_normal_equations,
    grouped_residuals,
    grouped_solve,
    robust_grouped_solve,
)
from ficap_ros.vision.kernels import frozen
from ficap_ros.vision.medians import (
    group_median_of_finite,
    group_nearest_quantile_of_finite,
    row_median,
)


@pytest.mark.parametrize("seed", [0, 1])
def test_grouped_least_squares_equal_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 40, 7)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    jac = rng.normal(size=(int(counts.sum()), 10)) * np.logspace(-3, 3, 10)
    rhs = rng.normal(size=len(jac))
    w = np.where(rng.uniform(size=len(jac)) < 0.2, 0.0, rng.uniform(0.1, 2.0, len(jac)))
    ata, atb, rows = grouped_normal_equations(jac, rhs, w, starts, 10)
    sol = rng.normal(size=(len(counts), 10))
    resid = grouped_residuals(jac, rhs, sol, starts)
    for g, (a, n) in enumerate(zip(starts, counts)):
        j, b, wg = jac[a:a + n], rhs[a:a + n], w[a:a + n]
        want = (j * wg[:, None]).T @ j
        np.testing.assert_allclose(ata[g], want, rtol=1e-12, atol=1e-12 * np.abs(want).max(initial=1.0))
        np.testing.assert_allclose(atb[g], (j * wg[:, None]).T @ b, rtol=1e-12, atol=1e-9)
        assert rows[g] == (wg > 0).sum()
        np.testing.assert_allclose(resid[a:a + n], b - j @ sol[g], rtol=1e-12, atol=1e-9)


def _edge_rows(rng: np.random.Generator, t: int) -> np.ndarray:
    """(t, 10) rows shaped as the cell-edge fit's: 8 dense columns, then -1 in one of two
    indicator columns."""
    jac = np.zeros((t, 10))
    jac[:, :8] = rng.normal(size=(t, 8)) * np.logspace(-3, 3, 8)
    jac[np.arange(t), 8 + (rng.uniform(size=t) < 0.5)] = -1.0
    return jac


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_indicator_columns_give_the_full_sums_exactly(seed: int) -> None:
    """Skipping the indicator columns' structural zeros changes no bit of the normal equations;
    with a non-finite row or measurement the same groups are left unsolved."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 60, 8)
    counts[:2] = 40, 50
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    jac = _edge_rows(rng, int(counts.sum()))
    jac[:40, 8] = 0.0  # group 0: one direction's shift untouched
    jac[:40, 9] = -1.0
    rhs = rng.normal(size=len(jac))
    w = np.where(rng.uniform(size=len(jac)) < 0.2, 0.0, rng.uniform(0.1, 2.0, len(jac)))
    for got, want in zip(grouped_normal_equations(jac, rhs, w, starts, 8),
                         grouped_normal_equations(jac, rhs, w, starts, 10)):
        np.testing.assert_array_equal(got, want)
    assert (grouped_normal_equations(jac, rhs, w, starts, 8)[0][0, 8] == 0.0).all()
    jac[45, 3], rhs[60] = np.inf, np.nan
    w[45] = w[60] = 1.0
    sparse = grouped_solve(jac, rhs, w, starts, 8, 24, True)
    full = grouped_solve(jac, rhs, w, starts, 10, 24, True)
    np.testing.assert_array_equal(sparse[1], full[1])
    assert not sparse[1][0] and not sparse[1][1]
    np.testing.assert_array_equal(sparse[0][2:], full[0][2:])


def _grouped_solve_numpy(jac, rhs, w, starts, min_rows):  # noqa: ANN001, ANN202
    """The column-scaled normal equations (summed over every column) solved by numpy's batched
    ``np.linalg.solve``."""
    ata, atb, rows = grouped_normal_equations(jac, rhs, w, starts, jac.shape[1])
    d = np.sqrt(np.maximum(np.einsum("nii->ni", ata), 1e-30))
    a_s = ata / d[:, :, None] / d[:, None, :]
    solved = (rows >= min_rows) & np.all(np.einsum("nii->ni", ata) > 0.0, axis=1)
    sol = np.zeros((len(starts), jac.shape[1]))
    sol[solved] = np.linalg.solve(a_s[solved], (atb / d)[solved][..., None])[..., 0] / d[solved]
    return sol, solved & np.isfinite(sol).all(axis=1), grouped_residuals(jac, rhs, sol, starts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grouped_solve_equals_numpys_solve_exactly(seed: int) -> None:
    """Same numbers as numpy's batched solve, bit for bit; a group with too few weighted rows, or
    a parameter no weighted row touches, stays unsolved at 0."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 80, 9)
    counts[:4] = 30, 10, 60, 70
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    jac = rng.normal(size=(int(counts.sum()), 10)) * np.logspace(-3, 3, 10)
    jac[:30, 9] = 0.0  # group 0: parameter 9 untouched
    rhs = rng.normal(size=len(jac))
    w = np.where(rng.uniform(size=len(jac)) < 0.2, 0.0, rng.uniform(0.1, 2.0, len(jac)))
    sol, solved, resid = grouped_solve(jac, rhs, w, starts, 10, 24, True)
    want_sol, want_solved, want_resid = _grouped_solve_numpy(jac, rhs, w, starts, 24)
    assert not solved[0] and (sol[0] == 0.0).all()
    assert not solved[1] and solved[2:4].all()
    np.testing.assert_array_equal(solved, want_solved)
    np.testing.assert_array_equal(sol, want_sol)
    np.testing.assert_array_equal(resid, want_resid)
    assert grouped_solve(jac, rhs, w, starts, 10, 24, False)[2].shape == (0,)


def test_singular_group_is_left_unsolved() -> None:
    """Two equal columns make one group's system singular: it stays unsolved at 0, the other is
    the least-squares solution; a non-finite row leaves its group unsolved at NaN."""
    rng = np.random.default_rng(3)
    jac = rng.normal(size=(90, 10))
    jac[:30, 1] = jac[:30, 0]
    jac[65, 4] = np.inf
    rhs, w, starts = rng.normal(size=90), np.ones(90), np.array([0, 30, 60])
    sol, solved, resid = grouped_solve(jac, rhs, w, starts, 10, 24, True)
    assert solved.tolist() == [False, True, False]
    assert (sol[0] == 0.0).all() and np.isnan(sol[2]).all()
    np.testing.assert_allclose(sol[1], np.linalg.lstsq(jac[30:60], rhs[30:60], rcond=None)[0], atol=1e-9)
    assert np.isfinite(resid[:60]).all()


def _robust_solve_numpy(jac, s, contrast, top_c, ok, vertical, starts, counts):  # noqa: ANN001, ANN202
    """The cell-edge fit's robust step in numpy (medians by sorting, numpy's batched solve)."""
    tag_of = np.repeat(np.arange(len(counts)), counts)
    w = np.where(ok, (contrast / np.maximum(top_c, 1.0)) ** 2, 0.0)
    _, _, r = _grouped_solve_numpy(jac, s, w, starts, 24)
    sig = 1.4826 * group_median_of_finite(np.abs(r), ok, counts)
    ok = ok & (np.abs(r) <= np.maximum(3.5 * sig[tag_of], 0.05))
    w = np.where(ok, (contrast / np.maximum(top_c, 1.0)) ** 2, 0.0)
    sol, solved, _ = _grouped_solve_numpy(jac, s, w, starts, 24)
    used = w > 0
    n_vertical = np.add.reduceat(used & vertical, starts)
    solved &= (n_vertical >= 12) & (np.add.reduceat(used, starts) - n_vertical >= 12)
    return sol, solved, ok


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robust_grouped_solve_equals_numpy_exactly(seed: int) -> None:
    """Outliers among the rows (a few far off), groups too small or with one direction short:
    the compiled robust step gives numpy's solutions, solved flags and kept rows bit for bit."""
    rng = np.random.default_rng(seed)
    counts = np.array([80, 20, 60, 120, 40])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    t = int(counts.sum())
    jac = rng.normal(size=(t, 10)) * np.logspace(-3, 1, 10)
    s = jac @ rng.normal(size=10) * 0.01 + rng.normal(0.0, 0.02, t)
    s[rng.uniform(size=t) < 0.08] += rng.choice([-1.0, 1.0]) * 0.8
    contrast = rng.uniform(5.0, 120.0, t)
    top_c = np.repeat(rng.uniform(60.0, 120.0, len(counts)), counts)
    ok = (contrast > 8.0) & (rng.uniform(size=t) < 0.9)
    vertical = rng.uniform(size=t) < 0.5
    vertical[starts[2]:starts[2] + counts[2]] = np.arange(counts[2]) < 8  # group 2: 8 vertical rows
    sol, solved, kept = robust_grouped_solve(jac, s, contrast, top_c, ok, vertical, starts, 10, 24, 12)
    want = _robust_solve_numpy(jac, s, contrast, top_c, ok, vertical, starts, counts)
    assert not solved[1] and not solved[2] and solved[[0, 3, 4]].all()
    assert (kept < ok).any()  # outliers dropped
    np.testing.assert_array_equal(sol, want[0])
    np.testing.assert_array_equal(solved, want[1])
    np.testing.assert_array_equal(kept, want[2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_boundary_rows_equal_numpy(seed: int) -> None:
    """Every cell boundary of the scene's tags (one seen obliquely by its random corners)."""
    _, corners = two_tag_scene(seed)
    ids = (5, 6)
    tag_of, _, (uv, nu) = corners_mod._stacked(corners_mod._cell_edge_samples, ids)
    h = tag_homographies(corners).reshape(len(corners), 9)[:, :8].copy()
    frames, rows = boundary_rows(h, tag_of, uv, nu)
    want_frames, want_rows = boundary_rows_numpy(h, tag_of, uv, nu)
    np.testing.assert_allclose(frames, want_frames, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rows, want_rows, rtol=1e-12, atol=1e-12)


def test_degenerate_homographies_give_non_finite_rows_not_exceptions() -> None:
    """A collapsed homography divides by zero: inf or NaN as in numpy, never ZeroDivisionError."""
    tag_of = np.array([0, 0, 1, 1], np.int64)
    uv = np.array([[0.5, 0.0], [0.0, 0.5], [1.0, 0.5], [0.5, 1.0]])
    nu = np.array([[0.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, -1.0]])
    frames, rows = boundary_rows(np.ones((2, 8)), tag_of, uv, nu)
    assert not np.isfinite(frames).all() and not np.isfinite(rows).all()


def _round_numpy(img, h, tag_of, uv, nu, keep, starts, counts):  # noqa: ANN001, ANN202
    """One round of the cell-edge fit in numpy: ``edges.step_offset`` (whose kernel has its own
    tests), the nearest-rank contrast quantile of ``medians``, ``_robust_solve_numpy``."""
    (px, py, _, nx, ny, cell), jac = boundary_rows(h, tag_of, uv, nu)
    half = np.minimum(4.0, 0.5 * cell)
    s, contrast = edges.step_offset(img, np.column_stack([px, py]), np.column_stack([nx, ny]), half, 11)
    step = half / 5
    top_c = group_nearest_quantile_of_finite(contrast, keep & np.isfinite(contrast), counts, 0.9)[tag_of]
    ok = (keep & (cell >= 2.0) & np.isfinite(s) & (np.abs(s) < half - step) & (contrast > 8.0)
          & (contrast >= 0.7 * top_c))
    return _robust_solve_numpy(jac, s, contrast, top_c, ok, np.abs(nu[:, 0]) > 0.5, starts, counts)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_fit_round_equals_numpy_exactly(seed: int) -> None:
    """Both of the scene's tags (one cut by the border) from corners half a pixel off, first with
    every sample, then with those the first round kept: numpy's solutions, flags and kept samples."""
    img, corners = two_tag_scene(seed)
    start = corners + np.random.default_rng(seed).normal(0.0, 0.5, corners.shape)
    tag_of, starts, (uv, nu) = corners_mod._stacked(corners_mod._cell_edge_samples, (5, 6))
    counts = np.bincount(tag_of, minlength=len(starts))
    h = tag_homographies(start).reshape(2, 9)[:, :8].copy()
    keep = np.ones(len(uv), dtype=bool)
    vertical = np.abs(nu[:, 0]) > 0.5
    for _ in range(2):
        got = edge_fit_round(frozen(img), h, tag_of, uv, nu, vertical, keep, starts, 4.0, 5, 2.0, 0.7, 24, 12)
        want = _round_numpy(img, h, tag_of, uv, nu, keep, starts, counts)
        assert got[1][0]  # the whole tag is solved
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        keep = got[2]


def _edge_fit_numpy(img, h, tag_of, uv, nu, starts, iterations):  # noqa: ANN001, ANN202
    """``fit_kernels.edge_fit`` as numpy glue around the compiled round (itself tested against
    numpy above): the rounds' homography updates and edge shifts."""
    keep = np.ones(len(uv), dtype=bool)
    vertical = np.abs(nu[:, 0]) > 0.5
    fitted, delta = np.zeros(len(h), dtype=bool), np.full(len(h), np.nan)
    for it in range(iterations):
        sol, solved, ok = edge_fit_round(frozen(img), h, tag_of, uv, nu, vertical, keep, starts, 4.0, 4, 2.0, 0.7,
                                         24, 12)
        h = h + np.where(solved[:, None], sol[:, :8], 0.0)
        delta = np.where(solved, sol[:, 8:].mean(axis=1), np.nan)
        fitted = solved
        if it == iterations - 2:
            keep = ok
    return h, fitted, delta


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_edge_fit_equals_its_rounds_in_numpy_exactly(seed: int, iterations: int) -> None:
    """The scene's two tags from starts a few tenths of a px off, and a third start a cell off:
    the same homographies, solved flags and edge shifts, bit for bit."""
    img, corners = two_tag_scene(seed)
    rng = np.random.default_rng(seed)
    start = corners + rng.normal(0.0, 0.3, corners.shape)
    off = corners[:1] + np.array([1.0, 0.0]) * np.linalg.norm(corners[0, 1] - corners[0, 0]) / TAG_CELLS
    start = np.concatenate([start, off])
    tag_of, starts, (uv, nu) = corners_mod._stacked(corners_mod._cell_edge_samples, (5, 6, 5))
    h = tag_homographies(start).reshape(3, 9)[:, :8].copy()
    want = _edge_fit_numpy(img, h.copy(), tag_of, uv, nu, starts, iterations)
    got = edge_fit(frozen(img), h, tag_of, uv, nu, starts, iterations, 4.0, 4, 2.0, 0.7, 24, 12)
    np.testing.assert_array_equal(h, want[0])
    for g, w in zip(got, want[1:]):
        np.testing.assert_array_equal(g, w)
    assert want[1][:2].all()


def _unbias_numpy(gray, corners_px, ids, cfg):  # noqa: ANN001, ANN202
    """``corners.unbias_corners_edge`` in numpy (the package's ``edges.step_offset`` for the
    profiles, ``medians`` for the medians), the reference of ``border_unbias``."""
    cfg = cfg or DetectorConfig()
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    if n == 0:
        return c_in.copy()
    tag_of, starts, (side, uv) = corners_mod._stacked(corners_mod._inner_edge_samples, tuple(int(i) for i in ids))
    counts = np.bincount(tag_of, minlength=len(starts))
    # uv on the outer edge straight across from each inner sample (one cell out).
    uv_out = uv + corners_mod._SIDE_OUT[side]
    nrm, rho = side_lines(c_in)
    nk = nrm[tag_of, side]  # (T, 2)
    try:
        hom = tag_homographies(c_in)
    except np.linalg.LinAlgError:
        return c_in.copy()
    hom_t = hom[tag_of]
    midline, valid, width0 = _border_midlines_numpy(gray, apply_homographies(hom_t, uv),
                                              apply_homographies(hom_t, uv_out), nk, cfg)
    group = tag_of * 4 + side
    corners = c_in
    keep = None
    for round_ in range(2):
        if round_ == 0:  # the first round's corners are the input's: its width is width0
            width = width0
        else:
            hom_t = tag_homographies(corners)[tag_of]
            p_in_c, p_out_c = apply_homographies(hom_t, uv), apply_homographies(hom_t, uv_out)
            width = np.einsum("td,td->t", nk, p_out_c - p_in_c)  # one cell across, corrected geometry
        d = midline + 0.5 * width - rho[tag_of, side]  # (T,) how far the fitted line is inside, px
        if keep is None:  # the outliers: from the first round
            keep = _inlier_samples_numpy(d, valid, starts, counts)
        delta = _pooled_delta_numpy(d, keep, group, n)
        corners = intersect_sides(nrm, rho + delta)
    # A correction beyond a third of a cell (or 2 px) is no tone curve: keep those tags' corners.
    cell = vector_norm(c_in[:, NEXT] - c_in).min(axis=1) / TAG_CELLS
    sane = (np.abs(delta).max(axis=1) <= np.minimum(cell / 3.0, 2.0)) & np.isfinite(corners).all(axis=(1, 2))
    return np.where(sane[:, None, None], corners, c_in)


def _border_midlines_numpy(
    gray: np.ndarray, p_in: np.ndarray, p_out: np.ndarray, nk: np.ndarray, cfg: DetectorConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both edges of the border measured straight across each white data cell, with the same
    window: the inner edge around ``p_in`` (then again around what was found, so the window sits
    on the edge), the outer edge around ``p_out`` (on the fitted line); ``nk`` (T, 2) the sides'
    outward normals.

    Returns:
        (midline (T,): position along ``nk`` of the midline between the two measured edges,
        which is free of the bias (both moved toward the black by the same amount); valid (T,):
        both edges measured cleanly; width0 (T,): one cell across at the input corners, px).
    """
    width0 = np.einsum("td,td->t", nk, p_out - p_in)  # px, one cell across
    half = np.maximum(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * width0), 0.75)
    samples = cfg.edge_profile_samples
    # The inner edge has its light side inward: offsets along -nk. Its first look and the outer
    # edge's in one sampling call.
    t = len(p_in)
    first, first_c = step_offset(gray, np.concatenate([p_in, p_out]), np.concatenate([-nk, nk]),
                                 np.concatenate([half, half]), samples)
    s1, o1, c_outer = np.clip(first[:t], -half, half), first[t:], first_c[t:]
    s2, c_inner = step_offset(gray, p_in - nk * s1[:, None], -nk, half, samples)
    inner = np.einsum("td,td->t", nk, p_in) - s1 - s2
    outer = np.einsum("td,td->t", nk, p_out) + o1
    step = half / ((samples - 1) // 2)
    # A white cell as white as the quiet zone across the border: where its neighbours (or the
    # pixel footprint) darken it, its edge is not the outer edge's mirror image.
    valid = (np.isfinite(inner) & np.isfinite(outer) & (width0 >= corners_mod._MIN_CELL_PX) & (np.abs(s2) < half - step)
             & (np.abs(o1) < half - step) & (c_outer > 8.0) & (c_inner >= corners_mod._MIN_CONTRAST_RATIO * c_outer))
    return 0.5 * (inner + outer), valid, width0


def _inlier_samples_numpy(d: np.ndarray, valid: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The valid samples within 3 MAD (at least 0.1 px) of their tag's median."""
    tag_of = np.repeat(np.arange(len(counts)), counts)
    tag_med = group_median_of_finite(d, valid, counts)
    tag_mad = 1.4826 * group_median_of_finite(np.abs(d - tag_med[tag_of]), valid, counts)
    return valid & np.isfinite(d) & (np.abs(d - tag_med[tag_of]) <= np.maximum(3.0 * tag_mad[tag_of], 0.1))


def _pooled_delta_numpy(d: np.ndarray, keep: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per-side delta (N, 4): each side's mean over its kept samples, shrunk toward its tag's
    mean (0 for a tag without samples)."""
    dv = np.where(keep, d, 0.0)
    side_sum = np.bincount(group, weights=dv, minlength=4 * n).reshape(n, 4)
    side_cnt = np.bincount(group, weights=keep.astype(np.float64), minlength=4 * n).reshape(n, 4)
    tag_cnt = side_cnt.sum(axis=1)
    has = tag_cnt > 0
    tag_mean = np.where(has, side_sum.sum(axis=1) / np.maximum(tag_cnt, 1e-12), 0.0)
    prior = corners_mod._SIDE_PRIOR_SAMPLES
    return (side_sum + prior * tag_mean[:, None]) / (side_cnt + prior)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_border_unbias_equals_numpy_exactly(seed: int) -> None:
    """Both of the scene's tags (one cut by the border) from line-pass corners: the corrected
    corners equal the numpy step's bit for bit, and move the corners (the scene's tone makes the
    line pass's edges biased)."""
    img, corners = two_tag_scene(seed)
    start = corners + np.random.default_rng(seed).normal(0.0, 0.3, corners.shape)
    lines, _ = edges.refine_corners_edge_ok(img, start)
    cfg = DetectorConfig()
    got = corners_mod.unbias_corners_edge(img, lines, np.array([5, 6]), cfg)
    want = _unbias_numpy(img, lines, np.array([5, 6]), cfg)
    np.testing.assert_array_equal(got, want)
    assert np.abs(got - lines).max() > 0.01


def _cell_centres_grey_numpy(gray: np.ndarray, hom: np.ndarray) -> np.ndarray:
    """(N, 8, 8) float grey at the nearest pixel to each cell's centre, [tag, v, u] (the
    ``tag36h11`` cells' layout), the image's edge pixel for a centre outside it."""
    q = hom @ CELL_CENTRES_H[TAG_AREA].T  # (N, 3, 64), the tag's own cells row-major
    x = np.clip(np.rint(q[:, 0] / q[:, 2]), 0, gray.shape[1] - 1).astype(np.intp)
    y = np.clip(np.rint(q[:, 1] / q[:, 2]), 0, gray.shape[0] - 1).astype(np.intp)
    return gray[y, x].astype(np.float64).reshape(-1, TAG_CELLS, TAG_CELLS)


def _noise_ratios_numpy(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``tag_noise.noise_ratios`` in numpy: the reference of ``tag_noise_ratios``."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0:
        return np.zeros(0)
    grey = _cell_centres_grey_numpy(gray, tag_homographies(c)).reshape(len(c), -1)
    black = stacked_tag_cells(tuple(int(i) for i in np.asarray(ids).reshape(-1))).reshape(len(c), TAG_CELLS, TAG_CELLS)
    black = black.astype(bool)
    # A tag of one colour would have no contrast (row_median gives 0 for an empty row).
    flat = black.reshape(len(c), -1)
    contrast = row_median(grey, ~flat) - row_median(grey, flat)
    g = grey.reshape(black.shape)
    steps = np.concatenate([(g[:, :, 1:] - g[:, :, :-1]).reshape(len(c), -1),
                            (g[:, 1:, :] - g[:, :-1, :]).reshape(len(c), -1)], axis=1)
    same = np.concatenate([(black[:, :, 1:] == black[:, :, :-1]).reshape(len(c), -1),
                           (black[:, 1:, :] == black[:, :-1, :]).reshape(len(c), -1)], axis=1)
    mad = row_median(np.abs(steps - row_median(steps, same)[:, None]), same)
    noise_sd = 1.4826 * mad / np.sqrt(2.0)
    cell_px = np.linalg.norm(c[:, [1, 2, 3, 0]] - c, axis=2).min(axis=1) / TAG_CELLS
    ratio = noise_sd / (np.maximum(contrast, 1.0) * np.sqrt(np.maximum(cell_px, 1e-6)))
    return np.where(same.any(axis=1), ratio, np.inf)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_tag_noise_ratios_equal_numpy_exactly(seed: int) -> None:
    """The scene's two tags (one cut by the border: its outer cells read the edge pixel) at their
    true corners and a pixel off: the ratios equal numpy's bit for bit."""
    img, corners = two_tag_scene(seed)
    ids = np.array([5, 6])
    for c in (corners, corners + np.random.default_rng(seed).normal(0.0, 1.0, corners.shape)):
        got = tag_noise.noise_ratios(img, c, ids)
        np.testing.assert_array_equal(got, _noise_ratios_numpy(img, c, ids))
        assert np.isfinite(got).all() and (got > 0).all()
