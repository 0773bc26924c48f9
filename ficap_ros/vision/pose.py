"""Rigid cap pose from the detected tag corners.

Three estimators, chosen by name (``PoseConfig.method``):

``joint`` (default)
    One PnP over every visible corner. Start: the best-supported of SQPnP over all corners and the
    per-tag IPPE poses (a consensus over tags, so one wrong tag cannot spoil the start); then
    Levenberg-Marquardt (MINPACK's, as ``scipy.optimize.least_squares`` runs it) of the reprojection error,
    with tag-level outlier rejection: a tag whose RMS reprojection error stands far above the
    others' is dropped and the pose re-solved; a tag the image shows partly hidden
    (``hidden_ids``: ``detection.partly_hidden``) already at twice the median tag's.
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

Tag weights (``joint``, ``UncertaintyConfig.weight_tags``): each tag's corner noise is estimated
from its own residuals with the frame's median as a prior (``tag_noise_px``), and the pose takes one
weighted Gauss-Newton step from the unweighted optimum (``_reweighted``): oblique, dark or
second-read tags with worse corners count less. On every ``ficap synth`` condition and blender_dev
set but the as-built one this lowers the median rotation error (docs/benchmarks.md).

Covariance (``CapPose.covariance``, 6x6, ROS order, camera axes): first-order propagation through
the weighted least-squares fit (``A = (J^T W J)^-1 J^T W`` maps corner displacements to pose
changes) of
    the residual-based term: each tag's corner residuals split into orthonormal patterns (shift,
        scale, turn, shears, projective: how misplaced plates, radial corner bias and noise move a
        tag's corners), each pattern group's variance pooled over the frame's tags with the
        degrees of freedom the fit took from it subtracted (its leverage), shared out among the
        tags in proportion to their corner noise, plus the tags' common radial offset;
    the corner errors neighbouring tags share, which the pose absorbs without residuals: uneven
        light (a spotlight) moves every tag's edges toward its darker side; its measure is how the
        tags' fitted edge shifts vary across the cap (``light_gradient_px``), scaled into noise the
        pose absorbs and into a shift of every tag along its foreshortening (the depth's mode);
    the floors of ``UncertaintyConfig`` added to it: independent corner noise, radial corner bias
        (per tag and common), a shift along the foreshortening, each plate shifted and turned as a
        rigid whole against the cap model, the intrinsics (principal point, focal length).
Pooling by pattern matters: a tag's corner errors are not independent (a blurred border moves all
four corners inward), and treating them as such misjudges which pose directions they disturb.
``rot_err95_deg`` / ``trans_err95_mm`` are the 95 % quantiles of the rotation angle / translation
length under the covariance (``error_bound95``), with two things the covariance alone does not say
(``uncertainty_bounds``): the tags' common radial offset is measured (its sign and size, from the
residuals), so its effect on the pose is a mean error, not a spread (the covariance holds its square,
as a mean squared error must); and the residual-based sigmas are estimates pooled from a few dozen
coefficients, so the bound is the predictive (F, Welch-Satterthwaite degrees of freedom) quantile,
not the Gaussian one.

Reliability (``CapPose.reliability``, in [0, 1]) is derived from the rotation bound alone, so it
ranks frames as the bound does: ``0.5 ** (rot_err95_deg / RELIABILITY_HALF_DEG)`` (one half at a
1 deg bound, 0.93 at 0.1 deg), times ``min(1, tags_used / 4)`` (with fewer tags the residuals say
little, and one tag has a mirror solution a first-order covariance does not see).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, Container, Sequence

import cv2
import numpy as np
from scipy.optimize import least_squares

try:  # least_squares' own MINPACK LM, called directly (see _refine); private, so optional
    from scipy.optimize._minpack import _lmder
except ImportError:  # another scipy (e.g. a distribution's in an apt + colcon install)
    _lmder = None
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel
from ficap_ros.geometry.transform import Transform, compose, from_rotvec
from ficap_ros.vision.detector import TagDetection

__all__ = [
    "POSE_METHODS",
    "PoseConfig",
    "CapPose",
    "PoseResult",
    "estimate_cap_pose",
    "reliability_score",
    "UncertaintyConfig",
    "CORNER_ESTIMATORS",
    "uncertainty_terms",
    "combine_uncertainty",
    "uncertainty_sources",
    "uncertainty_bounds",
    "error_bound95",
    "reprojection_errors_px",
]


@dataclass(frozen=True)
class UncertaintyConfig:
    """How the pose covariance is built: the residual-based term, the terms for corner errors that
    neighbouring tags share (which the pose absorbs without residuals), and the floors (1-sigma).

    The residual-based term carries what each frame's corners show (noise, per-tag corner bias,
    misplaced plates: ``uncertainty_terms``), tag by tag in proportion to each tag's own corner
    noise (``tag_noise_px``). What residuals cannot show is a corner error shared by neighbouring
    tags: the pose absorbs it and leaves no residual. Its measurable cause on ``ficap synth``
    frames is uneven light (spotlights, clipping): the tone-curve edge shift that each tag's cell
    fit measures (``TagDetection.edge_shift_px``) then varies smoothly across the cap, and the
    edges of each tag move toward its darker side, a field the pose absorbs. Its size is the
    frame's ``light_gradient_px`` (spread of a plane fitted to the tags' edge shifts over their
    image positions); ``light_gradient_gain`` turns it into corner noise the pose absorbs, and
    ``light_gradient_tilt_gain`` into a shift of every tag along its foreshortening (the
    projected normal, times sin of the view angle), the mode that moves the depth.

    The gains and ``residual_inflation`` were calibrated on ``ficap synth`` drives only (realistic
    chain, 540p/1080p x neutral/high/low, 60 frames each, seeds 100-122): the combination with the
    smallest bounds whose rotation and translation bounds cover >= 90 % in every condition; then
    checked, not fitted, on a second noise realisation of those drives and on blender_dev
    (docs/benchmarks.md, "Calibrated uncertainty"). Re-calibrated after the cell fit took one edge
    shift per boundary direction (``edge_shift_px`` is their mean): gains 0.5 / 0.3 -> 0.3 / 0.35,
    inflation and floors unchanged (with 0.5 / 0.3, 540p high's translation bound covered 88 %;
    the lower noise gain sharpens the rotation bounds under spotlights).

    The floors guarantee that no pose is ever "exact" and state what residuals cannot estimate.

    Profiles per corner estimator (``for_corners``): the defaults are the profile of the default
    cell-edge corners (``edge``). The tag-level photometric corner fit (``photometric``:
    ``DetectorConfig(edge_photometric=True)``, ``--photometric``, node ``detector.photometric``)
    leaves much less of the shift along the foreshortening under uneven light, and the same synth
    calibration grid picks ``light_gradient_tilt_gain`` 0.1 for it (0.3 / 1.0 for the others, as
    the defaults; held-out noise seeds agree). ``pipeline.FrameProcessor`` uses the profile of its
    detector's corner estimator when the pose's uncertainty is not set (``PoseConfig.uncertainty``
    None; docs/benchmarks.md, "Calibrated uncertainty with photometric corners").

    Attributes:
        corner_noise_px: independent corner noise, px (an edge fit over many 8-bit samples is
            limited to a few thousandths of a pixel by quantisation).
        corner_bias_px: radial offset of a tag's corners toward or away from its centre (blur and
            tone curve move dark borders), independent per tag, px.
        corner_bias_common_px: the same offset shared by every tag of a frame, px.
        model_mm, model_deg: each tag plate's placement on the built cap against the model, per
            axis (shift, mm; turn about the plate centre, deg). 0 by default: misplaced plates
            show in the residuals (blender_dev's as-built cap, ~1 mm / 1 deg per plate, is covered
            without a floor); raise them when the cap may have changed since its model was made.
        principal_point_px, focal_rel: intrinsics error (principal point per axis, px; focal
            length, relative). 0 by default: CameraInfo says nothing of it, rendered intrinsics
            are exact, and a constant intrinsics error is a constant rotation offset that a
            frontal calibration absorbs in the head angles.
        residual_inflation: factor (>= 1) on the residual-based sigmas.
        light_gradient_gain: corner noise absorbed by the pose per px of ``light_gradient_px``.
        light_gradient_tilt_gain: shared shift of the tags along their foreshortening per px of
            ``light_gradient_px``.
        tilt_shift_px: floor for that shared shift, px at a tag seen edge-on. 0 by default: on
            ``ficap synth`` drives it is -0.003 to +0.006 px outside the spotlights;
            blender_dev's neutral renders show +0.02 to +0.06 px, which no residual reveals and
            which moves the depth by up to ~0.45 mm. Its measured cause: the corner fit's bias
            under the lens blur on small foreshortened cells (2-3 px at 540p), about doubled by a
            lamp at the camera lighting each oblique face unevenly; ``ficap synth`` at
            blender_dev's poses and chains shows about half of it, so no synth-calibrated value
            covers it without widening 1080p's bounds past 3x (docs/benchmarks.md, "Calibrated
            uncertainty" and "Uneven light across a face"). Set it for a camera whose tags are
            small and blurred under a light beside the lens.
        weight_tags: weight each tag in the ``joint`` pose by its corner noise
            (``tag_noise_px``): one weighted Gauss-Newton step from the unweighted optimum.
    """

    corner_noise_px: float = 0.002
    corner_bias_px: float = 0.002
    corner_bias_common_px: float = 0.002
    model_mm: float = 0.0
    model_deg: float = 0.0
    principal_point_px: float = 0.0
    focal_rel: float = 0.0
    residual_inflation: float = 1.0
    light_gradient_gain: float = 0.3
    light_gradient_tilt_gain: float = 0.35
    tilt_shift_px: float = 0.0
    weight_tags: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.residual_inflation) and self.residual_inflation >= 1.0):
            raise ConfigError("residual_inflation must be >= 1")
        values = (self.corner_noise_px, self.corner_bias_px, self.corner_bias_common_px,
                  self.model_mm, self.model_deg, self.principal_point_px, self.focal_rel,
                  self.light_gradient_gain, self.light_gradient_tilt_gain, self.tilt_shift_px)
        if not all(np.isfinite(v) and v >= 0 for v in values):
            raise ConfigError("uncertainty sigmas and gains must be finite and >= 0")
        if self.corner_noise_px <= 0:
            raise ConfigError("corner_noise_px must be > 0 (no pose is exact)")

    @classmethod
    def for_corners(cls, corners: str = "edge") -> UncertaintyConfig:
        """The synth-calibrated profile for a corner estimator (``CORNER_ESTIMATORS``): ``edge``
        (the cell-edge fit and every other ``corner_refine``: the defaults) or ``photometric``.

        Raises:
            ConfigError: unknown corner estimator.
        """
        if corners not in _CORNER_PROFILES:
            raise ConfigError(f"unknown corner estimator {corners!r}; expected one of "
                              f"{', '.join(CORNER_ESTIMATORS)}")
        return cls(**_CORNER_PROFILES[corners])


#: ``UncertaintyConfig.for_corners``: the fields each corner estimator's profile changes from the
#: defaults (the ``edge`` profile), from ``bench_uncertainty.py --photometric --grid``.
_CORNER_PROFILES: dict[str, dict[str, float]] = {
    "edge": {},
    "photometric": {"light_gradient_tilt_gain": 0.1},
}
CORNER_ESTIMATORS = tuple(_CORNER_PROFILES)


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
            source of ``UncertaintyConfig`` propagated through the fit (module docstring); finite
            and positive definite (NaN only for a pose estimated ``with_uncertainty=False``).
        reliability: score in [0, 1] from ``rot_err95_deg`` (module docstring).
        method: the estimator's name.
        rot_err95_deg: predicted 95 % bound of the geodesic rotation error of ``T_cam_cap``, deg.
        trans_err95_mm: predicted 95 % bound of the length of its translation error, mm.
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


# -- geometry helpers -----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Observations:
    """Per-tag observations in undistorted pixels with their model corners in metres."""

    ids: tuple[int, ...]
    image_px: np.ndarray  # (T, 4, 2)
    model_m: np.ndarray  # (T, 4, 3)
    K: np.ndarray = field(repr=False)

    def subset(self, keep: np.ndarray) -> _Observations:
        keep = np.asarray(keep, dtype=bool)
        return _Observations(
            tuple(i for i, k in zip(self.ids, keep) if k), self.image_px[keep], self.model_m[keep], self.K
        )

    def __len__(self) -> int:
        return len(self.ids)


def _median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D array, bit for bit (the middle value, or the two
    middle values' sum halved, as numpy's mean of the two), at a tenth of its ~25 us: a pose takes
    three medians of a few dozen numbers."""
    v = np.asarray(values, dtype=np.float64).ravel()
    n = len(v)
    if n == 0 or not np.isfinite(v).all():
        return float(np.median(v))
    s = sorted(v.tolist())
    k = n // 2
    return s[k] if n % 2 else (s[k - 1] + s[k]) / 2.0


def _project(K: np.ndarray, T: Transform, points_m: np.ndarray) -> np.ndarray:
    """Pinhole projection (no distortion) of points (..., 3) in the cap frame."""
    p = T.apply(points_m.reshape(-1, 3))
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 1] * p[:, 1] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=-1).reshape(points_m.shape[:-1] + (2,))


def reprojection_errors_px(obs_px: np.ndarray, K: np.ndarray, T: Transform, model_m: np.ndarray) -> np.ndarray:
    """Per-tag RMS reprojection error (T,) in px of corners (T, 4, 2) under pose ``T``."""
    proj = _project(K, T, model_m)
    return np.sqrt(np.mean(np.sum((proj - obs_px) ** 2, axis=-1), axis=-1))


def _residuals_and_jacobian(
    x: np.ndarray, R0: np.ndarray, K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) and Jacobian (2N, 6) for x = (d_theta (3, rad, camera axes), t (3, m)).

    The pose is ``R = exp(d_theta) R0`` (R0 a 3x3 matrix), translation ``t``; perturbing on the
    left keeps the covariance in the camera (parent) frame, as ROS's PoseWithCovariance expects.
    """
    R = cv2.Rodrigues(np.ascontiguousarray(x[:3]))[0] @ R0
    return _residuals_and_jacobian_at(R, x[3:], K, model_m, image_px)


def _residuals_and_jacobian_at(
    R: np.ndarray, t: np.ndarray, K: np.ndarray, model_m: np.ndarray, image_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) and Jacobian (2N, 6) of the pose (R, t) for a perturbation
    ``(exp(d_theta) R, t + d_t)``: columns d_theta (rad, camera axes), then d_t (m)."""
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


def _at(T: Transform, obs: _Observations) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and Jacobian at pose ``T`` itself (d_theta = 0)."""
    return _residuals_and_jacobian_at(T.rotation_matrix, T.translation_m, obs.K, obs.model_m, obs.image_px)


def _refine(obs: _Observations, T0: Transform) -> tuple[Transform, float]:
    """Least-squares reprojection refinement; returns (pose, rms_px).

    MINPACK Levenberg-Marquardt (``lmder``, as ``scipy.optimize.least_squares(method="lm")`` runs
    it) over a left perturbation of the start, ``x = (d_theta, t)``, with the analytic Jacobian.
    The answer's residuals are the ones MINPACK ends with (no further evaluation).
    """
    R0 = T0.rotation_matrix
    x0 = np.concatenate([np.zeros(3), T0.translation_m])

    # MINPACK asks for the residuals and then the Jacobian at the same x: compute both once.
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = _residuals_and_jacobian(x, R0, obs.K, obs.model_m, obs.image_px)
        return cache[key]

    def fun(x: np.ndarray) -> np.ndarray:
        return both(x)[0]

    def jac(x: np.ndarray) -> np.ndarray:
        return both(x)[1]

    # MINPACK's lmder called as ``least_squares(fun, x0, jac=jac, method="lm", xtol=1e-10,
    # ftol=1e-10, max_nfev=50)`` calls it (scipy 1.17: gtol 1e-8, factor 100, diag None for its
    # default x_scale 'jac'), without that wrapper's argument handling and memoising layers: the
    # same iterates and answer, ~0.25 ms less a pose (a tracked frame solves once or twice). Its
    # two checks of the start are kept: the same errors for a start it would refuse.
    r0 = fun(x0)
    if not np.all(np.isfinite(r0)):
        raise ValueError("Residuals are not finite in the initial point.")
    if len(r0) < len(x0):
        raise ValueError("Method 'lm' doesn't work when the number of residuals is less than "
                         "the number of variables.")
    x, res = _minimise(fun, jac, x0)
    T = Transform(compose(from_rotvec(x[:3]), T0.rotation), x[3:])
    return T, float(np.sqrt(np.mean(res**2) * 2.0))


def _direct_lmder_works() -> bool:
    """This scipy's private lmder takes scipy 1.17's arguments: tried once on a line fit, so a
    TypeError raised later by our own residuals is never taken for a changed signature."""
    try:
        x, info, _status = _lmder(lambda x: x - 1.0, lambda x: np.eye(2), np.zeros(2), (), True, False,
                                  1e-10, 1e-10, 1e-8, 50, 100.0, None)
        return bool(np.allclose(x, 1.0)) and "fvec" in info
    except (TypeError, ValueError):
        return False


#: Whether ``_minimise`` calls lmder directly; None until its first call decides.
_DIRECT_LMDER: bool | None = None


def _minimise(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray],
              x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, residuals at x) of ``least_squares(fun, x0, jac=jac, method="lm", xtol=1e-10,
    ftol=1e-10, max_nfev=50)``: through MINPACK's lmder directly where this scipy has it with the
    signature scipy 1.17 gives it (``test_pose_solver`` checks the two agree bit for bit), else
    through ``least_squares`` itself."""
    global _DIRECT_LMDER
    if _DIRECT_LMDER is None:
        _DIRECT_LMDER = _lmder is not None and _direct_lmder_works()
    if _DIRECT_LMDER:
        x, info, _status = _lmder(fun, jac, x0.copy(), (), True, False, 1e-10, 1e-10, 1e-8, 50,
                                  100.0, None)
        return x, info["fvec"]
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=50)
    return sol.x, sol.fun


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
    return np.mean(np.linalg.norm(image_px - np.roll(image_px, 1, axis=1), axis=-1), axis=-1)


def _inlier_threshold(obs: _Observations, config: PoseConfig) -> np.ndarray:
    return np.maximum(config.inlier_px, config.inlier_fraction * _side_px(obs.image_px))


def _in_front(obs: _Observations, T: Transform) -> bool:
    z = T.apply(obs.model_m.reshape(-1, 3))[:, 2]
    return bool(np.all(z > 1e-3))


def _consensus_start(obs: _Observations, config: PoseConfig) -> tuple[Transform, np.ndarray] | None:
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
    used: _Observations
    rms_px: float


def _hidden_outliers(err: np.ndarray, median: float, hidden: np.ndarray, n_used: int,
                     config: PoseConfig) -> np.ndarray:
    """(T,) the tags the image shows partly hidden whose RMS reprojection error ``err`` exceeds
    ``config.hidden_ratio`` times the ``median`` of the ``n_used`` tags in use.

    The general rule (``outlier_ratio`` times the median, at least ``outlier_floor_px``) keeps a
    tag whose corners are 0.3-1 px off among tags at 0.1-0.2 px: its floor guards against dropping
    a tag on the residuals alone, which scatter (on ``ficap synth`` one fully visible tag in ten
    lies 1.5-2.5 times above its frame's median). A tag whose quiet zone something covers
    (``detection.partly_hidden``) has a cause for a large residual: its fits take the occluder's
    edge for the tag's, so twice the median is enough, and no floor. Its weight in the pose
    (``tag_noise_px``) would shrink, but its corners would still pull on the pose and count in
    ``rms_px``. Only with four or more tags in use (fewer say too little about which is off)."""
    if n_used < 4 or not hidden.any():
        return np.zeros(len(err), dtype=bool)
    return hidden & (err > config.hidden_ratio * median)


def _solve_joint(obs: _Observations, config: PoseConfig, start: Transform | None = None,
                 hidden: np.ndarray | None = None) -> _Solution | str:
    begin = None
    if start is not None and _in_front(obs, start):
        # A predicted pose (tracking) that every tag agrees with replaces the consensus search.
        inliers = reprojection_errors_px(obs.image_px, obs.K, start, obs.model_m) < _inlier_threshold(obs, config)
        if np.all(inliers):
            begin = (start, inliers)
    if begin is None:
        begin = _consensus_start(obs, config)
    if begin is None:
        return "no pose agrees with the detected tags"
    T, inliers = begin
    # ``used`` is always ``obs.subset(current)`` (obs's ids are unique): the mask is kept, not
    # rebuilt from the ids (np.isin, ~30 us a round).
    current = np.array(inliers, dtype=bool)
    used = obs.subset(current)
    # Tags that disagreed with the start may agree with the refined pose: re-admit, then trim.
    for _ in range(5):
        if len(used) < config.min_tags:
            return f"{len(used)} tag(s) left after outlier rejection, need {config.min_tags}"
        T, rms = _refine(used, T)
        err_all = reprojection_errors_px(obs.image_px, obs.K, T, obs.model_m)
        median = _median(err_all[current])
        limit = max(config.outlier_ratio * median, config.outlier_floor_px)
        keep = err_all <= limit
        if hidden is not None:
            keep &= ~_hidden_outliers(err_all, median, hidden, int(current.sum()), config)
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
    T, rms = _refine(used, T)
    return _Solution(T, used, rms)


def _kabsch(model_m: np.ndarray, camera_m: np.ndarray) -> Transform:
    """Rigid T_cam_cap minimising ||T model - camera|| (``Rotation.align_vectors`` is Kabsch)."""
    mc = model_m.mean(axis=0)
    cc = camera_m.mean(axis=0)
    rotation, _ = Rotation.align_vectors(camera_m - cc, model_m - mc)
    return Transform(rotation, cc - rotation.apply(mc))


def _solve_paper(obs: _Observations, config: PoseConfig) -> _Solution | str:
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
    res, _ = _at(T, used)
    return _Solution(T, used, float(np.sqrt(np.mean(res**2) * 2.0)))


def _solve_naive(obs: _Observations, config: PoseConfig) -> _Solution | str:
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
    res, _ = _at(T, obs)
    return _Solution(T, obs, float(np.sqrt(np.mean(res**2) * 2.0)))


_SOLVERS: dict[str, Callable[[_Observations, PoseConfig], _Solution | str]] = {
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
        obs = _make_obs(unique, model, K)
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


def _make_obs(corners: dict[int, np.ndarray], model: CapModel, K: np.ndarray) -> _Observations:
    ids = tuple(sorted(corners))
    return _Observations(
        ids,
        np.stack([corners[i] for i in ids]),
        np.stack([model.corners_of(i) for i in ids]) / 1000.0,
        K,
    )


def estimate_cap_pose(
    detections: Sequence[TagDetection],
    model: CapModel,
    camera: CameraModel,
    config: PoseConfig | None = None,
    start: Transform | None = None,
    with_uncertainty: bool = True,
    hidden_ids: Container[int] = (),
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
        with_uncertainty: build the covariance and its bounds (``uncertainty_terms``, about
            0.5 ms a pose). False for a pose only its ``T_cam_cap`` and tags are wanted of (the
            tracker's intermediate poses): ``T_cam_cap``, the tags and ``rms_px`` are the same,
            but ``covariance``, ``rot_err95_deg`` and ``trans_err95_mm`` are NaN and
            ``reliability`` is 0. Never for a pose that is reported.
        hidden_ids: ids of tags the image shows partly hidden (``detection.partly_hidden``),
            ``joint`` only: such a tag is dropped at a lower residual than others
            (``_hidden_outliers``).
    Returns:
        A ``PoseResult``: a ``CapPose``, or ``pose=None`` with the reason.
    """
    config = config or PoseConfig()
    uncertainty = config.uncertainty if config.uncertainty is not None else UncertaintyConfig()
    K = camera.K
    groups: dict[int, list[np.ndarray]] = {}
    ours = [d for d in detections if d.tag_id in model]
    if ours:
        # One undistortion call for every corner of the frame.
        undistorted = camera.undistort_px(np.concatenate([d.corners_px for d in ours])).reshape(-1, 4, 2)
        finite = np.isfinite(undistorted).all(axis=(1, 2))
        for det, corners, ok in zip(ours, undistorted, finite):
            if ok:
                groups.setdefault(det.tag_id, []).append(corners)
    tags_detected = len(groups)
    if tags_detected == 0:
        return PoseResult(None, 0, "no tag of the model detected")
    resolved = _resolve_duplicates(groups, model, K, config)
    if len(resolved) < config.min_tags:
        return PoseResult(
            None, tags_detected,
            f"{len(resolved)} usable tag(s) (after resolving duplicated ids), need {config.min_tags}",
        )
    obs = _make_obs(resolved, model, K)
    if config.method == "joint":
        hidden = np.array([i in hidden_ids for i in obs.ids], dtype=bool) if hidden_ids else None
        solution = _solve_joint(obs, config, start, hidden)
    else:
        solution = _SOLVERS[config.method](obs, config)
    if isinstance(solution, str):
        return PoseResult(None, tags_detected, solution)
    if not _in_front(solution.used, solution.T):
        return PoseResult(None, tags_detected, "pose puts the cap behind the camera")
    used_n = len(solution.used)
    T = solution.T
    tag_sigma = None
    if config.method == "joint" and uncertainty.weight_tags:
        T, tag_sigma = _reweighted(solution.used, T)
    res, J = _at(T, solution.used)
    rms = float(np.sqrt(np.mean(res**2) * 2.0))
    if with_uncertainty:
        # The cell fit's edge shift of each used tag (NaN: not fitted, or the id was duplicated).
        shifts: dict[int, float] = {}
        for det in ours:
            shifts[det.tag_id] = float("nan") if det.tag_id in shifts else float(det.edge_shift_px)
        edge_shift = np.array([shifts.get(i, float("nan")) for i in solution.used.ids])
        terms, seen = uncertainty_terms(solution.used, T, tag_sigma, edge_shift, at=(res, J))
        covariance = combine_uncertainty(terms, seen, uncertainty)
        rot95, trans95 = error_bound95(covariance, *uncertainty_bounds(terms, seen, uncertainty,
                                                                       covariance))
    else:
        covariance = np.full((6, 6), np.nan)
        rot95 = trans95 = float("nan")
    pose = CapPose(
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
    return PoseResult(pose, tags_detected, "")


# -- calibrated uncertainty ------------------------------------------------------------------------


#: Per-tag corner patterns (columns of ``_tag_basis``) grouped as the residuals are pooled.
_PATTERNS = {"shift": [0, 1], "scale": [2], "turn": [3], "shear": [4, 5], "projective": [6, 7]}
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
    return Q[:, :, :8]


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


def tag_noise_px(obs: _Observations, T: Transform) -> np.ndarray:
    """Per-tag corner noise estimate (tags,), px: the tag's own RMS reprojection residual and the
    frame's median tag RMS added in quadrature.

    What makes one tag's corners worse than another's (oblique view, small size, blur, a dark or
    clipped plate, no cell-edge fit, a tag added by the search's second reading) shows in its own
    residuals; a tag's 8 residuals are a noisy estimate of it (and the fit absorbed a share), so
    the frame's median is added as a prior: a tag with residuals at the median gets sqrt(2) times
    them, one far above the median its own. On every ``ficap synth`` condition and every
    blender_dev set but the as-built one, weighting the tags by it lowers the median rotation error
    (docs/benchmarks.md, "Calibrated uncertainty")."""
    return _tag_noise(_at(T, obs)[0], len(obs))


def _tag_noise(res: np.ndarray, n_tags: int) -> np.ndarray:
    rms = np.sqrt(np.mean(res.reshape(n_tags, 8) ** 2, axis=1))
    floor = max(_median(rms), 1e-6)
    return np.sqrt(rms**2 + floor**2)


def _reweighted(obs: _Observations, T: Transform) -> tuple[Transform, np.ndarray]:
    """The pose with each tag weighted by its corner noise (``tag_noise_px``), and that noise.

    One Gauss-Newton step of the weighted reprojection error from the unweighted optimum: the
    weights change the pose by a few hundredths of a degree, where the problem is linear (a second
    step moves it by under 1 % of the first). With fewer than four tags the residuals say too
    little about which tag is worse: equal weights."""
    n_tags = len(obs)
    if n_tags < 4:
        return T, np.ones(n_tags)
    res, J = _at(T, obs)
    sigma = _tag_noise(res, n_tags)
    w = np.repeat(1.0 / sigma**2, 8)
    try:
        dx = -np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * res))
    except np.linalg.LinAlgError:
        return T, sigma
    if not np.all(np.isfinite(dx)):
        return T, sigma
    return Transform(compose(from_rotvec(dx[:3]), T.rotation), T.translation_m + dx[3:]), sigma


def light_gradient_px(edge_shift_px: np.ndarray, centres_px: np.ndarray) -> float:
    """How unevenly the light moves the tags' edges across the cap, px: the spread (standard
    deviation over the tags) of a plane fitted to the tags' measured edge shifts
    (``TagDetection.edge_shift_px``) over their image positions. The smooth part only: a tag's own
    edge shift scatters with its noise and view angle, a spotlight's gradient is shared by its
    neighbours. 0 with fewer than six fitted tags (too few to tell a gradient from scatter)."""
    es = np.asarray(edge_shift_px, dtype=float)
    ok = np.isfinite(es)
    if ok.sum() < 6:
        return 0.0
    c = np.asarray(centres_px, dtype=float)[ok]
    c = (c - c.mean(axis=0)) / max(float(np.ptp(c, axis=0).max()), 1e-9)
    X = np.column_stack([np.ones(len(c)), c])
    # The normal equations (3 x 3; the columns are centred and scaled to about 1, so they are
    # as well conditioned as X), not lstsq's SVD; a degenerate layout (tags on a line) as lstsq.
    try:
        coef = np.linalg.solve(X.T @ X, X.T @ es[ok])
    except np.linalg.LinAlgError:
        coef, *_ = np.linalg.lstsq(X, es[ok], rcond=None)
    return float(np.std(X @ coef))


def _model_geometry(obs: _Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the used tags' model corners: centres (tags, 3), unit outward normals (tags, 3) and, per
    corner, the cross products e_k x (corner - its tag's centre) (4 * tags, 3, 3): cached on the
    corners' bytes (a tracked cap's frames use the same tags frame after frame)."""
    return _model_geometry_of(obs.model_m.tobytes(), len(obs))


@lru_cache(maxsize=64)
def _model_geometry_of(model_key: bytes, n_tags: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    model_m = np.frombuffer(model_key, dtype=np.float64).reshape(n_tags, 4, 3)
    centres = model_m.mean(axis=1)  # (tags, 3) cap frame, m
    a, b = model_m[:, 1] - model_m[:, 0], model_m[:, 3] - model_m[:, 0]
    normal = np.cross(a, b)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    lever = model_m.reshape(-1, 3) - np.repeat(model_m.mean(axis=1), 4, axis=0)
    cross = np.cross(np.eye(3)[None], lever[:, None])
    for x in (centres, normal, cross):
        x.setflags(write=False)
    return centres, normal, cross


def _tilt_mode(obs: _Observations, T: Transform) -> np.ndarray:
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


def uncertainty_terms(
    obs: _Observations, T: Transform, tag_sigma_px: np.ndarray | None = None,
    edge_shift_px: np.ndarray | None = None,
    at: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """What the covariance is built from.

    Args:
        obs: the tags the pose used.
        T: the pose.
        tag_sigma_px: per-tag corner noise (``tag_noise_px``) when the pose weighted its tags by
            it (``_reweighted``); None: equal weights. It sets the fit's weights and each tag's
            share of the residual-based variance (a tag with twice the noise gets four times the
            variance in every pattern).
        edge_shift_px: per tag, the edge shift its cell fit measured (NaN: not fitted); None:
            unknown (``light_gradient`` 0).
        at: ``_at(T, obs)`` when the caller has it already (``estimate_cap_pose`` computes it
            for ``rms_px``): the same residuals and Jacobian, not computed twice.

    Returns:
        terms: per error source, the pose covariance (6x6, ROS order) that one unit of its sigma
            causes, by first-order propagation through the (weighted) fit
            (``A = (J^T W J)^-1 J^T W``): each residual pattern group of ``_PATTERNS`` (1 px per
            pattern coordinate for a tag of median noise, scaled by the tag's relative noise,
            independent per tag), ``noise`` (1 px, every coordinate independent), ``bias``
            (1 px radial at every corner, independent per tag), ``bias_common`` (the same for
            all tags), ``model_t`` / ``model_r`` (each plate shifted 1 mm / turned 1 deg about
            each cap axis), ``principal_point`` (1 px per axis), ``focal`` (relative 1),
            ``tilt`` (every tag shifted along its foreshortening, ``_tilt_mode``, 1 px edge-on).
        seen: what the residuals show: per pattern group the sigma of its coefficients (each
            tag's divided by its relative noise) pooled over the tags, less the share the fit
            absorbed (the weighted hat matrix's leverage of the group), and ``bias_common``, the
            tags' mean radial offset (px per corner), scaled back by the share of it the fit left
            in the residuals; and ``light_gradient`` (``light_gradient_px``), px; per pattern
            group also ``<group>_dof``, the degrees of freedom its sigma was pooled from (the
            bounds widen for a sigma estimated from few, ``uncertainty_bounds``).
    """
    res, J = _at(T, obs) if at is None else at
    n_tags = len(obs)
    n = 4 * n_tags
    if tag_sigma_px is None:
        rel = np.ones(n_tags)
    else:
        rel = np.asarray(tag_sigma_px, dtype=float) / max(_median(tag_sigma_px), 1e-12)
    w = np.repeat(1.0 / rel**2, 8)  # weights per residual coordinate
    try:
        M = np.linalg.inv(J.T @ (w[:, None] * J))
    except np.linalg.LinAlgError:
        M = np.full((6, 6), np.inf)  # combine_uncertainty turns this into "unknown"
    A = M @ (J.T * w)  # (6, 2n): pose change per corner coordinate displacement
    # Rows in ROS order up front: every term below is then in ROS order as computed.
    A_ros = A[_ROS_ORDER]
    A_tag = A_ros.reshape(6, n_tags, 8).transpose(1, 0, 2)  # (tags, 6, 8)

    K = obs.K
    R = T.rotation_matrix
    Xc = obs.model_m.reshape(-1, 3) @ R.T + T.translation_m  # corners in the camera frame
    iz = 1.0 / Xc[:, 2]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    uv = obs.image_px.reshape(-1, 2)
    G = np.zeros((n, 2, 3))  # d(u, v)/d(point in the camera frame)
    G[:, 0, 0] = fx * iz
    G[:, 0, 1] = s * iz
    G[:, 0, 2] = -(fx * Xc[:, 0] + s * Xc[:, 1]) * iz * iz
    G[:, 1, 1] = fy * iz
    G[:, 1, 2] = -fy * Xc[:, 1] * iz * iz
    GR = G @ R  # d(u, v)/d(point in the cap frame)

    B = _tag_basis(obs.image_px)
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
    radial = 2.0 * B[:, :, 2]  # 1 px radial at each corner (the pattern has norm 1 over 4 corners)
    terms["bias"] = 4.0 * per_mode[2]
    terms["model_t"] = per_mode[8:11].sum(axis=0)
    terms["model_r"] = per_mode[11:14].sum(axis=0)
    # Modes shared by all tags (2n, k): a common radial offset, the principal point (x, y), the
    # focal length, the tilt.
    common = radial.reshape(-1)
    shared = np.zeros((2 * n, 5))
    shared[:, 0] = common
    shared[0::2, 1] = 1.0  # principal point x: every u
    shared[1::2, 2] = 1.0  # ... y: every v
    shared[:, 3] = (uv - K[:2, 2]).reshape(-1)
    shared[:, 4] = _tilt_mode(obs, T).reshape(-1)
    am_shared = A_ros @ shared  # (6, 5)
    a0 = am_shared[:, 0]
    terms["bias_common"] = np.outer(a0, a0)
    terms["principal_point"] = am_shared[:, 1:3] @ am_shared[:, 1:3].T
    terms["focal"] = np.outer(am_shared[:, 3], am_shared[:, 3])
    terms["tilt"] = np.outer(am_shared[:, 4], am_shared[:, 4])

    # The residuals in each tag's patterns; per group, the coefficients' variance pooled over the
    # tags (the frame's mean tag), with the degrees of freedom the fit took from the group (the
    # weighted hat matrix's leverage, w_t J_t M J_t^T) subtracted. Pooled with equal weights: the
    # weights come from the same residuals, and a variance pooled through them would be biased low.
    coef = np.einsum("tjm,tj->tm", B, -res.reshape(n_tags, 8))
    Jt = J.reshape(n_tags, 8, 6)
    # Batched matmuls, not three-operand einsums (those loop over every index: ~0.1 ms a pose).
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
    # The common radial offset the residuals show is what the fit left of it: part of it went into
    # the depth (that part moved the pose). Scale back to the whole by the share left. The mean
    # carries the tags' scale noise too (its standard error): subtract that in quadrature, or the
    # noise of a mean amplified up to tenfold would pass for an offset where there is none.
    common_left = 1.0 - float(common @ (w * (J @ (A @ common)))) / float(common @ (w * common))
    mean_se2 = seen["scale"] ** 2 / n_tags
    seen["bias_common"] = (float(np.sqrt(max(mean_scale**2 - mean_se2, 0.0)))
                           / 2.0 / max(common_left, 0.1))
    seen["light_gradient"] = (0.0 if edge_shift_px is None
                              else light_gradient_px(edge_shift_px, obs.image_px.mean(axis=1)))
    return terms, seen


def uncertainty_sources(terms: dict[str, np.ndarray], seen: dict[str, float],
                        config: UncertaintyConfig) -> dict[str, np.ndarray]:
    """The pose covariance's parts (6x6 each, ROS order), by source: ``residual_<group>`` (each
    pattern group of ``_PATTERNS`` at the sigma the residuals show), ``light_noise`` and
    ``light_tilt`` (the frame's ``light_gradient`` times the gains), ``common_offset`` (the
    measured common radial offset, a mean error: ``uncertainty_bounds``) and the floors
    (``floor_noise``, ``floor_bias``, ``floor_tilt``, ``floor_model``, ``floor_intrinsics``).
    ``combine_uncertainty`` is their sum; benchmarks/bench_uncertainty.py reports what each
    contributes to the bounds."""
    c = config
    k2 = c.residual_inflation**2
    gradient = seen.get("light_gradient", 0.0)
    parts = {f"residual_{g}": k2 * seen[g] ** 2 * terms[g] for g in _PATTERNS}
    parts.update(
        floor_noise=c.corner_noise_px**2 * terms["noise"],
        light_noise=(c.light_gradient_gain * gradient) ** 2 * terms["noise"],
        floor_bias=(c.corner_bias_px**2 * terms["bias"]
                    + c.corner_bias_common_px**2 * terms["bias_common"]),
        common_offset=k2 * seen["bias_common"] ** 2 * terms["bias_common"],
        light_tilt=(c.light_gradient_tilt_gain * gradient) ** 2 * terms["tilt"],
        floor_tilt=c.tilt_shift_px**2 * terms["tilt"],
        floor_model=c.model_mm**2 * terms["model_t"] + c.model_deg**2 * terms["model_r"],
        floor_intrinsics=(c.principal_point_px**2 * terms["principal_point"]
                          + c.focal_rel**2 * terms["focal"]),
    )
    return parts


def combine_uncertainty(terms: dict[str, np.ndarray], seen: dict[str, float],
                        config: UncertaintyConfig) -> np.ndarray:
    """The pose covariance (6x6, ROS order, camera axes): the residual-based term (each pattern
    group's sigma as the residuals show it), the shared corner errors uneven light causes (the
    frame's ``light_gradient`` times the gains of ``config``), plus the floors of ``config``, each
    source's unit covariance times its variance (``uncertainty_sources``). Finite and positive
    definite: a degenerate fit gives a huge diagonal (1 m, 180 deg), never zeros or infinities."""
    cov = sum(uncertainty_sources(terms, seen, config).values())
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)):
        cov = np.diag([1.0, 1.0, 1.0, np.pi**2, np.pi**2, np.pi**2])
    return cov


#: The 95 % quantile of F(nu, nu_e) over a grid of log(nu) (the error's effective dimensions: 1-3
#: for a zero-mean error, up to ~1e6 when a measured offset dominates) and 1 / nu_e (the degrees
#: of freedom its variance was estimated from; 0: known). F(nu, inf) = chi2(nu) / nu.
_F_LOG_NU = np.linspace(np.log(0.5), np.log(1e6), 90)
_F_INV_DOF = np.linspace(0.0, 0.5, 26)


def _f_quantile_table() -> np.ndarray:
    # scipy.stats' f.ppf(q, a, b) is fdtri(a, b, q) and chi2.ppf(q, nu) 2 * gammaincinv(nu / 2, q)
    # (bit-identical): not importing scipy.stats keeps its start-up cost off every command.
    from scipy.special import fdtri, gammaincinv

    nu = np.exp(_F_LOG_NU)[:, None]
    inv = _F_INV_DOF[None, :]
    with np.errstate(divide="ignore"):
        dof = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    return np.where(np.isinf(dof), 2.0 * gammaincinv(nu / 2, 0.95) / nu,
                    fdtri(nu, np.where(np.isinf(dof), 1.0, dof), 0.95))


_F_Q95 = _f_quantile_table()


#: ``_F_Q95`` and its grid as Python floats: ``_f_quantile95`` runs six times a pose, and numpy's
#: scalar indexing and arithmetic cost ~1 us an operation.
_F_Q95_ROWS = _F_Q95.tolist()
_F_X0, _F_DX = float(_F_LOG_NU[0]), float(_F_LOG_NU[1] - _F_LOG_NU[0])
_F_DY = float(_F_INV_DOF[1] - _F_INV_DOF[0])


def _f_quantile95(nu: float, dof: float) -> float:
    """Bilinear lookup of the 95 % quantile of F(nu, dof) (dof >= 2; inf: chi2(nu) / nu)."""
    x = (math.log(min(max(nu, 0.5), 1e6)) - _F_X0) / _F_DX
    y = min(1.0 / max(dof, 2.0), 0.5) / _F_DY
    i = min(int(x), len(_F_LOG_NU) - 2)
    j = min(int(y), len(_F_INV_DOF) - 2)
    fx, fy = x - i, y - j
    q0, q1 = _F_Q95_ROWS[i], _F_Q95_ROWS[i + 1]
    return float((q0[j] * (1 - fx) + q1[j] * fx) * (1 - fy) + (q0[j + 1] * (1 - fx) + q1[j + 1] * fx) * fy)


def _bound95(block: np.ndarray, offset: np.ndarray, dof: float) -> float:
    """95 % quantile of |m + e|, e ~ N(0, S) with ``block`` = S + m m^T: |m + e|^2 matched in mean
    and variance by a scaled chi-square (Welch-Satterthwaite; for m = 0 the quantile of old).
    When S is known only to ``dof`` degrees of freedom, S is first widened to its predictive size
    (by the ratio of the F to the chi-square quantile of its own effective dimensions: for m = 0
    exactly the predictive F quantile); the offset is a measurement, not widened. The three
    eigenvalues as Python floats (sums in numpy's order for three: left to right)."""
    S = 0.5 * (block + block.T) - np.outer(offset, offset)
    lam = [max(v, 0.0) for v in np.linalg.eigvalsh(S).tolist()]
    total = sum(lam)
    if math.isfinite(dof) and total > 0.0:
        nu_s = total * total / sum(v * v for v in lam)
        widen = _f_quantile95(nu_s, dof) / _f_quantile95(nu_s, math.inf)
        lam = [v * widen for v in lam]
        S = S * widen
    mean = sum(lam) + float(offset @ offset)
    if mean <= 0.0:
        return 0.0
    var = 2.0 * sum(v * v for v in lam) + float(4.0 * offset @ S @ offset)
    nu = 2.0 * mean * mean / var if var > 1e-12 * mean * mean else 1e6
    return math.sqrt(mean * _f_quantile95(nu, math.inf))


def uncertainty_bounds(terms: dict[str, np.ndarray], seen: dict[str, float],
                       config: UncertaintyConfig,
                       covariance: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """What ``error_bound95`` needs beyond the covariance: the measured offset and how well the
    random part is known.

    offset (6,), ROS order: the pose error that the tags' common radial offset the residuals
        show (``seen["bias_common"]``) causes. The covariance (``combine_uncertainty``) carries
        it as its square (the frame's mean squared error: a consumer does not know its sign);
        for the bounds it is a mean, not a spread: a measured offset moves the pose by its
        effect, not by 1.96 times it. Its sign is immaterial to a bound on the error's length.
    dof (rotation, translation): effective degrees of freedom (Welch-Satterthwaite) of the
        random part's variance in each block: each residual pattern group's sigma was pooled
        from ``<group>_dof`` coefficients; the floors and light terms count as known."""
    k = config.residual_inflation
    unit = terms["bias_common"]  # a a^T (one mode shared by all tags): a from its largest column
    j = int(np.argmax(np.diagonal(unit)))
    offset = unit[:, j] / np.sqrt(max(float(unit[j, j]), 1e-300)) * k * seen.get("bias_common", 0.0)
    if not np.all(np.isfinite(offset)):
        offset = np.zeros(6)
    diag = (np.diagonal(covariance) - offset * offset).tolist()
    den = [0.0, 0.0]  # rotation, translation: sum of (part's trace)^2 / its dof
    for group in _PATTERNS:
        dof = seen.get(group + "_dof", np.inf)
        if math.isfinite(dof) and dof > 0.0:
            d = (np.diagonal(terms[group]) * (k * seen.get(group, 0.0)) ** 2).tolist()
            den[0] += sum(d[3:]) ** 2 / dof
            den[1] += sum(d[:3]) ** 2 / dof
    total = [sum(diag[3:]), sum(diag[:3])]
    dofs = [float(t * t / e) if e > 0.0 and t > 0.0 else float("inf") for t, e in zip(total, den)]
    return offset, (dofs[0], dofs[1])


def error_bound95(covariance: np.ndarray, offset: np.ndarray | None = None,
                  dof: tuple[float, float] = (float("inf"), float("inf"))) -> tuple[float, float]:
    """(rotation deg, translation mm): 95 % quantiles of the geodesic rotation error and of the
    translation error's length under the covariance (first order).

    Args:
        covariance: 6x6, ROS order: the error's second moment (``combine_uncertainty``).
        offset: (6,) the part of it that is a measured mean error (``uncertainty_bounds``):
            the covariance holds ``S + offset offset^T`` with ``S`` the random part. None: 0.
        dof: (rotation, translation) degrees of freedom the random part is known to; inf: known
            (Gaussian), finite: the predictive (F) quantile.
    """
    m = np.zeros(6) if offset is None else np.asarray(offset, dtype=float)
    out = []
    for rows, scale, nu_e in ((slice(3, 6), np.degrees(1.0), dof[0]), (slice(0, 3), 1e3, dof[1])):
        block = covariance[rows, rows]
        if not np.all(np.isfinite(block)):
            out.append(float("inf"))
            continue
        out.append(_bound95(block, m[rows], nu_e) * scale)
    return out[0], out[1]
