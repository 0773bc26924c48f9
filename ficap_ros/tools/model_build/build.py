"""``build_model``: the as-built cap from per-frame detections, along the steps of the package
docstring: usable frames, observations, the adjustment (outliers dropped, the size's source
chosen), its uncertainty, the gauge alignment to the nominal cap, the report.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.model_build.adjustment import (
    Priors,
    Problem,
    initial_values,
    observation_rms_px,
    rotate_covariance,
    solve,
    structure_covariance,
    unpack,
)
from ficap_ros.tools.model_build.config import BuildConfig, CoverageError
from ficap_ros.tools.model_build.geometry import (
    align_model,
    corners_from_params,
    size_ratio,
)
from ficap_ros.tools.model_build.observations import (
    UsedFrame,
    coverage_problems,
    ids_per_frame,
    problem_from,
    usable_frames,
)
from ficap_ros.tools.model_build.replay_check import assembly_size_sigma
from ficap_ros.tools.model_build.report import BuildResult, deviations
from ficap_ros.vision.detector import TagDetection

__all__ = ["build_model"]


@dataclass(frozen=True)
class _Fit:
    """The adjustment's outcome: the last solution, the observations it kept, the settings it
    ended with (``auto`` may free the size), the observations dropped as outliers, what the images
    alone say about the size (NaN when not run) and the median apparent tag side, px."""

    solution: Any
    problem: Problem
    config: BuildConfig
    dropped: int
    size_images: float
    offset_images: float
    side_px: float


@dataclass(frozen=True)
class _Aligned:
    """The solution in the nominal cap frame: the built model and corners (mm), their covariance
    (mm^2), the edge offset and its variance, and each used frame's T_cam_cap (m)."""

    model: CapModel
    built: np.ndarray
    cov_corners: np.ndarray
    offset: float
    offset_var: float
    poses: tuple[Transform, ...]


def _solve_dropping_outliers(problem: Problem, x0: np.ndarray, priors: Priors, config: BuildConfig,
                             nominal: CapModel, allow_partial: bool, say: Callable[[str], None],
                             problems: list[str]) -> tuple[Any, Problem, int]:
    """Solve; drop the observations whose corner rms is an outlier and solve again (coverage
    problems that leaves are added to ``problems``). Returns (solution, problem, dropped)."""
    solution = solve(problem, x0, priors, config)
    dropped = 0
    per_obs = observation_rms_px(solution.x, problem, priors, config)
    limit = max(config.outlier_px, 5.0 * float(np.median(per_obs)))
    bad = per_obs > limit
    if bad.any():
        dropped = int(bad.sum())
        say(f"dropping {dropped} tag observation(s) above {limit:.2f} px rms; solving again")
        problem = problem.subset(~bad)
        after = coverage_problems(nominal, ids_per_frame(problem, nominal), config)
        if after and not allow_partial:
            raise CoverageError(after[0] + f" (after dropping {dropped} outlier observation(s))")
        problems += [p for p in after if p not in problems]
        solution = solve(problem, solution.x, priors, config)
    return solution, problem, dropped


def _size_from_images(problem: Problem, solution: Any, priors: Priors, config: BuildConfig,
                      nominal: CapModel) -> tuple[float, float]:
    """(size ratio, edge offset px) the images alone give: the same problem with the size free,
    from the anchored solution (a diagnostic beside the anchored model, and the ``auto``
    decision); NaN when the size is not anchored or the offset not fitted."""
    size_images = offset_images = float("nan")
    if config.anchor_size and config.fit_edge_offset:
        free = replace(config, anchor_size=False)
        x_free = solve(problem, solution.x, priors, free).x
        t_free, offset_images, _ = unpack(x_free, problem, free)
        size_images = size_ratio(corners_from_params(t_free[:, :3], t_free[:, 3:]), nominal.corners_mm)
    return size_images, offset_images


def _choose_size(problem: Problem, solution: Any, priors: Priors, config: BuildConfig,
                 nominal: CapModel, offset_images: float, side_px: float,
                 say: Callable[[str], None]) -> tuple[Any, BuildConfig]:
    """``size="auto"``: when the size change the fitted edge offset implies is below what hand
    assembly does, the printed tag side sets the size (solved again with the offset held at 0 and
    the size free); else the nominal layout does. Returns (solution, settings used)."""
    if not (config.size == "auto" and config.anchor_size and config.fit_edge_offset):
        return solution, config
    bias_size = 2.0 * abs(offset_images) / side_px
    assembly_size = assembly_size_sigma(nominal, config)
    if bias_size < assembly_size:
        say(f"edge offset {offset_images:+.3f} px changes the size by {100 * bias_size:.3f} %, less "
            f"than hand assembly's {100 * assembly_size:.3f} %: the printed tag side sets the size")
        anchored = config
        config = replace(config, fit_edge_offset=False, edge_offset_px=0.0, anchor_size=False)
        x_side = np.delete(solution.x, 6 * problem.n_tags) if anchored.fit_edge_offset else solution.x
        return solve(problem, x_side, priors, config), config
    say(f"edge offset {offset_images:+.3f} px changes the size by {100 * bias_size:.3f} %, more "
        f"than hand assembly's {100 * assembly_size:.3f} %: the nominal layout sets the size")
    return solution, config


def _fit(problem: Problem, x0: np.ndarray, priors: Priors, config: BuildConfig, nominal: CapModel,
         allow_partial: bool, say: Callable[[str], None], problems: list[str]) -> _Fit:
    """The adjustment: outliers dropped, the images' own size measured, the size's source chosen."""
    solution, problem, dropped = _solve_dropping_outliers(problem, x0, priors, config, nominal,
                                                          allow_partial, say, problems)
    size_images, offset_images = _size_from_images(problem, solution, priors, config, nominal)
    quads = problem.obs_px
    side_px = float(np.median(np.linalg.norm(np.roll(quads, -1, axis=1) - quads, axis=-1)))
    solution, config = _choose_size(problem, solution, priors, config, nominal, offset_images,
                                    side_px, say)
    return _Fit(solution, problem, config, dropped, size_images, offset_images, side_px)


def _aligned(fit: _Fit, nominal: CapModel) -> _Aligned:
    """The uncertainty of the solved corners (before the gauge alignment; the covariance is
    projected onto it), then the built corners Kabsch-aligned to the nominal ones."""
    tags, offset, frames_x = unpack(fit.solution.x, fit.problem, fit.config)
    raw = corners_from_params(tags[:, :3], tags[:, 3:])
    cov_corners, offset_var = structure_covariance(fit.solution, fit.problem, fit.config, raw)
    T_nom_built = align_model(raw, nominal.corners_mm)  # mm
    built = T_nom_built.apply(raw)
    model = CapModel(nominal.ids, built)
    R_nb = T_nom_built.rotation.as_matrix()
    cov_corners = rotate_covariance(cov_corners, R_nb)
    T_built_nom_m = Transform(T_nom_built.rotation, T_nom_built.translation_m / 1000.0).inv()
    poses = tuple(
        Transform(Rotation.from_rotvec(fx[:3]), fx[3:] / 1000.0) * T_built_nom_m for fx in frames_x
    )
    return _Aligned(model, built, cov_corners, offset, offset_var, poses)


def _result(fit: _Fit, a: _Aligned, priors: Priors, nominal: CapModel, frames_given: int,
            used: Sequence[UsedFrame], problems: list[str],
            say: Callable[[str], None]) -> BuildResult:
    """The report: per-tag deviations and every reason not to trust the model."""
    config, solution = fit.config, fit.solution
    size_source = ("nominal layout" if config.anchor_size else
                   "images" if config.fit_edge_offset else "tag side")
    per_obs = observation_rms_px(solution.x, fit.problem, priors, config)
    converged = bool(solution.status > 0)
    if not converged:
        problems.append(f"the solver stopped at its budget of {config.max_nfev} evaluations "
                        "without converging")
    devs = deviations(nominal, a.built, a.cov_corners, fit.problem, per_obs, a.poses, config)
    for d in devs:
        if d.problem:
            problems.append(f"tag {d.tag_id}: {d.problem}")
    rms = float(np.sqrt(np.mean(per_obs ** 2)))
    say(f"reprojection rms {rms:.3f} px after {solution.nfev} evaluations, edge offset {a.offset:+.3f} px")
    return BuildResult(
        model=a.model,
        nominal=nominal,
        deviations=tuple(devs),
        rms_px=rms,
        edge_offset_px=float(a.offset),
        edge_offset_sigma_px=float(np.sqrt(a.offset_var)),
        median_side_px=fit.side_px,
        size_ratio=size_ratio(a.built, nominal.corners_mm),
        size_ratio_images=fit.size_images,
        edge_offset_images_px=float(fit.offset_images),
        size_source=size_source,
        frames_given=frames_given,
        frames_used=len(used),
        frame_indices=tuple(index for index, _, _ in used),
        T_cam_cap=a.poses,
        observations=len(fit.problem.obs_tag),
        observations_dropped=fit.dropped,
        converged=converged,
        nfev=int(solution.nfev),
        problems=tuple(problems),
    )


def build_model(
    frames: Sequence[Sequence[TagDetection]],
    camera: CameraModel | Sequence[CameraModel],
    nominal: CapModel | None = None,
    config: BuildConfig | None = None,
    progress: Callable[[str], None] | None = None,
    allow_partial: bool = False,
) -> BuildResult:
    """Estimate the as-built cap from per-frame detections.

    Args:
        frames: the detections of each frame (ids outside the model are ignored; an id seen twice
            in one frame is ignored in that frame).
        camera: the intrinsics of every frame, or one per frame.
        nominal: the model to start from and align to (default: the cap-spec nominal).
        config: settings.
        progress: called with a one-line message at each stage.
        allow_partial: build even when a tag is not covered (it then rests on its prior and is
            listed in ``problems``) instead of raising ``CoverageError``.
    Returns:
        A ``BuildResult``; check ``result.problems`` (and ``replay_check``) before using
        ``result.model`` (``result.model.save(path)`` writes a normal cap model YAML).
    Raises:
        CoverageError: fewer than two usable frames; or, unless ``allow_partial``, a tag not seen
            often enough with enough others.
        ConfigError: one camera per frame was expected but the counts differ.
    """
    config = config or BuildConfig()
    nominal = nominal or nominal_model()
    say = progress or (lambda _msg: None)
    cameras = [camera] * len(frames) if isinstance(camera, CameraModel) else list(camera)
    if len(cameras) != len(frames):
        raise ConfigError(f"{len(frames)} frames but {len(cameras)} cameras")
    # 1. Usable frames: enough distinct model tags, and an initial pose from the nominal model.
    used = usable_frames(frames, cameras, nominal, config, say)
    problems: list[str] = []
    coverage = coverage_problems(nominal, [[d.tag_id for d in dets] for _, _, dets in used], config)
    if coverage and not allow_partial:
        raise CoverageError(coverage[0])
    problems += coverage
    say(f"adjusting {len(nominal)} tags over {len(used)} frames")
    # 2. Flat observations; 3. the adjustment from the nominal tags and the frames' nominal poses.
    problem = problem_from(used, cameras, nominal)
    x0, priors = initial_values(nominal, [T for _, T, _ in used], config)
    fit = _fit(problem, x0, priors, config, nominal, allow_partial, say, problems)
    # 4. Uncertainty and 5. the gauge; 6. the report.
    return _result(fit, _aligned(fit, nominal), priors, nominal, len(frames), used, problems, say)
