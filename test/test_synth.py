"""Renderer and drive generator: rendered corners are exact, lighting and motion as specified."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import nominal_model
from ficap_ros.errors import ConfigError
from ficap_ros.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.synth import (
    HEAD_CENTRE_M,
    HEAD_SEMI_AXES_M,
    NECK_CENTRE_M,
    NECK_SEMI_AXES_M,
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.transform import Transform

MODEL = nominal_model()


def _detect(image: np.ndarray) -> dict[int, np.ndarray]:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params
    )
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) for c, i in zip(corners, ids.ravel())}


def _view_angles_deg(T_cam_cap: Transform) -> dict[int, float]:
    """Angle between each tag's outward normal and the direction to the camera, deg."""
    normals = T_cam_cap.rotation.apply(MODEL.normals)
    centres = T_cam_cap.apply(MODEL.centres_mm / 1000.0)
    to_cam = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ij,ij->i", normals, to_cam), -1.0, 1.0)
    return {tag_id: float(np.degrees(np.arccos(c))) for tag_id, c in zip(MODEL.ids, cos)}


def _corner_errors(frame, max_view_deg: float = 60.0) -> tuple[np.ndarray, list[int], list[int]]:
    """Signed corner errors (n, 2) of well-seen tags, their ids, and ids wrongly detected."""
    found = _detect(frame.image)
    angles = _view_angles_deg(frame.T_cam_cap)
    wanted = [k for k, v in frame.visible_fraction.items() if v >= 0.99 and angles[k] < max_view_deg]
    wrong = [k for k in found if k not in frame.corners_px]
    missing = [k for k in wanted if k not in found]
    errors = np.concatenate([found[k] - frame.corners_px[k] for k in wanted if k in found])
    return errors, missing, wrong


def test_head_and_neck_lie_inside_every_face() -> None:
    faces = MODEL.face_corners_mm() / 1000.0
    g = np.linspace(0.0, 1.0, 9)
    pts = np.array([f[0] + a * (f[1] - f[0]) + b * (f[3] - f[0]) for f in faces for a in g for b in g])
    for centre, axes in ((HEAD_CENTRE_M, HEAD_SEMI_AXES_M), (NECK_CENTRE_M, NECK_SEMI_AXES_M)):
        r = np.sqrt((((pts - np.array(centre)) / np.array(axes)) ** 2).sum(axis=1))
        assert r.min() > 1.0  # every face point outside the ellipsoid


def test_frontal_1080p_corners_match_truth() -> None:
    scene = default_scene("1080p")
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, RenderConfig(lighting="neutral"), seed=1)
    assert frame.image.shape == (1080, 1920) and frame.image.dtype == np.uint8
    errors, missing, wrong = _corner_errors(frame)
    assert not missing and not wrong
    assert len(errors) >= 4 * 10
    dist = np.linalg.norm(errors, axis=1)
    assert dist.mean() < 0.3
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)  # no half-pixel convention slip


def test_distorted_camera_corners_match_truth() -> None:
    base = default_scene("540p").camera
    camera = CameraModel(base.width_px, base.height_px, base.K, [-0.28, 0.09, 0.001, -0.0005, 0.0],
                         "plumb_bob")
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(15.0, -5.0, 2.0))
    frame = render(MODEL, camera, T, RenderConfig(noise_sigma=1.0), seed=2)
    assert frame.image.shape == (540, 960)
    ideal = T.apply(MODEL.corners_of(11) / 1000.0)
    assert np.allclose(frame.corners_px[11], camera.project(ideal))
    # The distortion is strong enough to matter: the pinhole projection is pixels away.
    pinhole = CameraModel(base.width_px, base.height_px, base.K, [], "none")
    shift = np.abs(np.array([frame.corners_px[k] - pinhole.project(T.apply(MODEL.corners_of(k) / 1e3))
                             for k in frame.corners_px])).max()
    assert shift > 3.0
    errors, missing, wrong = _corner_errors(frame)
    assert not missing and not wrong and len(errors) >= 4 * 6
    assert np.linalg.norm(errors, axis=1).mean() < 0.3
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)


def test_back_faces_never_reported() -> None:
    scene = default_scene("540p")
    for yaw in (-80.0, 0.0, 55.0):
        T = scene.cap_pose(rotation_from_ypr_deg(yaw, -10.0, 0.0))
        frame = render(MODEL, scene.camera, T, RenderConfig(noise_sigma=0.0), seed=0)
        normals = T.rotation.apply(MODEL.normals)
        centres = T.apply(MODEL.centres_mm / 1000.0)
        facing = {t for t, n, c in zip(MODEL.ids, normals, centres) if n @ c < 0}
        assert set(frame.corners_px) == facing == set(frame.visible_fraction)
        assert len(facing) >= 5
        if abs(yaw) > 45:
            assert len(facing) < len(MODEL) - 5
        assert not set(_detect(frame.image)) - facing


def test_occluder_hides_faces_at_large_yaw() -> None:
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(80.0, 0.0, 0.0))
    plain = RenderConfig(noise_sigma=0.0, head=False)
    free = render(MODEL, scene.camera, T, plain).visible_fraction
    # The default head sits inside the cap: it never covers a front-facing face here.
    default = render(MODEL, scene.camera, T, RenderConfig(noise_sigma=0.0)).visible_fraction
    assert all(default[k] >= free[k] - 0.02 for k in free)
    # A bigger head (thick hair poking past the cap rim) hides faces through the depth test.
    big = RenderConfig(noise_sigma=0.0, head_centre_m=(0.0, 0.0, -0.03),
                       head_semi_axes_m=(0.12, 0.1, 0.13))
    frame = render(MODEL, scene.camera, T, big)
    hidden = [k for k in free if free[k] > 0.5 and frame.visible_fraction[k] < 0.2]
    assert hidden
    assert not set(hidden) & set(_detect(frame.image))


def test_lighting_modes_differ_as_specified() -> None:
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(10.0, 0.0, 0.0))
    images = {m: render(MODEL, scene.camera, T, RenderConfig(lighting=m), seed=4).image
              for m in ("neutral", "high", "low")}
    masks = {}
    for tag_id, c in render(MODEL, scene.camera, T, RenderConfig(noise_sigma=0.0)).corners_px.items():
        mask = np.zeros((540, 960), np.uint8)
        cv2.fillConvexPoly(mask, np.round(c).astype(np.int32), 1)
        masks[tag_id] = mask
    cap = np.any(np.stack(list(masks.values())), axis=0)
    sat = {m: float(np.mean(im[cap] >= 254)) for m, im in images.items()}
    assert sat["high"] > 0.05 and sat["neutral"] < 0.001
    assert images["low"][cap].mean() < 0.5 * images["neutral"][cap].mean()
    # Neutral: white ~200-225 and black ~25-40 on the cap.
    assert 195 <= np.percentile(images["neutral"][cap], 95) <= 232
    assert 18 <= np.percentile(images["neutral"][cap], 5) <= 45
    assert np.percentile(images["low"][cap], 99) <= 110
    # Same seed, same image; other seed, other noise.
    again = render(MODEL, scene.camera, T, RenderConfig(lighting="high"), seed=4).image
    assert np.array_equal(again, images["high"])


def test_color_blur_jpeg_options() -> None:
    scene = default_scene((480, 270))
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, RenderConfig(color=True, blur_sigma_px=0.8, jpeg_quality=80))
    assert frame.image.shape == (270, 480, 3) and frame.image.dtype == np.uint8
    with pytest.raises(ConfigError):
        RenderConfig(lighting="sunset")


def test_drive_motion_is_naturalistic_and_consistent() -> None:
    scene = default_scene("540p")
    fps = 30.0
    drive = naturalistic_drive(int(60 * fps), fps=fps, seed=3, scene=scene, frontal_s=3.0)
    ypr = np.array([f.ypr_deg for f in drive])
    assert np.all(np.abs(ypr[:, 0]) <= 62.0)
    assert ypr[:, 0].max() > 40.0 and ypr[:, 0].min() < -40.0
    assert np.any(ypr[:, 1] < -15.0)  # instrument cluster
    start = [f for f in drive if f.frontal]
    assert len(start) == int(3.0 * fps)
    assert max(angle_deg(Rotation.identity(), f.R_frontal_head) for f in start) < 1.0
    assert [f.index for f in drive] == list(range(len(drive)))
    assert drive[31].stamp_ns == round(31 * 1e9 / fps)
    # Smooth: no frame-to-frame jump above what 400 deg/s allows.
    steps = [angle_deg(a.R_frontal_head, b.R_frontal_head) for a, b in zip(drive, drive[1:])]
    assert max(steps) < 400.0 / fps
    for f in drive[::97]:
        expected = scene.R_cam_frontal * f.R_frontal_head * scene.R_cap_head.inv()
        assert angle_deg(expected, f.T_cam_cap.rotation) < 1e-9
        back = scene.R_cam_frontal.inv() * f.T_cam_cap.rotation * scene.R_cap_head
        assert angle_deg(back, f.R_frontal_head) < 1e-9
        assert np.allclose(rotation_from_ypr_deg(*f.ypr_deg).as_matrix(), f.R_frontal_head.as_matrix())
        # The head turns about the neck pivot (plus a lean of at most a few cm).
        pivot_to_cap = f.T_cam_cap.translation_m - scene.p_cam_neck_m
        turned = scene.R_cam_frontal.apply(f.R_frontal_head.apply(np.array(scene.neck_to_cap_m)))
        assert np.linalg.norm(pivot_to_cap - turned) < 0.03
    again = naturalistic_drive(100, fps=fps, seed=3, scene=scene)
    assert all(np.array_equal(a.ypr_deg, b.ypr_deg) for a, b in zip(again, drive))


def test_default_scene_tag_size() -> None:
    scene = default_scene("540p")
    frame = render(MODEL, scene.camera, scene.cap_pose(Rotation.identity()), RenderConfig())
    c = frame.corners_px[11]
    side = np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1))
    assert 55.0 <= side <= 65.0
