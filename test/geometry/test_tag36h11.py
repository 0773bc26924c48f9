"""The tag36h11 family: cells against OpenCV's dictionary, the homographies from cell units, the
cell grid, reading a tag's cells, and decoding quads of unknown id."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from tag_images import DICT, oblique_tag

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.tag36h11 import (
    BORDER,
    CELL_CENTRES,
    QUIET_ZONE,
    TAG_AREA,
    TAG_CELLS,
    apply_homographies,
    cell_errors,
    decode_tags,
    homography_corners,
    read_tag_cells,
    stacked_tag_cells,
    tag_cells,
    tag_homographies,
    usable_quads,
)
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)

N_IDS = DICT.bytesList.shape[0]
#: c0..c3 in tag cell units.
UNIT_CORNERS = np.array([[0.0, 0.0], [TAG_CELLS, 0.0], [TAG_CELLS, TAG_CELLS], [0.0, TAG_CELLS]])


@given(st.integers(0, N_IDS - 1))
def test_cells_are_the_dictionarys_bits_inside_a_black_border(tag_id: int) -> None:
    """The cells are OpenCV's drawing of the tag (read at the cell centres of a 10 px-a-cell
    drawing, row-major from c0), its 6 x 6 data cells the dictionary's code (bit 1 = white, from
    its byte list), inside a black ring; the array is cached read-only."""
    cells = tag_cells(tag_id)
    drawing = cv2.aruco.generateImageMarker(DICT, tag_id, 10 * TAG_CELLS, borderBits=1)
    bits = cv2.aruco.Dictionary.getBitsFromByteList(DICT.bytesList[tag_id:tag_id + 1], 6)
    assert cells.shape == (TAG_CELLS, TAG_CELLS) and cells.dtype == bool
    np.testing.assert_array_equal(cells, drawing[5::10, 5::10] == 0)
    np.testing.assert_array_equal(cells[1:-1, 1:-1], bits == 0)
    assert cells[BORDER.reshape(TAG_CELLS, TAG_CELLS)].all()
    assert not cells.flags.writeable and tag_cells(tag_id) is cells


def test_stacked_cells_and_the_cell_grid() -> None:
    ids = (3, 0, 586)
    stacked = stacked_tag_cells(ids)
    assert stacked.shape == (3, TAG_CELLS, TAG_CELLS) and not stacked.flags.writeable
    for k, i in enumerate(ids):
        np.testing.assert_array_equal(stacked[k], tag_cells(i))
    assert stacked_tag_cells(()).shape == (0, TAG_CELLS, TAG_CELLS)
    # 10 x 10 cell centres: the 36 of the quiet-zone ring around the 64 of the tag, 28 of them border.
    assert CELL_CENTRES.shape == (100, 2) and QUIET_ZONE.sum() == 36 and TAG_AREA.sum() == 64 and BORDER.sum() == 28
    np.testing.assert_array_equal(CELL_CENTRES[TAG_AREA][[0, 7, 63]], [[0.5, 0.5], [7.5, 0.5], [7.5, 7.5]])


@st.composite
def _quads(draw: st.DrawFn) -> np.ndarray:
    """Convex quadrilaterals in OpenCV's corner order: a square of side 5-500 px, turned, under a
    perspective (each corner moved by up to a fifth of the side), anywhere in a 4K frame."""
    side = draw(st.floats(5.0, 500.0))
    angle = draw(st.floats(0.0, 2 * np.pi))
    jitter = np.array(draw(st.lists(st.floats(-0.2, 0.2), min_size=8, max_size=8))).reshape(4, 2)
    centre = np.array([draw(st.floats(0.0, 3840.0)), draw(st.floats(0.0, 2160.0))])
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) / 2
    return (square + jitter) @ rot.T * side + centre


@given(st.lists(_quads(), min_size=1, max_size=4))
def test_homographies_map_the_tag_corners_onto_the_quads(quads: list[np.ndarray]) -> None:
    """c0..c3 in cell units land on the corners; ``homography_corners`` inverts the map; a point
    through ``apply_homographies`` lands where OpenCV's perspective transform of the same quad puts it."""
    c = np.array(quads)
    hom = tag_homographies(c)
    scale = max(1.0, float(np.abs(c).max()))
    p = np.einsum("nij,kj->nki", hom, np.column_stack([UNIT_CORNERS, np.ones(4)]))
    np.testing.assert_allclose(p[..., :2] / p[..., 2:3], c, atol=1e-9 * scale)
    assert (hom[:, 2, 2] == 1.0).all()
    np.testing.assert_allclose(homography_corners(hom.reshape(-1, 9)[:, :8]), c, atol=1e-9 * scale)
    uv = np.tile([[2.5, 5.25]], (len(c), 1))
    for k in range(len(c)):
        ref = cv2.getPerspectiveTransform(UNIT_CORNERS.astype(np.float32), c[k].astype(np.float32))
        want = cv2.perspectiveTransform(uv[k][None, None].astype(np.float64), ref)[0, 0]
        np.testing.assert_allclose(apply_homographies(hom[k:k + 1], uv[k:k + 1])[0], want, rtol=1e-4, atol=1e-3)


def test_usable_quads_are_those_the_homographies_accept() -> None:
    good = np.array([[10.0, 10.0], [40.0, 12.0], [42.0, 41.0], [9.0, 39.0]])
    collinear = np.array([[10.0, 40.0], [10.0, 10.0], [20.0, 10.0], [30.0, 10.0]])  # c1, c2, c3 on a line
    nan = np.full((4, 2), np.nan)
    np.testing.assert_array_equal(usable_quads(np.stack([good, collinear, nan, good])), [True, False, False, True])
    tag_homographies(good[None])
    for bad in (collinear, nan):
        with pytest.raises(np.linalg.LinAlgError):
            tag_homographies(np.stack([good, bad]))


@settings(max_examples=25)
@given(st.integers(0, N_IDS - 1), st.floats(0.0, 360.0), st.floats(0.0, 0.3), st.integers(0, 3))
def test_a_drawn_tag_reads_back_as_its_id_in_any_corner_order(tag_id: int, angle: float, tilt: float,
                                                               roll: int) -> None:
    """Drawn by OpenCV under a perspective: its cells read back (``read_tag_cells``, no cell
    wrong at the true corners), and ``decode_tags`` given its corners in any rotation names its id
    with no bit error and returns the corners in the id's own order."""
    rng = np.random.default_rng(tag_id)
    img, truth = oblique_tag(tag_id, 80.0, angle, tilt, 0.6, rng)
    read_black, white, black, finite = read_tag_cells(img, tag_homographies(truth[None]))
    assert finite[0] and white[0] - black[0] > 100
    np.testing.assert_array_equal(read_black[0], tag_cells(tag_id).ravel())
    assert cell_errors(img, truth[None], [tag_id])[0] == 0
    ok, ids, errors, ordered = decode_tags(img, np.roll(truth, roll, axis=0)[None])
    assert ok[0] and ids[0] == tag_id and errors[0] == 0
    np.testing.assert_allclose(ordered[0], truth)


def test_cells_read_a_cell_off_are_wrong() -> None:
    """At corners one cell off (or without a homography) a tag's own cells do not read right."""
    rng = np.random.default_rng(1)
    img, truth = oblique_tag(17, 80.0, 0.0, 0.0, 0.6, rng)
    off = truth + (truth[1] - truth[0]) / TAG_CELLS
    collinear = np.array([[10.0, 40.0], [10.0, 10.0], [20.0, 10.0], [30.0, 10.0]])
    errors = cell_errors(img, np.stack([truth, off]), [17, 17])
    assert errors[0] == 0 and errors[1] >= 8
    assert cell_errors(img, collinear[None], [17])[0] == 64
    assert cell_errors(img, np.zeros((0, 4, 2)), []).shape == (0,)


def test_decode_tags_reads_every_corner_order_and_returns_opencv_order() -> None:
    rng = np.random.default_rng(5)
    img, truth = oblique_tag(17, 60.0, 20.0, 0.1, 0.6, rng)
    for r in range(4):
        ok, ids, errors, ordered = decode_tags(img, np.roll(truth, r, axis=0)[None])
        assert ok[0] and ids[0] == 17 and errors[0] == 0
        np.testing.assert_allclose(ordered[0], truth)  # c0 back at the tag's top-left


def test_decode_tags_rejects_what_is_not_a_tag() -> None:
    """Random quads on noise, on a textured render and on a tag's inner squares read as nothing."""
    rng = np.random.default_rng(11)
    noise = cv2.GaussianBlur(rng.integers(0, 256, (480, 640)).astype(np.uint8), (0, 0), 1.5)
    scene = default_scene("540p")
    frame = render(nominal_model(), scene.camera, naturalistic_drive(2, 30.0, 0, scene)[0].T_cam_cap,
                   RenderConfig(), seed=0).image
    quads = []
    for _ in range(3000):
        centre = rng.uniform(40, 440, 2)
        quads.append(centre + rng.uniform(-30, 30, (4, 2)) + np.array([[-20, -20], [20, -20], [20, 20], [-20, 20]]))
    quads = np.array(quads)
    for image in (noise, cv2.resize(frame, (640, 480)) if frame.ndim == 2 else
                  cv2.cvtColor(cv2.resize(frame, (640, 480)), cv2.COLOR_BGR2GRAY)):
        ok, *_ = decode_tags(image, quads)
        assert not ok.any()
    # The inner 6x6 data square of a real tag is not a tag either (its border is not black).
    img, truth = oblique_tag(3, 80.0, 0.0, 0.0, 0.0, rng)
    centre = truth.mean(axis=0)
    ok, *_ = decode_tags(img, (centre + (truth - centre) * 6 / 8)[None])
    assert not ok[0]
