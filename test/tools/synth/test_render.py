"""ficap_ros.tools.synth.render: rendered corners are exact (ideal and distorted cameras, against an
independent detector), motion blur's truth is the pose at mid-exposure, colour and JPEG options."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from synth_frames import IDEAL, MODEL, corner_errors, edge_crossing_px, frontal_square

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import RenderConfig, default_scene, render


def test_frontal_1080p_corners_match_truth() -> None:
    scene = default_scene("1080p")
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, IDEAL, seed=1)
    assert frame.image.shape == (1080, 1920) and frame.image.dtype == np.uint8
    errors, missing, wrong = corner_errors(frame)
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
    frame = render(MODEL, camera, T, IDEAL, seed=2)
    assert frame.image.shape == (540, 960)
    ideal = T.apply(MODEL.corners_of(11) / 1000.0)
    assert np.allclose(frame.corners_px[11], camera.project(ideal))
    # The distortion is strong enough to matter: the pinhole projection is pixels away.
    pinhole = CameraModel(base.width_px, base.height_px, base.K, [], "none")
    shift = np.abs(np.array([frame.corners_px[k] - pinhole.project(T.apply(MODEL.corners_of(k) / 1e3))
                             for k in frame.corners_px])).max()
    assert shift > 3.0
    errors, missing, wrong = corner_errors(frame)
    assert not missing and not wrong and len(errors) >= 4 * 6
    assert np.linalg.norm(errors, axis=1).mean() < 0.3
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)


def test_motion_blur_truth_is_mid_exposure() -> None:
    """A tag sliding sideways at constant speed: the frame's truth is the pose at mid-exposure, the
    pose is sampled over the whole exposure, and in linear light the smeared edge's 50 % point
    stays at the mid-exposure edge while its width grows with the travel."""
    model, T0 = frontal_square(0.2)
    camera = default_scene("540p").camera
    speed_m_s = 0.3
    exposure_ms = 8.0
    asked: list[float] = []

    def pose_at(dt_s: float) -> Transform:
        asked.append(dt_s)
        return Transform(T0.rotation, T0.translation_m + [speed_m_s * dt_s, 0.0, 0.0])

    base = RenderConfig(tone="linear", psf_sigma_px=0.5, noise=False, head=False, background=False)
    moving = render(model, camera, pose_at, replace(base, exposure_ms=exposure_ms))
    still = render(model, camera, T0, replace(base, exposure_ms=exposure_ms))
    np.testing.assert_allclose(moving.corners_px[0], camera.project(T0.apply(model.corners_mm[0] / 1000.0)))
    np.testing.assert_array_equal(moving.corners_px[0], still.corners_px[0])
    assert moving.T_cam_cap is not None and np.allclose(moving.T_cam_cap.translation_m, T0.translation_m)
    travel_px = camera.K[0, 0] * speed_m_s * exposure_ms / 1000.0 / T0.translation_m[2]
    assert travel_px > 5.0
    times = np.array(sorted(set(asked)))
    assert len(times) % 2 == 1 and len(times) >= 2 * travel_px - 1  # <= 0.5 px between sub-frames
    half = exposure_ms / 2000.0
    assert -half <= times.min() < -0.9 * half and half >= times.max() > 0.9 * half
    np.testing.assert_allclose(times + times[::-1], 0.0, atol=1e-15)  # symmetric about 0
    c = still.corners_px[0]
    x_edge = float(c[[0, 3], 0].mean())
    cell = (c[3, 1] - c[0, 1]) / 8
    rows = slice(int(c[0, 1] + 2 * cell), int(c[3, 1] - 2 * cell))
    for frame in (moving, still):
        img = frame.image.astype(np.float64)
        w8 = np.median(img[rows, int(round(x_edge - 0.55 * cell))])
        b8 = np.median(img[rows, int(round(x_edge + 0.55 * cell))])
        assert abs(edge_crossing_px(frame.image, x_edge, rows, 0.5 * (w8 + b8)) - x_edge) < 0.08
    # The smear: 10-90 % width of a box of length L convolved with the 0.5 px PSF is ~0.8 L.
    def width(frame) -> float:
        prof = frame.image[rows].astype(np.float64).mean(axis=0)
        x0 = int(x_edge) - 12
        seg = prof[x0:x0 + 25]
        lo, hi = seg.min(), seg.max()
        return float(np.sum((seg < lo + 0.9 * (hi - lo)) & (seg > lo + 0.1 * (hi - lo))))

    assert width(still) <= 2 and abs(width(moving) - 0.8 * travel_px) <= 1.5
    # The default is still frames: a Transform pose is one sub-frame, whatever the exposure.
    assert np.array_equal(still.image, render(model, camera, T0, base).image)


def test_color_blur_jpeg_options() -> None:
    scene = default_scene((480, 270))
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, RenderConfig(color=True, psf_sigma_px=0.8, jpeg_quality=80))
    assert frame.image.shape == (270, 480, 3) and frame.image.dtype == np.uint8
    with pytest.raises(ConfigError):
        RenderConfig(lighting="sunset")
