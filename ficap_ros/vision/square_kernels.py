"""Square-consistent tag corners: each tag's four corners moved to the nearest image a square can make.

A printed tag is a square. Through a pinhole camera with known intrinsics K its image is the
homography H ~ K [r1 r2 t] (r1 and r2 orthonormal): 6 degrees of freedom (the tag's pose; its
size only scales its depth). Four corners measured one by one, or from a free 8-parameter
homography, have 8: the two the square leaves out carry only the corners' error (noise and each
corner's own misplacement), which no cap pose can explain (every pose of the rigid cap puts a
square's image on each tag). ``square_tag_corners`` fits each tag's pose to its corners (least
squares in px: a few Gauss-Newton steps from each of the two tilts the corners' homography gives
at the tag's centre, the better fit kept) and returns the pose's corners: the corners' projection
onto the square's images, which keeps what a tag's pose can say and drops the rest. It holds in
undistorted pixels (the pinhole's), where the pose works.
"""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.vision.fit_kernels import tag_homography
from ficap_ros.vision.jit import njit, register_warm_up
from ficap_ros.vision.kernels import frozen
from ficap_ros.vision.pose_kernels import corner_rows

__all__ = ["square_tag_corners"]

#: A Gauss-Newton step of a tag's pose that lowers its corners' sum of squared residuals by less
#: than this, px^2, ends its fit (its corners then move by well under a thousandth of a px).
_CONVERGED_PX2 = 1e-12
#: The square's corners in its own plane (half-side 1; corner order and axes as the tag's cells:
#: c0 top left, x right, y down), its z 0.
_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


@njit(inline="always", error_model="numpy")
def _start_rotations(m: np.ndarray, rot1: np.ndarray, rot2: np.ndarray) -> bool:
    """The two rotations of a square whose image through the normalised camera is near the
    quadrilateral ``m`` (4, 2), from the homography's Jacobian at the square's centre (IPPE,
    Collins and Bartoli 2014: a plane's pose from one point's affine map, unique up to the
    tilt's sign; the homography in closed form, Heckbert's square-to-quadrilateral map). Writes
    ``rot1``, ``rot2`` (3, 3); False for a degenerate quadrilateral."""
    hm = np.empty((3, 3))
    if not tag_homography(m, hm):
        return False
    # The tag's map from cell units (0-8) to the image; the centred square's (u = 4 (x + 1)) has
    # four cells' columns and the tag's centre as its origin.
    ax, ay, az = 4.0 * hm[0, 0], 4.0 * hm[1, 0], 4.0 * hm[2, 0]
    bx, by, bz = 4.0 * hm[0, 1], 4.0 * hm[1, 1], 4.0 * hm[2, 1]
    x0, y0 = hm[0, 2], hm[1, 2]
    ox, oy, oz = x0 + ax + bx, y0 + ay + by, 1.0 + az + bz
    p, q = ox / oz, oy / oz
    j00, j01 = (ax - p * az) / oz, (bx - p * bz) / oz
    j10, j11 = (ay - q * az) / oz, (by - q * bz) / oz
    # rv: the rotation taking the optical axis to the centre's ray (p, q, 1).
    r = math.hypot(p, q)
    sn = math.sqrt(1.0 + r * r)
    rv = np.eye(3)
    if r > 0.0:
        k0, k1 = -q / r, p / r
        sin_t, cos_t = r / sn, 1.0 / sn
        v = 1.0 - cos_t
        rv[0, 0], rv[0, 1], rv[0, 2] = 1.0 - v * k1 * k1, v * k0 * k1, sin_t * k1
        rv[1, 0], rv[1, 1], rv[1, 2] = v * k0 * k1, 1.0 - v * k0 * k0, -sin_t * k0
        rv[2, 0], rv[2, 1], rv[2, 2] = -sin_t * k1, sin_t * k0, cos_t
    b00, b01 = rv[0, 0] - p * rv[2, 0], rv[0, 1] - p * rv[2, 1]
    b10, b11 = rv[1, 0] - q * rv[2, 0], rv[1, 1] - q * rv[2, 1]
    det = b00 * b11 - b01 * b10
    a00 = (b11 * j00 - b01 * j10) / det
    a01 = (b11 * j01 - b01 * j11) / det
    a10 = (-b10 * j00 + b00 * j10) / det
    a11 = (-b10 * j01 + b00 * j11) / det
    t00, t01, t11 = a00 * a00 + a01 * a01, a00 * a10 + a01 * a11, a10 * a10 + a11 * a11
    gamma = math.sqrt(0.5 * (t00 + t11 + math.sqrt((t00 - t11) * (t00 - t11) + 4.0 * t01 * t01)))
    if not (math.isfinite(gamma) and gamma > 0.0):
        return False
    r00, r01, r10, r11 = a00 / gamma, a01 / gamma, a10 / gamma, a11 / gamma
    c0 = math.sqrt(max(1.0 - r00 * r00 - r10 * r10, 0.0))
    c1 = math.sqrt(max(1.0 - r01 * r01 - r11 * r11, 0.0))
    if -r00 * r01 - r10 * r11 < 0.0:
        c1 = -c1
    for sign, out in ((1.0, rot1), (-1.0, rot2)):
        e0, e1 = sign * c0, sign * c1
        # Columns in rv's frame: (r00, r10, e0), (r01, r11, e1) and their cross product.
        l2x, l2y, l2z = r10 * e1 - e0 * r11, e0 * r01 - r00 * e1, r00 * r11 - r01 * r10
        for i in range(3):
            out[i, 0] = rv[i, 0] * r00 + rv[i, 1] * r10 + rv[i, 2] * e0
            out[i, 1] = rv[i, 0] * r01 + rv[i, 1] * r11 + rv[i, 2] * e1
            out[i, 2] = rv[i, 0] * l2x + rv[i, 1] * l2y + rv[i, 2] * l2z
    return math.isfinite(rot1[0, 0] + rot1[1, 1] + rot1[2, 2] + rot2[0, 0] + rot2[1, 1] + rot2[2, 2])


@njit(inline="always", error_model="numpy")
def _start_translation(m: np.ndarray, rot: np.ndarray, t: np.ndarray) -> bool:
    """``t`` (3,) <- the square's translation at rotation ``rot`` that best fits the normalised
    corners ``m`` (4, 2) (linear least squares of the projection's cross-multiplied equations);
    False where they are singular."""
    # Rows t0 - u t2 = u xz - xx and t1 - v t2 = v xz - xy per corner; their normal equations
    # [[4, 0, -su], [0, 4, -sv], [-su, -sv, suv]] t = g, solved by elimination.
    su = sv = suv = 0.0
    g0 = g1 = g2 = 0.0
    for i in range(4):
        xx = rot[0, 0] * _SQUARE[i, 0] + rot[0, 1] * _SQUARE[i, 1]
        xy = rot[1, 0] * _SQUARE[i, 0] + rot[1, 1] * _SQUARE[i, 1]
        xz = rot[2, 0] * _SQUARE[i, 0] + rot[2, 1] * _SQUARE[i, 1]
        u, v = m[i, 0], m[i, 1]
        ru, rv = u * xz - xx, v * xz - xy
        su += u
        sv += v
        suv += u * u + v * v
        g0 += ru
        g1 += rv
        g2 -= u * ru + v * rv
    d = suv - (su * su + sv * sv) / 4.0
    if not (math.isfinite(d) and d != 0.0):
        return False
    t[2] = (g2 + (su * g0 + sv * g1) / 4.0) / d
    t[0] = (g0 + su * t[2]) / 4.0
    t[1] = (g1 + sv * t[2]) / 4.0
    return t[2] > 0.0


@njit(inline="always", error_model="numpy")
def _rotate(rot: np.ndarray, w0: float, w1: float, w2: float) -> None:
    """``rot`` (3, 3) <- exp(w) rot in place; w = (w0, w1, w2) a rotation vector, rad (Rodrigues)."""
    angle = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if angle < 1e-15:
        return
    k0, k1, k2 = w0 / angle, w1 / angle, w2 / angle
    s, c = math.sin(angle), math.cos(angle)
    v = 1.0 - c
    e00, e01, e02 = c + v * k0 * k0, v * k0 * k1 - s * k2, v * k0 * k2 + s * k1
    e10, e11, e12 = v * k0 * k1 + s * k2, c + v * k1 * k1, v * k1 * k2 - s * k0
    e20, e21, e22 = v * k0 * k2 - s * k1, v * k1 * k2 + s * k0, c + v * k2 * k2
    for j in range(3):
        r0, r1, r2 = rot[0, j], rot[1, j], rot[2, j]
        rot[0, j] = e00 * r0 + e01 * r1 + e02 * r2
        rot[1, j] = e10 * r0 + e11 * r1 + e12 * r2
        rot[2, j] = e20 * r0 + e21 * r1 + e22 * r2


@njit(inline="always", error_model="numpy")
def _gauss_newton_step(res: np.ndarray, jac: np.ndarray, a: np.ndarray, step: np.ndarray) -> bool:
    """``step`` (6,) <- the least-squares solution of ``jac`` (8, 6) step = -``res`` (8,), by its
    normal equations' Cholesky factor (``a`` (6, 6) scratch); False where they are not positive
    definite."""
    for i in range(6):
        acc = 0.0
        for r in range(8):
            acc -= jac[r, i] * res[r]
        step[i] = acc
        for j in range(i + 1):
            acc = 0.0
            for r in range(8):
                acc += jac[r, i] * jac[r, j]
            a[i, j] = acc
    for j in range(6):  # the lower triangle in place
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, 6):
            acc = a[i, j]
            for k in range(j):
                acc -= a[i, k] * a[j, k]
            a[i, j] = acc / d
    for i in range(6):  # forward substitution, then back
        acc = step[i]
        for k in range(i):
            acc -= a[i, k] * step[k]
        step[i] = acc / a[i, i]
    for i in range(5, -1, -1):
        acc = step[i]
        for k in range(i + 1, 6):
            acc -= a[k, i] * step[k]
        step[i] = acc / a[i, i]
    return True


@njit(inline="always", error_model="numpy")
def _residuals(rot: np.ndarray, t: np.ndarray, K: np.ndarray, image_px: np.ndarray,
               res: np.ndarray, jac: np.ndarray) -> None:
    """Residuals (8,) px (projection - corner) of the square at (rot, t) and their Jacobian (8, 6)
    (a left rotation d_theta, then d_t): ``pose_kernels.corner_rows`` of each corner."""
    for i in range(4):
        x0 = rot[0, 0] * _SQUARE[i, 0] + rot[0, 1] * _SQUARE[i, 1]
        x1 = rot[1, 0] * _SQUARE[i, 0] + rot[1, 1] * _SQUARE[i, 1]
        x2 = rot[2, 0] * _SQUARE[i, 0] + rot[2, 1] * _SQUARE[i, 1]
        corner_rows(x0, x1, x2, t, K, image_px[i, 0], image_px[i, 1], res, jac, i)


@njit(inline="always", error_model="numpy")
def _refine(rot: np.ndarray, t: np.ndarray, K: np.ndarray, image_px: np.ndarray, res: np.ndarray,
            jac: np.ndarray, a: np.ndarray, step: np.ndarray, iterations: int) -> float:
    """At most ``iterations`` Gauss-Newton steps of the square's pose (``rot``, ``t`` in place)
    toward the corners ``image_px`` (4, 2) px, until a step lowers the sum of squared residuals by
    less than ``_CONVERGED_PX2``; leaves ``res`` the final residuals and returns their sum of
    squares (inf where a step fails or the square ends behind the camera)."""
    last = np.inf
    for _ in range(iterations):
        _residuals(rot, t, K, image_px, res, jac)
        cost = 0.0
        for i in range(8):
            cost += res[i] * res[i]
        if not last - cost > _CONVERGED_PX2 + 1e-9 * cost:  # converged (a step that no longer lowers it)
            break
        last = cost
        if not _gauss_newton_step(res, jac, a, step):
            return np.inf
        _rotate(rot, step[0], step[1], step[2])
        t[0], t[1], t[2] = t[0] + step[3], t[1] + step[4], t[2] + step[5]
    if not t[2] > 0.0:
        return np.inf
    _residuals(rot, t, K, image_px, res, jac)
    cost = 0.0
    for i in range(8):
        cost += res[i] * res[i]
    return cost if math.isfinite(cost) else np.inf


@njit(error_model="numpy")
def square_tag_corners(corners_px: np.ndarray, K: np.ndarray, iterations: int,
                       max_move_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Each tag's corners projected onto the images of a square (module docstring).

    Args:
        corners_px: (N, 4, 2) float64 the tags' corners, undistorted px (the pinhole's; tag
            corner order c0..c3 as the detector gives them).
        K: (3, 3) float64 the camera matrix (with its skew).
        iterations: the most Gauss-Newton steps of each tag's pose from each of its two starts.
        max_move_px: the farthest a corner may move; a tag whose fit moves one farther (a
            quadrilateral no square's image is near: a corner off by much more than noise) keeps
            its corners.

    Returns:
        (corners (N, 4, 2) the square-consistent corners (the input's where not squared),
        squared (N,) bool).
    """
    n = corners_px.shape[0]
    out = corners_px.copy()
    squared = np.zeros(n, np.bool_)
    k_inv = np.linalg.inv(K)
    m = np.empty((4, 2))
    rot1, rot2, t = np.empty((3, 3)), np.empty((3, 3)), np.empty(3)
    best_res = np.empty(8)
    res, jac = np.empty(8), np.empty((8, 6))
    a, step = np.empty((6, 6)), np.empty(6)
    for g in range(n):
        for i in range(4):
            px, py = corners_px[g, i, 0], corners_px[g, i, 1]
            w = k_inv[2, 0] * px + k_inv[2, 1] * py + k_inv[2, 2]
            m[i, 0] = (k_inv[0, 0] * px + k_inv[0, 1] * py + k_inv[0, 2]) / w
            m[i, 1] = (k_inv[1, 0] * px + k_inv[1, 1] * py + k_inv[1, 2]) / w
        if not _start_rotations(m, rot1, rot2):
            continue
        best = np.inf
        for rot in (rot1, rot2):
            if not _start_translation(m, rot, t):
                continue
            cost = _refine(rot, t, K, corners_px[g], res, jac, a, step, iterations)
            if cost < best:
                best = cost
                for i in range(8):
                    best_res[i] = res[i]
        if best == np.inf:
            continue
        worst = 0.0
        for i in range(4):
            worst = max(worst, math.hypot(best_res[2 * i], best_res[2 * i + 1]))
        if not worst <= max_move_px:
            continue
        for i in range(4):
            out[g, i, 0] = corners_px[g, i, 0] + best_res[2 * i]
            out[g, i, 1] = corners_px[g, i, 1] + best_res[2 * i + 1]
        squared[g] = True
    return out, squared


@register_warm_up
def _warm_up() -> None:
    """The kernel once on a tiny input of the pipeline's argument types."""
    K = frozen(np.array([[1000.0, 0.0, 640.0], [0.0, 1000.0, 360.0], [0.0, 0.0, 1.0]]))
    corners = np.array([[[600.0, 320.0], [680.0, 321.0], [679.0, 400.0], [601.0, 399.0]]])
    square_tag_corners(corners, K, 3, 1.0)
