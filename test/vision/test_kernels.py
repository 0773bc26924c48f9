"""The corner stage's compiled kernels against their numpy references (``edges_reference``): the
profiles hold ``cv2.remap``'s own samples (contrast, a difference of samples, equal exactly), and
the step offsets and fitted lines agree to float rounding (offsets within 2e-6 px, line offsets
within 1e-5 px, normals within 1e-7, the same profiles kept), inside the image and reaching off
it."""

from __future__ import annotations

import numpy as np
import pytest
from edges_reference import edge_lines as edge_lines_numpy
from edges_reference import outward_sides, side_windows
from edges_reference import refine_corners_edge_ok as line_pass_numpy
from edges_reference import step_offset as step_offset_numpy
from tag_images import tag_image, two_tag_scene

from ficap_ros.vision import edges
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.kernels import area_steps, edge_lines


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_area_steps_equal_the_remap_reference(seed: int) -> None:
    img, _ = two_tag_scene(seed)
    rng = np.random.default_rng(seed + 10)
    n = 3000
    centre = rng.uniform([-6.0, -6.0], [326.0, 246.0], (n, 2))  # some profiles off the image
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    to_light = np.column_stack([np.cos(angle), np.sin(angle)])
    half = rng.uniform(0.75, 4.0, n)
    for samples in (9, 11, 17):
        want_s, want_c = step_offset_numpy(img, centre, to_light, half, samples)
        got_s, got_c = edges.step_offset(img, centre, to_light, half, samples)
        np.testing.assert_array_equal(got_c, want_c)
        np.testing.assert_allclose(got_s, want_s, rtol=0.0, atol=2e-6)
    # The kernel's own flag: every sample within the image's pixel centres.
    one = np.ones(1, np.float32)
    _, _, inside = area_steps(img, 1.0 * one, 5.0 * one, -0.5 * one, 0.0 * one, 4, np.ones(1), np.full(1, 0.25))
    assert not inside[0]
    _, _, inside = area_steps(img, 3.0 * one, 5.0 * one, -0.5 * one, 0.0 * one, 4, np.ones(1), np.full(1, 0.25))
    assert inside[0]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_edge_lines_equal_the_numpy_reference(seed: int) -> None:
    img, corners = two_tag_scene(seed)
    cfg = DetectorConfig()
    a, d, _, _, nrm = outward_sides(corners)
    cell_px = np.repeat(edges.vector_norm(corners[:, edges.NEXT] - corners).mean(axis=1) / 8.0, 4)
    half = side_windows(corners, a, nrm, cell_px, cfg)
    for k, m in ((8, 24), (4, 12)):
        t = np.linspace(0.15, 0.85, m)
        for check_inside in (False, True):
            want = edge_lines_numpy(img, a, d, nrm, half, t, k, check_inside)
            got = edge_lines(img, a, d, nrm, half, t, k, check_inside)
            np.testing.assert_array_equal(got[2], want[2])
            np.testing.assert_allclose(got[0], want[0], rtol=0.0, atol=1e-7)
            np.testing.assert_allclose(got[1], want[1], rtol=0.0, atol=1e-5)
    # The tag cut by the border loses profiles only when they are checked.
    kept_all = edge_lines(img, a, d, nrm, half, np.linspace(0.15, 0.85, 24), 8, False)[2]
    kept_in = edge_lines(img, a, d, nrm, half, np.linspace(0.15, 0.85, 24), 8, True)[2]
    assert kept_in[4:].sum() < kept_all[4:].sum() and (kept_in[:4] == kept_all[:4]).all()


def test_the_line_pass_finds_true_corners() -> None:
    """End to end through the kernel: the refined corners of the whole tag within 0.1 px of the
    truth (a blurred, noisy render; the line pass alone keeps the tone curve's bias, here none)."""
    rng = np.random.default_rng(4)
    truth = np.array([[60.0, 50.0], [150.0, 58.0], [146.0, 150.0], [55.0, 142.0]])
    img = tag_image(3, truth, (220, 200), rng, background=120, levels=(20.0, 230.0), blur=0.7, noise=2.0)
    refined, ok = edges.refine_corners_edge_ok(img, truth[None] + rng.normal(0.0, 0.8, (1, 4, 2)))
    assert ok.all()
    assert np.abs(refined[0] - truth).max() < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_line_pass_equals_the_numpy_reference(seed: int) -> None:
    """The whole line pass from starts up to a pixel off (one tag cut by the border), both
    settings the detector uses: the same tags refined, corners within 1e-5 px."""
    img, corners = two_tag_scene(seed)
    start = corners + np.random.default_rng(seed).normal(0.0, 0.7, corners.shape)
    for cfg in (DetectorConfig(), DetectorConfig(edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                                                 edge_samples_per_side=12, edge_profile_samples=9)):
        want, want_ok = line_pass_numpy(img, start, cfg)
        got, got_ok = edges.refine_corners_edge_ok(img, start, cfg)
        np.testing.assert_array_equal(got_ok, want_ok)
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-5)


def test_degenerate_inputs_give_non_finite_values_not_exceptions() -> None:
    """A collapsed tag divides by zero: inf or NaN as in numpy, which the callers refuse (the tag
    keeps its corners), never ZeroDivisionError."""
    img, _ = two_tag_scene(0)
    point = np.full((1, 4, 2), 100.0)
    refined, ok = edges.refine_corners_edge_ok(img, point)
    assert not ok[0] and (refined == point).all()
