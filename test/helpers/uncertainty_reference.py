"""The pose uncertainty's unit covariances vectorised in numpy: the reference the compiled
``ficap_ros.vision.uncertainty_kernels.propagated_terms`` is tested against (the same formulas,
numpy's summation order)."""

from __future__ import annotations

import math

import numpy as np

from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.reprojection import TagObservations
from ficap_ros.vision.uncertainty import _PATTERNS, _model_geometry

_ROS_ORDER = np.array([3, 4, 5, 0, 1, 2])


def _tag_basis(corners_px: np.ndarray) -> np.ndarray:
    """(tags, 8, 8): per tag an orthonormal basis of its corners' displacements (x0 y0 ... x3 y3):
    shift x, shift y, scale (radial), turn, two shears, and the two left (projective), in that
    order (Gram-Schmidt from the tag's observed corner layout; the identity completes it)."""
    n_tags = corners_px.shape[0]
    p = corners_px - corners_px.mean(axis=1, keepdims=True)
    p = p / np.maximum(np.linalg.norm(p.reshape(n_tags, -1), axis=1), 1e-9)[:, None, None]
    px, py = p[..., 0], p[..., 1]
    # Columns (x0 y0 ... x3 y3 down each): the six patterns, then the identity's eight; the shift
    # columns and the identity are the same for every tag (copied from one template).
    M = np.repeat(_BASIS_TEMPLATE, n_tags, axis=0)
    M[:, 0::2, 2], M[:, 1::2, 2] = px, py  # scale (radial)
    M[:, 0::2, 3], M[:, 1::2, 3] = -py, px  # turn
    M[:, 0::2, 4], M[:, 1::2, 4] = px, -py  # shear
    M[:, 0::2, 5], M[:, 1::2, 5] = py, px  # shear
    Q, _ = np.linalg.qr(M)
    Q = Q[:, :, :8]
    sign = np.where(np.einsum("tij,tij->tj", Q[:, :, :6], M[:, :, :6]) < 0.0, -1.0, 1.0)
    Q[:, :, :6] *= sign[:, None, :]  # each pattern's column along its pattern
    return Q


def _basis_template() -> np.ndarray:
    """(1, 8, 14): ``_tag_basis``'s columns that do not depend on the tag: shift x, shift y
    (0 and 1), the identity (6..13); the tag's four patterns (2..5) are filled in."""
    t = np.zeros((1, 8, 14))
    t[0, 0::2, 0] = 1.0
    t[0, 1::2, 1] = 1.0
    t[0, :, 6:] = np.eye(8)
    t.setflags(write=False)
    return t


_BASIS_TEMPLATE = _basis_template()


def _tilt_mode(obs: TagObservations, T: Transform) -> np.ndarray:
    """(2n,): each tag's corners shifted by 1 px along the image direction of its outward normal,
    times the sine of its view angle (0 for a tag seen head-on, 1 edge-on)."""
    centres, normal, _ = _model_geometry(obs)
    c_cam = T.apply(centres)
    n_cam = normal @ T.rotation_matrix.T
    K = obs.K

    def project(p: np.ndarray) -> np.ndarray:
        q = p @ K.T
        return q[:, :2] / q[:, 2:3]

    d = project(c_cam + 1e-3 * n_cam) - project(c_cam)
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    cos_view = np.abs(np.einsum("ij,ij->i", n_cam, c_cam)) / np.maximum(np.linalg.norm(c_cam, axis=1), 1e-12)
    sin_view = np.sqrt(np.clip(1.0 - cos_view**2, 0.0, 1.0))
    return np.repeat((u * sin_view[:, None])[:, None, :], 4, axis=1).reshape(-1)


def _propagation(J: np.ndarray, w: np.ndarray,
                 info: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(M, A) of the weighted fit with Jacobian ``J`` (2n, k: the pose's 6 columns first) and
    weights ``w`` (2n,): ``M = (J^T W J + info)^-1`` (``info``: a prior's information on the
    unknowns, None: none) and ``A = M J^T W`` (k, 2n), the unknowns' change per corner coordinate
    displacement. A singular fit gives an infinite M (``combine_uncertainty`` turns it into
    "unknown")."""
    H = J.T @ (w[:, None] * J)
    if info is not None:
        H = H + info
    try:
        M = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        M = np.full(H.shape, np.inf)
    return M, M @ (J.T * w)


def _per_tag_terms(obs: TagObservations, T: Transform, A_ros: np.ndarray, B: np.ndarray,
                   rel: np.ndarray) -> dict[str, np.ndarray]:
    """The terms of the error sources independent per tag: ``noise``, the pattern groups of
    ``_PATTERNS`` (each tag's at its relative noise ``rel``), ``bias``, ``model_t``, ``model_r``.
    ``A_ros`` (6, 2n): the fit's map in ROS order; ``B`` (tags, 8, 8): ``_tag_basis``."""
    n_tags = len(obs)
    A_tag = A_ros.reshape(6, n_tags, 8).transpose(1, 0, 2)  # (tags, 6, 8)
    GR = _image_gradient(obs, T) @ T.rotation_matrix  # d(u, v)/d(point in the cap frame)
    share = rel / np.sqrt(np.mean(rel**2))  # each tag's sigma over the frame's mean tag's
    # Modes independent per tag (tags, 8, k), all in one product: the 8 basis patterns, then
    # each plate shifted 1 mm along each cap axis (model_t), then turned 1 deg about each
    # (model_r: e_k x (corner - tag centre), the corner's move when its plate turns about axis k).
    shift = GR * 1e-3  # (n, 2, 3): 1 mm along each cap axis
    turn = np.einsum("nij,nkj->nik", GR, _model_geometry(obs)[2] * np.radians(1.0))
    modes = np.concatenate([B, shift.reshape(n_tags, 8, 3), turn.reshape(n_tags, 8, 3)], axis=2)
    am = A_tag @ modes  # (tags, 6, 14): the pose's response to each tag's mode
    # Per mode, the covariance summed over the tags (independent): (14, 6, 6). The pattern
    # groups' with each tag's relative noise (share), bias and the model's without.
    scaled = am[:, :, :8] * share[:, None, None]
    per_mode_s = np.einsum("tkm,tlm->mkl", scaled, scaled)
    per_mode = np.einsum("tkm,tlm->mkl", am, am)
    terms: dict[str, np.ndarray] = {"noise": A_ros @ A_ros.T}
    for group, idx in _PATTERNS.items():
        terms[group] = per_mode_s[idx].sum(axis=0)
    terms["bias"] = 4.0 * per_mode[2]
    terms["model_t"] = per_mode[8:11].sum(axis=0)
    terms["model_r"] = per_mode[11:14].sum(axis=0)
    return terms


def _image_gradient(obs: TagObservations, T: Transform) -> np.ndarray:
    """(4 * tags, 2, 3): d(u, v)/d(point in the camera frame) at each model corner under ``T``."""
    K = obs.K
    Xc = obs.model_m.reshape(-1, 3) @ T.rotation_matrix.T + T.translation_m  # corners, camera frame
    iz = 1.0 / Xc[:, 2]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    G = np.zeros((len(Xc), 2, 3))
    G[:, 0, 0] = fx * iz
    G[:, 0, 1] = s * iz
    G[:, 0, 2] = -(fx * Xc[:, 0] + s * Xc[:, 1]) * iz * iz
    G[:, 1, 1] = fy * iz
    G[:, 1, 2] = -fy * Xc[:, 1] * iz * iz
    return G


def _shared_terms(obs: TagObservations, T: Transform, A_ros: np.ndarray,
                  common: np.ndarray) -> dict[str, np.ndarray]:
    """The terms of the error sources shared by all tags: ``bias_common`` (``common`` (2n,): 1 px
    radial at each corner), ``principal_point`` (x, y), ``focal`` and ``tilt``."""
    uv = obs.image_px.reshape(-1, 2)
    shared = np.zeros((len(common), 5))
    shared[:, 0] = common
    shared[0::2, 1] = 1.0  # principal point x: every u
    shared[1::2, 2] = 1.0  # ... y: every v
    shared[:, 3] = (uv - obs.K[:2, 2]).reshape(-1)
    shared[:, 4] = _tilt_mode(obs, T).reshape(-1)
    am_shared = A_ros @ shared  # (6, 5)
    a0 = am_shared[:, 0]
    return {
        "bias_common": np.outer(a0, a0),
        "principal_point": am_shared[:, 1:3] @ am_shared[:, 1:3].T,
        "focal": np.outer(am_shared[:, 3], am_shared[:, 3]),
        "tilt": np.outer(am_shared[:, 4], am_shared[:, 4]),
    }


def _residual_sigmas(res: np.ndarray, J: np.ndarray, M: np.ndarray, B: np.ndarray,
                     rel: np.ndarray) -> tuple[dict[str, float], float]:
    """(seen, mean_scale): per pattern group of ``_PATTERNS`` the sigma the residuals show and its
    ``<group>_dof``; and the tags' mean scale (radial) coefficient, px.

    The residuals in each tag's patterns; per group, the coefficients' variance pooled over the
    tags (the frame's mean tag), with the degrees of freedom the fit took from the group (the
    weighted hat matrix's leverage, w_t J_t M J_t^T) subtracted. Pooled with equal weights: the
    weights come from the same residuals, and a variance pooled through them would be biased low.
    """
    n_tags = len(rel)
    coef = np.einsum("tjm,tj->tm", B, -res.reshape(n_tags, 8))
    Jt = J.reshape(n_tags, 8, -1)
    # Batched matmuls, not three-operand einsums (those loop over every index).
    hat = (Jt @ M) @ Jt.transpose(0, 2, 1) / rel[:, None, None] ** 2
    leverage = (B * (hat @ B)).sum(axis=1)
    mean_scale = float(coef[:, 2].mean())
    seen: dict[str, float] = {}
    # Per pattern: the tags' squared coefficients and leverages summed (the scale's about their
    # mean), then per group (Python floats: five groups of one or two patterns).
    coef[:, 2] -= mean_scale
    sq = (coef * coef).sum(axis=0).tolist()
    lev = leverage.sum(axis=0).tolist()
    for group, idx in _PATTERNS.items():
        dof = len(idx) * n_tags - sum(lev[i] for i in idx)
        dof -= 1.0 if group == "scale" else 0.0  # the common offset, taken out above
        seen[group] = math.sqrt(sum(sq[i] for i in idx) / dof) if dof > 0.5 else 0.0
        seen[group + "_dof"] = max(dof, 0.0)  # how well the residuals know it (error_bound95)
    return seen, mean_scale


def _common_offset_px(common: np.ndarray, w: np.ndarray, J: np.ndarray, A: np.ndarray,
                      mean_scale: float, scale_sigma: float, n_tags: int) -> tuple[float, float, float]:
    """The tags' common radial offset, its standard error and its signed estimate, px per
    corner, from their mean scale coefficient."""
    common_left = 1.0 - float(common @ (w * (J @ (A @ common)))) / float(common @ (w * common))
    mean_se2 = scale_sigma ** 2 / n_tags
    left = max(common_left, 0.1)
    return (float(np.sqrt(max(mean_scale**2 - mean_se2, 0.0))) / 2.0 / left,
            math.sqrt(mean_se2) / 2.0 / left, mean_scale / 2.0 / left)


def reference_terms(obs: TagObservations, T: Transform, res: np.ndarray, J: np.ndarray, rel: np.ndarray,
                    info: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict[str, float],
                                                             np.ndarray]:
    """(terms, seen, A_ros) of ``uncertainty.uncertainty_terms``' propagation, in numpy: the
    kernel's part of it (no frame measures, no motion terms)."""
    n_tags = len(obs)
    w = np.repeat(1.0 / rel**2, 8)
    M, A = _propagation(J, w, info)
    A_ros = A[_ROS_ORDER]
    B = _tag_basis(obs.image_px)
    common = (2.0 * B[:, :, 2]).reshape(-1)
    terms = _per_tag_terms(obs, T, A_ros, B, rel)
    terms.update(_shared_terms(obs, T, A_ros, common))
    seen, mean_scale = _residual_sigmas(res, J, M, B, rel)
    seen["bias_common"], seen["bias_common_se"], seen["bias_common_signed"] = _common_offset_px(
        common, w, J, A, mean_scale, seen["scale"], n_tags)
    seen["mean_scale"] = mean_scale
    return terms, seen, A_ros
