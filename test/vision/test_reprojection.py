"""ficap_ros.vision.reprojection: the observation record, projection, residuals and their Jacobian
(against finite differences of a left perturbation), and the median helper (against np.median)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.reprojection import (
    TagObservations,
    median,
    project_px,
    reprojection_errors_px,
    residuals_and_jacobian,
)

MODEL = nominal_model()
CAMERA = CameraModel.pinhole(1920, 1080, hfov_deg=60.0)
T_TRUE = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", [20.0, 5.0, 2.0], degrees=True),
                   [0.01, -0.02, 0.5])


def _observations(noise_px: float = 0.0, seed: int = 0) -> TagObservations:
    rng = np.random.default_rng(seed)
    ids = [int(i) for i in MODEL.ids[:8]]
    corners = {i: CAMERA.project(T_TRUE.apply(MODEL.corners_of(i) / 1000.0)) + rng.normal(0.0, noise_px, (4, 2))
               for i in ids}
    return TagObservations.of(corners, MODEL, CAMERA.K)


@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=1, max_size=60))
def test_median_equals_numpys(values: list[float]) -> None:
    assert median(np.array(values)) == float(np.median(np.array(values)))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's median of nothing
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=9))
def test_median_of_non_finite_values_is_numpys(values: list[float]) -> None:
    with np.errstate(all="ignore"):
        ours, ref = median(np.array(values, dtype=float)), float(np.median(np.array(values, dtype=float)))
    assert ours == ref or (np.isnan(ours) and np.isnan(ref))


def test_observations_record() -> None:
    obs = _observations()
    assert obs.ids == tuple(sorted(obs.ids)) and len(obs) == 8
    assert obs.image_px.shape == (8, 4, 2) and obs.model_m.shape == (8, 4, 3)
    np.testing.assert_array_equal(obs.model_m[0], MODEL.corners_of(obs.ids[0]) / 1000.0)
    keep = np.arange(8) % 3 == 0
    sub = obs.subset(keep)
    assert sub.ids == tuple(np.array(obs.ids)[keep]) and sub.K is obs.K
    np.testing.assert_array_equal(sub.image_px, obs.image_px[keep])


def test_exact_corners_reproject_exactly() -> None:
    obs = _observations()
    np.testing.assert_allclose(project_px(obs.K, T_TRUE, obs.model_m), obs.image_px, atol=1e-9)
    assert reprojection_errors_px(obs.image_px, obs.K, T_TRUE, obs.model_m).max() < 1e-9
    res, J = residuals_and_jacobian(T_TRUE, obs)
    assert res.shape == (64,) and J.shape == (64, 6) and np.abs(res).max() < 1e-9


def test_squared_observations_keep_the_measured_corners() -> None:
    """``TagObservations.of(..., square=True)``: each tag fitted to its corners' square's image
    (exact square images stay; noisy corners come nearer the truth: isotropic noise keeps 6 of a
    tag's 8 degrees of freedom), the measured corners kept beside them through ``subset``, and
    ``measured_residuals`` the residuals against those."""
    rng = np.random.default_rng(4)
    exact = _observations()
    squared_exact = TagObservations.of(dict(zip(exact.ids, exact.image_px)), MODEL, CAMERA.K, square=True)
    np.testing.assert_allclose(squared_exact.image_px, exact.image_px, atol=1e-6)
    noisy = {i: c + rng.normal(0.0, 0.2, (4, 2)) for i, c in zip(exact.ids, exact.image_px)}
    obs = TagObservations.of(noisy, MODEL, CAMERA.K, square=True)
    np.testing.assert_array_equal(obs.measured_px, np.stack([noisy[i] for i in obs.ids]))
    assert np.sqrt(np.mean((obs.image_px - exact.image_px) ** 2)) < 0.95 * np.sqrt(
        np.mean((obs.measured_px - exact.image_px) ** 2))
    res, _ = residuals_and_jacobian(T_TRUE, obs)
    measured = obs.measured_residuals(res)
    np.testing.assert_allclose(measured, (exact.image_px - obs.measured_px).reshape(-1), atol=1e-9)
    keep = np.arange(8) % 2 == 0
    np.testing.assert_array_equal(obs.subset(keep).measured_px, obs.measured_px[keep])
    plain = TagObservations.of(noisy, MODEL, CAMERA.K)
    assert plain.measured_px is None and plain.measured_residuals(res) is res


def test_rms_errors_are_per_tag() -> None:
    obs = _observations(0.3, seed=2)
    err = reprojection_errors_px(obs.image_px, obs.K, T_TRUE, obs.model_m)
    res, _ = residuals_and_jacobian(T_TRUE, obs)
    np.testing.assert_allclose(err, np.sqrt(np.mean(res.reshape(8, 8) ** 2, axis=1) * 2.0), rtol=1e-12)


@pytest.mark.parametrize("column", range(6))
def test_jacobian_is_the_left_perturbation_derivative(column: int) -> None:
    """Columns d_theta (rad, camera axes) then d_t (m): central differences of
    ``(exp(d_theta) R, t + d_t)`` agree to the difference's own truncation error."""
    obs = _observations(0.2, seed=3)
    _, J = residuals_and_jacobian(T_TRUE, obs)
    h = 1e-6
    step = np.zeros(6)
    step[column] = h

    def at(x: np.ndarray) -> np.ndarray:
        return residuals_and_jacobian(T_TRUE.turned(x[:3], T_TRUE.translation_m + x[3:]), obs)[0]

    numeric = (at(step) - at(-step)) / (2 * h)
    scale = np.abs(J[:, column]).max()
    np.testing.assert_allclose(J[:, column], numeric, atol=1e-6 * scale)


def _timed(obs: TagObservations, seed: int = 1) -> TagObservations:
    times = np.random.default_rng(seed).uniform(-0.011, 0.011, (len(obs), 4))
    return TagObservations(obs.ids, obs.image_px, obs.model_m, obs.K, times)


VELOCITY = np.array([0.05, -0.02, 0.1, 0.5, 4.0, -0.3])
ACCEL = np.array([1.0, 0.5, -2.0, 5.0, 60.0, -3.0])


@pytest.mark.parametrize("accel", [None, ACCEL])
@pytest.mark.parametrize("column", range(12))
def test_moving_jacobian_is_the_derivative_of_pose_and_velocity(column: int,
                                                                accel: np.ndarray | None) -> None:
    """Columns 0-5: a left perturbation of the pose at the stamp; 6-11: the velocity (twist
    order), with or without an acceleration. Central differences; the angular columns to the
    first-order J_l they use (the rotation over a corner's time is a few degrees at most)."""
    from ficap_ros.vision.reprojection import residuals_and_jacobian_moving

    obs = _timed(_observations(0.2))
    _, J = residuals_and_jacobian_moving(T_TRUE.rotation_matrix, T_TRUE.translation_m, VELOCITY, obs,
                                         accel)
    eps = 1e-7

    def res(sign: float) -> np.ndarray:
        dx = np.zeros(12)
        dx[column] = sign * eps
        T = T_TRUE.turned(dx[:3], T_TRUE.translation_m + dx[3:6])
        return residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m, VELOCITY + dx[6:], obs,
                                             accel)[0]

    numeric = (res(1.0) - res(-1.0)) / (2 * eps)
    scale = np.abs(numeric).max()
    np.testing.assert_allclose(J[:, column], numeric, atol=(1e-3 if column >= 9 else 1e-6) * scale)


def test_moving_points_add_half_the_acceleration_times_time_squared() -> None:
    """A cap speeding up along a line and about a fixed axis: the points at ``tau`` are the pose
    turned by ``w tau + alpha tau^2 / 2`` and shifted by ``v tau + a tau^2 / 2``; no acceleration
    is constant velocity."""
    from ficap_ros.vision.reprojection import moving_points_m

    model = np.array([[0.01, 0.02, 0.0], [-0.03, 0.0, 0.01]])
    tau = np.array([0.011, -0.007])
    got = moving_points_m(T_TRUE.rotation_matrix, T_TRUE.translation_m, VELOCITY, model, tau, ACCEL)
    for k in range(2):
        turn = Rotation.from_rotvec(VELOCITY[3:] * tau[k] + 0.5 * ACCEL[3:] * tau[k] ** 2)
        want = (turn * T_TRUE.rotation).apply(model[k]) + T_TRUE.translation_m \
            + VELOCITY[:3] * tau[k] + 0.5 * ACCEL[:3] * tau[k] ** 2
        np.testing.assert_allclose(got[k], want, atol=1e-12)
    np.testing.assert_array_equal(
        moving_points_m(T_TRUE.rotation_matrix, T_TRUE.translation_m, VELOCITY, model, tau, None),
        moving_points_m(T_TRUE.rotation_matrix, T_TRUE.translation_m, VELOCITY, model, tau))


def test_corners_at_the_stamp_are_the_static_fit() -> None:
    """Corners timed at the stamp (0) give the static residuals and Jacobian, and no velocity
    columns; ``subset`` keeps the times with their tags."""
    from ficap_ros.vision.reprojection import residuals_and_jacobian_moving

    obs = _observations(0.3)
    zero = TagObservations(obs.ids, obs.image_px, obs.model_m, obs.K, np.zeros((len(obs), 4)))
    res, J = residuals_and_jacobian_moving(T_TRUE.rotation_matrix, T_TRUE.translation_m, VELOCITY, zero)
    res0, J0 = residuals_and_jacobian(T_TRUE, obs)
    np.testing.assert_allclose(res, res0, atol=1e-12)
    np.testing.assert_allclose(J[:, :6], J0, rtol=1e-12, atol=1e-9)
    assert not J[:, 6:].any()
    timed = _timed(obs)
    keep = np.arange(len(obs)) % 2 == 0
    np.testing.assert_array_equal(timed.subset(keep).time_s, timed.time_s[keep])
    assert obs.subset(keep).time_s is None
