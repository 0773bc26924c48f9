"""Whether a built model places the cap better than the nominal one: every frame posed with both
(``replay_check``, no ground truth needed), and the distance change hand assembly allows
(``depth_change_limit``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.tools.model_build.config import BuildConfig
from ficap_ros.tools.model_build.geometry import rms_radius
from ficap_ros.tools.model_build.report import BuildResult
from ficap_ros.vision.detector import TagDetection

__all__ = ["ReplayCheck", "assembly_size_sigma", "depth_change_limit", "replay_check"]


@dataclass(frozen=True)
class ReplayCheck:
    """The recording's frames posed with the nominal and with the built model (``replay_check``).

    Both models share the nominal cap frame (the built one is aligned to it), so their poses of
    one frame are directly comparable. Nothing here needs ground truth.

    Attributes:
        frames: frames posed by both models.
        rms_px_nominal, rms_px_built: median over frames of the pose's reprojection rms, px.
        translation_change_mm: median |t_built - t_nominal|, mm.
        translation_change_p95_mm: its 95th percentile, mm.
        depth_change: median of |t_built| / |t_nominal| - 1 (a fraction; > 0: the built model puts
            the cap farther away, the signature of a grown cap).
        rotation_change_deg: median geodesic angle between the two orientations, deg.
        problems: the built model would place the cap worse than the nominal one (it must not be
            used: ``ficap model build`` refuses to write it).
        warnings: the built model fits the recording worse than the nominal one (not to be trusted;
            written only with ``--allow-partial``).
    """

    frames: int
    rms_px_nominal: float
    rms_px_built: float
    translation_change_mm: float
    translation_change_p95_mm: float
    depth_change: float
    rotation_change_deg: float
    problems: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.problems and not self.warnings

    def table(self) -> str:
        return "\n".join([
            f"replay check over {self.frames} frames (pose of every frame with each model):",
            f"  reprojection rms median: nominal {self.rms_px_nominal:.3f} px, built {self.rms_px_built:.3f} px",
            f"  translation built vs nominal: median {self.translation_change_mm:.2f} mm, "
            f"p95 {self.translation_change_p95_mm:.2f} mm; distance {100.0 * self.depth_change:+.3f} %; "
            f"rotation median {self.rotation_change_deg:.3f} deg",
        ] + [f"  PROBLEM: {p}" for p in self.problems] + [f"  WARNING: {w}" for w in self.warnings])

    def to_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "rms_px_nominal": self.rms_px_nominal,
            "rms_px_built": self.rms_px_built,
            "translation_change_mm": self.translation_change_mm,
            "translation_change_p95_mm": self.translation_change_p95_mm,
            "depth_change": self.depth_change,
            "rotation_change_deg": self.rotation_change_deg,
            "problems": list(self.problems),
            "warnings": list(self.warnings),
        }


def assembly_size_sigma(nominal: CapModel, config: BuildConfig) -> float:
    """How much (relative, 1 sigma) hand assembly changes the cap's size: the mean of N independent
    radial plate errors of ``assembly_sigma_mm`` over the RMS radius of the tag centres."""
    return config.assembly_sigma_mm / (np.sqrt(len(nominal)) * rms_radius(nominal.centres_mm))


def depth_change_limit(result: BuildResult, config: BuildConfig) -> float:
    """The ``replay_check`` distance limit for a build result.

    A size anchored to the nominal layout leaves the nominal model's pose distances alone, so
    ``config.max_depth_change`` applies. A size measured from the printed tag side (``auto``
    found the corners unbiased) is a real measurement of a cap that may be larger or smaller
    than nominal by what hand assembly does, so up to three of its sigmas are allowed (the
    nominal model's own distances are then off by about that much).
    """
    if result.size_source == "tag side" and config.size == "auto":
        return max(config.max_depth_change, 3.0 * assembly_size_sigma(result.nominal, config))
    return config.max_depth_change


def replay_check(
    frames: Sequence[Sequence[TagDetection]],
    camera: CameraModel | Sequence[CameraModel],
    built: CapModel,
    nominal: CapModel | None = None,
    config: BuildConfig | None = None,
    max_depth_change: float | None = None,
) -> ReplayCheck:
    """Pose every frame with the nominal and with the built model and compare (no truth needed).

    The poses come from ``ficap_ros.vision.pose.estimate_cap_pose`` with the replay's default settings, on
    the detections the model was built from. Problems: the built model fits the frames worse (its
    median reprojection rms is higher: a warning), or it moves the cap along the line of sight by
    more than ``config.max_depth_change`` (a problem): the nominal layout fixes the cap's size to
    within what hand assembly changes, so a distance change beyond that means the built cap has
    the wrong size and would place the cap worse than the nominal model. ``max_depth_change``
    overrides the config's limit (``depth_change_limit`` gives the one for a build result).
    """
    from ficap_ros.vision.pose import estimate_cap_pose

    config = config or BuildConfig()
    nominal = nominal or nominal_model()
    cameras = [camera] * len(frames) if isinstance(camera, CameraModel) else list(camera)
    if len(cameras) != len(frames):
        raise ConfigError(f"{len(frames)} frames but {len(cameras)} cameras")
    rms_n, rms_b, dt_mm, depth, rot = [], [], [], [], []
    for dets, cam in zip(frames, cameras):
        a = estimate_cap_pose(dets, nominal, cam).pose
        b = estimate_cap_pose(dets, built, cam).pose
        if a is None or b is None:
            continue
        rms_n.append(a.rms_px)
        rms_b.append(b.rms_px)
        ta, tb = a.T_cam_cap.translation_m, b.T_cam_cap.translation_m
        dt_mm.append(1000.0 * float(np.linalg.norm(tb - ta)))
        depth.append(float(np.linalg.norm(tb) / np.linalg.norm(ta)) - 1.0)
        rot.append(float(np.degrees((a.T_cam_cap.rotation.inv() * b.T_cam_cap.rotation).magnitude())))
    if not rms_n:
        return ReplayCheck(0, *([float("nan")] * 6), problems=("no frame could be posed by both models",))
    check = dict(
        frames=len(rms_n),
        rms_px_nominal=float(np.median(rms_n)),
        rms_px_built=float(np.median(rms_b)),
        translation_change_mm=float(np.median(dt_mm)),
        translation_change_p95_mm=float(np.percentile(dt_mm, 95)),
        depth_change=float(np.median(depth)),
        rotation_change_deg=float(np.median(rot)),
    )
    problems, warnings = [], []
    if check["rms_px_built"] > check["rms_px_nominal"]:
        warnings.append(
            f"the built model fits the recording worse than the nominal one (median reprojection "
            f"rms {check['rms_px_built']:.3f} px vs {check['rms_px_nominal']:.3f} px)"
        )
    limit = config.max_depth_change if max_depth_change is None else max_depth_change
    if abs(check["depth_change"]) > limit:
        problems.append(
            f"the built model moves the cap {100.0 * check['depth_change']:+.2f} % along the line of "
            f"sight (median {check['translation_change_mm']:.2f} mm) against the nominal one; hand "
            f"assembly cannot change the cap's size that much (limit "
            f"{100.0 * limit:.2f} %): the built cap's scale is wrong"
        )
    return ReplayCheck(**check, problems=tuple(problems), warnings=tuple(warnings))
