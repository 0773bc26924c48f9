"""The line fits of the four outer border edges: sub-pixel corners from rendered tags, the wide pass
for starts a few px off, the step estimator, and the side-line geometry the corner stage uses."""

from __future__ import annotations

import numpy as np
import pytest
from edges_reference import outward_sides as _outward_sides
from edges_reference import side_windows as _side_windows
from hypothesis import given
from hypothesis import strategies as st
from tag_images import random_tag, tag_image

from ficap_ros.vision.detector import DetectorConfig, TagDetector
from ficap_ros.vision.edges import (
    NEXT,
    intersect_sides,
    line_windows,
    refine_corners_edge,
    refine_corners_edge_ok,
    refine_corners_edge_wide,
    side_lines,
    step_offset,
    vector_norm,
)

#: A sharp (unblurred, noiseless) 96 px tag at a sub-pixel place on a 200 x 200 canvas.
SHARP_CORNERS = np.array([[52.3, 47.6], [148.3, 51.1], [146.8, 147.2], [50.9, 143.4]])


def _sharp_tag(tag_id: int = 11) -> np.ndarray:
    return tag_image(tag_id, SHARP_CORNERS, (200, 200), np.random.default_rng(0), background=235,
                     levels=(20, 235), blur=0.0, noise=0.0)


def _corner_rms(refine: str, side_px: float, n: int = 10) -> float:
    det = TagDetector(DetectorConfig(corner_refine=refine))
    rng = np.random.default_rng(int(side_px))
    errs = []
    for _ in range(n):
        img, truth = random_tag(rng, side_px)
        found = [d for d in det.detect(img) if d.tag_id == 7]
        assert len(found) == 1
        errs.append(found[0].corners_px - truth)
    return float(np.sqrt(np.mean(np.sum(np.concatenate(errs) ** 2, axis=1))))


@pytest.mark.parametrize("side_px", [30.0, 60.0, 150.0])
def test_edge_refine_is_subpixel_and_beats_subpix(side_px):
    edge = _corner_rms("edge", side_px)
    subpix = _corner_rms("subpix", side_px)
    assert edge <= 0.1, f"edge RMS {edge:.3f} px"
    assert subpix >= 2.5 * edge, f"subpix {subpix:.3f} px vs edge {edge:.3f} px"


def test_line_fit_puts_a_sharp_tags_corners_back_from_a_px_off() -> None:
    """Without blur or a tone curve the area location of every step is exact: from corners up to
    a px off, two passes land on the true corners (the rest is the interpolation of a sharp step)."""
    img = _sharp_tag()
    start = SHARP_CORNERS + np.array([[0.9, -0.6], [-0.7, 0.8], [0.5, 0.9], [-0.8, -0.9]])
    refined, ok = refine_corners_edge_ok(img, start[None])
    assert ok[0]
    err = np.linalg.norm(refined[0] - SHARP_CORNERS, axis=1)
    assert err.max() <= 0.05, err
    np.testing.assert_array_equal(refine_corners_edge(img, start[None]), refined)


def test_a_start_beyond_the_search_is_refused_and_kept() -> None:
    """A start 6.4 px off (beyond ``edge_max_shift_px``): not refined, its corners kept as given;
    the wide pass (8 px each way, then the fine passes) reaches the corners from there."""
    img = _sharp_tag()
    start = SHARP_CORNERS + np.array([5.0, -4.0])
    refined, ok = refine_corners_edge_ok(img, start[None])
    assert not ok[0]
    np.testing.assert_array_equal(refined[0], start)
    wide = refine_corners_edge_wide(img, start[None], DetectorConfig())
    assert np.linalg.norm(wide[0] - SHARP_CORNERS, axis=1).max() <= 0.05
    empty, ok_empty = refine_corners_edge_ok(img, np.zeros((0, 4, 2)))
    assert empty.shape == (0, 4, 2) and ok_empty.shape == (0,)


def test_step_offset_finds_a_blurred_step_in_linear_light() -> None:
    """A vertical dark-to-light step at x = 40.3 px, blurred (Gaussian, sd 0.8 px) in linear grey
    and rounded to 8 bits: the area location along +x is exact for any blur the window (here 5 px
    each way) holds, wherever the window's centre, and the contrast is the levels' difference."""
    from scipy.special import ndtr

    x = np.arange(96, dtype=np.float64)
    row = 30.0 + 180.0 * ndtr((x - 40.3) / 0.8)
    img = np.round(np.tile(row, (32, 1))).astype(np.uint8)
    centres = np.array([[39.0, 10.0], [40.0, 15.0], [41.5, 20.0]])
    to_light = np.tile([1.0, 0.0], (3, 1))
    s, contrast = step_offset(img, centres, to_light, np.full(3, 5.0), 17)
    np.testing.assert_allclose(centres[:, 0] + s, 40.3, atol=0.02)
    np.testing.assert_allclose(contrast, 180.0, atol=2.0)


def test_line_windows_are_the_line_pass_windows_on_parallelograms() -> None:
    """The corner stage measures the line estimator's bias with the line pass's windows
    (``line_windows``): the same half-lengths, side for side, on parallelograms of every size;
    on other quadrilaterals it takes the tag's width at the farther opposite corner, where the
    line pass takes the mean of the two, so its windows are never narrower."""
    rng = np.random.default_rng(4)
    cfg = DetectorConfig()
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    shapes = {"parallelogram": [], "any": []}
    for _ in range(40):
        shear = np.array([[1.0, rng.uniform(-0.4, 0.4)], [0.0, rng.uniform(0.5, 1.0)]])
        base = square @ shear.T * rng.uniform(5, 80) + 200
        shapes["parallelogram"].append(base)
        shapes["any"].append(base + rng.normal(0, 3, (4, 2)))
    for name, quads in shapes.items():
        corners = np.array(quads)
        cell_px = np.repeat(vector_norm(corners[:, NEXT] - corners).mean(axis=1) / 8, 4)
        a, _, _, _, nrm = _outward_sides(corners)
        ours, theirs = line_windows(corners, cfg).ravel(), _side_windows(corners, a, nrm, cell_px, cfg)
        if name == "parallelogram":
            np.testing.assert_allclose(ours, theirs, rtol=1e-9)
        else:
            assert (ours >= theirs - 1e-9).all() and (ours > theirs + 1e-3).any()


_coordinate = st.floats(-1e3, 1e3, allow_nan=False)


@st.composite
def _convex_quads(draw: st.DrawFn) -> np.ndarray:
    """A convex quadrilateral (either handedness): a square of side 4-400 px, turned, each corner
    moved by up to a tenth of the side."""
    side = draw(st.floats(4.0, 400.0))
    angle = draw(st.floats(0.0, 2 * np.pi))
    jitter = np.array(draw(st.lists(st.floats(-0.1, 0.1), min_size=8, max_size=8))).reshape(4, 2)
    flip = draw(st.booleans())
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) / 2
    if flip:
        square = square[::-1]
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return (square + jitter) @ rot.T * side + np.array([draw(_coordinate), draw(_coordinate)])


@given(_convex_quads())
def test_side_lines_intersect_back_at_the_corners(quad: np.ndarray) -> None:
    """Corner k is where side k-1's line meets side k's, and each side's normal points away from the
    tag (the centre lies inside every line), whatever the corner order's handedness."""
    nrm, rho = side_lines(quad[None])
    np.testing.assert_allclose(intersect_sides(nrm, rho)[0], quad, atol=1e-9 * max(1.0, np.abs(quad).max()))
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=2), 1.0, rtol=1e-12)
    assert (nrm[0] @ quad.mean(axis=0) < rho[0]).all()


@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=2, max_size=24).filter(lambda v: len(v) % 2 == 0))
def test_vector_norm_is_numpys_bit_for_bit(values: list[float]) -> None:
    x = np.array(values).reshape(-1, 2)
    np.testing.assert_array_equal(vector_norm(x), np.linalg.norm(x, axis=-1))
    np.testing.assert_array_equal(vector_norm(x[None], keepdims=True), np.linalg.norm(x[None], axis=-1, keepdims=True))
