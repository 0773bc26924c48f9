"""The uncertainty of a cap pose: its covariance, its 95 % error bounds and the tags' weights.

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
        pose absorbs; and a strong light's edge shifts leave every tag's corners shifted along its
        foreshortening (the depth's mode) by an amount that follows the tags' mean edge shift (the
        light's strength), stated where it exceeds what the other terms already state there;
        and the edge corners' own bias, the same in every tag of a frame (one blur, one tone curve,
        one fit), a radial offset the pose takes into the depth: its size follows the frame's
        corner noise over its cell width (``shared_bias_ratio``);
    the floors of ``UncertaintyConfig`` added to it: independent corner noise, radial corner bias
        (per tag and common), a shift along the foreshortening, each plate shifted and turned as a
        rigid whole against the cap model, the intrinsics (principal point, focal length).
Pooling by pattern matters: a tag's corner errors are not independent (a blurred border moves all
four corners inward), and treating them as such misjudges which pose directions they disturb.

Bounds: ``rot_err95_deg`` / ``trans_err95_mm`` are the 95 % quantiles of the rotation angle /
translation length under the covariance (``error_bounds.error_bound95``), with two things the covariance alone
does not say (``uncertainty_bounds``): the residual-based sigmas are estimates pooled from a few
dozen coefficients, so the bound is the predictive (F, Welch-Satterthwaite degrees of freedom)
quantile, not the Gaussian one; and where the tags' common radial offset the residuals show is
used (``UncertaintyConfig.common_offset_gain``), it is a measured mean error, not a spread (the
covariance holds its square, as a mean squared error must).

Depth is what the shared corner errors move most: a radial offset of every corner by delta px
moves the depth by about z * sqrt(2) * delta / (tag side in px), so at a given distance the same
offset costs a low-resolution camera twice the depth error. The pose's change reproduces only a
small share of the corners' displacement; the rest stays in each tag's scale residual, so the
tags' mean scale coefficient, scaled back by the share left (``uncertainty_kernels``), measures
the offset, and the scale coefficients' scatter its standard error. Its size follows the depth
error on path-traced renders across cameras, lights and tone curves
(``benchmarks/bench_uncertainty.py``): the edge profile states the offset as measured, with its
standard error beside it (``common_offset_gain`` and ``common_offset_se_gain`` 1; the
leave-one-set-out fit on those renders checks the factor). Its sign does not follow the depth error from one
recording to the next (``seen["bias_common_signed"]``: with the error on some renders, against it
on an as-built cap and through fast glances), and where the offset differs from tag to tag its
mean need not be what moves the depth (the tags that fix the depth may carry little of it), so it
enters the covariance as a mean squared error and never corrects the pose. The residual-based
terms alone state the depth error of frames without such an offset about right; the corner noise
over the cell width (``shared_bias_ratio``) does not follow the offset (it is largest where there
is none) and serves the profiles calibrated with it.

Tag weights (``joint`` pose, ``UncertaintyConfig.weight_tags``): each tag's corner noise is
estimated from its own residuals with the frame's median as a prior (``tag_noise_px``), and the pose
takes one weighted Gauss-Newton step from the unweighted optimum (``reweighted``), so oblique, dark
or second-read tags with worse corners count less.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.frame_measures import (
    edge_shift_mean_px,
    light_gradient_px,
    shared_bias_ratio,
)
from ficap_ros.vision.reprojection import (
    TagObservations,
    median,
    residuals_and_jacobian,
)
from ficap_ros.vision.uncertainty_kernels import propagated_terms

__all__ = [
    "UncertaintyConfig",
    "CORNER_ESTIMATORS",
    "tag_noise_px",
    "tag_noise_from_residuals",
    "reweighted",
    "uncertainty_terms",
    "common_offset_mode",
    "uncertainty_sources",
    "combine_uncertainty",
    "uncertainty_bounds",
]


@dataclass(frozen=True)
class UncertaintyConfig:
    """How the pose covariance is built: the residual-based term, the terms for corner errors that
    neighbouring tags share (which the pose absorbs without residuals), and the floors (1-sigma).

    The residual-based term carries what each frame's corners show (noise, per-tag corner bias,
    misplaced plates: ``uncertainty_terms``), tag by tag in proportion to each tag's own corner
    noise (``tag_noise_px``). What residuals cannot show is a corner error shared by neighbouring
    tags: the pose absorbs it and leaves no residual. Uneven light (spotlights, clipping) causes
    one: the tone-curve edge shift each tag's cell fit measures (``TagDetection.edge_shift_px``)
    then varies smoothly across the cap, and the edges of each tag move toward its darker side, a
    field the pose absorbs. Its size is the frame's ``light_gradient_px`` (spread of a plane fitted
    to the tags' edge shifts over their image positions); ``light_gradient_gain`` turns it into
    corner noise the pose absorbs, and ``light_gradient_tilt_gain`` into a shift of every tag along
    its foreshortening (the projected normal, times the sine of the view angle), the mode that
    moves the depth. A spotlight centred on the cap has no linear slope, yet its edge shifts still
    leave such a shift: what sizes it in the edge corners is the light's strength, the fitted tags'
    mean edge shift (``seen["edge_shift_mean"]``). ``edge_shift_tilt_gain`` times it is the shift's
    sigma, px edge-on, counted only beyond the variance the other terms already state along the
    same direction (``uncertainty_sources``): the residual and common-offset terms cover most of it
    where the corners show it.

    The corner stage's own bias is shared too: every tag of a frame has the same blur and tone
    curve and goes through the same fit, so what the fit leaves of the tone curve's edge shift
    is a radial offset of every tag's corners alike, which the pose takes into the depth without
    a residual. The fit measures the shift across one cell (a border's two edges, the cells'
    boundaries), exact where a cell is much wider than the blur and the noise; its error grows
    as the blur reaches across a cell and as the edges get noisier, which the frame shows as its
    corner noise (the median tag's ``tag_noise_px``: a blurred, low-contrast edge is placed less
    precisely) over its cell width (``shared_bias_ratio``). ``shared_bias_gain`` turns that ratio
    into the offset's sigma, px. What the residuals show of the offset (the tags' mean radial
    coefficient, scaled back by the share of it the depth left: ``seen["bias_common"]``) states
    it better for the edge corners: ``common_offset_gain`` times it is a mean error of the frame
    (``uncertainty_bounds``), and the edge profile uses it in place of the ratio. Below its standard
    error it reads 0, yet such an offset is not ruled out: ``common_offset_se_gain`` states that.

    The light gains and ``residual_inflation`` are calibrated on ``ficap synth`` drives
    (the smallest bounds whose rotation and translation bounds cover at least 90 % in every
    lighting and resolution condition). The edge profile's offset gain is fitted on the path-traced
    renders leave one set out (bench_uncertainty states the rule and the gain each fold picks): one
    gain on the measured offset and its standard error states the offset as measured; a joint fit with
    ``shared_bias_gain`` trades the two terms for each other and leaves the set whose depth error
    follows the offset under-covered. Both are checked, not fitted, on synth drives.
    ``benchmarks/bench_uncertainty.py`` runs both checks and the leave-one-set-out fit
    (docs/benchmarks/uncertainty.md). The floors state what residuals cannot estimate and
    guarantee that no pose is ever "exact".

    Profiles per corner estimator (``for_corners``): the defaults are the profile of the default
    cell-edge corners (``edge``). The tag-level photometric corner fit (``photometric``:
    ``DetectorConfig(edge_photometric=True)``, ``--photometric``, node ``detector.photometric``)
    leaves much less of the shift along the foreshortening under uneven light and less of the
    shared bias, so its profile has a smaller ``light_gradient_tilt_gain`` and states the measured
    offset and its standard error at a smaller gain (0.75, fitted by the same rule,
    ``bench_uncertainty.py --photometric``). Corners that keep the tone curve's bias
    (``uncorrected``: every ``corner_refine`` but ``edge``: OpenCV's sub-pixel corners,
    AprilTag's, the search's polygon) sit a tenth of a px to over a px inside every tag alike: an
    offset large enough that the part the depth leaves in the residuals measures it, so their
    profile uses it (``common_offset_gain`` 1, the ratio term beside it at the gain it was
    calibrated with). ``pipeline.FrameProcessor`` uses the profile of
    its detector's corner estimator when the pose's uncertainty is not set
    (``PoseConfig.uncertainty`` None).

    Attributes:
        corner_noise_px: independent corner noise, px (> 0: an edge fit over many 8-bit samples is
            still limited by their quantisation).
        corner_bias_px: radial offset of a tag's corners toward or away from its centre (blur and
            tone curve move dark borders), independent per tag, px.
        corner_bias_common_px: the same offset shared by every tag of a frame, px (a floor).
        shared_bias_gain: sigma of the edge corners' radial offset shared by every tag, px per
            unit of the frame's ``shared_bias_ratio`` (its corner noise over its cell width). 0 in
            the edge profile, which states the offset by what the residuals show of it.
        common_offset_gain: factor on the tags' common radial offset as the residuals show it
            (``uncertainty_bounds``: a measured mean error). 1 by default: the offset as
            measured; 0.75 in the ``photometric`` profile.
        common_offset_se_gain: factor on that estimate's standard error
            (``seen["bias_common_se"]``), a sigma along the same mode: below its standard error
            the estimate reads 0, yet such an offset is not ruled out. 1 by default (the
            offset's own uncertainty as measured); 0.75 in the ``photometric`` profile; 0 in
            the ``uncorrected`` one, calibrated without it.
        model_mm, model_deg: each tag plate's placement on the built cap against the model, per
            axis (shift, mm; turn about the plate centre, deg). 0 by default: misplaced plates
            show in the residuals; raise them when the cap may have changed since its model was
            made.
        principal_point_px, focal_rel: intrinsics error (principal point per axis, px; focal
            length, relative). 0 by default: CameraInfo says nothing of it, and a constant
            intrinsics error is a constant rotation offset that a frontal calibration absorbs in
            the head angles.
        residual_inflation: factor (>= 1) on the residual-based sigmas.
        light_gradient_gain: corner noise absorbed by the pose per px of ``light_gradient_px``.
        light_gradient_tilt_gain: shared shift of the tags along their foreshortening per px of
            ``light_gradient_px``. 0 in the edge profile (``edge_shift_tilt_gain`` states it).
        edge_shift_tilt_gain: shared shift of the tags along their foreshortening (px edge-on) per
            px of the fitted tags' mean edge shift, beyond what the other terms state along it.
            0 in the ``photometric`` and ``uncorrected`` profiles (their light gradient term).
        tilt_shift_px: floor for that shared shift, px at a tag seen edge-on. 0 by default: no
            residual reveals it, and it arises where tags are small and blurred (the corner fit's
            bias on small foreshortened cells) under a light beside the lens, which lights each
            oblique face unevenly; set it for such a camera.
        weight_tags: weight each tag in the ``joint`` pose by its corner noise
            (``tag_noise_px``): one weighted Gauss-Newton step from the unweighted optimum.
        motion_blur_gain: shared shrink of the tags along their image motion over the exposure,
            per px of that motion (the mode ``blur`` of ``motion_blur.blur_modes``, known when the
            camera's exposure is): a tag smeared along its motion and then bent by the tone curve
            has its edges across the motion pulled toward the black, in every tag alike, so the
            pose absorbs it.
        motion_blur_shift_gain: shared shift of the tags along their motion, per px of it (the
            mode ``blur_shift``): edges fitted on a smeared tag settle off its mid-exposure
            place, alike in every tag, which the pose takes for a turn. Both gains are fitted
            on rendered fast glances (path-traced and synth, global and rolling shutter): the
            pair whose bounds hold in at least 90 % of every recording's fast frames with the
            sharpest fast-frame bounds, each recording's checked with gains fitted without it
            (``benchmarks/bench_glance.py``); they act only when the exposure is given. The
            motion-aware corners (``DetectorConfig.motion_corners``) fit the smear, so little of
            the shrink is left, and the shift's gain is 0: the common offset
            (``common_offset_gain``) covers what is left of the shift.
    """

    corner_noise_px: float = 0.002
    corner_bias_px: float = 0.002
    corner_bias_common_px: float = 0.002
    shared_bias_gain: float = 0.0
    common_offset_gain: float = 1.0
    common_offset_se_gain: float = 1.0
    model_mm: float = 0.0
    model_deg: float = 0.0
    principal_point_px: float = 0.0
    focal_rel: float = 0.0
    residual_inflation: float = 1.0
    light_gradient_gain: float = 0.3
    light_gradient_tilt_gain: float = 0.0
    edge_shift_tilt_gain: float = 0.05
    tilt_shift_px: float = 0.0
    weight_tags: bool = True
    motion_blur_gain: float = 0.025
    motion_blur_shift_gain: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.residual_inflation) and self.residual_inflation >= 1.0):
            raise ConfigError("residual_inflation must be >= 1")
        values = (self.corner_noise_px, self.corner_bias_px, self.corner_bias_common_px,
                  self.model_mm, self.model_deg, self.principal_point_px, self.focal_rel,
                  self.light_gradient_gain, self.light_gradient_tilt_gain, self.tilt_shift_px,
                  self.motion_blur_gain, self.motion_blur_shift_gain, self.shared_bias_gain,
                  self.common_offset_gain, self.common_offset_se_gain, self.edge_shift_tilt_gain)
        if not all(np.isfinite(v) and v >= 0 for v in values):
            raise ConfigError("uncertainty sigmas and gains must be finite and >= 0")
        if self.corner_noise_px <= 0:
            raise ConfigError("corner_noise_px must be > 0 (no pose is exact)")

    @classmethod
    def for_corners(cls, corners: str = "edge") -> UncertaintyConfig:
        """The calibrated profile for a corner estimator (``CORNER_ESTIMATORS``): ``edge`` (the
        cell-edge fit: the defaults), ``photometric`` or ``uncorrected`` (corners that keep the
        tone curve's bias: ``pipeline.corner_estimator``).

        Raises:
            ConfigError: unknown corner estimator.
        """
        if corners not in _CORNER_PROFILES:
            raise ConfigError(f"unknown corner estimator {corners!r}; expected one of "
                              f"{', '.join(CORNER_ESTIMATORS)}")
        return cls(**_CORNER_PROFILES[corners])


#: ``UncertaintyConfig.for_corners``: the fields each corner estimator's profile changes from the
#: defaults (the ``edge`` profile). The photometric corners leave less of the tilt under uneven
#: light and a smaller shared offset, which their profile states from the measured offset and its
#: standard error (``bench_uncertainty.py --photometric``). Uncorrected corners use the measured common offset
#: as measured, with the ratio term beside it. Both state the tilt by the light gradient.
_CORNER_PROFILES: dict[str, dict[str, float]] = {
    "edge": {},
    "photometric": {"light_gradient_tilt_gain": 0.1, "edge_shift_tilt_gain": 0.0,
                    "shared_bias_gain": 0.0, "common_offset_gain": 0.75, "common_offset_se_gain": 0.75},
    "uncorrected": {"light_gradient_tilt_gain": 0.35, "edge_shift_tilt_gain": 0.0,
                    "common_offset_gain": 1.0, "common_offset_se_gain": 0.0, "shared_bias_gain": 0.95},
}
CORNER_ESTIMATORS = tuple(_CORNER_PROFILES)


#: Per-tag corner patterns (columns of each tag's orthonormal basis, ``uncertainty_kernels``)
#: grouped as the residuals are pooled.
_PATTERNS = {"shift": [0, 1], "scale": [2], "turn": [3], "shear": [4, 5], "projective": [6, 7]}
#: The compiled kernel's outputs (``uncertainty_kernels.propagated_terms``), in its order: the
#: unit covariances, and what the residuals show (its last value, the tags' mean scale
#: coefficient, is its own intermediate).
_TERM_NAMES = (*_PATTERNS, "noise", "bias", "model_t", "model_r", "bias_common", "principal_point",
               "focal", "tilt")
_SEEN_NAMES = (*_PATTERNS, *(g + "_dof" for g in _PATTERNS), "bias_common", "bias_common_se",
               "bias_common_signed")


def tag_noise_px(obs: TagObservations, T: Transform) -> np.ndarray:
    """Per-tag corner noise estimate (tags,), px: the tag's own RMS reprojection residual and the
    frame's median tag RMS added in quadrature.

    What makes one tag's corners worse than another's (oblique view, small size, blur, a dark or
    clipped plate, no cell-edge fit, a tag added by the search's second reading) shows in its own
    residuals; a tag's 8 residuals are a noisy estimate of it (and the fit absorbed a share), so
    the frame's median is added as a prior: a tag with residuals at the median gets sqrt(2) times
    them, one far above the median its own."""
    return tag_noise_from_residuals(obs.measured_residuals(residuals_and_jacobian(T, obs)[0]), len(obs))


def tag_noise_from_residuals(res: np.ndarray, n_tags: int) -> np.ndarray:
    """``tag_noise_px`` from the corners' residuals (8 * tags,) of any fit, px."""
    rms = np.sqrt(np.mean(res.reshape(n_tags, 8) ** 2, axis=1))
    floor = max(median(rms), 1e-6)
    return np.sqrt(rms**2 + floor**2)


def reweighted(obs: TagObservations, T: Transform) -> tuple[Transform, np.ndarray]:
    """The pose with each tag weighted by its corner noise (``tag_noise_px``), and that noise.

    One Gauss-Newton step of the weighted reprojection error from the unweighted optimum: the
    weights move the pose by little, where the problem is linear, so one step is enough. With
    fewer than four tags the residuals say too little about which tag is worse: equal weights."""
    n_tags = len(obs)
    if n_tags < 4:
        return T, np.ones(n_tags)
    res, J = residuals_and_jacobian(T, obs)
    sigma = tag_noise_from_residuals(obs.measured_residuals(res), n_tags)
    w = np.repeat(1.0 / sigma**2, 8)
    try:
        dx = -np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * res))
    except np.linalg.LinAlgError:
        return T, sigma
    if not np.all(np.isfinite(dx)):
        return T, sigma
    return T.turned(dx[:3], T.translation_m + dx[3:]), sigma


def _model_geometry(obs: TagObservations) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def uncertainty_terms(
    obs: TagObservations, T: Transform, tag_sigma_px: np.ndarray | None = None,
    edge_shift_px: np.ndarray | None = None,
    at: tuple[np.ndarray, np.ndarray] | None = None,
    prior_information: np.ndarray | None = None,
    motion_term: np.ndarray | None = None,
    shared_modes: dict[str, np.ndarray] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """What the covariance is built from.

    Args:
        obs: the tags the pose used.
        T: the pose.
        tag_sigma_px: per-tag corner noise (``tag_noise_px``) when the pose weighted its tags by
            it (``reweighted``); None: equal weights. It sets the fit's weights and each tag's
            share of the residual-based variance (a tag with twice the noise gets four times the
            variance in every pattern).
        edge_shift_px: per tag, the edge shift its cell fit measured (NaN: not fitted); None:
            unknown (``light_gradient`` 0).
        at: ``residuals_and_jacobian(T, obs)`` when the caller has it already: the same residuals
            and Jacobian, not computed twice. A moving cap's fit (rolling shutter) passes its own:
            the Jacobian has the pose's six columns first and the velocity's after them.
        prior_information: a moving cap's fit with the velocity among its unknowns: what its
            prior adds to the normal matrix (columns of ``at``'s Jacobian; px units,
            ``motion.MovingFit.prior_information``), so the velocity is marginalised out of the
            pose's terms.
        motion_term: a moving cap's fit: the pose covariance (6x6, ROS order) its velocity
            prior's own error causes (``motion.MovingFit.motion_term``), the term
            ``motion_prior``.
        shared_modes: further corner errors shared by the tags, by name: (2n,) each corner's
            displacement (px) per unit of the source (``motion_blur.blur_modes``); each becomes the
            term of its name.

    Returns:
        terms: per error source, the pose covariance (6x6, ROS order) that one unit of its sigma
            causes, by first-order propagation through the (weighted) fit
            (``A = (J^T W J)^-1 J^T W``): each residual pattern group of ``_PATTERNS`` (1 px per
            pattern coordinate for a tag of median noise, scaled by the tag's relative noise,
            independent per tag), ``noise`` (1 px, every coordinate independent), ``bias``
            (1 px radial at every corner, independent per tag), ``bias_common`` (the same for
            all tags), ``model_t`` / ``model_r`` (each plate shifted 1 mm / turned 1 deg about
            each cap axis), ``principal_point`` (1 px per axis), ``focal`` (relative 1),
            ``tilt`` (every tag shifted along its foreshortening, 1 px edge-on).
        seen: what the residuals show: per pattern group the sigma of its coefficients (each
            tag's divided by its relative noise) pooled over the tags, less the share the fit
            absorbed (the weighted hat matrix's leverage of the group), and ``bias_common``, the
            tags' mean radial offset (px per corner), scaled back by the share of it the fit left
            in the residuals, ``bias_common_se`` its standard error and ``bias_common_signed`` the
            same offset with its sign, its standard error not subtracted (px, positive outward:
            the corners outside the model's projection; an outward offset of every tag's corners
            moves the pose toward the camera); ``light_gradient`` (``light_gradient_px``) and ``edge_shift_mean`` (``edge_shift_mean_px``), px;
            ``shared_bias_ratio`` (of the tags' corner noise from these residuals:
            ``tag_noise_from_residuals``); per pattern group also ``<group>_dof``, the degrees of
            freedom its sigma was pooled from (the bounds widen for a sigma estimated from few).
    """
    res, J = residuals_and_jacobian(T, obs) if at is None else at
    n_tags = len(obs)
    terms, seen, A_ros = _propagated(obs, T, res, J, tag_sigma_px, prior_information)
    seen["light_gradient"] = (0.0 if edge_shift_px is None
                              else light_gradient_px(edge_shift_px, obs.image_px.mean(axis=1)))
    seen["edge_shift_mean"] = edge_shift_mean_px(edge_shift_px)
    seen["shared_bias_ratio"] = shared_bias_ratio(obs.image_px, tag_noise_from_residuals(res, n_tags))
    if motion_term is not None:
        terms["motion_prior"] = motion_term
    for name, mode in (shared_modes or {}).items():
        a_mode = A_ros @ mode
        terms[name] = np.outer(a_mode, a_mode)
    return terms, seen


def _propagated(obs: TagObservations, T: Transform, res: np.ndarray, J: np.ndarray,
                tag_sigma_px: np.ndarray | None,
                prior_information: np.ndarray | None) -> tuple[dict[str, np.ndarray], dict[str, float],
                                                               np.ndarray]:
    """``uncertainty_terms``' unit covariances by name, what the residuals show by name, and the
    fit's map in ROS order (6, 2n): the compiled ``uncertainty_kernels.propagated_terms``."""
    if tag_sigma_px is None:
        rel = np.ones(len(obs))
    else:
        rel = np.asarray(tag_sigma_px, dtype=float) / max(median(tag_sigma_px), 1e-12)
    w = np.repeat(1.0 / rel**2, 8)  # weights per residual coordinate
    k = J.shape[1]
    info = np.zeros((k, k)) if prior_information is None else np.array(prior_information, dtype=float)
    centres, normal, cross = _model_geometry(obs)
    unit, measured, A_ros = propagated_terms(
        np.ascontiguousarray(res, dtype=float), np.ascontiguousarray(J, dtype=float), w, info,
        np.array(obs.image_px, dtype=float).reshape(-1, 2), np.array(obs.model_m, dtype=float).reshape(-1, 3),
        np.array(T.rotation_matrix), np.array(T.translation_m, dtype=float), np.array(obs.K, dtype=float),
        rel, cross, centres, normal)
    return dict(zip(_TERM_NAMES, unit)), dict(zip(_SEEN_NAMES, measured.tolist())), A_ros


def uncertainty_sources(terms: dict[str, np.ndarray], seen: dict[str, float],
                        config: UncertaintyConfig) -> dict[str, np.ndarray]:
    """The pose covariance's parts (6x6 each, ROS order), by source: ``residual_<group>`` (each
    pattern group of ``_PATTERNS`` at the sigma the residuals show), ``light_noise`` and
    ``light_tilt`` (the frame's ``light_gradient`` times the gains), ``light_shift_tilt`` (the
    frame's ``edge_shift_mean`` times ``edge_shift_tilt_gain``, beyond what the other parts state
    along the tilt: ``_beyond_px2``), ``shared_bias`` (the edge
    corners' radial offset shared by the tags: the frame's ``shared_bias_ratio`` times
    ``shared_bias_gain``), ``common_offset`` (the measured common radial offset times
    ``common_offset_gain``, a mean error: ``uncertainty_bounds``), ``common_offset_se`` (its
    standard error times ``common_offset_se_gain``, where that is above 0) and the floors
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
        shared_bias=((c.shared_bias_gain * seen.get("shared_bias_ratio", 0.0)) ** 2
                     * terms["bias_common"]),
        common_offset=(k2 * (c.common_offset_gain * seen["bias_common"]) ** 2
                       * terms["bias_common"]),
        light_tilt=(c.light_gradient_tilt_gain * gradient) ** 2 * terms["tilt"],
        floor_tilt=c.tilt_shift_px**2 * terms["tilt"],
        floor_model=c.model_mm**2 * terms["model_t"] + c.model_deg**2 * terms["model_r"],
        floor_intrinsics=(c.principal_point_px**2 * terms["principal_point"]
                          + c.focal_rel**2 * terms["focal"]),
    )
    if c.common_offset_se_gain > 0.0:
        se_px = c.common_offset_se_gain * seen.get("bias_common_se", 0.0)
        parts["common_offset_se"] = k2 * se_px**2 * terms["bias_common"]
    if "motion_prior" in terms:
        parts["motion_prior"] = terms["motion_prior"]
    if "blur" in terms:
        parts["motion_blur"] = (c.motion_blur_gain**2 * terms["blur"]
                                + c.motion_blur_shift_gain**2 * terms["blur_shift"])
    if c.edge_shift_tilt_gain > 0.0:
        shift_px = c.edge_shift_tilt_gain * abs(seen.get("edge_shift_mean", 0.0))
        parts["light_shift_tilt"] = _beyond_px2(shift_px, terms["tilt"], parts) * terms["tilt"]
    return parts


def _beyond_px2(sigma_px: float, tilt: np.ndarray, parts: dict[str, np.ndarray]) -> float:
    """The variance (px^2, edge-on) of a shift along the tilt mode of sigma ``sigma_px`` that
    ``parts`` (6x6 covariances, ROS order) do not state already: sigma^2 less their variance
    along the mode's translation (in px^2 of the mode), at least 0. ``tilt``: the mode's unit
    covariance a a^T (``uncertainty_terms``' ``tilt``), rank one."""
    a2 = tilt[:3, :3]
    norm2 = float(np.trace(a2))  # |a_t|^2, m^2 per px^2
    if not (sigma_px > 0.0 and np.isfinite(norm2) and norm2 > 0.0):
        return 0.0
    other = sum(parts.values())[:3, :3]
    stated_px2 = float(np.sum(a2 * other)) / norm2**2  # a_t^T C a_t / |a_t|^4
    return max(sigma_px**2 - stated_px2, 0.0) if np.isfinite(stated_px2) else sigma_px**2


def combine_uncertainty(terms: dict[str, np.ndarray], seen: dict[str, float],
                        config: UncertaintyConfig) -> np.ndarray:
    """The pose covariance (6x6, ROS order, camera axes): the residual-based term (each pattern
    group's sigma as the residuals show it), the shared corner errors uneven light causes (the
    frame's ``light_gradient`` times the gains of ``config``) and the corner stage's shared bias
    (``shared_bias_ratio`` times ``shared_bias_gain``), plus the floors of ``config``, each
    source's unit covariance times its variance (``uncertainty_sources``). Finite and positive
    definite: a degenerate fit gives a huge diagonal (1 m, 180 deg), never zeros or infinities."""
    cov = sum(uncertainty_sources(terms, seen, config).values())
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)):
        cov = np.diag([1.0, 1.0, 1.0, np.pi**2, np.pi**2, np.pi**2])
    return cov


def common_offset_mode(terms: dict[str, np.ndarray]) -> np.ndarray:
    """(6,) ROS order: the pose error one px of the tags' common radial offset causes, the mode
    ``a`` of ``terms["bias_common"]`` (a a^T, one mode shared by all tags) from its largest column;
    its sign is the matrix's to lose (an outward offset, a larger image, brings the cap closer:
    the caller orients it where the sign matters)."""
    unit = terms["bias_common"]
    j = int(np.argmax(np.diagonal(unit)))
    return unit[:, j] / np.sqrt(max(float(unit[j, j]), 1e-300))


def uncertainty_bounds(terms: dict[str, np.ndarray], seen: dict[str, float],
                       config: UncertaintyConfig,
                       covariance: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """What ``error_bounds.error_bound95`` needs beyond the covariance: the measured offset and
    how well the random part is known.

    offset (6,), ROS order: the pose error that the tags' common radial offset the residuals
        show (``seen["bias_common"]``, times ``common_offset_gain``) causes. The covariance
        (``combine_uncertainty``) carries it as its square (the frame's mean squared error: a
        consumer does not know its sign); for the bounds it is a mean, not a spread: a measured
        offset moves the pose by its effect, not by 1.96 times it. Its sign is immaterial to a
        bound on the error's length.
    dof (rotation, translation): effective degrees of freedom (Welch-Satterthwaite) of the
        random part's variance in each block: each residual pattern group's sigma was pooled
        from ``<group>_dof`` coefficients; the floors and light terms count as known."""
    k = config.residual_inflation
    offset = common_offset_mode(terms) * k * config.common_offset_gain * seen.get("bias_common", 0.0)
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
