"""The pose solvers' compiled reprojection against the vectorised numpy formulas it replaces:
residuals and Jacobian, the tags' RMS errors and the moving corners' image velocity, equal to the bit for random poses, cameras with
skew and tag counts, and the Jacobian is the residuals' derivative under a left perturbation."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.pose_kernels import reprojection_rt
from ficap_ros.vision.reprojection import (
    TagObservations,
    moving_points_m,
    project_px,
    reprojection_errors_px,
    residuals_and_jacobian_rt,
)
from ficap_ros.vision.shutter import _corner_velocity_px_s


def _numpy_reference(R: np.ndarray, t: np.ndarray, K: np.ndarray, model_m: np.ndarray,
                     image_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The residuals and Jacobian vectorised over the corners (the kernel's reference)."""
    X = model_m.reshape(-1, 3) @ R.T
    p = X + t
    fx, fy, s, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    iz = 1.0 / p[:, 2]
    xn, yn = p[:, 0] * iz, p[:, 1] * iz
    u = fx * xn + s * yn + cx
    v = fy * yn + cy
    obs = image_px.reshape(-1, 2)
    n = len(p)
    res = np.empty(2 * n)
    res[0::2] = u - obs[:, 0]
    res[1::2] = v - obs[:, 1]
    du_dp = np.empty((n, 3))
    du_dp[:, 0] = fx * iz
    du_dp[:, 1] = s * iz
    du_dp[:, 2] = -(u - cx) * iz
    dv_dp = np.zeros((n, 3))
    dv_dp[:, 1] = fy * iz
    dv_dp[:, 2] = -(v - cy) * iz
    jac = np.empty((2 * n, 6))
    x0, x1, x2 = X[:, 0], X[:, 1], X[:, 2]
    for rows, g in ((jac[0::2], du_dp), (jac[1::2], dv_dp)):
        rows[:, 0] = x1 * g[:, 2] - x2 * g[:, 1]
        rows[:, 1] = x2 * g[:, 0] - x0 * g[:, 2]
        rows[:, 2] = x0 * g[:, 1] - x1 * g[:, 0]
        rows[:, 3:] = g
    return res, jac


def _case(seed: int, tags: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    t = np.array([rng.normal(0.0, 0.05), rng.normal(0.0, 0.05), rng.uniform(0.4, 1.2)])
    K = np.array([[rng.uniform(500, 2000), rng.normal(0.0, 2.0), rng.uniform(300, 1000)],
                  [0.0, rng.uniform(500, 2000), rng.uniform(200, 600)], [0.0, 0.0, 1.0]])
    model = rng.normal(0.0, 0.06, size=(tags, 4, 3))
    image = rng.normal(500.0, 200.0, size=(tags, 4, 2))
    return R, t, K, model, image


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 23))
def test_the_kernel_equals_numpy_to_the_bit(seed: int, tags: int) -> None:
    R, t, K, model, image = _case(seed, tags)
    res, jac = residuals_and_jacobian_rt(R, t, K, model, image)
    ref_res, ref_jac = _numpy_reference(R, t, K, model, image)
    assert res.shape == (8 * tags,) and jac.shape == (8 * tags, 6)
    assert np.array_equal(res, ref_res) and np.array_equal(jac, ref_jac)


def test_the_jacobian_is_the_derivative_of_a_left_perturbation() -> None:
    R, t, K, model, image = _case(7, 5)
    res, jac = residuals_and_jacobian_rt(R, t, K, model, image)
    eps = 1e-6
    for k in range(6):
        ends = []
        for sign in (1.0, -1.0):
            d = np.zeros(6)
            d[k] = sign * eps
            R_k = Rotation.from_rotvec(d[:3]).as_matrix() @ R
            ends.append(residuals_and_jacobian_rt(R_k, t + d[3:], K, model, image)[0])
        numeric = (ends[0] - ends[1]) / (2 * eps)
        np.testing.assert_allclose(jac[:, k], numeric, rtol=1e-5, atol=1e-3 * np.abs(numeric).max())


def test_a_point_on_the_camera_plane_gives_inf_not_an_exception() -> None:
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    res, jac = reprojection_rt(np.array([[0.1, 0.0, 0.0]]), np.zeros(3), K, np.zeros((1, 2)))
    assert not np.all(np.isfinite(res)) and not np.all(np.isfinite(jac))


def test_the_wrapper_takes_any_layout() -> None:
    """Non-contiguous inputs and a list give what their contiguous float copies give."""
    R, t, K, model, image = _case(3, 4)
    expect = residuals_and_jacobian_rt(R, t, K, model, image)
    got = residuals_and_jacobian_rt(np.asfortranarray(R), t.tolist(), np.asfortranarray(K),
                                    model[:, ::-1][:, ::-1], np.asfortranarray(image.reshape(-1, 2)))
    assert np.array_equal(expect[0], got[0]) and np.array_equal(expect[1], got[1])


def _errors_reference(obs_px: np.ndarray, K: np.ndarray, T: Transform, model_m: np.ndarray) -> np.ndarray:
    """The per-tag RMS reprojection errors vectorised over the tags (the kernel's reference)."""
    p = T.apply(model_m.reshape(-1, 3))
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 1] * p[:, 1] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    proj = np.stack([u, v], axis=-1).reshape(model_m.shape[:-1] + (2,))
    return np.sqrt(np.mean(np.sum((proj - obs_px) ** 2, axis=-1), axis=-1))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 23))
def test_tag_errors_equal_the_numpy_formulas_to_the_bit(seed: int, tags: int) -> None:
    """``reprojection_errors_px`` (the compiled ``tag_errors_px``) equals the vectorised formulas
    bit for bit: the solvers' inlier and outlier decisions compare these values."""
    R, t, K, model, image = _case(seed, tags)
    T = Transform(Rotation.from_matrix(R), t)
    ours = reprojection_errors_px(image, K, T, model)
    assert np.array_equal(ours, _errors_reference(image, K, T, model), equal_nan=True)


def _corner_rate_reference(K: np.ndarray, T: Transform, velocity: np.ndarray,
                           model_m: np.ndarray) -> np.ndarray:
    """The corners' central-difference image velocity vectorised (``moving_points_m`` at a time
    per corner, ``project_px`` through the identity pose): the kernel's reference."""
    eps = 1e-3
    ends = [project_px(K, Transform.identity(),
                       moving_points_m(T.rotation_matrix, T.translation_m, velocity, model_m,
                                       np.full(model_m.shape[:2], s))).reshape(-1, 2)
            for s in (-eps, eps)]
    return (ends[1] - ends[0]) / (2 * eps)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 23), st.floats(0.0, 10.0))
def test_the_corner_rate_equals_the_numpy_formulas_to_the_bit(seed: int, tags: int,
                                                             speed: float) -> None:
    """``shutter``'s corner velocity (the compiled ``corner_rate_px_s``) equals the vectorised
    moving projection bit for bit, for random poses, skewed cameras and velocities from still to
    fast: the readout evidence's speed test compares these values."""
    R, t, K, model, _ = _case(seed, tags)
    T = Transform(Rotation.from_matrix(R), t)
    velocity = np.random.default_rng(seed).normal(size=6) * speed
    obs = TagObservations(tuple(range(tags)), np.zeros((tags, 4, 2)), model, K)
    ours = _corner_velocity_px_s(obs, T, velocity)
    assert np.array_equal(ours, _corner_rate_reference(K, T, velocity, model), equal_nan=True)
