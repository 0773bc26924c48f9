"""The pose solvers' compiled kernels: the reprojection residuals of a pose and their Jacobian,
the tags' RMS reprojection errors, and the corners' image velocity of a moving cap.

``reprojection_rt`` is ``reprojection.residuals_and_jacobian_rt``'s work after the rotation, in
one pass over the corners: each rotated model point shifted into the camera frame, projected
through K (no distortion: the observations are undistorted pixels), its residual ``projection -
observation`` and the two Jacobian rows of a left perturbation ``(exp(d_theta) R, t + d_t)``. The
joint solve asks for it at every Gauss-Newton step, the uncertainty and the readout evidence once
more per frame, each time for a few dozen tags: on such small arrays numpy's per-call set-up
costs more than the arithmetic. The rotation stays numpy's matrix product (the caller's), and the
rest is the vectorised formulas' own operations in their order, element by element (no fused
multiply-add): the values equal numpy's to the bit. It divides as numpy does
(``error_model="numpy"``): a point on the camera's plane gives inf or NaN, never an exception.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.kernels import frozen

__all__ = ["reprojection_rt", "tag_errors_px", "corner_rate_px_s"]


@njit(error_model="numpy")
def reprojection_rt(X: np.ndarray, t: np.ndarray, K: np.ndarray,
                    image_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) px and Jacobian (2N, 6) of the pose (R, t (3,) m) against the corners
    ``image_px`` (N, 2), undistorted px, of model points whose rotated positions ``X`` = R m
    (N, 3), m, in the camera's axes, the caller computes (numpy's matrix product: the same
    rounding as every other use of the pose); K (3, 3) with its skew. Rows alternate u and v of
    each corner; columns d_theta (rad, camera axes), then d_t (m). All float64, C-contiguous."""
    n = X.shape[0]
    res = np.empty(2 * n)
    jac = np.empty((2 * n, 6))
    for i in range(n):
        corner_rows(X[i, 0], X[i, 1], X[i, 2], t, K, image_px[i, 0], image_px[i, 1], res, jac, i)
    return res, jac


@njit(inline="always", error_model="numpy")
def corner_rows(x0: float, x1: float, x2: float, t: np.ndarray, K: np.ndarray, u_px: float, v_px: float,
                res: np.ndarray, jac: np.ndarray, i: int) -> None:
    """Corner ``i``'s two rows of ``reprojection_rt``: the rotated model point (x0, x1, x2), m,
    shifted by ``t`` and projected through ``K``; ``res[2i], res[2i + 1]`` its residual against
    the observed (u_px, v_px) and ``jac[2i], jac[2i + 1]`` its Jacobian (d_theta, then d_t)."""
    fx, fy, skew, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    iz = 1.0 / (x2 + t[2])
    xn, yn = (x0 + t[0]) * iz, (x1 + t[1]) * iz
    u = fx * xn + skew * yn + cx
    v = fy * yn + cy
    ru, rv = 2 * i, 2 * i + 1
    res[ru] = u - u_px
    res[rv] = v - v_px
    # d(u, v)/dp; a left rotation moves the point by d_theta x X: d/d_theta = X x d/dp.
    g0, g1, g2 = fx * iz, skew * iz, -(u - cx) * iz
    jac[ru, 0] = x1 * g2 - x2 * g1
    jac[ru, 1] = x2 * g0 - x0 * g2
    jac[ru, 2] = x0 * g1 - x1 * g0
    jac[ru, 3], jac[ru, 4], jac[ru, 5] = g0, g1, g2
    h0, h1, h2 = 0.0, fy * iz, -(v - cy) * iz
    jac[rv, 0] = x1 * h2 - x2 * h1
    jac[rv, 1] = x2 * h0 - x0 * h2
    jac[rv, 2] = x0 * h1 - x1 * h0
    jac[rv, 3], jac[rv, 4], jac[rv, 5] = h0, h1, h2


@njit(error_model="numpy")
def tag_errors_px(X: np.ndarray, t: np.ndarray, K: np.ndarray, image_px: np.ndarray) -> np.ndarray:
    """Per-tag RMS reprojection error (T,), px, of the corners ``image_px`` (4T, 2), undistorted
    px, under the pose whose rotated model points ``X`` = R m (4T, 3) the caller computes (numpy's
    matrix product) and translation t (3,), m: ``reprojection.reprojection_errors_px``'s
    operations in their order (the projection ``K00 x / z + K01 y / z + K02``, each corner's
    squared distance, the mean of a tag's four), the same values to the bit."""
    n = X.shape[0] // 4
    out = np.empty(n)
    for k in range(n):
        total = 0.0
        for c in range(4 * k, 4 * k + 4):
            p0, p1, z = X[c, 0] + t[0], X[c, 1] + t[1], X[c, 2] + t[2]
            u = K[0, 0] * p0 / z + K[0, 1] * p1 / z + K[0, 2]
            v = K[1, 1] * p1 / z + K[1, 2]
            du, dv = u - image_px[c, 0], v - image_px[c, 1]
            total += du * du + dv * dv
        out[k] = np.sqrt(total / 4.0)
    return out


@njit(error_model="numpy")
def corner_rate_px_s(Y: np.ndarray, turns: np.ndarray, shifts_m: np.ndarray, t: np.ndarray,
                     K: np.ndarray, span_s: float) -> np.ndarray:
    """(N, 2) px/s: the difference of each point's pinhole projection between two moments over
    ``span_s``, s (``shutter``'s central difference of a moving cap's corners): the rotated model
    points ``Y`` = R m (N, 3), m, the caller computes (numpy's matrix product), turned by each
    moment's rotation ``turns`` (2, 3, 3) and moved by ``t`` (3,) plus its shift ``shifts_m``
    (2, 3), m. ``reprojection.moving_points_m`` and ``project_px``'s operations in their order:
    the turn's row products summed as numpy's ``einsum`` sums three (first and third, then the
    second), then ``+ t + shift``, then ``K00 x / z + K01 y / z + K02``; the same values to the
    bit as numpy's where neither fuses a multiply and an add (test_pose_kernels checks it)."""
    n = Y.shape[0]
    out = np.empty((n, 2))
    uv = np.empty((2, 2))
    for k in range(n):
        y0, y1, y2 = Y[k, 0], Y[k, 1], Y[k, 2]
        for e in range(2):
            E = turns[e]
            x = (E[0, 0] * y0 + E[0, 2] * y2) + E[0, 1] * y1 + t[0] + shifts_m[e, 0]
            y = (E[1, 0] * y0 + E[1, 2] * y2) + E[1, 1] * y1 + t[1] + shifts_m[e, 1]
            z = (E[2, 0] * y0 + E[2, 2] * y2) + E[2, 1] * y1 + t[2] + shifts_m[e, 2]
            uv[e, 0] = K[0, 0] * x / z + K[0, 1] * y / z + K[0, 2]
            uv[e, 1] = K[1, 1] * y / z + K[1, 2]
        out[k, 0] = (uv[1, 0] - uv[0, 0]) / span_s
        out[k, 1] = (uv[1, 1] - uv[0, 1]) / span_s
    return out


@register_warm_up
def _warm_up() -> None:
    """``reprojection_rt`` once on one tag's corners for each of the solvers' argument types (a
    pose's translation read-only, or the least-squares solver's writable unknowns),
    ``tag_errors_px`` and ``corner_rate_px_s``."""
    model = np.array([[-0.01, 0.01, 0.0], [0.01, 0.01, 0.0], [0.01, -0.01, 0.0], [-0.01, -0.01, 0.0]])
    K = frozen(np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]))
    t = frozen(np.array([0.0, 0.0, 0.5]))
    for translation in (t, np.array(t)):
        reprojection_rt(model, translation, K, np.full((4, 2), 300.0))
    tag_errors_px(model, t, K, np.full((4, 2), 300.0))
    corner_rate_px_s(model, np.stack([np.eye(3)] * 2), np.zeros((2, 3)), t, K, 2e-3)
