"""Partly hidden tags: read from their quiet zone, dropped by the pose at a lower residual.

Rendered frames with exact ground truth: ``ficap synth``'s head pushed 6 mm up in the cap frame
pokes through the rim and covers a corner of tags 0 and 2 (about 92 % of each tag visible), as hair
and headrests do on the blender_dev renders."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import (
    HEAD_CENTRE_M,
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import DetectorConfig, TagDetection
from ficap_ros.vision.occlusion import partly_hidden
from ficap_ros.vision.pipeline import FrameProcessor, hidden_tag_ids
from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose

MODEL = nominal_model()
#: The default head moved 6 mm along the cap's z: it covers one corner of tags 0 and 2.
HEAD_OVER_RIM_M = (HEAD_CENTRE_M[0], HEAD_CENTRE_M[1], HEAD_CENTRE_M[2] + 0.006)


@lru_cache(maxsize=None)
def _frame(resolution: str, lighting: str, head: tuple[float, float, float]):
    scene = default_scene(resolution)
    drive = naturalistic_drive(1, fps=30, seed=11, scene=scene)
    cfg = RenderConfig(lighting=lighting, head_centre_m=head, jpeg_quality=95)
    return scene, drive[0], render(MODEL, scene.camera, drive[0].T_cam_cap, cfg, seed=1)


def _detections(resolution: str, lighting: str, head: tuple[float, float, float]):
    scene, frame, rf = _frame(resolution, lighting, head)
    proc = FrameProcessor(MODEL, DetectorConfig(hidden_check=False))
    return proc.process(rf.image, scene.camera, frame.stamp_ns).detections, rf


@pytest.mark.parametrize("lighting", ["neutral", "high", "low"])
def test_a_head_over_a_tags_corner_is_seen_and_whole_tags_are_not(lighting: str) -> None:
    # Fully visible tags (every lighting, the default head and the moved one): none flagged; the
    # tags the moved head covers in part, where they are detected at all: flagged.
    for head in (HEAD_CENTRE_M, HEAD_OVER_RIM_M):
        dets, rf = _detections("1080p", lighting, head)
        flags = partly_hidden(rf.image, np.stack([d.corners_px for d in dets]), np.array([d.tag_id for d in dets]))
        for d, flag in zip(dets, flags):
            visible = rf.visible_fraction[d.tag_id]
            if visible >= 0.999:
                assert not flag, (head, d.tag_id)
            elif visible < 0.95:
                assert flag, (head, d.tag_id, visible)
    dets, rf = _detections("1080p", lighting, HEAD_OVER_RIM_M)
    partial = {d.tag_id for d in dets if rf.visible_fraction[d.tag_id] < 0.95}
    assert partial, "the moved head should leave a partly hidden tag that still verifies"


def test_a_tag_at_the_image_border_is_hidden() -> None:
    dets, rf = _detections("540p", "neutral", HEAD_CENTRE_M)
    d = max(dets, key=lambda d: np.ptp(d.corners_px[:, 0]))  # a large, near-frontal tag
    c = d.corners_px[None]
    assert not partly_hidden(rf.image, c, np.array([d.tag_id]))[0]
    # Crop the image so that its left edge runs along the tag's left edge: its white margin there
    # is off the image, its corners c0 and c3 on the image's first column or just outside.
    x0 = int(np.ceil(d.corners_px[[0, 3], 0].max()))
    cropped = np.ascontiguousarray(rf.image[:, x0:])
    shifted = c - np.array([x0, 0.0])
    assert partly_hidden(cropped, shifted, np.array([d.tag_id]))[0]


def _projected(T: Transform, ids: list[int], camera) -> dict[int, np.ndarray]:
    pts = T.apply(np.concatenate([MODEL.corners_of(i) for i in ids]) / 1000.0)
    return dict(zip(ids, camera.project(pts).reshape(-1, 4, 2)))


def test_the_pose_drops_a_hidden_tag_at_twice_the_median_residual() -> None:
    scene = default_scene("1080p")
    T = Transform(Rotation.from_euler("xyz", [0.3, -0.2, 0.1]) * naturalistic_drive(1, scene=scene)[0].T_cam_cap.rotation,
                  naturalistic_drive(1, scene=scene)[0].T_cam_cap.translation_m)
    ids = [i for i in MODEL.ids if i not in (1, 8)]
    rng = np.random.default_rng(5)
    corners = {i: c + rng.normal(0.0, 0.1, c.shape) for i, c in _projected(T, ids, scene.camera).items()}
    # One tag's corners pulled 0.6 px toward an occluder (below the general 1 px floor).
    corners[11] = corners[11] + np.array([0.6, 0.3])
    dets = [TagDetection(i, c) for i, c in corners.items()]
    plain = estimate_cap_pose(dets, MODEL, scene.camera).pose
    seen = estimate_cap_pose(dets, MODEL, scene.camera, hidden_ids={11}).pose
    assert 11 in plain.used_ids and 11 not in seen.used_ids
    assert seen.tags_used == plain.tags_used - 1
    assert seen.rms_px < plain.rms_px
    assert angle_deg(seen.T_cam_cap.rotation, T.rotation) < angle_deg(plain.T_cam_cap.rotation, T.rotation)
    # A hidden tag whose corners agree with the others stays; with fewer than four tags none goes.
    fine = estimate_cap_pose(dets, MODEL, scene.camera, hidden_ids={12}).pose
    assert 12 in fine.used_ids
    few = [d for d in dets if d.tag_id in (10, 11, 12)]
    assert 11 in estimate_cap_pose(few, MODEL, scene.camera, hidden_ids={11}).pose.used_ids
    with pytest.raises(ConfigError):
        PoseConfig(hidden_ratio=1.0)


def test_replay_leaves_out_the_hidden_tag_with_a_bad_corner() -> None:
    # 1080p, spotlights: the head's edge over tag 2's corner moves its corners 0.18 px (the fully
    # visible tags: ~0.1); the pose without the check keeps it (under 4x the median), with the
    # check it goes. Tag 0, found by the search's completion, has a corner under the head that the
    # line pass puts 10 px off; fitted again from the completion's prediction it is within 0.5 px.
    scene, frame, rf = _frame("1080p", "high", HEAD_OVER_RIM_M)
    out = {}
    for check in (False, True):
        proc = FrameProcessor(MODEL, DetectorConfig(hidden_check=check))
        out[check] = proc.process(rf.image, scene.camera, frame.stamp_ns)
    assert {d.tag_id for d in out[False].detections} == {d.tag_id for d in out[True].detections}
    assert {0, 2} <= hidden_tag_ids(rf.image, out[True].detections)
    assert 2 in out[False].pose.used_ids and 2 not in out[True].pose.used_ids
    for r in out.values():
        tag0 = next(d for d in r.detections if d.tag_id == 0)
        assert np.linalg.norm(tag0.corners_px - rf.corners_px[0], axis=1).max() < 0.5
    assert out[True].pose.rms_px < out[False].pose.rms_px
    err = {k: angle_deg(v.pose.T_cam_cap.rotation, frame.T_cam_cap.rotation) for k, v in out.items()}
    assert err[True] < err[False] + 0.002


def test_one_degenerate_quadrilateral_does_not_flag_or_unfit_the_others() -> None:
    # The frame's tags are read together; a tag whose corners give no homography (three on a
    # line, NaN) is flagged (or left unfitted) alone: the others' answers are the ones they get
    # without it (not every tag of the frame flagged hidden, or left unfitted).
    from ficap_ros.vision.corners import fit_tags_photometric

    dets, rf = _detections("540p", "neutral", HEAD_CENTRE_M)
    c = np.stack([d.corners_px for d in dets])
    ids = np.array([d.tag_id for d in dets])
    alone = partly_hidden(rf.image, c, ids)
    fit_alone, ok_alone = fit_tags_photometric(rf.image, c, ids)
    assert ok_alone.sum() >= len(ids) - 2 and not alone.all()
    # c1, c2, c3 on a line (tag_homographies refuses it), and NaN corners.
    for bad in (np.array([[10.0, 40.0], [10.0, 10.0], [20.0, 10.0], [30.0, 10.0]]), np.full((4, 2), np.nan)):
        with_bad = np.concatenate([c[:2], bad[None], c[2:]])
        ids_bad = np.concatenate([ids[:2], [ids[0]], ids[2:]])
        flags = partly_hidden(rf.image, with_bad, ids_bad)
        assert flags[2] and np.array_equal(np.delete(flags, 2), alone)
        fit, ok = fit_tags_photometric(rf.image, with_bad, ids_bad)
        assert not ok[2] and np.array_equal(np.delete(ok, 2), ok_alone)
        np.testing.assert_array_equal(np.delete(fit, 2, axis=0), fit_alone)
        np.testing.assert_array_equal(fit[2], bad)
