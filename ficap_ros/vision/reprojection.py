"""The tag corners a cap pose is fitted to, and their reprojection under a pose.

``TagObservations`` is the record both the pose solvers (``pose``) and the pose's uncertainty
(``uncertainty``) work on: per tag, its four corners in undistorted pixels and the model's four
corners in the cap frame, in metres. The residuals are ``projection - observation`` per corner
coordinate (u0 v0 u1 v1 ... ), px, and the Jacobian is taken for a left perturbation of the pose,
``(exp(d_theta) R, t + d_t)``: columns d_theta (rad, camera axes), then d_t (m), so a covariance
of the pose is in the camera (parent) frame, as ROS's PoseWithCovariance expects.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform

__all__ = [
    "TagObservations",
    "project_px",
    "reprojection_errors_px",
    "residuals_and_jacobian",
    "residuals_and_jacobian_rt",
    "median",
]


@dataclass(frozen=True)
class TagObservations:
    """Per-tag observations in undistorted pixels with their model corners in metres.

    Attributes:
        ids: tag ids, unique, in the order of the arrays.
        image_px: (T, 4, 2) corners in the undistorted image, px.
        model_m: (T, 4, 3) the same corners on the cap model, cap frame, m.
        K: 3x3 intrinsics of the undistorted image.
    """

    ids: tuple[int, ...]
    image_px: np.ndarray
    model_m: np.ndarray
    K: np.ndarray = field(repr=False)

    @classmethod
    def of(cls, corners_px: Mapping[int, np.ndarray], model: CapModel, K: np.ndarray) -> TagObservations:
        """From undistorted corners (4, 2) per tag id of ``model``, in ascending id order."""
        ids = tuple(sorted(corners_px))
        return cls(
            ids,
            np.stack([corners_px[i] for i in ids]),
            np.stack([model.corners_of(i) for i in ids]) / 1000.0,
            K,
        )

    def subset(self, keep: np.ndarray) -> TagObservations:
        """The tags where the boolean mask ``keep`` (T,) is set."""
        keep = np.asarray(keep, dtype=bool)
        return TagObservations(
            tuple(i for i, k in zip(self.ids, keep) if k), self.image_px[keep], self.model_m[keep], self.K
        )

    def __len__(self) -> int:
        return len(self.ids)


def median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D array, bit for bit: the middle value, or the two middle
    values' sum halved (numpy's mean of the two), sorted as Python floats. A pose takes a few
    medians of a few dozen numbers each, where numpy's median costs more in its set-up than in
    the sort."""
    v = np.asarray(values, dtype=np.float64).ravel()
    n = len(v)
    if n == 0 or not np.isfinite(v).all():
        return float(np.median(v))
    s = sorted(v.tolist())
    k = n // 2
    return s[k] if n % 2 else (s[k - 1] + s[k]) / 2.0


def project_px(K: np.ndarray, T: Transform, points_m: np.ndarray) -> np.ndarray:
    """Pinhole projection (no distortion), px, of points (..., 3) in the cap frame, m, under
    ``T`` = T_cam_cap."""
    p = T.apply(points_m.reshape(-1, 3))
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 1] * p[:, 1] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1).reshape(points_m.shape[:-1] + (2,))


def reprojection_errors_px(obs_px: np.ndarray, K: np.ndarray, T: Transform, model_m: np.ndarray) -> np.ndarray:
    """Per-tag RMS reprojection error (T,) in px of corners (T, 4, 2) under pose ``T``."""
    proj = project_px(K, T, model_m)
    return np.sqrt(np.mean(np.sum((proj - obs_px) ** 2, axis=-1), axis=-1))


def residuals_and_jacobian_rt(
    R: np.ndarray, t: np.ndarray, K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) and Jacobian (2N, 6) of the pose (R (3x3), t (3,), m) against corners
    ``image_px`` (..., 2) of the model points ``model_m`` (..., 3), m.

    Rows alternate u and v of each corner; the Jacobian's columns are a left perturbation
    ``(exp(d_theta) R, t + d_t)``: d_theta (rad, camera axes), then d_t (m).
    """
    X = model_m.reshape(-1, 3) @ R.T  # model points rotated into the camera's axes
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
    # d(u, v)/dp; a left rotation moves a point by d_theta x X, so d(u, v)/d_theta = X x d(u, v)/dp.
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
        rows[:, 0] = x1 * g[:, 2] - x2 * g[:, 1]  # X x g, written out (np.cross is slow on small arrays)
        rows[:, 1] = x2 * g[:, 0] - x0 * g[:, 2]
        rows[:, 2] = x0 * g[:, 1] - x1 * g[:, 0]
        rows[:, 3:] = g
    return res, jac


def residuals_and_jacobian(T: Transform, obs: TagObservations) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (8T,) and Jacobian (8T, 6) of ``obs`` at pose ``T`` = T_cam_cap itself."""
    return residuals_and_jacobian_rt(T.rotation_matrix, T.translation_m, obs.K, obs.model_m, obs.image_px)
