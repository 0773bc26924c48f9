"""Square-consistent corners: a square's exact image is left as it is, noisy corners go to the
least-squares image of a square (scipy's solver on the same 6-DOF pose agrees), the part removed
is orthogonal to every pose change (first-order optimality), the result is idempotent, and a
quadrilateral no square's image is near keeps its corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ficap_ros.vision.square_kernels import square_tag_corners

SQUARE = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])


def _camera(rng: np.random.Generator) -> np.ndarray:
    return np.array([[rng.uniform(500, 2000), rng.normal(0.0, 1.0), rng.uniform(300, 1000)],
                     [0.0, rng.uniform(500, 2000), rng.uniform(200, 600)], [0.0, 0.0, 1.0]])


def _project(K: np.ndarray, rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    p = (SQUARE @ Rotation.from_rotvec(rotvec).as_matrix().T + t) @ K.T
    return p[:, :2] / p[:, 2:3]


def _tag(rng: np.random.Generator, max_view_deg: float = 78.0) -> tuple[np.ndarray, np.ndarray]:
    """A tag's rotation vector (tilted up to ``max_view_deg`` from facing the camera, turned
    freely in its plane) and its translation (half-side 1: 16 mm at 0.3-1.2 m)."""
    axis = rng.normal(size=2)
    tilt = Rotation.from_rotvec(np.r_[axis / np.linalg.norm(axis), 0.0] * np.radians(rng.uniform(0, max_view_deg)))
    turn = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    t = np.array([rng.uniform(-8, 8), rng.uniform(-5, 5), rng.uniform(20, 75)])
    return (tilt * turn).as_rotvec(), t


def _cases(seed: int, n: int, noise_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    K = _camera(rng)
    true = np.array([_project(K, *_tag(rng)) for _ in range(n)])
    return K, true, true + rng.normal(scale=noise_px, size=true.shape)


def _scipy_reference(K: np.ndarray, corners: np.ndarray, start: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The square's least-squares image by scipy's solver (6-DOF pose, px residuals)."""
    fit = least_squares(lambda x: (_project(K, x[:3], x[3:]) - corners).ravel(), np.r_[start[0], start[1]],
                        xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return _project(K, fit.x[:3], fit.x[3:])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31))
def test_a_square_image_is_left_as_it_is(seed: int) -> None:
    K, true, _ = _cases(seed, 8, 0.0)
    out, squared = square_tag_corners(true, K, 6, 1.0)
    assert squared.all()
    np.testing.assert_allclose(out, true, atol=1e-6)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31))
def test_noisy_corners_go_to_the_least_squares_square_image(seed: int) -> None:
    """The kernel's corners fit at least as well as scipy's optimum from the true pose (near a
    head-on view the tilt's sign leaves two minima; the kernel refines both and keeps the lower),
    and equal it where they are the same minimum."""
    rng = np.random.default_rng(seed)
    K = _camera(rng)
    for _ in range(4):
        pose = _tag(rng)
        noisy = _project(K, *pose) + rng.normal(scale=0.3, size=(4, 2))
        out, squared = square_tag_corners(noisy[None], K, 6, 2.0)
        assert squared[0]
        ref = _scipy_reference(K, noisy, pose)
        cost, ref_cost = np.sum((out[0] - noisy) ** 2), np.sum((ref - noisy) ** 2)
        assert cost <= ref_cost + 1e-6
        if cost > ref_cost - 1e-6:
            np.testing.assert_allclose(out[0], ref, atol=2e-3)


def test_the_removed_part_is_orthogonal_to_every_pose_change() -> None:
    K, _, noisy = _cases(3, 40, 0.25)
    out, squared = square_tag_corners(noisy, K, 6, 2.0)
    assert squared.all()
    for c_out, c_in in zip(out, noisy):
        normalised = (np.c_[c_out, np.ones(4)] @ np.linalg.inv(K).T)[:, :2]  # OpenCV's K has no skew
        ok, rvec, tvec = cv2.solvePnP(SQUARE, np.ascontiguousarray(normalised).reshape(4, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
        assert ok
        x = np.r_[rvec.ravel(), tvec.ravel()]
        np.testing.assert_allclose(_project(K, x[:3], x[3:]), c_out, atol=1e-6)
        jac = np.empty((8, 6))
        for i in range(6):
            d = np.zeros(6)
            d[i] = 1e-6 * max(abs(x[i]), 1.0)
            y = x + d
            jac[:, i] = (_project(K, y[:3], y[3:]) - c_out).ravel() / d[i]
        removed = (c_in - c_out).ravel()
        # J^T r = 0 at the optimum: the removed part has no component along any pose change.
        cosines = (jac.T @ removed) / (np.linalg.norm(jac, axis=0) * np.linalg.norm(removed))
        assert np.abs(cosines).max() < 1e-4


def test_squaring_is_idempotent_and_removes_two_of_eight_noise_dof() -> None:
    K, true, noisy = _cases(7, 600, 0.2)
    out, squared = square_tag_corners(noisy, K, 6, 2.0)
    again, _ = square_tag_corners(out, K, 6, 2.0)
    assert squared.all()
    np.testing.assert_allclose(again, out, atol=1e-6)
    # Isotropic noise keeps 6 of its 8 degrees of freedom: rms ratio sqrt(6 / 8).
    ratio = np.sqrt(np.mean((out - true) ** 2) / np.mean((noisy - true) ** 2))
    assert ratio == pytest.approx(np.sqrt(6 / 8), abs=0.04)


def test_a_quadrilateral_far_from_any_square_image_keeps_its_corners() -> None:
    K, true, _ = _cases(11, 3, 0.0)
    bad = true.copy()
    bad[0, 2] += [6.0, -4.0]  # one corner far off
    bad[1, 1] = bad[1, 0]  # degenerate: two corners on one another
    out, squared = square_tag_corners(bad, K, 6, 1.0)
    assert list(squared) == [False, False, True]
    np.testing.assert_array_equal(out[:2], bad[:2])
    np.testing.assert_allclose(out[2], true[2], atol=1e-6)
