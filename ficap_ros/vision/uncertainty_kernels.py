"""The pose uncertainty's compiled kernel: the unit covariances of the error sources and what the
residuals show, in one pass over the used tags (``uncertainty.uncertainty_terms``' arithmetic).

A frame's covariance is built from a few dozen small matrix products per tag (the fit's map
``A = (J^T W J + info)^-1 J^T W``, each tag's orthonormal corner patterns, the pose's response to
each pattern and to each plate's shift and turn, the hat matrix's leverage of each pattern): on
such small arrays numpy's per-call set-up costs more than the arithmetic, so the whole assembly
is one kernel. The formulas are ``uncertainty``'s (its module docstring); the tests' vectorised
numpy reference (test/helpers/uncertainty_reference.py) sums in another order, so the two agree
to rounding (relative 1e-12), not to the bit. The tag basis is a Householder QR, each pattern's column then
signed along its pattern.

Output layout: ``terms`` (13, 6, 6), each ROS order (translation, then rotation): the pattern
groups shift, scale, turn, shear, projective, then noise, bias, model_t, model_r, bias_common,
principal_point, focal, tilt; ``seen`` (14,): the groups' sigmas, their dofs (same order),
bias_common, its standard error and its signed estimate, and the tags' mean scale coefficient;
``A_ros`` (6, 2n), the fit's map in ROS order.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.vision.jit import njit, register_warm_up

__all__ = ["propagated_terms"]

#: The per-tag pattern groups' first column in the tag basis and their column counts (shift 0-1,
#: scale 2, turn 3, shears 4-5, projective 6-7).
_GROUP_FIRST = (0, 2, 3, 4, 6)
_GROUP_COUNT = (2, 1, 1, 2, 2)

_ROS_ROW = (3, 4, 5, 0, 1, 2)
_ONE_DEG_RAD = np.pi / 180.0


@njit(error_model="numpy")
def _inverse(H: np.ndarray) -> np.ndarray:
    """H^-1 (k, k) by Gauss-Jordan elimination with partial pivoting; all inf when H is singular
    (a zero pivot) or not finite."""
    k = H.shape[0]
    a = H.copy()
    inv = np.eye(k)
    for c in range(k):
        p = c
        for r in range(c + 1, k):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if not (a[p, c] != 0.0 and np.isfinite(a[p, c])):
            return np.full((k, k), np.inf)
        if p != c:
            for j in range(k):
                a[c, j], a[p, j] = a[p, j], a[c, j]
                inv[c, j], inv[p, j] = inv[p, j], inv[c, j]
        d = a[c, c]
        for j in range(k):
            a[c, j] /= d
            inv[c, j] /= d
        for r in range(k):
            if r != c and a[r, c] != 0.0:
                f = a[r, c]
                for j in range(k):
                    a[r, j] -= f * a[c, j]
                    inv[r, j] -= f * inv[c, j]
    return inv


@njit(error_model="numpy")
def _map(J: np.ndarray, w: np.ndarray, info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, A): ``M = (J^T W J + info)^-1`` (k, k) and ``A = M J^T W`` (k, m)."""
    m, k = J.shape
    H = info.copy()
    for i in range(m):
        for a in range(k):
            wa = w[i] * J[i, a]
            for b in range(k):
                H[a, b] += wa * J[i, b]
    M = _inverse(H)
    A = np.zeros((k, m))
    for i in range(m):
        for a in range(k):
            s = 0.0
            for b in range(k):
                s += M[a, b] * J[i, b]
            A[a, i] = s * w[i]
    return M, A


@njit(inline="always")
def _householder_q(M: np.ndarray) -> np.ndarray:
    """Q (8, 8) of the QR factorisation of M (8, 8) by Householder reflections in LAPACK's
    convention (dgeqr2's reflectors, ``beta = -sign(alpha) |(alpha, x)|``, then dorg2r's product):
    the columns' signs are LAPACK's, which the pattern coefficients' signs follow."""
    A = M.copy()
    tau = np.zeros(8)
    for j in range(8):
        xnorm2 = 0.0
        for i in range(j + 1, 8):
            xnorm2 += A[i, j] * A[i, j]
        if xnorm2 == 0.0:
            continue
        alpha = A[j, j]
        beta = -np.copysign(np.sqrt(alpha * alpha + xnorm2), alpha)
        tau[j] = (beta - alpha) / beta
        scale = 1.0 / (alpha - beta)
        for i in range(j + 1, 8):
            A[i, j] *= scale
        A[j, j] = beta
        for c in range(j + 1, 8):  # H_j applied to the columns right of j
            _reflect_column(A, j, tau[j], A, c)
    Q = np.eye(8)
    for j in range(7, -1, -1):  # Q = H_0 ... H_7 I, built from the last reflector back
        if tau[j] == 0.0:
            continue
        for c in range(j, 8):
            _reflect_column(A, j, tau[j], Q, c)
    return Q


@njit(inline="always")
def _reflect_column(V: np.ndarray, j: int, tau_j: float, X: np.ndarray, c: int) -> None:
    """X[:, c] = H_j X[:, c] for the reflector H_j = I - tau_j v v^T, v = (0.., 1, V[j+1:, j])."""
    s = X[j, c]
    for i in range(j + 1, 8):
        s += V[i, j] * X[i, c]
    s *= tau_j
    X[j, c] -= s
    for i in range(j + 1, 8):
        X[i, c] -= s * V[i, j]


@njit(error_model="numpy")
def _tag_basis(corners_px: np.ndarray) -> np.ndarray:
    """(8, 8) an orthonormal basis of one tag's corner displacements (x0 y0 ... x3 y3): shift x,
    shift y, scale, turn, two shears, then the two left (projective), from the corners (4, 2):
    the Q of those six patterns and the first two unit vectors (the rest of the identity never
    enters an 8-column Q), each pattern's column signed along its
    pattern, so that a radial offset has the same sign of scale coefficient in every tag (a QR's
    own signs follow the data and would cancel part of the tags' mean)."""
    cx = 0.25 * (corners_px[0, 0] + corners_px[1, 0] + corners_px[2, 0] + corners_px[3, 0])
    cy = 0.25 * (corners_px[0, 1] + corners_px[1, 1] + corners_px[2, 1] + corners_px[3, 1])
    px, py = np.empty(4), np.empty(4)
    norm = 0.0
    for c in range(4):
        px[c], py[c] = corners_px[c, 0] - cx, corners_px[c, 1] - cy
        norm += px[c] * px[c] + py[c] * py[c]
    norm = max(np.sqrt(norm), 1e-9)
    M = np.zeros((8, 8))
    for c in range(4):
        x, y = px[c] / norm, py[c] / norm
        M[2 * c, 0] = 1.0
        M[2 * c + 1, 1] = 1.0
        M[2 * c, 2], M[2 * c + 1, 2] = x, y
        M[2 * c, 3], M[2 * c + 1, 3] = -y, x
        M[2 * c, 4], M[2 * c + 1, 4] = x, -y
        M[2 * c, 5], M[2 * c + 1, 5] = y, x
    M[0, 6] = 1.0
    M[1, 7] = 1.0
    Q = _householder_q(M)
    for j in range(6):  # each pattern's column along its pattern: one sign for every tag
        if _column_dot(Q, M, j) < 0.0:
            for i in range(8):
                Q[i, j] = -Q[i, j]
    return Q


@njit(error_model="numpy")
def _column_dot(Q: np.ndarray, M: np.ndarray, j: int) -> float:
    s = 0.0
    for i in range(8):
        s += Q[i, j] * M[i, j]
    return s


@njit(error_model="numpy")
def _corner_gradients(model_m: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(4n, 2, 3): d(u, v)/d(point in the cap frame) at each model corner (4n, 3) under (R, t):
    the projection's gradient in the camera frame times R."""
    n = model_m.shape[0]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    GR = np.zeros((n, 2, 3))
    G = np.zeros((2, 3))
    for c in range(n):
        X = np.empty(3)
        for r in range(3):
            X[r] = R[r, 0] * model_m[c, 0] + R[r, 1] * model_m[c, 1] + R[r, 2] * model_m[c, 2] + t[r]
        iz = 1.0 / X[2]
        G[0, 0], G[0, 1], G[0, 2] = fx * iz, s * iz, -(fx * X[0] + s * X[1]) * iz * iz
        G[1, 0], G[1, 1], G[1, 2] = 0.0, fy * iz, -fy * X[1] * iz * iz
        for i in range(2):
            for j in range(3):
                GR[c, i, j] = G[i, 0] * R[0, j] + G[i, 1] * R[1, j] + G[i, 2] * R[2, j]
    return GR


@njit(error_model="numpy")
def _tilt_mode(centres: np.ndarray, normal: np.ndarray, R: np.ndarray, t: np.ndarray,
               K: np.ndarray) -> np.ndarray:
    """(8n,): each tag's corners shifted by 1 px along the image direction of its outward normal,
    times the sine of its view angle (the tilt mode of ``uncertainty``'s module docstring)."""
    n = centres.shape[0]
    mode = np.empty(8 * n)
    c, nc, qc, qe = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for k in range(n):
        for r in range(3):
            c[r] = R[r, 0] * centres[k, 0] + R[r, 1] * centres[k, 1] + R[r, 2] * centres[k, 2] + t[r]
            nc[r] = R[r, 0] * normal[k, 0] + R[r, 1] * normal[k, 1] + R[r, 2] * normal[k, 2]
        for r in range(3):
            qc[r] = K[r, 0] * c[0] + K[r, 1] * c[1] + K[r, 2] * c[2]
            qe[r] = (K[r, 0] * (c[0] + 1e-3 * nc[0]) + K[r, 1] * (c[1] + 1e-3 * nc[1])
                     + K[r, 2] * (c[2] + 1e-3 * nc[2]))
        dx = qe[0] / qe[2] - qc[0] / qc[2]
        dy = qe[1] / qe[2] - qc[1] / qc[2]
        dn = max(np.sqrt(dx * dx + dy * dy), 1e-12)
        cos_view = abs(nc[0] * c[0] + nc[1] * c[1] + nc[2] * c[2]) / max(
            np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]), 1e-12)
        sin_view = np.sqrt(min(max(1.0 - cos_view * cos_view, 0.0), 1.0))
        for corner in range(4):
            mode[8 * k + 2 * corner] = dx / dn * sin_view
            mode[8 * k + 2 * corner + 1] = dy / dn * sin_view
    return mode


@njit(inline="always")
def _add_outer(out: np.ndarray, a: np.ndarray, scale: float) -> None:
    """out += scale * a a^T for a (6,)."""
    for i in range(6):
        for j in range(6):
            out[i, j] += scale * a[i] * a[j]


@njit(error_model="numpy")
def _per_tag_terms(terms: np.ndarray, A_ros: np.ndarray, B: np.ndarray, GR: np.ndarray,
                   cross: np.ndarray, rel: np.ndarray) -> None:
    """Into ``terms``: the pattern groups (each tag at its share of the noise), ``bias``,
    ``model_t``, ``model_r``."""
    n = B.shape[0]
    mean_sq = 0.0
    for k in range(n):
        mean_sq += rel[k] * rel[k]
    root = np.sqrt(mean_sq / n)
    modes = np.empty((8, 14))
    am = np.empty(6)
    for k in range(n):
        share2 = (rel[k] / root) ** 2
        modes[:, :8] = B[k]
        for c in range(4):
            for i in range(2):
                for j in range(3):
                    modes[2 * c + i, 8 + j] = GR[4 * k + c, i, j] * 1e-3
                    s = 0.0
                    for q in range(3):
                        s += GR[4 * k + c, i, q] * cross[4 * k + c, j, q] * _ONE_DEG_RAD
                    modes[2 * c + i, 11 + j] = s
        for col in range(14):
            for r in range(6):
                s = 0.0
                for j in range(8):
                    s += A_ros[r, 8 * k + j] * modes[j, col]
                am[r] = s
            if col < 8:
                g = 0
                while g < 4 and _GROUP_FIRST[g + 1] <= col:
                    g += 1
                _add_outer(terms[g], am, share2)
                if col == 2:
                    _add_outer(terms[6], am, 4.0)  # bias: 1 px radial, twice the unit pattern
            else:
                _add_outer(terms[7 if col < 11 else 8], am, 1.0)


@njit(error_model="numpy")
def _shared_terms(terms: np.ndarray, A_ros: np.ndarray, common: np.ndarray, image_px: np.ndarray,
                  K: np.ndarray, tilt: np.ndarray) -> None:
    """Into ``terms``: ``noise``, ``bias_common``, ``principal_point``, ``focal``, ``tilt``."""
    m = A_ros.shape[1]
    a = np.zeros((5, 6))
    for r in range(6):
        for i in range(m):
            v = A_ros[r, i]
            a[0, r] += v * common[i]
            if i % 2 == 0:
                a[1, r] += v
                a[3, r] += v * (image_px[i // 2, 0] - K[0, 2])
            else:
                a[2, r] += v
                a[3, r] += v * (image_px[i // 2, 1] - K[1, 2])
            a[4, r] += v * tilt[i]
        for r2 in range(6):
            s = 0.0
            for i in range(m):
                s += A_ros[r, i] * A_ros[r2, i]
            terms[5, r, r2] = s
    _add_outer(terms[9], a[0], 1.0)
    _add_outer(terms[10], a[1], 1.0)
    _add_outer(terms[10], a[2], 1.0)
    _add_outer(terms[11], a[3], 1.0)
    _add_outer(terms[12], a[4], 1.0)


@njit(inline="always")
def _small_product(out: np.ndarray, a: np.ndarray, b: np.ndarray, b_transposed: bool) -> None:
    """out = a b (or a b^T) for small matrices, in loops (no BLAS call's set-up)."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            s = 0.0
            if b_transposed:
                for q in range(a.shape[1]):
                    s += a[i, q] * b[j, q]
            else:
                for q in range(a.shape[1]):
                    s += a[i, q] * b[q, j]
            out[i, j] = s


@njit(error_model="numpy")
def _residual_sigmas(seen: np.ndarray, res: np.ndarray, J: np.ndarray, M: np.ndarray, B: np.ndarray,
                     rel: np.ndarray) -> None:
    """Into ``seen``: per group its sigma and dof, and the tags' mean scale coefficient
    (the residual pattern groups of ``uncertainty._PATTERNS``)."""
    n = B.shape[0]
    coef = np.zeros((n, 8))
    lev = np.zeros(8)
    k = J.shape[1]
    JM = np.empty((8, k))
    hat = np.empty((8, 8))
    HB = np.empty((8, 8))
    for t in range(n):
        _small_product(JM, J[8 * t : 8 * t + 8], M, False)
        _small_product(hat, JM, J[8 * t : 8 * t + 8], True)
        _small_product(HB, hat, B[t], False)
        for p in range(8):
            s = 0.0
            lv = 0.0
            for j in range(8):
                s -= B[t, j, p] * res[8 * t + j]
                lv += B[t, j, p] * HB[j, p]
            coef[t, p] = s
            lev[p] += lv / rel[t] ** 2
    mean_scale = 0.0
    for t in range(n):
        mean_scale += coef[t, 2]
    mean_scale /= n
    sq = np.zeros(8)
    for t in range(n):
        coef[t, 2] -= mean_scale
        for p in range(8):
            sq[p] += coef[t, p] * coef[t, p]
    for g in range(5):
        dof = _GROUP_COUNT[g] * n
        total = 0.0
        for p in range(_GROUP_FIRST[g], _GROUP_FIRST[g] + _GROUP_COUNT[g]):
            dof -= lev[p]
            total += sq[p]
        if g == 1:
            dof -= 1.0  # the common offset, taken out above
        seen[g] = np.sqrt(total / dof) if dof > 0.5 else 0.0
        seen[5 + g] = max(dof, 0.0)
    seen[13] = mean_scale


@njit(error_model="numpy")
def _common_offset_px(common: np.ndarray, w: np.ndarray, J: np.ndarray, A: np.ndarray,
                      mean_scale: float, scale_sigma: float, n_tags: int) -> tuple[float, float, float]:
    """The tags' common radial offset, its standard error and its signed estimate, px per corner,
    from their mean scale coefficient: what the fit left of it scaled back by the share left; the
    offset's size with the mean's own noise (its standard error) subtracted in quadrature
    (``uncertainty``'s module docstring), the signed estimate without (positive: outward, the
    tags seen larger than the model at the pose)."""
    k = A.shape[0]
    Ac = np.zeros(k)
    for a in range(k):
        for i in range(common.shape[0]):
            Ac[a] += A[a, i] * common[i]
    num = 0.0
    den = 0.0
    for i in range(common.shape[0]):
        JAc = 0.0
        for a in range(k):
            JAc += J[i, a] * Ac[a]
        num += common[i] * w[i] * JAc
        den += common[i] * w[i] * common[i]
    left = max(1.0 - num / den, 0.1)
    mean_se2 = scale_sigma**2 / n_tags
    return (np.sqrt(max(mean_scale**2 - mean_se2, 0.0)) / 2.0 / left, np.sqrt(mean_se2) / 2.0 / left,
            mean_scale / 2.0 / left)


@njit(error_model="numpy")
def propagated_terms(res: np.ndarray, J: np.ndarray, w: np.ndarray, info: np.ndarray,
                     image_px: np.ndarray, model_m: np.ndarray, R: np.ndarray, t: np.ndarray,
                     K: np.ndarray, rel: np.ndarray, cross: np.ndarray, centres: np.ndarray,
                     normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(terms (13, 6, 6), seen (14,), A_ros (6, 8n)) of a pose (R, t (m)) fitted to n tags.

    Args:
        res, J: the fit's residuals (8n,) px and Jacobian (8n, k), the pose's six columns first.
        w: (8n,) weights per residual coordinate; info: (k, k) a prior's information (zeros:
            none).
        image_px: (4n, 2) undistorted corners; model_m: (4n, 3) model corners, m.
        K: (3, 3) intrinsics; rel: (n,) each tag's noise relative to the median tag's.
        cross: (4n, 3, 3) e_k x (corner - its tag's centre); centres, normal: (n, 3) the tags'
            centres (m) and unit outward normals, cap frame.
    """
    n = rel.shape[0]
    M, A = _map(J, w, info)
    A_ros = np.empty((6, A.shape[1]))
    for r in range(6):
        A_ros[r] = A[_ROS_ROW[r]]
    B = np.empty((n, 8, 8))
    common = np.empty(8 * n)
    for k in range(n):
        B[k] = _tag_basis(image_px[4 * k : 4 * k + 4])
        for j in range(8):
            common[8 * k + j] = 2.0 * B[k, j, 2]
    terms = np.zeros((13, 6, 6))
    _per_tag_terms(terms, A_ros, B, _corner_gradients(model_m, R, t, K), cross, rel)
    _shared_terms(terms, A_ros, common, image_px, K, _tilt_mode(centres, normal, R, t, K))
    seen = np.zeros(14)
    _residual_sigmas(seen, res, J, M, B, rel)
    seen[10], seen[11], seen[12] = _common_offset_px(common, w, J, A, seen[13], seen[1], n)
    return terms, seen, A_ros


@register_warm_up
def _warm_up() -> None:
    """``propagated_terms`` once on two tags (the static fit's argument types)."""
    square = np.array([[-0.01, 0.01, 0.0], [0.01, 0.01, 0.0], [0.01, -0.01, 0.0], [-0.01, -0.01, 0.0]])
    model = np.concatenate([square, square + np.array([0.03, 0.0, 0.0])])
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    t = np.array([0.0, 0.0, 0.5])
    image = model[:, :2] / 0.5 * 800.0 + np.array([320.0, 240.0])
    J = np.random.default_rng(0).normal(size=(16, 6))
    # The tags' model geometry reaches the kernel read-only (cached): a type of its own to numba.
    cross, centres, normal = np.zeros((8, 3, 3)), np.zeros((2, 3)), np.tile(np.array([0.0, 0.0, 1.0]), (2, 1))
    for a in (cross, centres, normal):
        a.setflags(write=False)
    propagated_terms(np.zeros(16), J, np.ones(16), np.zeros((6, 6)), image, model, np.eye(3), t, K,
                     np.ones(2), cross, centres, normal)
