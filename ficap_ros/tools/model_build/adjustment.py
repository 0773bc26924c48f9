"""The bundle adjustment of the as-built model: unknowns, residuals, their sparse Jacobian, the
solve, and the Gauss-Newton covariance of the built corners.

Parameters: every tag's rotation vector and centre in the cap frame (mm), the global edge offset
(px, when fitted), every frame's camera pose (rotation vector, translation mm). Residuals: the
reprojection errors of the undistorted corners (px) through ``edge_shift_px``, the priors toward
each plate's nominal place and orientation, and (``anchor_size``) the size anchor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.model_build.config import BuildConfig
from ficap_ros.tools.model_build.geometry import (
    corners_from_params,
    edge_shift_px,
    rms_radius,
    tag_frames,
)

__all__ = ["Problem", "SIZE_SIGMA", "Priors", "initial_values", "unpack", "project", "residuals",
           "n_params", "jacobian", "solve", "observation_rms_px", "rotate_covariance",
           "structure_covariance"]


@dataclass
class Problem:
    """Observations in flat arrays: one row per tag observation (frame, tag, 4 corners)."""

    obs_frame: np.ndarray  # (M,) index into frames
    obs_tag: np.ndarray  # (M,) index into model tags
    obs_px: np.ndarray  # (M, 4, 2) undistorted corners
    intr: np.ndarray  # (M, 4) fx, fy, cx, cy of the observation's frame
    n_frames: int
    n_tags: int

    def subset(self, keep: np.ndarray) -> Problem:
        return Problem(self.obs_frame[keep], self.obs_tag[keep], self.obs_px[keep], self.intr[keep],
                        self.n_frames, self.n_tags)


#: Relative sigma of the size anchor: stiff enough to hold the size to a few parts per million,
#: soft enough to keep the problem well conditioned.
SIZE_SIGMA = 1e-4


@dataclass(frozen=True)
class Priors:
    """Where hand assembly puts each plate: nominal centres (mm) and orientations, with their
    sigmas (mm, rad)."""

    centres_mm: np.ndarray  # (N, 3) nominal tag centres
    rotations: Rotation  # (N,) nominal tag orientations
    sigma_mm: float
    sigma_rad: float

    @property
    def radius_mm(self) -> float:
        return rms_radius(self.centres_mm)


def initial_values(nominal: CapModel, poses: Sequence[Transform],
                   config: BuildConfig) -> tuple[np.ndarray, Priors]:
    """The start of the adjustment and its priors: the nominal tag frames, the edge offset of the
    config (when fitted), the camera poses from the nominal model (translations in mm)."""
    r_tags, centres = tag_frames(nominal.corners_mm)
    priors = Priors(centres.copy(), r_tags, config.assembly_sigma_mm,
                    np.radians(config.assembly_sigma_deg))
    x_tags = np.hstack([r_tags.as_rotvec(), centres])
    x_frames = np.array([np.hstack([T.rvec, T.translation_m * 1000.0]) for T in poses])
    x_offset = [config.edge_offset_px] if config.fit_edge_offset else []
    x0 = np.concatenate([x_tags.reshape(-1), x_offset, x_frames.reshape(-1)])
    return x0, priors


def unpack(x: np.ndarray, p: Problem, config: BuildConfig) -> tuple[np.ndarray, float, np.ndarray]:
    """(tag parameters (N, 6): rotation vector, centre mm; edge offset px; frame parameters (F, 6):
    rotation vector, translation mm) of a parameter vector."""
    n_tag = 6 * p.n_tags
    tags = x[:n_tag].reshape(p.n_tags, 6)
    if config.fit_edge_offset:
        offset, frames = float(x[n_tag]), x[n_tag + 1:]
    else:
        offset, frames = config.edge_offset_px, x[n_tag:]
    return tags, offset, frames.reshape(p.n_frames, 6)


def project(tags: np.ndarray, frames: np.ndarray, p: Problem) -> np.ndarray:
    """Pinhole projection (M, 4, 2) of every observed tag's corners in its frame, px."""
    corners_cap = corners_from_params(tags[:, :3], tags[:, 3:])  # (N, 4, 3)
    r_cam = Rotation.from_rotvec(frames[:, :3]).as_matrix()  # (F, 3, 3)
    pts = corners_cap[p.obs_tag]  # (M, 4, 3)
    cam = np.einsum("mij,mkj->mki", r_cam[p.obs_frame], pts) + frames[p.obs_frame, None, 3:]
    z = cam[..., 2]
    u = p.intr[:, None, 0] * cam[..., 0] / z + p.intr[:, None, 2]
    v = p.intr[:, None, 1] * cam[..., 1] / z + p.intr[:, None, 3]
    return np.stack([u, v], axis=-1)


def residuals(x: np.ndarray, p: Problem, priors: Priors, config: BuildConfig) -> np.ndarray:
    """Corner residuals (px, 8 per observation), then the priors' and the size anchor's rows."""
    tags, offset, frames = unpack(x, p, config)
    predicted = edge_shift_px(project(tags, frames, p), offset)
    res = predicted - p.obs_px
    # Priors: where hand assembly puts a plate (anchors the cap's size and the gauge).
    prior_t = (tags[:, 3:] - priors.centres_mm) / priors.sigma_mm
    prior_r = (priors.rotations.inv() * Rotation.from_rotvec(tags[:, :3])).as_rotvec() / priors.sigma_rad
    parts = [res.reshape(-1), prior_t.reshape(-1), prior_r.reshape(-1)]
    if config.anchor_size:
        size = rms_radius(tags[:, 3:]) / priors.radius_mm - 1.0
        parts.append(np.array([size / SIZE_SIGMA]))
    return np.concatenate(parts)


def n_params(p: Problem, config: BuildConfig) -> int:
    """Length of the parameter vector."""
    return 6 * (p.n_tags + p.n_frames) + int(config.fit_edge_offset)


def jacobian(x: np.ndarray, p: Problem, priors: Priors, config: BuildConfig) -> csr_matrix:
    """Sparse Jacobian of ``residuals``: forward differences in 13 grouped evaluations, the size
    anchor's row analytic.

    Tags never share a residual row with each other, nor frames with each other, so the k-th
    parameter of every tag (or every frame) is stepped at once (the usual column grouping of a
    bundle adjustment). The size anchor's row touches every tag centre; left to a generic grouped
    difference it would split the centres into 3N groups (6x the evaluations), so it is written
    out: d r / d t_i = (t_i - mean t) / (N r).
    """
    n_tag6 = 6 * p.n_tags
    frame_base = n_tag6 + int(config.fit_edge_offset)
    m8 = 8 * len(p.obs_tag)
    f0 = residuals(x, p, priors, config)
    obs_rows = np.arange(m8).reshape(-1, 8)
    rows, cols, vals = [], [], []

    def stepped(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(h, change of the residuals) with the parameters ``idx`` stepped by h together."""
        h = 1.49e-8 * np.maximum(1.0, np.abs(x[idx]))
        xs = x.copy()
        xs[idx] += h
        return h, residuals(xs, p, priors, config) - f0

    def add_observation_rows(idx: np.ndarray, owner: np.ndarray, h: np.ndarray,
                             df: np.ndarray) -> None:
        # ``owner``: the tag (or frame) of each observation, whose ``idx`` parameter moves its rows.
        rows.append(obs_rows.reshape(-1))
        cols.append(np.repeat(idx[owner], 8))
        vals.append((df[:m8].reshape(-1, 8) / h[owner, None]).reshape(-1))

    for k in range(6):
        # Every tag's k-th parameter: observation rows and the tag's own prior rows.
        idx = 6 * np.arange(p.n_tags) + k
        h, df = stepped(idx)
        add_observation_rows(idx, p.obs_tag, h, df)
        prior_rows = m8 + (3 * np.arange(p.n_tags)[:, None] + np.arange(3)[None, :])
        if k >= 3:  # a centre: its own translation-prior row
            pr = m8 + 3 * np.arange(p.n_tags) + (k - 3)
            rows.append(pr)
            cols.append(idx)
            vals.append(df[pr] / h)
        else:  # a rotation: the three rotation-prior rows of its tag
            pr = (prior_rows + 3 * p.n_tags).reshape(-1)
            rows.append(pr)
            cols.append(np.repeat(idx, 3))
            vals.append(df[pr] / np.repeat(h, 3))
        # Every frame's k-th parameter: observation rows only.
        idx = frame_base + 6 * np.arange(p.n_frames) + k
        h, df = stepped(idx)
        add_observation_rows(idx, p.obs_frame, h, df)
    if config.fit_edge_offset:
        h, df = stepped(np.array([n_tag6]))
        rows.append(np.arange(m8))
        cols.append(np.full(m8, n_tag6))
        vals.append(df[:m8] / h[0])
    n_rows = len(f0)
    if config.anchor_size:
        t = x[:n_tag6].reshape(-1, 6)[:, 3:]
        radius = rms_radius(t)
        grad = (t - t.mean(axis=0)) / (len(t) * radius) / priors.radius_mm / SIZE_SIGMA
        rows.append(np.full(3 * p.n_tags, n_rows - 1))
        cols.append((6 * np.arange(p.n_tags)[:, None] + 3 + np.arange(3)[None, :]).reshape(-1))
        vals.append(grad.reshape(-1))
    return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_rows, n_params(p, config))).tocsr()


def solve(p: Problem, x0: np.ndarray, priors: Priors, config: BuildConfig):  # type: ignore[no-untyped-def]
    """``least_squares`` (TRF, robust loss, the sparse Jacobian) from ``x0``."""
    return least_squares(
        residuals, x0, jac=jacobian, args=(p, priors, config),
        method="trf", loss=config.loss, f_scale=config.f_scale_px, x_scale="jac",
        # Tolerances of 1e-8: tighter ones (scipy's defaults) change no result in the 5th digit
        # but cost many more evaluations.
        max_nfev=config.max_nfev, xtol=1e-8, ftol=1e-8, gtol=1e-8,
    )


def observation_rms_px(x: np.ndarray, p: Problem, priors: Priors, config: BuildConfig) -> np.ndarray:
    """RMS corner residual of each observation, px."""
    res = residuals(x, p, priors, config)[: 8 * len(p.obs_tag)]
    return np.sqrt(np.mean(res.reshape(-1, 4, 2) ** 2, axis=(1, 2)) * 2.0)


def rotate_covariance(cov: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Covariance (K, 3, K, 3) of points, expressed after rotating every point by ``R``."""
    return np.einsum("ab,ibjc,dc->iajd", R, cov, R)


def structure_covariance(solution, p: Problem, config: BuildConfig,  # type: ignore[no-untyped-def]
                          corners_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Covariance of the built corners (N*4, 3, N*4, 3), mm^2, with the whole cap's rigid motion
    projected out, and the edge offset's variance (px^2).

    Gauss-Newton covariance sigma^2 (J^T J)^-1 of the structure (tag poses and edge offset), the
    camera poses eliminated by the Schur complement (each frame's 6x6 block is independent).
    sigma^2 is the residual variance per degree of freedom. The rigid motion of the whole cap is
    only held by the priors and is removed by the alignment to the nominal, so it is projected out.
    """
    J = solution.jac.tocsr() if hasattr(solution.jac, "tocsr") else np.asarray(solution.jac)
    n_struct = 6 * p.n_tags + int(config.fit_edge_offset)
    H = (J.T @ J)
    H = H.toarray() if hasattr(H, "toarray") else np.asarray(H)
    A = H[:n_struct, :n_struct]
    B = H[:n_struct, n_struct:]
    S = A.copy()
    for f in range(p.n_frames):
        sl = slice(6 * f, 6 * f + 6)
        D = H[n_struct:, n_struct:][sl, sl]
        Bf = B[:, sl]
        S -= Bf @ np.linalg.solve(D, Bf.T)
    cov_struct = np.linalg.pinv(S, hermitian=True)
    m_obs = 8 * len(p.obs_tag)
    dof = max(m_obs - H.shape[0], 1)
    res = solution.fun[:m_obs]
    sigma2 = float(np.sum(res * res) / dof)
    cov_struct *= sigma2
    offset_var = float(cov_struct[-1, -1]) if config.fit_edge_offset else 0.0

    # Corners as a linear function of the tag parameters (numerical, per tag: 6 columns).
    n = p.n_tags
    Jc = np.zeros((n * 12, n_struct))
    tags = solution.x[: 6 * n].reshape(n, 6)
    for i in range(n):
        for k in range(6):
            step = 1e-6 if k < 3 else 1e-4
            hi, lo = tags[i].copy(), tags[i].copy()
            hi[k] += step
            lo[k] -= step
            dc = (corners_from_params(hi[None, :3], hi[None, 3:]) -
                  corners_from_params(lo[None, :3], lo[None, 3:]))[0] / (2 * step)
            Jc[12 * i: 12 * i + 12, 6 * i + k] = dc.reshape(-1)
    cov = Jc @ cov_struct @ Jc.T
    # Project out infinitesimal rigid motions of all corners (the gauge).
    pts = corners_mm.reshape(-1, 3)
    pts = pts - pts.mean(axis=0)
    G = np.zeros((len(pts) * 3, 6))
    for a in range(3):
        G[a::3, a] = 1.0
        e = np.zeros(3)
        e[a] = 1.0
        G[:, 3 + a] = np.cross(e, pts).reshape(-1)
    P = np.eye(len(G)) - G @ np.linalg.pinv(G)
    cov = P @ cov @ P.T
    return cov.reshape(n * 4, 3, n * 4, 3), offset_var
