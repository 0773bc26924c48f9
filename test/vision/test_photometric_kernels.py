"""The photometric fit's compiled kernels against the numpy reference (``photometric_reference``)
and their small parts against numpy and scipy.

The fit's corners agree with the reference's within 1e-5 px and the same tags are fitted (the
reference evaluates the blurred shares in float32, the kernels in float64); the pixels it selects
are checked against a per-box oracle in test_photometric.py.
"""

from __future__ import annotations

import numpy as np
import photometric_reference
import pytest
from corner_eval import drive_frames
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import ndtr

from ficap_ros.geometry.tag36h11 import stacked_tag_cells, tag_homographies
from ficap_ros.tools.synth import RenderConfig
from ficap_ros.vision import photometric, photometric_kernels
from ficap_ros.vision.tone import srgb_encode_slope, srgb_to_linear_scalar


@pytest.mark.parametrize("resolution, lighting", [("540p", "low"), ("1080p", "neutral")])
def test_fit_equals_the_numpy_reference(resolution: str, lighting: str) -> None:
    fr = drive_frames(resolution, RenderConfig(lighting=lighting, jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999))
    rng = np.random.default_rng(2)
    start = np.array([fr.corners_px[t] for t in ids]) + rng.normal(0.0, 0.15, (len(ids), 4, 2))
    hom, cells = tag_homographies(start), stacked_tag_cells(tuple(int(i) for i in ids))
    for free_tone, iterations in ((True, 3), (False, 2)):
        # Every step (the reference takes them all).
        got, ok = photometric.fit_tags(fr.image, start, hom, cells, free_tone=free_tone, iterations=iterations,
                                       converged_px=0.0)
        want, ok_ref = photometric_reference.fit_tags(fr.image, start, hom, cells, free_tone=free_tone,
                                                      iterations=iterations)
        np.testing.assert_array_equal(ok, ok_ref)
        assert ok.sum() >= len(ids) - 2
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-5)


@pytest.mark.parametrize("resolution, lighting", [("540p", "low"), ("1080p", "neutral")])
def test_the_convergence_stop_moves_no_corner_beyond_its_threshold(resolution: str, lighting: str) -> None:
    """A still tag that stops once a step moves its corners under ``STILL_CONVERGED_PX`` lands where
    every step would take it, within a few times that (the steps shrink), and fits the same tags;
    some tags do stop early (else the stop saves nothing)."""
    fr = drive_frames(resolution, RenderConfig(lighting=lighting, jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999))
    rng = np.random.default_rng(3)
    start = np.array([fr.corners_px[t] for t in ids]) + rng.normal(0.0, 0.15, (len(ids), 4, 2))
    hom, cells = tag_homographies(start), stacked_tag_cells(tuple(int(i) for i in ids))
    stopped, ok = photometric.fit_tags(fr.image, start, hom, cells, iterations=4)
    full, ok_full = photometric.fit_tags(fr.image, start, hom, cells, iterations=4, converged_px=0.0)
    np.testing.assert_array_equal(ok, ok_full)
    gap = np.linalg.norm(stopped - full, axis=2)[ok]
    assert gap.max() <= 3.0 * photometric.STILL_CONVERGED_PX
    assert (gap.max(axis=1) == 0.0).sum() < ok.sum()


def test_normal_cdf_and_density_match_scipy() -> None:
    z = np.linspace(-10.0, 10.0, 4001)
    cdf = np.array([photometric_kernels._cdf_pdf(float(v))[0] for v in z])
    pdf = np.array([photometric_kernels._cdf_pdf(float(v))[1] for v in z])
    np.testing.assert_allclose(cdf, ndtr(z), rtol=0.0, atol=1e-7)
    np.testing.assert_allclose(pdf, np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi), rtol=0.0, atol=1e-15)


@given(st.floats(-1.0, 2.0))
@settings(max_examples=200, deadline=None)
def test_srgb_curves_match_the_tone_module(linear: float) -> None:
    enc, slope = srgb_encode_slope(np.array([linear]))
    got = photometric_kernels._srgb_encode(linear)
    assert got[0] == pytest.approx(enc[0], rel=1e-12, abs=1e-15)
    assert got[1] == pytest.approx(slope[0], rel=1e-12, abs=1e-15)
    assert photometric_kernels._srgb_to_linear(linear) == pytest.approx(srgb_to_linear_scalar(linear), rel=1e-12)


@given(st.integers(-40, 40))
def test_rounding_is_numpys_half_to_even(twice: int) -> None:
    x = twice / 2.0
    assert photometric_kernels._round_half_even(x) == int(np.round(x))
    assert photometric_kernels._round_half_even(x + 1e-9) == int(np.round(x + 1e-9))


def test_solve_matches_numpy_and_refuses_a_singular_system() -> None:
    rng = np.random.default_rng(0)
    for n in (3, 8, 16):
        m = rng.normal(size=(n, n))
        a = m @ m.T + 1e-3 * np.eye(n)
        b = rng.normal(size=n)
        ok, x = photometric_kernels._solve(a.copy(), b.copy())
        assert ok
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-9, atol=1e-9)
    singular = np.ones((4, 4))
    singular[:, 0] = 0.0
    assert not photometric_kernels._solve(singular, np.ones(4))[0]


def _moving_case(rng: np.random.Generator) -> tuple:
    """A tag of 6 px cells turned and moved 5 px over the exposure: its pixels near boundaries,
    homography, levels, table and warps."""
    ang = 0.4
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    corners = (np.array([[-1, -1], [1, -1], [1, 1.1], [-1, 1]]) * 24.0) @ rot.T + [60.0, 55.0]
    motion = np.tile([4.0, -3.0], (4, 1)) + rng.normal(0.0, 0.3, (4, 2))
    hom = tag_homographies(corners)[0]
    h = (hom / hom[2, 2]).ravel()[:8].copy()
    table = photometric._black_tables(stacked_tag_cells((7,)))[0]
    warps, instants = photometric.motion_warps(corners[None], motion[None], 0.7)
    ys, xs = np.mgrid[30:80, 30:85]
    # Flat levels: the kernels' rows leave out how the level planes' coordinates move with h.
    theta = np.array([0.03, 0.0, 0.0, 0.6, 0.0, 0.0, 0.1, 0.05])
    return xs.ravel().astype(float), ys.ravel().astype(float), h, theta, table, warps[0, :instants[0]]


def test_moving_model_equals_the_numpy_reference_and_its_jacobian_the_differences() -> None:
    px, py, h, theta, table, warps = _moving_case(np.random.default_rng(3))
    assert len(warps) >= 7
    n = len(px)
    mean, jac, r = np.empty((n, 12)), np.empty((n, 16)), np.empty(n)
    bu, bv = np.empty((n, len(warps)), np.int64), np.empty((n, len(warps)), np.int64)
    photometric_kernels.coverage_moving(px, py, h, 0.66 * np.exp(theta[6]), table, warps, True, bu, bv, mean,
                                        np.empty((2, 3, 4)))
    photometric_kernels.model_rows_moving(np.zeros(n), theta, mean, True, jac, r)
    want = photometric_reference.moving_model_grey(px, py, h, theta, table, warps, 0.66, True)
    np.testing.assert_allclose(-r, want, rtol=0.0, atol=2e-3)  # A & S's CDF in the kernels
    assert np.ptp(want) > 100.0  # the pattern is in view
    # The rows leave out how the blur's sds in tag units change with h (as the still fit's do):
    # the translations' rows agree to the differences' own precision, the others to 3 %.
    for i, tol in ((0, 0.03), (1, 0.03), (2, 2e-3), (3, 0.03), (4, 0.03), (5, 2e-3), (6, 0.03), (7, 0.03)):
        step = 1e-6
        hp, hm = h.copy(), h.copy()
        hp[i] += step
        hm[i] -= step
        diff = (photometric_reference.moving_model_grey(px, py, hp, theta, table, warps, 0.66, True)
                - photometric_reference.moving_model_grey(px, py, hm, theta, table, warps, 0.66, True)) / (2 * step)
        np.testing.assert_allclose(jac[:, i], diff, rtol=0.0, atol=tol * np.abs(diff).max())


def test_a_still_tag_through_the_moving_kernels_is_the_still_fit() -> None:
    fr = drive_frames("540p", RenderConfig(lighting="neutral", jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999))[:6]
    start = np.array([fr.corners_px[t] for t in ids]) + np.random.default_rng(4).normal(0.0, 0.1, (len(ids), 4, 2))
    hom, cells = tag_homographies(start), stacked_tag_cells(tuple(int(i) for i in ids))
    still, ok = photometric.fit_tags(fr.image, start, hom, cells, converged_px=0.0)
    moving, ok_m = photometric.fit_tags(fr.image, start, hom, cells, motion_px=np.zeros((len(ids), 4, 2)))
    np.testing.assert_array_equal(ok, ok_m)
    np.testing.assert_allclose(moving, still, rtol=0.0, atol=1e-9)
