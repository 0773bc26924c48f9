"""Rotation metrics, head angles, robust averaging, and camera models."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.errors import IntrinsicsError
from ficap_ros.geometry.camera import CameraModel, load_camera_yaml
from ficap_ros.geometry.metrics import (
    angle_deg,
    phi3_deg,
    robust_mean_rotation,
    rotation_from_ypr_deg,
    summarize_errors,
    yaw_pitch_roll_deg,
)
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform


def test_phi3_is_half_the_geodesic_angle() -> None:
    rng = np.random.default_rng(0)
    a = Rotation.random(50, random_state=1)
    delta = Rotation.from_rotvec(rng.normal(size=(50, 3)) * 0.3)
    b = delta * a
    np.testing.assert_allclose(angle_deg(a, b), np.degrees(delta.magnitude()), atol=1e-9)
    np.testing.assert_allclose(phi3_deg(a, b), np.degrees(delta.magnitude()) / 2, atol=1e-6)
    # Sign of the quaternion does not matter.
    q = a.as_quat()
    assert phi3_deg(Rotation.from_quat(q[0]), Rotation.from_quat(-q[0])) == pytest.approx(0, abs=1e-6)


def test_yaw_pitch_roll_convention() -> None:
    left = rotation_from_ypr_deg(30, 0, 0)
    # Yaw +30: the nose (x) turns toward +y (left).
    assert left.apply([1, 0, 0])[1] > 0.4
    down = rotation_from_ypr_deg(0, 20, 0)
    assert down.apply([1, 0, 0])[2] < -0.3  # pitch +: nose DOWN (REP-103, right-hand about +y left)
    roll = rotation_from_ypr_deg(0, 0, 15)
    assert roll.apply([0, 1, 0])[2] > 0.2  # roll +: left ear up, toward the right shoulder
    ypr = np.array([40.0, -20.0, 5.0])
    np.testing.assert_allclose(yaw_pitch_roll_deg(rotation_from_ypr_deg(*ypr)), ypr, atol=1e-9)


def _tf2_get_rpy(q_xyzw: np.ndarray) -> tuple[float, float, float]:
    """tf2's ``Quaternion -> Matrix3x3 -> getRPY`` (LinearMath/Matrix3x3.h), written out here from
    its formulas so the test does not lean on scipy's Euler code: the matrix of ``setRotation`` and
    ``getEulerYPR``'s yaw = atan2(m10, m00), pitch = asin(-m20), roll = atan2(m21, m22) (radians)."""
    x, y, z, w = (float(v) for v in q_xyzw)
    s = 2.0 / (x * x + y * y + z * z + w * w)
    xs, ys, zs = x * s, y * s, z * s
    wx, wy, wz = w * xs, w * ys, w * zs
    xx, xy, xz = x * xs, x * ys, x * zs
    yy, yz, zz = y * ys, y * zs, z * zs
    m = [[1.0 - (yy + zz), xy - wz, xz + wy],
         [xy + wz, 1.0 - (xx + zz), yz - wx],
         [xz - wy, yz + wx, 1.0 - (xx + yy)]]
    yaw = math.atan2(m[1][0], m[0][0])
    pitch = math.asin(max(-1.0, min(1.0, -m[2][0])))
    roll = math.atan2(m[2][1], m[2][2])
    return roll, pitch, yaw


def test_head_angles_match_tf2_get_rpy() -> None:
    # A known rotation: the head turned 25 deg about +y (REP-103's left axis), i.e. nose down,
    # as the quaternion (0, sin(12.5 deg), 0, cos(12.5 deg)); then a general one.
    half = math.radians(25.0) / 2
    q_down = np.array([0.0, math.sin(half), 0.0, math.cos(half)])
    roll, pitch, yaw = _tf2_get_rpy(q_down)
    assert math.degrees(pitch) == pytest.approx(25.0, abs=1e-9)
    ypr = yaw_pitch_roll_deg(Rotation.from_quat(q_down))
    assert ypr[1] == pytest.approx(25.0, abs=1e-9)  # same sign as tf2: nose down positive
    assert Rotation.from_quat(q_down).apply([1.0, 0.0, 0.0])[2] < 0  # and it is nose down
    rng = np.random.default_rng(5)
    for q in Rotation.from_euler("ZYX", rng.uniform(-60, 60, (20, 3)), degrees=True).as_quat():
        r, p, y = _tf2_get_rpy(q)
        np.testing.assert_allclose(yaw_pitch_roll_deg(Rotation.from_quat(q)),
                                   np.degrees([y, p, r]), atol=1e-9)


def test_robust_mean_ignores_outliers() -> None:
    rng = np.random.default_rng(2)
    truth = Rotation.from_euler("xyz", [10, -5, 3], degrees=True)
    noise = Rotation.from_rotvec(np.radians(rng.normal(0, 0.5, (100, 3))))
    outliers = Rotation.from_rotvec(np.radians(rng.normal(0, 30, (15, 3))))
    rots = Rotation.concatenate([noise * truth, outliers * truth])
    mean, inliers = robust_mean_rotation(rots)
    assert angle_deg(mean, truth) < 0.3
    assert inliers[:100].mean() > 0.9 and inliers[100:].mean() < 0.3


def test_summary() -> None:
    s = summarize_errors(np.array([1.0, 2.0, np.nan, 3.0]))
    assert s["n"] == 3 and s["median"] == 2.0 and s["mean"] == 2.0


def test_transform_algebra() -> None:
    a = Transform(Rotation.from_euler("z", 30, degrees=True), [1, 2, 3])
    b = Transform(Rotation.from_euler("x", -20, degrees=True), [0.5, 0, -1])
    p = np.array([0.3, -0.2, 0.9])
    np.testing.assert_allclose((a * b).apply(p), a.apply(b.apply(p)))
    np.testing.assert_allclose((a * a.inv()).matrix, np.eye(4), atol=1e-12)
    w, x, y, z = a.q_wxyz
    np.testing.assert_allclose(a.q_xyzw, [x, y, z, w])
    # The forward body frame's x is the optical axis, its z is the camera's -y (up).
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([1, 0, 0]), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([0, 0, 1]), [0, -1, 0], atol=1e-12)


@pytest.mark.parametrize(
    "k, d, model, message",
    [
        ([np.nan, 0, 480, 0, 500, 270, 0, 0, 1], [], "none", "NaN"),
        ([0, 0, 0, 0, 0, 0, 0, 0, 0], [], "none", "focal lengths must be positive"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 1], [0.1], "kannala", "unknown distortion model"),
        ([500, 0, 2000, 0, 500, 270, 0, 0, 1], [], "none", "principal point"),
    ],
)
def test_bad_intrinsics(k, d, model, message) -> None:
    with pytest.raises(IntrinsicsError, match=message):
        CameraModel(960, 540, k, d, model)


@pytest.mark.parametrize(
    "model, d",
    [("plumb_bob", [-0.2, 0.05, 0.001, 0.002, 0.0]),
     ("rational_polynomial", [-0.2, 0.05, 0.001, 0.002, 0.0, 0.01, 0.002, 0.0]),
     ("equidistant", [0.05, -0.01, 0.002, -0.001])],
)
def test_undistort_inverts_project(model: str, d: list[float]) -> None:
    cam = CameraModel(960, 540, [700, 0, 480, 0, 700, 270, 0, 0, 1], d, model)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, 50), rng.uniform(-0.25, 0.25, 50), np.ones(50)])
    ideal = pts[:, :2] * 700 + [480, 270]
    np.testing.assert_allclose(cam.undistort_px(cam.project(pts)), ideal, atol=1e-3)


def test_rectified_camera_info_uses_p() -> None:
    p = [600, 0, 470, 0, 0, 610, 280, 0, 0, 0, 1, 0]
    cam = CameraModel.from_camera_info(960, 540, [700, 0, 480, 0, 700, 270, 0, 0, 1],
                                       [-0.3, 0.1, 0, 0, 0], "plumb_bob", p=p, rectified=True)
    assert cam.K[0, 0] == 600 and cam.distortion_model == "none"


def test_camera_yaml_round_trip(tmp_path) -> None:
    import yaml

    cam = CameraModel(960, 540, [700, 0, 480, 0, 701, 270, 0, 0, 1], [-0.2, 0.05, 0, 0, 0], "plumb_bob")
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(cam.to_camera_yaml()))
    back = load_camera_yaml(path)
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.D, cam.D)
    assert back.distortion_model == "plumb_bob"
