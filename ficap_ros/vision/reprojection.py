"""The tag corners a cap pose is fitted to, and their reprojection under a pose.

``TagObservations`` is the record both the pose solvers (``pose``) and the pose's uncertainty
(``uncertainty``) work on: per tag, its four corners in undistorted pixels and the model's four
corners in the cap frame, in metres. The residuals are ``projection - observation`` per corner
coordinate (u0 v0 u1 v1 ... ), px, and the Jacobian is taken for a left perturbation of the pose,
``(exp(d_theta) R, t + d_t)``: columns d_theta (rad, camera axes), then d_t (m), so a covariance
of the pose is in the camera (parent) frame, as ROS's PoseWithCovariance expects. The joint pose's
observations are square-consistent (``TagObservations.of(..., square=True)``: each tag's corners
moved onto the nearest image of a square, ``square_kernels``), the measured corners kept beside them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pose_kernels import reprojection_rt, tag_errors_px
from ficap_ros.vision.square_kernels import square_tag_corners

__all__ = [
    "TagObservations",
    "undistorted_corners",
    "SQUARE_ITERATIONS",
    "SQUARE_MAX_MOVE_PX",
    "edge_shifts_px",
    "project_px",
    "reprojection_errors_px",
    "residuals_and_jacobian",
    "residuals_and_jacobian_rt",
    "residuals_and_jacobian_moving",
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
        time_s: (T, 4) when each corner was seen, s from the stamp (a rolling shutter's row
            times); None: every corner at the stamp (a global shutter).
        measured_px: (T, 4, 2) the corners as measured where ``image_px`` are their squares'
            images (``square_corners``), px; None: ``image_px`` are the measured corners. The
            pose is fitted to ``image_px``; what each tag's corners say of their own noise (the
            tag weights, the residual-based uncertainty) is read from the measured corners
            (``measured_residuals``): the two degrees of freedom a square lacks are evidence of
            a tag's corner noise though no pose explains them.
    """

    ids: tuple[int, ...]
    image_px: np.ndarray
    model_m: np.ndarray
    K: np.ndarray = field(repr=False)
    time_s: np.ndarray | None = field(default=None, repr=False)
    measured_px: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def of(cls, corners_px: Mapping[int, np.ndarray], model: CapModel, K: np.ndarray,
           time_s: Mapping[int, np.ndarray] | None = None, square: bool = False) -> TagObservations:
        """From undistorted corners (4, 2) per tag id of ``model``, in ascending id order, and
        optionally each corner's time (4,) per id, s. ``square``: fitted to the corners' squares'
        images (``square_corners``), the measured corners kept as ``measured_px``."""
        ids = tuple(sorted(corners_px))
        image_px = np.stack([corners_px[i] for i in ids])
        measured_px = None
        if square and ids:
            measured_px, image_px = image_px, square_tag_corners(
                np.ascontiguousarray(image_px, dtype=np.float64), np.ascontiguousarray(K, dtype=np.float64),
                SQUARE_ITERATIONS, SQUARE_MAX_MOVE_PX)[0]
        return cls(
            ids,
            image_px,
            np.stack([model.corners_of(i) for i in ids]) / 1000.0,
            K,
            None if time_s is None else np.stack([time_s[i] for i in ids]),
            measured_px,
        )

    def subset(self, keep: np.ndarray) -> TagObservations:
        """The tags where the boolean mask ``keep`` (T,) is set."""
        keep = np.asarray(keep, dtype=bool)
        return TagObservations(
            tuple(i for i, k in zip(self.ids, keep) if k), self.image_px[keep], self.model_m[keep], self.K,
            None if self.time_s is None else self.time_s[keep],
            None if self.measured_px is None else self.measured_px[keep],
        )

    def measured_residuals(self, res: np.ndarray) -> np.ndarray:
        """Residuals (8 T,) ``projection - image_px`` of a pose as against the measured corners
        (``measured_px``; the same array where there are none)."""
        if self.measured_px is None:
            return res
        return res + (self.image_px - self.measured_px).reshape(-1)

    def __len__(self) -> int:
        return len(self.ids)


def undistorted_corners(ours: Sequence[TagDetection],
                        camera: CameraModel) -> dict[int, list[np.ndarray]]:
    """The undistorted corners (4, 2) of the model's detected tags, per id (a list: an id may be
    detected twice); corners that do not undistort to finite pixels are left out."""
    groups: dict[int, list[np.ndarray]] = {}
    if ours:
        # One undistortion call for every corner of the frame.
        undistorted = camera.undistort_px(np.concatenate([d.corners_px for d in ours])).reshape(-1, 4, 2)
        finite = np.isfinite(undistorted).all(axis=(1, 2))
        for det, corners, ok in zip(ours, undistorted, finite):
            if ok:
                groups.setdefault(det.tag_id, []).append(corners)
    return groups


#: Gauss-Newton steps of each tag's own pose (``square_kernels``): from its homography's pose they
#: bring the corners within a thousandth of a px of the least-squares optimum.
SQUARE_ITERATIONS = 6
#: The farthest a corner moves onto a square's image, px: a tag whose corners are farther from
#: every square's image (a corner off by far more than noise) keeps them, for the pose's outlier
#: tests to judge.
SQUARE_MAX_MOVE_PX = 1.0


def edge_shifts_px(ours: Sequence[TagDetection], ids: Sequence[int]) -> np.ndarray:
    """The cell fit's edge shift of each of the tags ``ids``, px (NaN: not fitted, or the id was
    detected twice)."""
    shifts: dict[int, float] = {}
    for det in ours:
        shifts[det.tag_id] = float("nan") if det.tag_id in shifts else float(det.edge_shift_px)
    return np.array([shifts.get(i, float("nan")) for i in ids])


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
    """Per-tag RMS reprojection error (T,) in px of corners (T, 4, 2) under pose ``T``: the
    pinhole projection of ``project_px``, each corner's squared distance, the mean of a tag's
    four. The model points are rotated here (numpy), the rest is the compiled
    ``pose_kernels.tag_errors_px`` (the same values to the bit)."""
    X = np.asarray(model_m, dtype=np.float64).reshape(-1, 3) @ T.rotation_matrix.T
    return tag_errors_px(np.ascontiguousarray(X), T.translation_m, np.asarray(K, dtype=np.float64),
                         np.ascontiguousarray(obs_px, dtype=np.float64).reshape(-1, 2))


def residuals_and_jacobian_rt(
    R: np.ndarray, t: np.ndarray, K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) and Jacobian (2N, 6) of the pose (R (3x3), t (3,), m) against corners
    ``image_px`` (..., 2) of the model points ``model_m`` (..., 3), m.

    Rows alternate u and v of each corner; the Jacobian's columns are a left perturbation
    ``(exp(d_theta) R, t + d_t)``: d_theta (rad, camera axes), then d_t (m). The model points
    are rotated here (numpy), the rest is the compiled ``pose_kernels.reprojection_rt``'s (one
    pass over the corners, the same values to the bit).
    """
    X = np.asarray(model_m, dtype=np.float64).reshape(-1, 3) @ np.asarray(R, dtype=np.float64).T
    return reprojection_rt(np.ascontiguousarray(X),
                           np.ascontiguousarray(t, dtype=np.float64).reshape(3),
                           np.ascontiguousarray(K, dtype=np.float64),
                           np.ascontiguousarray(image_px, dtype=np.float64).reshape(-1, 2))


def residuals_and_jacobian(T: Transform, obs: TagObservations) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (8T,) and Jacobian (8T, 6) of ``obs`` at pose ``T`` = T_cam_cap itself."""
    return residuals_and_jacobian_rt(T.rotation_matrix, T.translation_m, obs.K, obs.model_m, obs.image_px)


def _skew(a: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices [a]_x of vectors (N, 3)."""
    out = np.zeros(a.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -a[..., 2], a[..., 1]
    out[..., 1, 0], out[..., 1, 2] = a[..., 2], -a[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -a[..., 1], a[..., 0]
    return out


def rotations_of(rotvecs_rad: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of rotation vectors (N, 3), rad (Rodrigues' formula)."""
    theta = np.linalg.norm(rotvecs_rad, axis=-1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = _skew(rotvecs_rad / safe[:, None])
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c1 = np.where(small, 0.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3) + s * k + c1 * (k @ k)


def moving_points_m(R: np.ndarray, t: np.ndarray, velocity: np.ndarray, model_m: np.ndarray,
                    time_s: np.ndarray, accel: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame positions (N, 3), m, of model points ``model_m`` (..., 3) at their times
    ``time_s`` (...,), s from the stamp, of a cap at pose (R, t) at the stamp moving at
    ``velocity`` (6,): linear m/s, then angular rad/s (camera axes), speeding up at ``accel``
    (6,: m/s^2, rad/s^2, camera axes; None: constant velocity): the motion over ``tau`` is the
    turn ``exp(tau w + tau^2 alpha / 2)`` and the shift ``tau v + tau^2 a / 2``."""
    tau = np.asarray(time_s, dtype=np.float64).reshape(-1)
    turn, shift = _motion_over(tau, velocity, accel)
    Y = model_m.reshape(-1, 3) @ R.T
    E = rotations_of(turn)
    return np.einsum("nij,nj->ni", E, Y) + t + shift


def _motion_over(tau: np.ndarray, velocity: np.ndarray,
                 accel: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) rotation vectors (rad) and (N, 3) shifts (m) of a cap moving at ``velocity`` with
    ``accel`` (None: none) over the times ``tau`` (N,) from the stamp (camera axes)."""
    turn = tau[:, None] * velocity[3:]
    shift = tau[:, None] * velocity[:3]
    if accel is not None:
        half_sq = 0.5 * tau[:, None] ** 2
        turn = turn + half_sq * accel[3:]
        shift = shift + half_sq * accel[:3]
    return turn, shift


def residuals_and_jacobian_moving(
    R: np.ndarray, t: np.ndarray, velocity: np.ndarray, obs: TagObservations,
    accel: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) and Jacobian (2N, 12) of a cap at pose (R, t) at the stamp moving at
    ``velocity`` (6,: linear m/s, angular rad/s, camera axes) over the corners' times
    ``obs.time_s`` (module docstring), speeding up at ``accel`` (``moving_points_m``; a known
    term, no columns of its own: by ``tau / 2`` times the velocity's columns it moves the
    corners).

    Rows alternate u and v of each corner; the columns: the pose's left perturbation (d_theta,
    d_t), then the velocity in twist order, d_v (m/s) and d_w (rad/s). A corner seen at the stamp (time 0) gives the same
    residuals and pose columns as ``residuals_and_jacobian_rt``, and zeros in the velocity's."""
    tau = np.asarray(obs.time_s, dtype=np.float64).reshape(-1)
    phi, shift = _motion_over(tau, velocity, accel)
    Y = obs.model_m.reshape(-1, 3) @ R.T
    E = rotations_of(phi)
    P = np.einsum("nij,nj->ni", E, Y)  # the rotated model points at each corner's time
    p = P + t + shift
    K = obs.K
    fx, fy, s, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    iz = 1.0 / p[:, 2]
    xn, yn = p[:, 0] * iz, p[:, 1] * iz
    u = fx * xn + s * yn + cx
    v = fy * yn + cy
    image = obs.image_px.reshape(-1, 2)
    n = len(p)
    res = np.empty(2 * n)
    res[0::2] = u - image[:, 0]
    res[1::2] = v - image[:, 1]
    G = np.zeros((n, 2, 3))  # d(u, v)/dp
    G[:, 0, 0] = fx * iz
    G[:, 0, 1] = s * iz
    G[:, 0, 2] = -(u - cx) * iz
    G[:, 1, 1] = fy * iz
    G[:, 1, 2] = -(v - cy) * iz
    # dp/d_theta = -[P]_x E; dp/d_w = -[P]_x J_l(phi) tau, phi the turn over the corner's time,
    # J_l to first order (phi is small).
    GP = -G @ _skew(P)
    Jl = np.eye(3) + 0.5 * _skew(phi)
    jac = np.empty((n, 2, 12))
    jac[:, :, 0:3] = GP @ E
    jac[:, :, 3:6] = G
    jac[:, :, 6:9] = G * tau[:, None, None]
    jac[:, :, 9:12] = (GP @ Jl) * tau[:, None, None]
    return res, jac.reshape(2 * n, 12)
