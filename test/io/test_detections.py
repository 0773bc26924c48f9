"""Per-tag detections (ficap_ros.io.detections): each tag's use and residual under the cap pose, the
apriltag_msgs message in AprilTag's own conventions (checked against pupil-apriltags, AprilTag 3's
Python binding), the named fits and detections.csv."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.detections import (
    DETECTION_COLUMNS,
    TagFits,
    apriltag_array,
    apriltag_corners,
    apriltag_homographies,
    detections_csv_text,
    fit_values,
    tag_fits,
)
from ficap_ros.io.labels import FrameRecord
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import DetectorConfig, TagDetection, TagDetector
from ficap_ros.vision.pipeline import FrameProcessor
from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose


@pytest.fixture(scope="module")
def frame():
    """(camera, truth T_cam_cap, pipeline result) of one rendered 540p frame of the cap."""
    scene = default_scene("540p")
    T = naturalistic_drive(1, fps=30.0, seed=4, scene=scene)[0].T_cam_cap
    image = render(nominal_model(), scene.camera, T, RenderConfig(), seed=3).image
    result = FrameProcessor(tracking=False).process(image, scene.camera)
    assert result.pose is not None and len(result.detections) >= 6
    return scene.camera, T, result


def test_used_tags_and_residuals_follow_the_pose(frame) -> None:
    camera, _, result = frame
    model = nominal_model()
    fits = tag_fits(result.detections, result.pose, model, camera)
    assert list(fits.ids) == [d.tag_id for d in result.detections]
    assert set(fits.ids[fits.used]) == set(result.pose.used_ids)
    assert np.all(fits.residual_px[fits.used] < 0.5)
    # The pose's rms is over its tags' corners moved onto squares' images (``PoseConfig.square_tags``):
    # below the fits' residuals' quadratic mean (those of the detected corners), which it equals
    # (undistorted px against distorted) for a pose fitted to the detected corners.
    rms = math.sqrt(np.mean(fits.residual_px[fits.used] ** 2))
    assert result.pose.rms_px < rms
    plain = estimate_cap_pose(result.detections, model, camera, PoseConfig(square_tags=False)).pose
    plain_fits = tag_fits(result.detections, plain, model, camera)
    plain_rms = math.sqrt(np.mean(plain_fits.residual_px[plain_fits.used] ** 2))
    assert plain_rms == pytest.approx(plain.rms_px, rel=0.05, abs=0.01)
    # A pose 2 mm off makes every residual grow; without a pose none is measured and none used.
    moved = Transform(result.pose.T_cam_cap.rotation, result.pose.T_cam_cap.translation_m + [0.002, 0, 0])
    off = tag_fits(result.detections, _with_pose(result.pose, moved), model, camera)
    assert np.all(off.residual_px > fits.residual_px)
    none = tag_fits(result.detections, None, model, camera)
    assert not none.used.any() and np.isnan(none.residual_px).all()
    empty = tag_fits((), None, model, camera)
    assert len(empty) == 0 and empty.corners_px.shape == (0, 4, 2)


def _with_pose(pose, T: Transform):  # noqa: ANN001, ANN202
    from dataclasses import replace

    return replace(pose, T_cam_cap=T)


def test_the_message_follows_apriltag_conventions() -> None:
    """Corners, centre and homography as AprilTag 3 reports them for the same detection: the
    apriltag backend's raw corners (converted to OpenCV's convention by the detector) go back to
    pupil-apriltags' own, to float32 rounding."""
    pytest.importorskip("pupil_apriltags")
    from tag_images import oblique_tag

    # pupil-apriltags' Detector, freed in the order the detector module's subclass ensures.
    from ficap_ros.vision.detector import _apriltag_detector_class

    image, _ = oblique_tag(7, 80, 20, 0.3, 0.7, np.random.default_rng(1))
    cfg = DetectorConfig(backend="apriltag", corner_refine="none")
    (ours,) = TagDetector(cfg).detect(image)
    (theirs,) = _apriltag_detector_class()(  # the backend's settings
        families="tag36h11", nthreads=1, quad_decimate=float(cfg.quad_decimate), quad_sigma=0.0,
        refine_edges=True, decode_sharpening=0.25).detect(image)
    fits = TagFits(np.array([7]), ours.corners_px[None], np.array([True]), np.array([0.1]),
                   np.array([0]), np.array([theirs.decision_margin]))
    msg = apriltag_array(ROSBAGS, messages.header(ROSBAGS, 5, "cam"), fits)
    (d,) = msg.detections
    got = np.array([[c.x, c.y] for c in d.corners])
    np.testing.assert_allclose(got, theirs.corners, atol=1e-4)
    np.testing.assert_allclose([d.centre.x, d.centre.y], theirs.center, atol=1e-3)
    H = np.reshape(d.homography, (3, 3))
    np.testing.assert_allclose(H, theirs.homography / theirs.homography[2, 2], rtol=1e-3, atol=1e-3)
    assert (d.family, d.id, d.hamming) == ("tag36h11", 7, 0)
    assert d.decision_margin == pytest.approx(theirs.decision_margin)
    raw = messages.jazzy_typestore().serialize_cdr(msg, "apriltag_msgs/msg/AprilTagDetectionArray")
    back = messages.jazzy_typestore().deserialize_cdr(raw, "apriltag_msgs/msg/AprilTagDetectionArray")
    assert back.detections[0].id == 7


@given(arrays(np.float64, (4, 2), elements=st.floats(-1e4, 1e4)))
def test_apriltag_corners_go_back(c: np.ndarray) -> None:
    p = apriltag_corners(c)
    np.testing.assert_allclose(p[[1, 0, 3, 2]] - 0.5, c, rtol=0, atol=1e-9)


@given(st.lists(st.tuples(st.floats(50.0, 1800.0), st.floats(50.0, 1000.0), st.floats(8.0, 200.0),
                          st.floats(0.0, 6.28), st.floats(-0.3, 0.3)), min_size=1, max_size=5))
def test_each_homography_maps_the_tag_square_onto_its_corners(tags) -> None:  # noqa: ANN001
    """The message's homography takes tag coordinates (-1, 1), (1, 1), (1, -1), (-1, -1) to p0..p3
    and (0, 0) to the centre, for every tag of the array at once."""
    corners = []
    for cx, cy, side, angle, skew in tags:
        R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2
        square[:, 0] *= np.where(square[:, 1] < 0, 1 - skew, 1 + skew)  # seen obliquely
        corners.append(square @ R.T + [cx, cy])
    n = len(corners)
    fits = TagFits(np.arange(n), np.array(corners), np.ones(n, bool), np.zeros(n), np.zeros(n, int),
                   np.zeros(n))
    msg = apriltag_array(ROSBAGS, messages.header(ROSBAGS, 0, "cam"), fits)
    for k, d in enumerate(msg.detections):
        H = np.reshape(d.homography, (3, 3))
        assert H[2, 2] == 1.0
        xy = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [0.0, 0.0]])
        m = (H @ np.c_[xy, np.ones(5)].T).T
        got = m[:, :2] / m[:, 2:]
        np.testing.assert_allclose(got[:4], apriltag_corners(fits.corners_px[k]), atol=1e-6)
        np.testing.assert_allclose(got[4], [d.centre.x, d.centre.y], atol=1e-9)


@given(st.lists(st.integers(0, 4), min_size=0, max_size=6), st.integers(0, 2**32 - 1))
def test_homographies_solved_at_once_are_each_frames_own_to_the_bit(sizes: list[int], seed: int) -> None:
    """apriltag_homographies over several frames (some without tags) gives each frame the values
    apriltag_array solves for it alone, bit for bit: labels.mcap's bytes do not depend on it."""
    rng = np.random.default_rng(seed)
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    frames = []
    for n in sizes:
        corners = (square[None] * rng.uniform(5.0, 80.0, (n, 1, 1)) + rng.uniform(0.0, 1900.0, (n, 1, 2))
                   + rng.normal(0.0, 1.5, (n, 4, 2)))
        frames.append(TagFits(np.arange(n), corners, np.ones(n, bool), np.zeros(n), np.zeros(n, int),
                              np.zeros(n)))
    together = apriltag_homographies(frames)
    assert len(together) == len(frames)
    head = messages.header(ROSBAGS, 0, "cam")
    for fits, H in zip(frames, together):
        assert H.shape == (len(fits), 3, 3)
        alone = apriltag_array(ROSBAGS, head, fits)
        given_h = apriltag_array(ROSBAGS, head, fits, H)
        for a, b in zip(alone.detections, given_h.detections):
            assert a.homography.tobytes() == b.homography.tobytes()
            assert (a.centre.x, a.centre.y) == (b.centre.x, b.centre.y)


def _fits() -> TagFits:
    corners = np.arange(16, dtype=np.float64).reshape(2, 4, 2) + 0.123456
    return TagFits(np.array([3, 11]), corners, np.array([True, False]), np.array([0.25, np.nan]),
                   np.array([0, 1]), np.array([np.nan, 55.5]))


def test_fit_values_are_named_numbers() -> None:
    values = fit_values(_fits())
    assert list(values) == ["tag3/used", "tag3/residual_px", "tag11/used", "tag11/residual_px"]
    assert values["tag3/used"] == 1.0 and values["tag11/used"] == 0.0
    assert values["tag3/residual_px"] == 0.25 and math.isnan(values["tag11/residual_px"])


def test_detections_csv_has_a_row_per_tag() -> None:
    recs = [FrameRecord.processed(4, 99, "cam", None, (3, 11), tags=_fits()),
            FrameRecord.unprocessed(5, 100, "cam", "bad JPEG")]  # no tags: no rows
    rows = list(csv.reader(io.StringIO(detections_csv_text(recs))))
    assert tuple(rows[0]) == DETECTION_COLUMNS and len(rows) == 3
    first = dict(zip(rows[0], rows[1]))
    assert (first["frame"], first["stamp_ns"], first["tag_id"], first["used"]) == ("4", "99", "3", "1")
    assert (first["residual_px"], first["decision_margin"]) == ("0.2500", "")
    assert (first["c0_x_px"], first["c3_y_px"]) == ("0.1235", "7.1235")
    second = dict(zip(rows[0], rows[2]))
    assert (second["used"], second["residual_px"], second["hamming"]) == ("0", "", "1")


@given(arrays(np.float64, (3, 4, 2), elements=st.one_of(
    st.floats(-1e4, 1e4), st.sampled_from([np.nan, np.inf, -np.inf]))))
def test_detections_csv_writes_each_corner_to_four_decimals_or_empty(corners: np.ndarray) -> None:
    fits = TagFits(np.array([1, 2, 3]), corners, np.array([True, False, True]),
                   np.array([0.5, np.nan, np.inf]), np.array([0, 1, 2]), np.array([1.0, np.nan, 2.0]))
    rows = list(csv.reader(io.StringIO(detections_csv_text(
        [FrameRecord.processed(7, 123, "cam", None, (1, 2, 3), tags=fits)]))))
    assert len(rows) == 4 and all(len(r) == len(DETECTION_COLUMNS) for r in rows)
    for row, c in zip(rows[1:], corners.reshape(3, 8)):
        expect = [f"{v:.4f}" if math.isfinite(v) else "" for v in c]
        assert row[7:] == expect
    assert [r[4] for r in rows[1:]] == ["0.5000", "", ""]


def test_detections_of_a_record_without_pose_keep_their_corners() -> None:
    model = nominal_model()
    d = TagDetection(5, np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]))
    from ficap_ros.geometry.camera import CameraModel

    fits = tag_fits([d], None, model, CameraModel.pinhole(64, 48, hfov_deg=60.0))
    np.testing.assert_array_equal(fits.corners_px[0], d.corners_px)
    assert fits.ids.tolist() == [5] and math.isnan(fits.decision_margin[0])
