"""Rigid cap pose from the detected tag corners.

Three estimators, chosen by name (``PoseConfig.method``):

``joint`` (default)
    One PnP over every visible corner. Start: the best-supported of SQPnP over all corners and the
    per-tag IPPE poses (a consensus over tags, so one wrong tag cannot spoil the start); then
    MINPACK's Levenberg-Marquardt of the reprojection error (``scipy.optimize.leastsq``, the call
    ``least_squares(method="lm")`` makes), with tag-level outlier rejection: a tag whose RMS
    reprojection error stands far above the others' is dropped and the pose re-solved; a tag the
    image shows partly hidden (``hidden_ids``: ``detection.partly_hidden``) already at twice the
    median tag's. Then each tag is weighted by its corner noise (``uncertainty.reweighted``).
``paper``
    Jha & Busso's method (Fi-Cap, section 3.2): a pose per tag from its four corners (IPPE), the 3-D
    corners rebuilt in the camera frame, Kabsch to the model (``Rotation.align_vectors``), and the
    corners that do not fit the model dropped one by one until the 3-D residual is under a threshold.
``naive``
    The floor we measure against: one SQPnP over all corners, then OpenCV's LM refinement; no
    outlier handling. Not for production use.

Every estimator undistorts the corners first (``CameraModel.undistort_px``), so all lens models
share one pinhole solver, and works in metres (model corners are mm / 1000).

Duplicated ids (a tag seen twice: a reflection, a second cap, a spurious decode) are resolved after
a first pose from the unique tags: the copy that agrees with the pose is kept, or both are dropped.

Covariance and bounds (``CapPose.covariance``, ``rot_err95_deg``, ``trans_err95_mm``): see
``ficap_ros.vision.uncertainty``.

Reliability (``CapPose.reliability``, in [0, 1]) is derived from the rotation bound alone, so it
ranks frames as the bound does: ``0.5 ** (rot_err95_deg / RELIABILITY_HALF_DEG)`` (one half at a
1 deg bound, 0.93 at 0.1 deg), times ``min(1, tags_used / 4)`` (with fewer tags the residuals say
little, and one tag has a mirror solution a first-order covariance does not see).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Container, Sequence

import cv2
import numpy as np
from scipy.optimize import leastsq
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.edges import PREV
from ficap_ros.vision.error_bounds import error_bound95
from ficap_ros.vision.motion import (
    MotionConfig,
    MotionPrior,
    MovingFit,
    corner_times_s,
    moving_pose,
    static_velocity,
)
from ficap_ros.vision.motion_blur import prior_blur_modes
from ficap_ros.vision.reprojection import (
    TagObservations,
    edge_shifts_px,
    median,
    reprojection_errors_px,
    residuals_and_jacobian,
    residuals_and_jacobian_rt,
    undistorted_corners,
)
from ficap_ros.vision.uncertainty import (
    UncertaintyConfig,
    combine_uncertainty,
    reweighted,
    uncertainty_bounds,
    uncertainty_terms,
)

__all__ = [
    "POSE_METHODS",
    "PoseConfig",
    "CapPose",
    "PoseResult",
    "estimate_cap_pose",
    "reliability_score",
    "reprojection_errors_px",
    "RELIABILITY_HALF_DEG",
]


@dataclass(frozen=True)
class PoseConfig:
    """Settings of the pose estimators.

    Attributes:
        method: ``joint``, ``paper`` or ``naive`` (the baseline).
        min_tags: fewest tags for a pose.
        outlier_ratio: ``joint``: a tag is an outlier when its RMS reprojection error exceeds
            ``outlier_ratio`` times the median tag RMS and ``outlier_floor_px``.
        outlier_floor_px: see ``outlier_ratio``.
        hidden_ratio: ``joint``: a tag the image shows partly hidden (``estimate_cap_pose``'s
            ``hidden_ids``) is an outlier when its RMS reprojection error exceeds this times the
            median tag RMS, with no floor (``_hidden_outliers``).
        inlier_px: a tag agrees with a candidate pose (consensus start, duplicate resolution) when
            its RMS reprojection error is below ``max(inlier_px, inlier_fraction * side_px)``.
        inlier_fraction: see ``inlier_px``.
        paper_threshold_mm: ``paper``: trimming stops when the RMS 3-D corner residual is below this.
        paper_min_corners: ``paper``: never trim below this many corners.
        uncertainty: the error sources of the covariance (``UncertaintyConfig``); None: the
            profile of the corner estimator in use (``pipeline.pose_config_for``), the defaults
            when ``estimate_cap_pose`` is called directly.
        motion: the head's motion sizes behind the velocity prior (``motion.MotionConfig``).
        square_tags: ``joint`` with a global shutter: the pose is fitted to each tag's corners
            moved onto the nearest image of a square (``TagObservations.of``), without the part of
            their error no pose explains (``rms_px`` is the rest); the tag weights and the
            residual-based uncertainty still read each tag's noise from its measured corners. A
            rolling shutter's tags are not squares' images (each row sees the cap at its own
            time): they keep their corners.
    """

    method: str = "joint"
    min_tags: int = 1
    outlier_ratio: float = 4.0
    outlier_floor_px: float = 1.0
    hidden_ratio: float = 2.0
    inlier_px: float = 3.0
    inlier_fraction: float = 0.1
    paper_threshold_mm: float = 1.0
    paper_min_corners: int = 4
    uncertainty: UncertaintyConfig | None = None
    motion: MotionConfig = field(default_factory=MotionConfig)
    square_tags: bool = True

    def __post_init__(self) -> None:
        if self.method not in POSE_METHODS:
            raise ConfigError(
                f"unknown pose method {self.method!r}; expected one of {', '.join(POSE_METHODS)}"
            )
        if self.min_tags < 1:
            raise ConfigError(f"min_tags must be >= 1, got {self.min_tags}")
        if self.outlier_ratio <= 1.0:
            raise ConfigError(f"outlier_ratio must be > 1, got {self.outlier_ratio}")
        if not self.hidden_ratio > 1.0:
            raise ConfigError(f"hidden_ratio must be > 1, got {self.hidden_ratio}")


@dataclass(frozen=True)
class CapPose:
    """A cap pose.

    Attributes:
        T_cam_cap: pose of the cap frame C in the camera optical frame (translation in metres).
        tags_detected: model tags detected in the frame (unique ids).
        tags_used: tags kept by the estimator.
        used_ids: their ids, sorted.
        rms_px: RMS reprojection error of the used corners, px (undistorted image).
        covariance: 6x6, ROS order (x, y, z in m; rotation about the camera's x, y, z in rad), of a
            small perturbation ``T = (exp(d_theta) R, t + d_t)`` of ``T_cam_cap``: every error
            source of ``UncertaintyConfig`` propagated through the fit (``vision.uncertainty``);
            finite and positive definite (NaN only for a pose estimated ``with_uncertainty=False``).
        reliability: score in [0, 1] from ``rot_err95_deg`` (module docstring).
        method: the estimator's name.
        rot_err95_deg: predicted 95 % bound of the geodesic rotation error of ``T_cam_cap``, deg.
        trans_err95_mm: predicted 95 % bound of the length of its translation error, mm.
        velocity: the cap's velocity at the stamp where the estimator measures it, else None:
            (6,) ROS twist order in the camera's axes: the cap origin's linear velocity, m/s,
            then the angular velocity, rad/s (``vision.motion``: from the poses before).
        velocity_covariance: its 6x6 covariance (same order), None with ``velocity``.
    """

    T_cam_cap: Transform
    tags_detected: int
    tags_used: int
    used_ids: tuple[int, ...]
    rms_px: float
    covariance: np.ndarray
    reliability: float
    method: str
    rot_err95_deg: float = float("nan")
    trans_err95_mm: float = float("nan")
    velocity: np.ndarray | None = None
    velocity_covariance: np.ndarray | None = None

    @property
    def rotation_sigma_deg(self) -> float:
        """Square root of the largest eigenvalue of the rotation covariance, deg."""
        return _rotation_sigma_deg(self.covariance)


@dataclass(frozen=True)
class PoseResult:
    """An estimator's answer for one frame: a pose, or none with the reason."""

    pose: CapPose | None
    tags_detected: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.pose is not None


# -- the least-squares refinement -------------------------------------------------------------------

#: Machine epsilon: below it a rotation vector is the identity (as ``cv2.Rodrigues`` treats it).
_EPS = float(np.finfo(np.float64).eps)


def _rodrigues(rotvec_rad: Sequence[float]) -> np.ndarray:
    """The rotation matrix (3, 3) of a rotation vector (rad) by Rodrigues' formula,
    ``R = cos(theta) I + (1 - cos(theta)) r r^T + sin(theta) [r]_x`` with ``r`` the unit axis, in
    ``cv2.Rodrigues``' arithmetic term for term (the same matrix, bit for bit), without the
    derivative that call always computes as well. The identity below machine epsilon."""
    x, y, z = rotvec_rad
    theta = math.sqrt(x * x + y * y + z * z)
    if theta < _EPS:
        return np.eye(3)
    c, s = math.cos(theta), math.sin(theta)
    c1 = 1.0 - c
    inv = 1.0 / theta
    x, y, z = x * inv, y * inv, z * inv
    c0 = c * 0.0
    xy, xz, yz = x * y, x * z, y * z
    return np.array([[c + c1 * (x * x) + s * 0.0, c0 + c1 * xy + s * -z, c0 + c1 * xz + s * y],
                     [c0 + c1 * xy + s * z, c + c1 * (y * y) + s * 0.0, c0 + c1 * yz + s * -x],
                     [c0 + c1 * xz + s * -y, c0 + c1 * yz + s * x, c + c1 * (z * z) + s * 0.0]])


def _turned_residuals_and_jacobian(x: np.ndarray, R0: np.ndarray,
                                   obs: TagObservations) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (8T,) and Jacobian (8T, 6) of the pose ``(exp(x[:3]) R0, x[3:])``: x is a left
    turn d_theta (3, rad, camera axes) of the 3x3 rotation R0 and the translation t (3, m)."""
    R = _rodrigues(x[:3].tolist()) @ R0
    return residuals_and_jacobian_rt(R, x[3:], obs.K, obs.model_m, obs.image_px)


def _refine(obs: TagObservations, T0: Transform) -> tuple[Transform, float]:
    """Least-squares reprojection refinement; returns (pose, rms_px).

    MINPACK's Levenberg-Marquardt (lmder through ``scipy.optimize.leastsq``: the call
    ``least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-10,
    max_nfev=50)`` makes, the same iterates and answer without that wrapper's per-call set-up)
    over a left perturbation of the start, ``x = (d_theta, t)``, with the analytic Jacobian.
    The answer's residuals are the ones MINPACK ends with (no further evaluation).

    Raises:
        ValueError: non-finite residuals at the start, or fewer residuals than unknowns (as
            ``least_squares`` raises them).
    """
    R0 = T0.rotation_matrix
    x0 = np.concatenate([np.zeros(3), T0.translation_m])

    # MINPACK asks for the residuals and then the Jacobian at the same x: compute both once.
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _turned_residuals_and_jacobian(x, R0, obs)
        return cache[key]

    r0 = both(x0)[0]
    if not np.all(np.isfinite(r0)):
        raise ValueError("Residuals are not finite in the initial point.")
    if len(r0) < len(x0):
        raise ValueError("Method 'lm' doesn't work when the number of residuals is less than "
                         "the number of variables.")
    # full_output: the final residuals, and no warning when MINPACK stops at maxfev.
    x, _cov, info, _message, _status = leastsq(
        lambda x: both(x)[0], x0, Dfun=lambda x: both(x)[1], full_output=True, col_deriv=False,
        ftol=1e-10, xtol=1e-10, gtol=1e-8, maxfev=50, factor=100.0, diag=None)
    return T0.turned(x[:3], x[3:]), float(np.sqrt(np.mean(info["fvec"] ** 2) * 2.0))


def _rotation_sigma_deg(cov: np.ndarray) -> float:
    block = cov[3:, 3:]
    if not np.all(np.isfinite(block)):
        return float("inf")
    return float(np.degrees(np.sqrt(max(np.max(np.linalg.eigvalsh(block)), 0.0))))


#: The 95 % rotation bound at which reliability is one half, deg.
RELIABILITY_HALF_DEG = 1.0


def reliability_score(tags_used: int, rot_err95_deg: float) -> float:
    """Reliability in [0, 1] from the rotation bound; the mapping is in the module docstring."""
    if not np.isfinite(rot_err95_deg) or tags_used < 1:
        return 0.0
    # Fewer than four tags: a weak geometry whose residuals say little (one tag leaves 2 degrees of
    # freedom) and, for one tag, IPPE's mirror solution, which a first-order covariance cannot see.
    score = 0.5 ** (rot_err95_deg / RELIABILITY_HALF_DEG) * min(1.0, tags_used / 4.0)
    return float(np.clip(score, 0.0, 1.0))


def _tag_pose_candidates(K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray) -> list[Transform]:
    """Both IPPE solutions of one tag, as cap poses (T_cam_cap)."""
    half = TAG_SIDE_MM / 2000.0
    square = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            square, image_px.reshape(4, 1, 2), K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
    except cv2.error:
        return []
    # T_tag_cap from the model: tag frame has x along TL->TR, y along BL->TL (IPPE_SQUARE's layout).
    T_cap_tag = _tag_frame(model_m)
    T_tag_cap = T_cap_tag.inv()
    out = []
    for k in range(n):
        T_cam_tag = Transform.from_rvec_tvec(rvecs[k], tvecs[k])
        out.append(T_cam_tag * T_tag_cap)
    return out


def _tag_frame(corners_m: np.ndarray) -> Transform:
    """T_cap_tag for a tag with corners (4, 3) (TL, TR, BR, BL) in the cap frame, m.

    Tag frame: origin at the centre, x toward the right edge, y toward the top edge, z out of the
    printed face toward the viewer (IPPE_SQUARE's object layout).
    """
    c = corners_m.mean(axis=0)
    x = (corners_m[1] - corners_m[0]) + (corners_m[2] - corners_m[3])
    y = (corners_m[0] - corners_m[3]) + (corners_m[1] - corners_m[2])
    x /= np.linalg.norm(x)
    y -= x * (x @ y)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return Transform(Rotation.from_matrix(np.stack([x, y, z], axis=1)), c)


def _side_px(image_px: np.ndarray) -> np.ndarray:
    """Mean side length of each tag (T,) in px."""
    return np.mean(np.linalg.norm(image_px - image_px[:, PREV], axis=-1), axis=-1)



def _inlier_threshold(obs: TagObservations, config: PoseConfig) -> np.ndarray:
    return np.maximum(config.inlier_px, config.inlier_fraction * _side_px(obs.image_px))


def _in_front(obs: TagObservations, T: Transform) -> bool:
    z = T.apply(obs.model_m.reshape(-1, 3))[:, 2]
    return bool(np.all(z > 1e-3))


def _consensus_start(obs: TagObservations, config: PoseConfig) -> tuple[Transform, np.ndarray] | None:
    """The candidate pose most tags agree with, and the tags that agree (boolean mask)."""
    threshold = _inlier_threshold(obs, config)
    candidates: list[Transform] = []
    if len(obs) >= 2:
        ok, rvec, tvec = cv2.solvePnP(
            obs.model_m.reshape(-1, 1, 3), obs.image_px.reshape(-1, 1, 2), obs.K, None,
            flags=cv2.SOLVEPNP_SQPNP,
        )
        if ok:
            T = Transform.from_rvec_tvec(rvec, tvec)
            inliers = reprojection_errors_px(obs.image_px, obs.K, T, obs.model_m) < threshold
            # The common case: every tag agrees with the all-corner solution; no search needed.
            if np.all(inliers) and _in_front(obs, T):
                return T, inliers
            candidates.append(T)
    for i in range(len(obs)):
        candidates.extend(_tag_pose_candidates(obs.K, obs.model_m[i], obs.image_px[i]))
    best: tuple[int, float, Transform, np.ndarray] | None = None
    for T in candidates:
        if not _in_front(obs, T):
            continue
        err = reprojection_errors_px(obs.image_px, obs.K, T, obs.model_m)
        inliers = err < threshold
        count = int(np.sum(inliers))
        cost = float(np.sum(np.minimum(err, threshold) ** 2))
        if best is None or count > best[0] or (count == best[0] and cost < best[1]):
            best = (count, cost, T, inliers)
    if best is None or best[0] == 0:
        return None
    return best[2], best[3]


# -- estimators -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Solution:
    T: Transform
    used: TagObservations
    rms_px: float


def _hidden_outliers(err: np.ndarray, median_px: float, hidden: np.ndarray, n_used: int,
                     config: PoseConfig) -> np.ndarray:
    """(T,) the tags the image shows partly hidden whose RMS reprojection error ``err`` exceeds
    ``config.hidden_ratio`` times the median ``median_px`` of the ``n_used`` tags in use.

    The general rule (``outlier_ratio`` times the median, at least ``outlier_floor_px``) keeps a
    tag whose corners are somewhat worse than the others': its floor guards against dropping a
    tag on the residuals alone, which scatter (a fully visible tag's RMS may stand well above
    its frame's median). A tag whose quiet zone something covers (``detection.partly_hidden``)
    has a cause for a large residual: its fits take the occluder's edge for the tag's, so twice
    the median is enough, and no floor. Its weight in the pose (``tag_noise_px``) would shrink,
    but its corners would still pull on the pose and count in ``rms_px``. Only with four or more
    tags in use (fewer say too little about which is off)."""
    if n_used < 4 or not hidden.any():
        return np.zeros(len(err), dtype=bool)
    return hidden & (err > config.hidden_ratio * median_px)


def _static_errors(obs: TagObservations, T: Transform) -> np.ndarray:
    return reprojection_errors_px(obs.image_px, obs.K, T, obs.model_m)  # per tag, px


def _solve_joint(obs: TagObservations, config: PoseConfig, start: Transform | None = None,
                 hidden: np.ndarray | None = None, fit: MovingFit | None = None) -> _Solution | str:
    """The joint estimator; ``fit``: a moving cap's (rolling shutter), None: the static fit."""
    refine = _refine if fit is None else fit.refine
    errors = _static_errors if fit is None else fit.errors
    begin = None
    if start is not None and _in_front(obs, start):
        # A predicted pose (tracking) that every tag agrees with replaces the consensus search.
        if fit is not None:
            fit.begin(start)
        inliers = errors(obs, start) < _inlier_threshold(obs, config)
        if np.all(inliers):
            begin = (start, inliers)
    if begin is None:
        begin = _consensus_start(obs, config)
    if begin is None:
        return "no pose agrees with the detected tags"
    T, inliers = begin
    if fit is not None and fit.velocity is None:
        fit.begin(T)
    # ``used`` is always ``obs.subset(current)`` (obs's ids are unique): the mask is kept, not
    # rebuilt from the ids each round.
    current = np.array(inliers, dtype=bool)
    used = obs.subset(current)
    # Tags that disagreed with the start may agree with the refined pose: re-admit, then trim.
    for _ in range(5):
        if len(used) < config.min_tags:
            return f"{len(used)} tag(s) left after outlier rejection, need {config.min_tags}"
        T, rms = refine(used, T)
        err_all = errors(obs, T)
        median_px = median(err_all[current])
        limit = max(config.outlier_ratio * median_px, config.outlier_floor_px)
        keep = err_all <= limit
        if hidden is not None:
            keep &= ~_hidden_outliers(err_all, median_px, hidden, int(current.sum()), config)
        if not np.any(keep):
            return "every tag is an outlier"
        if np.array_equal(keep, current):
            return _Solution(T, used, rms)  # refined on exactly the tags it keeps
        # Drop only the worst offender per round, so one bad tag cannot drag good ones out.
        bad = current & ~keep
        if np.any(bad):
            worst = int(np.argmax(np.where(bad, err_all, -np.inf)))
            current[worst] = False
            readmit = ~current & keep
            readmit[worst] = False
            current |= readmit
        else:
            current |= keep
        used = obs.subset(current)
    T, rms = refine(used, T)
    return _Solution(T, used, rms)


def _kabsch(model_m: np.ndarray, camera_m: np.ndarray) -> Transform:
    """Rigid T_cam_cap minimising ||T model - camera|| (``Rotation.align_vectors`` is Kabsch)."""
    mc = model_m.mean(axis=0)
    cc = camera_m.mean(axis=0)
    rotation, _ = Rotation.align_vectors(camera_m - cc, model_m - mc)
    return Transform(rotation, cc - rotation.apply(mc))


def _solve_paper(obs: TagObservations, config: PoseConfig) -> _Solution | str:
    # Per-tag pose: of IPPE's two solutions keep the one with the lower reprojection error, as
    # AprilTag does; rebuild the tag's 3-D corners in the camera frame from it.
    rebuilt = []
    for i in range(len(obs)):
        best = None
        for T_cam_cap in _tag_pose_candidates(obs.K, obs.model_m[i], obs.image_px[i]):
            err = reprojection_errors_px(obs.image_px[i : i + 1], obs.K, T_cam_cap, obs.model_m[i : i + 1])[0]
            if best is None or err < best[0]:
                best = (err, T_cam_cap)
        if best is None:
            return f"no pose for tag {obs.ids[i]}"
        rebuilt.append(best[1].apply(obs.model_m[i]))
    cam_pts = np.concatenate(rebuilt)
    model_pts = obs.model_m.reshape(-1, 3)
    keep = np.ones(len(model_pts), dtype=bool)
    threshold_m = config.paper_threshold_mm / 1000.0
    while True:
        T = _kabsch(model_pts[keep], cam_pts[keep])
        resid = np.linalg.norm(T.apply(model_pts) - cam_pts, axis=1)
        rms = float(np.sqrt(np.mean(resid[keep] ** 2)))
        if rms <= threshold_m or keep.sum() <= max(config.paper_min_corners, 4):
            break
        keep[int(np.argmax(np.where(keep, resid, -np.inf)))] = False
    # A tag is used when any of its corners survived; report reprojection statistics on those.
    tag_keep = keep.reshape(-1, 4).any(axis=1)
    used = obs.subset(tag_keep)
    res, _ = residuals_and_jacobian(T, used)
    return _Solution(T, used, float(np.sqrt(np.mean(res**2) * 2.0)))


def _solve_naive(obs: TagObservations, config: PoseConfig) -> _Solution | str:
    obj = obs.model_m.reshape(-1, 1, 3)
    img = obs.image_px.reshape(-1, 1, 2)
    if len(obs) >= 2:
        ok, rvec, tvec = cv2.solvePnP(obj, img, obs.K, None, flags=cv2.SOLVEPNP_SQPNP)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, obs.K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return "solvePnP failed"
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, obs.K, None, rvec, tvec)
    T = Transform.from_rvec_tvec(rvec, tvec)
    res, _ = residuals_and_jacobian(T, obs)
    return _Solution(T, obs, float(np.sqrt(np.mean(res**2) * 2.0)))


_SOLVERS: dict[str, Callable[[TagObservations, PoseConfig], _Solution | str]] = {
    "joint": _solve_joint,
    "paper": _solve_paper,
    "naive": _solve_naive,
}
POSE_METHODS = tuple(_SOLVERS)


def _resolve_duplicates(
    groups: dict[int, list[np.ndarray]], model: CapModel, K: np.ndarray, config: PoseConfig
) -> dict[int, np.ndarray]:
    """One corner set per id: unique ids as they are; for a duplicated id, the copy that agrees
    with the pose of the unique tags (the best one under the inlier threshold), else neither."""
    unique = {i: c[0] for i, c in groups.items() if len(c) == 1}
    dupes = {i: c for i, c in groups.items() if len(c) > 1}
    if not dupes:
        return unique
    if unique:
        obs = TagObservations.of(unique, model, K)
        start = _consensus_start(obs, config)
        if start is not None:
            T, _ = start
            for tag_id, copies in dupes.items():
                model_m = model.corners_of(tag_id)[None] / 1000.0
                stack = np.stack(copies)
                err = np.array([reprojection_errors_px(c[None], K, T, model_m)[0] for c in stack])
                threshold = max(config.inlier_px, config.inlier_fraction * float(_side_px(stack).mean()))
                best = int(np.argmin(err))
                if err[best] < threshold:
                    unique[tag_id] = stack[best]
    return unique


def _solve(obs: TagObservations, config: PoseConfig, start: Transform | None,
           hidden_ids: Container[int], fit: MovingFit | None = None) -> _Solution | str:
    """The configured estimator's solution, or the reason there is none. ``fit``: the moving
    cap's fit of a rolling shutter (``joint`` only)."""
    if config.method == "joint":
        hidden = np.array([i in hidden_ids for i in obs.ids], dtype=bool) if hidden_ids else None
        return _solve_joint(obs, config, start, hidden, fit)
    return _SOLVERS[config.method](obs, config)


def _uncertainty(used: TagObservations, T: Transform, tag_sigma_px: np.ndarray | None,
                 edge_shift_px: np.ndarray, at: tuple[np.ndarray, np.ndarray],
                 config: UncertaintyConfig,
                 blur: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, float, float]:
    """(covariance, rot_err95_deg, trans_err95_mm) of the pose ``T`` fitted to ``used``."""
    terms, seen = uncertainty_terms(used, T, tag_sigma_px, edge_shift_px, at=at, shared_modes=blur)
    covariance = combine_uncertainty(terms, seen, config)
    rot95, trans95 = error_bound95(covariance, *uncertainty_bounds(terms, seen, config, covariance))
    return covariance, rot95, trans95


def _cap_pose(solution: _Solution, ours: Sequence[TagDetection], tags_detected: int,
              config: PoseConfig, with_uncertainty: bool,
              blur: dict[str, np.ndarray] | None = None) -> CapPose:
    """The reported pose of a solution: tag weights (``joint``), its rms and uncertainty
    (``blur``: the motion blur's shared corner errors, ``motion_blur.blur_modes``)."""
    uncertainty = config.uncertainty if config.uncertainty is not None else UncertaintyConfig()
    used_n = len(solution.used)
    T = solution.T
    tag_sigma = None
    if config.method == "joint" and uncertainty.weight_tags:
        T, tag_sigma = reweighted(solution.used, T)
    res, J = residuals_and_jacobian(T, solution.used)
    rms = float(np.sqrt(np.mean(res**2) * 2.0))
    if with_uncertainty:
        covariance, rot95, trans95 = _uncertainty(solution.used, T, tag_sigma,
                                                  edge_shifts_px(ours, solution.used.ids),
                                                  (solution.used.measured_residuals(res), J),
                                                  uncertainty, blur)
    else:
        covariance = np.full((6, 6), np.nan)
        rot95 = trans95 = float("nan")
    return CapPose(
        T_cam_cap=T,
        tags_detected=tags_detected,
        tags_used=used_n,
        used_ids=solution.used.ids,
        rms_px=rms,
        covariance=covariance,
        reliability=reliability_score(used_n, rot95),
        method=config.method,
        rot_err95_deg=rot95,
        trans_err95_mm=trans95,
    )


def _moving_cap_pose(solution: _Solution, fit: MovingFit, ours: Sequence[TagDetection],
                     tags_detected: int, config: PoseConfig, with_uncertainty: bool,
                     exposure_s: float) -> CapPose:
    """The reported pose of a moving cap's solution (rolling shutter, ``motion.moving_pose``)."""
    uncertainty = config.uncertainty if config.uncertainty is not None else UncertaintyConfig()
    used = solution.used
    m = moving_pose(fit, used, solution.T, edge_shifts_px(ours, used.ids), uncertainty,
                    with_uncertainty, exposure_s)
    return CapPose(
        T_cam_cap=m.T_cam_cap, tags_detected=tags_detected, tags_used=len(used),
        used_ids=used.ids, rms_px=m.rms_px, covariance=m.covariance,
        reliability=reliability_score(len(used), m.rot_err95_deg), method=config.method,
        rot_err95_deg=m.rot_err95_deg, trans_err95_mm=m.trans_err95_mm, velocity=m.velocity,
        velocity_covariance=m.velocity_covariance)


def estimate_cap_pose(
    detections: Sequence[TagDetection],
    model: CapModel,
    camera: CameraModel,
    config: PoseConfig | None = None,
    start: Transform | None = None,
    with_uncertainty: bool = True,
    hidden_ids: Container[int] = (),
    timing: CameraTiming | None = None,
    prior: MotionPrior | None = None,
) -> PoseResult:
    """Estimate T_cam_cap from detections of the model's tags.

    Args:
        detections: tags in the (distorted) image; ids outside the model are ignored.
        model: the cap model (corners in mm).
        camera: intrinsics of the image the detections come from.
        config: estimator settings.
        start: a predicted pose (tracking), ``joint`` only: when every tag agrees with it, it
            replaces the consensus search as the refinement's start. The answer does not depend on
            it beyond the optimiser's tolerance.
        with_uncertainty: build the covariance and its bounds (``uncertainty_terms``). False for
            a pose only its ``T_cam_cap`` and tags are wanted of (the tracker's intermediate
            poses): ``T_cam_cap``, the tags and ``rms_px`` are the same, but ``covariance``,
            ``rot_err95_deg`` and ``trans_err95_mm`` are NaN and ``reliability`` is 0. Never for
            a pose that is reported.
        hidden_ids: ids of tags the image shows partly hidden (``detection.partly_hidden``),
            ``joint`` only: such a tag is dropped at a lower residual than others
            (``_hidden_outliers``).
        timing: the camera's timing; a rolling shutter (``CameraTiming.rolling``) and the
            ``joint`` method: each corner is seen at its row's time and the pose at the stamp is
            solved with the cap's velocity (``motion.MovingFit``). None: a global shutter.
        prior: what the frames before say about the velocity (``motion.MotionPrior``: the
            tracker's); None: no past frame. A global-shutter pose with a past pose gets the
            prior's velocity (``motion.static_velocity``); the pose itself does not depend on it.
    Returns:
        A ``PoseResult``: a ``CapPose``, or ``pose=None`` with the reason.
    """
    config = config or PoseConfig()
    ours = [d for d in detections if d.tag_id in model]
    groups = undistorted_corners(ours, camera)
    tags_detected = len(groups)
    if tags_detected == 0:
        return PoseResult(None, 0, "no tag of the model detected")
    resolved = _resolve_duplicates(groups, model, camera.K, config)
    if len(resolved) < config.min_tags:
        return PoseResult(
            None, tags_detected,
            f"{len(resolved)} usable tag(s) (after resolving duplicated ids), need {config.min_tags}",
        )
    moving = timing is not None and timing.rolling and config.method == "joint"
    fit = MovingFit(prior or MotionPrior(config=config.motion)) if moving else None
    times = corner_times_s(resolved, camera, timing) if fit is not None else None  # type: ignore[arg-type]
    obs = TagObservations.of(resolved, model, camera.K, times, config.square_tags and config.method == "joint"
                             and not moving)
    solution = _solve(obs, config, start, hidden_ids, fit)
    if isinstance(solution, str):
        return PoseResult(None, tags_detected, solution)
    if not _in_front(solution.used, solution.T):
        return PoseResult(None, tags_detected, "pose puts the cap behind the camera")
    if fit is not None:
        return PoseResult(_moving_cap_pose(solution, fit, ours, tags_detected, config,
                                           with_uncertainty, timing.exposure_ms * 1e-3),  # type: ignore[union-attr]
                          tags_detected, "")
    blur = prior_blur_modes(prior, solution.used, solution.T, timing)
    pose = _cap_pose(solution, ours, tags_detected, config, with_uncertainty, blur)
    velocity = None if prior is None else static_velocity(prior, pose.T_cam_cap, pose.covariance)
    if velocity is not None:
        pose = replace(pose, velocity=velocity[0], velocity_covariance=velocity[1])
    return PoseResult(pose, tags_detected, "")
