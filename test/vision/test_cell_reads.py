"""The compiled cell reading against ``tag36h11.read_tag_cells`` (the numpy and ``cv2.remap``
reference): every read cell, level and finite flag equal exactly, for tags inside the image,
reaching off it, far beyond it and through homographies with non-finite points; and
``cell_errors`` equal to ``tag36h11.cell_errors``."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from tag_images import tag_image, two_tag_scene

from ficap_ros.geometry import tag36h11
from ficap_ros.vision.cell_reads import cell_errors, read_cells


def _tag(tag_id: int, side_px: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A blurred, noisy rendered tag of side ``side_px`` on a 160 x 160 grey image, and its corners."""
    corners = 80.0 + side_px * np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) + 0.3
    img = tag_image(tag_id, corners, (160, 160), np.random.default_rng(seed), background=128,
                    levels=(30.0, 220.0), blur=0.7, noise=2.0)
    return img, corners


def _random_quads(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """(n, 4, 2) convex-ish quadrilaterals: a square of random size and angle, corners jittered."""
    centre = rng.uniform(lo, hi, (n, 1, 2))
    side = rng.uniform(6.0, 120.0, (n, 1, 1))
    angle = rng.uniform(0.0, 2.0 * np.pi, (n, 1))
    unit = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    rot = np.stack([np.cos(angle), -np.sin(angle), np.sin(angle), np.cos(angle)], axis=-1).reshape(n, 2, 2)
    quads = centre + side * np.einsum("nij,kj->nki", rot, unit)
    return quads + rng.normal(0.0, 0.08, quads.shape) * side


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_read_cells_equal_the_remap_reference(seed: int) -> None:
    img, _ = two_tag_scene(seed)
    rng = np.random.default_rng(seed)
    quads = _random_quads(rng, 400, -60.0, 380.0)  # some inside, some across the border, some beyond
    hom = tag36h11.tag_homographies(quads)
    want = tag36h11.read_tag_cells(img, hom)
    got = read_cells(img, hom)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert want[3].all()


def test_read_cells_of_a_rendered_tag_read_its_code() -> None:
    img, corners = _tag(7, 64.0)
    read_black, white, black, finite = read_cells(img, tag36h11.tag_homographies(corners[None]))
    np.testing.assert_array_equal(read_black[0], tag36h11.tag_cells(7).ravel())
    assert finite[0] and white[0] - black[0] > 100.0


def test_non_finite_points_read_as_the_reference() -> None:
    img, _ = two_tag_scene(0)
    hom = tag36h11.tag_homographies(_random_quads(np.random.default_rng(5), 6, 40.0, 200.0))
    hom[1, 2] = [0.0, 0.0, 0.0]  # every point at infinity
    hom[2, 0, 0] = np.nan
    hom[3, 2] = [1.0, 0.0, -4.5]  # the line u = 4.5 maps to infinity: one column of centres
    hom[4, 0] *= 1e38  # finite in float64, beyond float32
    with np.errstate(all="ignore"):
        want = tag36h11.read_tag_cells(img, hom)
        got = read_cells(img, hom)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert not want[3][1:5].any() and want[3][0] and want[3][5]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), tag_id=st.integers(0, 586))
def test_cell_errors_equal_the_reference(seed: int, tag_id: int) -> None:
    rng = np.random.default_rng(seed)
    img, corners = _tag(tag_id, float(rng.uniform(24.0, 80.0)), seed)
    quads = corners[None] + rng.normal(0.0, 1.5, (8, 4, 2))
    ids = np.full(8, tag_id)
    np.testing.assert_array_equal(cell_errors(img, quads, ids), tag36h11.cell_errors(img, quads, ids))


def test_cell_errors_of_no_tags_and_degenerate_quads() -> None:
    img, corners = _tag(3, 40.0)
    assert cell_errors(img, np.zeros((0, 4, 2)), np.zeros(0, int)).shape == (0,)
    line = np.array([[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]])
    np.testing.assert_array_equal(cell_errors(img, line, [3]), [64])
    assert cell_errors(img, corners[None], [3])[0] == 0
