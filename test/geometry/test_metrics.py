"""ficap_ros.geometry.metrics: rotation metrics, head angles, robust averaging, error summaries and
corner errors (seeded cases and hypothesis properties)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.metrics import (
    angle_deg,
    corner_errors_px,
    phi3_deg,
    robust_mean_rotation,
    rotation_from_ypr_deg,
    summarize_errors,
    yaw_pitch_roll_deg,
)


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


# -- properties (hypothesis) ---------------------------------------------------------------------------

quaternions = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 1e-2)
rotations = quaternions.map(lambda q: Rotation.from_quat(np.asarray(q)))


@given(rotations, rotations, rotations)
def test_angles_are_a_metric_of_orientations(a: Rotation, b: Rotation, c: Rotation) -> None:
    """Symmetric, zero on itself, unchanged by a common rotation of both frames (applied on the
    left or the right), twice Phi3 (to arccos's resolution near 0: about 1e-6 deg), and within a
    half turn."""
    ab = angle_deg(a, b)
    assert ab == pytest.approx(angle_deg(b, a), abs=1e-6)
    assert angle_deg(a, a) == pytest.approx(0.0, abs=1e-6)
    assert angle_deg(c * a, c * b) == pytest.approx(ab, abs=1e-6)
    assert angle_deg(a * c, b * c) == pytest.approx(ab, abs=1e-6)
    assert ab == pytest.approx(2.0 * phi3_deg(a, b), abs=1e-5)
    assert 0.0 <= ab <= 180.0 + 1e-9
    assert angle_deg(a, c) <= angle_deg(a, b) + angle_deg(b, c) + 1e-6  # the triangle inequality


@given(st.floats(-179.0, 179.0), st.floats(-89.0, 89.0), st.floats(-179.0, 179.0))
def test_head_angles_round_trip(yaw: float, pitch: float, roll: float) -> None:
    ypr = yaw_pitch_roll_deg(rotation_from_ypr_deg(yaw, pitch, roll))
    np.testing.assert_allclose(ypr, [yaw, pitch, roll], atol=1e-7)


@given(st.lists(st.one_of(st.floats(-1e6, 1e6), st.just(float("nan"))), min_size=1, max_size=40))
def test_summary_ignores_nans(values: list[float]) -> None:
    e = np.array(values)
    finite = e[np.isfinite(e)]
    s = summarize_errors(e)
    assert s["n"] == finite.size
    if finite.size:
        assert s["median"] == float(np.median(finite)) and s["max"] == float(finite.max())
        assert s["mean"] == pytest.approx(float(np.mean(finite)))
    else:
        assert np.isnan(s["median"]) and np.isnan(s["mean"])


@given(st.floats(-2.0, 2.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0))
def test_corner_errors_split_radial_and_distance(radial_px: float, dx: float, dy: float) -> None:
    """Corners moved radially by r have radial error r and distance |r|; a common shift adds its
    length to every distance's bound and nothing to the mean radial error of a square."""
    true = np.array([[[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]]) + 100.0
    out = (true - true.mean(axis=1, keepdims=True)) / (10.0 * np.sqrt(2.0))
    dist, radial = corner_errors_px(true + radial_px * out, true)
    np.testing.assert_allclose(radial, radial_px, atol=1e-12)
    np.testing.assert_allclose(dist, abs(radial_px), atol=1e-12)
    dist, radial = corner_errors_px(true + [dx, dy], true)
    np.testing.assert_allclose(dist, np.hypot(dx, dy), atol=1e-12)
    assert float(radial.mean()) == pytest.approx(0.0, abs=1e-12)


@given(st.floats(-179.0, 179.0), st.floats(-89.0, 89.0), st.floats(-179.0, 179.0))
def test_head_angles_in_radians_are_the_degrees_converted(yaw: float, pitch: float, roll: float) -> None:
    from ficap_ros.geometry.metrics import yaw_pitch_roll_rad

    R = rotation_from_ypr_deg(yaw, pitch, roll)
    np.testing.assert_allclose(yaw_pitch_roll_rad(R), np.radians(yaw_pitch_roll_deg(R)),
                               rtol=1e-12, atol=1e-15)
