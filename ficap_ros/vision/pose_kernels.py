"""The pose solvers' compiled kernels: the reprojection residuals of a pose and their Jacobian,
and the joint pose's Levenberg-Marquardt refinement over them.

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

``refine_lm`` is the whole least-squares refinement in one call: Levenberg-Marquardt steps on the
normal equations of ``reprojection_rt``'s residuals, each step a left turn of the rotation
(``exp(d_theta) R``, composed, so Gauss-Newton converges quadratically) and a shift of the
translation, until the step is negligible against the pose or the cost stops falling (the
tolerances of MINPACK's lmder: relative 1e-10), in at most ``max_evaluations`` residual passes.
It reaches the reprojection minimum MINPACK reaches; its iterates differ, so the answer agrees to
the solver's tolerance, not to the bit.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up

__all__ = ["reprojection_rt", "refine_lm", "rotation_of", "solve_spd"]


@njit(error_model="numpy")
def reprojection_rt(X: np.ndarray, t: np.ndarray, K: np.ndarray,
                    image_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) px and Jacobian (2N, 6) of the pose (R, t (3,) m) against the corners
    ``image_px`` (N, 2), undistorted px, of model points whose rotated positions ``X`` = R m
    (N, 3), m, in the camera's axes, the caller computes (numpy's matrix product: the same
    rounding as every other use of the pose); K (3, 3) with its skew. Rows alternate u and v of
    each corner; columns d_theta (rad, camera axes), then d_t (m). All float64, C-contiguous."""
    n = X.shape[0]
    fx, fy, skew, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    res = np.empty(2 * n)
    jac = np.empty((2 * n, 6))
    for i in range(n):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        iz = 1.0 / (x2 + t[2])
        xn, yn = (x0 + t[0]) * iz, (x1 + t[1]) * iz
        u = fx * xn + skew * yn + cx
        v = fy * yn + cy
        ru, rv = 2 * i, 2 * i + 1
        res[ru] = u - image_px[i, 0]
        res[rv] = v - image_px[i, 1]
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
    return res, jac


@njit(inline="always")
def rotation_of(w0: float, w1: float, w2: float) -> np.ndarray:
    """The rotation matrix (3, 3) of the rotation vector (w0, w1, w2), rad (Rodrigues' formula);
    the identity below machine epsilon."""
    theta = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    R = np.eye(3)
    if theta < 2.220446049250313e-16:
        return R
    c, s = np.cos(theta), np.sin(theta)
    c1 = 1.0 - c
    x, y, z = w0 / theta, w1 / theta, w2 / theta
    R[0, 0], R[0, 1], R[0, 2] = c + c1 * x * x, c1 * x * y - s * z, c1 * x * z + s * y
    R[1, 0], R[1, 1], R[1, 2] = c1 * x * y + s * z, c + c1 * y * y, c1 * y * z - s * x
    R[2, 0], R[2, 1], R[2, 2] = c1 * x * z - s * y, c1 * y * z + s * x, c + c1 * z * z
    return R


@njit(inline="always")
def _rotated(model_m: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N, 3) model points ``model_m`` (N, 3) rotated by R."""
    n = model_m.shape[0]
    X = np.empty((n, 3))
    for i in range(n):
        for r in range(3):
            X[i, r] = R[r, 0] * model_m[i, 0] + R[r, 1] * model_m[i, 1] + R[r, 2] * model_m[i, 2]
    return X


@njit(inline="always")
def _normal_equations(res: np.ndarray, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(J^T J (6, 6), J^T r (6,), r^T r) of residuals (M,) and Jacobian (M, 6)."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    for i in range(res.shape[0]):
        r = res[i]
        cost += r * r
        for a in range(6):
            ja = jac[i, a]
            g[a] += ja * r
            for b in range(a, 6):
                H[a, b] += ja * jac[i, b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, cost


@njit(error_model="numpy")
def solve_spd(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, bool]:
    """x with ``H x = g`` for a symmetric positive definite H (k, k) by Cholesky; (zeros, False)
    when H is not positive definite (or not finite)."""
    k = H.shape[0]
    L = np.zeros((k, k))
    for j in range(k):
        d = H[j, j]
        for m in range(j):
            d -= L[j, m] * L[j, m]
        if not d > 0.0:
            return np.zeros(k), False
        L[j, j] = np.sqrt(d)
        for i in range(j + 1, k):
            v = H[i, j]
            for m in range(j):
                v -= L[i, m] * L[j, m]
            L[i, j] = v / L[j, j]
    y = np.empty(k)
    for i in range(k):
        v = g[i]
        for m in range(i):
            v -= L[i, m] * y[m]
        y[i] = v / L[i, i]
    x = np.empty(k)
    for i in range(k - 1, -1, -1):
        v = y[i]
        for m in range(i + 1, k):
            v -= L[m, i] * x[m]
        x[i] = v / L[i, i]
    return x, True


@njit(inline="always")
def _turn_between(R: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """The rotation vector (3,), rad, of ``R R0^T``: the left turn from R0 to R (angle from
    atan2 of its sine and cosine, well conditioned at small angles)."""
    D = R @ R0.T
    w = np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) * 0.5
    sine = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    cosine = 0.5 * (D[0, 0] + D[1, 1] + D[2, 2] - 1.0)
    if sine < 1e-300:
        return w
    return w * (np.arctan2(sine, cosine) / sine)


@njit(error_model="numpy")
def refine_lm(R0: np.ndarray, t0: np.ndarray, K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray,
              max_evaluations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The pose (``turn`` (3,): the rotation vector, rad, of its left turn from R0; t (3,), m)
    minimising the squared reprojection residuals of the model
    points ``model_m`` (N, 3), m, against the undistorted corners ``image_px`` (N, 2), from the
    start (R0, t0), and the residuals (2N,) px there.

    Levenberg-Marquardt with Marquardt's scaling (the damping times the normal matrix's diagonal,
    the largest seen): a step that lowers the cost is taken and the damping eased tenfold, one
    that does not is refused and the damping raised tenfold. Stops when a taken step is below
    1e-10 of the pose (scaled by the diagonal) or lowers the cost by less than 1e-10 of it, after
    ``max_evaluations`` residual passes, or when the damping has no step left to try.

    Returns:
        (turn, t, residuals, status): status 0 converged, 1 the evaluations ran out, 2 the
        start's residuals are not finite (no turn, t0 and those residuals returned).
    """
    R = R0.copy()
    t = t0.copy()
    res, jac = reprojection_rt(_rotated(model_m, R), t, K, image_px)
    for i in range(res.shape[0]):
        if not np.isfinite(res[i]):
            return _turn_between(R, R0), t, res, 2
    H, g, cost = _normal_equations(res, jac)
    scale = np.zeros(6)
    damping = 1e-6
    evaluations = 1
    while evaluations < max_evaluations:
        for a in range(6):
            scale[a] = max(scale[a], H[a, a])
        A = H.copy()
        for a in range(6):
            A[a, a] += damping * scale[a]
        step, ok = solve_spd(A, -g)
        if not ok:
            if damping > 1e16:
                return _turn_between(R, R0), t, res, 0
            damping *= 10.0
            continue
        R_new = rotation_of(step[0], step[1], step[2]) @ R
        t_new = t + step[3:]
        res_new, jac_new = reprojection_rt(_rotated(model_m, R_new), t_new, K, image_px)
        evaluations += 1
        H_new, g_new, cost_new = _normal_equations(res_new, jac_new)
        if not cost_new <= cost:  # worse, or not finite
            if damping > 1e16:
                return _turn_between(R, R0), t, res, 0
            damping *= 10.0
            continue
        step_norm = 0.0
        pose_norm = 0.0
        for a in range(6):
            step_norm += scale[a] * step[a] * step[a]
        for a in range(3):
            pose_norm += scale[3 + a] * t_new[a] * t_new[a]
        reduction = cost - cost_new
        R, t, res, H, g, cost = R_new, t_new, res_new, H_new, g_new, cost_new
        damping = max(damping / 10.0, 1e-12)
        if step_norm <= 1e-20 * pose_norm or reduction <= 1e-10 * (cost + reduction):
            return _turn_between(R, R0), t, res, 0
    return _turn_between(R, R0), t, res, 1


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a`` marked read-only: a pose's rotation, translation and the intrinsics reach the
    kernels so, and numba compiles a read-only argument as a type of its own."""
    a.setflags(write=False)
    return a


@register_warm_up
def _warm_up() -> None:
    """``reprojection_rt`` and ``refine_lm`` once on one tag's corners (the solvers' argument
    types)."""
    model = np.array([[-0.01, 0.01, 0.0], [0.01, 0.01, 0.0], [0.01, -0.01, 0.0], [-0.01, -0.01, 0.0]])
    K = _read_only(np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]]))
    t = _read_only(np.array([0.0, 0.0, 0.5]))
    reprojection_rt(model, t, K, np.full((4, 2), 300.0))
    refine_lm(_read_only(np.eye(3)), t, K, model, np.full((4, 2), 300.0), 5)
