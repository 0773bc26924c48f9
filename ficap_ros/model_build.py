"""The cap as built, by bundle adjustment over frames that see many tags at once.

Unknowns: every tag is a rigid 32 mm square with its own 6-DoF pose in the cap frame (``R_cap_tag``,
``t_cap_tag_mm``), and every frame has its camera pose ``T_cam_cap``. Residuals are the
reprojection errors of the detected corners (undistorted with the frame's intrinsics, so every lens
model shares one pinhole projection), minimised with ``scipy.optimize.least_squares`` (TRF, sparse
Jacobian from ``jac_sparsity``, robust ``soft_l1`` loss so a bad corner cannot drag a tag).

Gauge: the reprojections are unchanged by a rigid motion of the whole cap (the 32 mm tag side fixes
the scale). A weak prior (``prior_sigma_mm``) on every tag centre toward the nominal keeps the
solver well posed; after the solve the model is Kabsch-aligned to the nominal corners, so the
as-built cap frame is the nominal one in the least-squares sense, and per-tag deviations are
relative to it.

Tag frame (local): x along the tag's top edge (TL -> TR), y down (TL -> BL), z = x cross y (into
the cap); local corners (-16, -16, 0), (16, -16, 0), (16, 16, 0), (-16, 16, 0) mm = TL, TR, BR, BL.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import TAG_SIDE_MM, CapModel, nominal_model
from ficap_ros.detection import TagDetection
from ficap_ros.errors import ConfigError, ModelError
from ficap_ros.transform import Transform

__all__ = [
    "CoverageError",
    "BuildConfig",
    "TagDeviation",
    "BuildResult",
    "build_model",
    "tag_frames",
    "align_model",
]

_HALF = TAG_SIDE_MM / 2.0
#: Tag corners in the tag's own frame, mm (TL, TR, BR, BL).
LOCAL_CORNERS_MM = np.array(
    [[-_HALF, -_HALF, 0.0], [_HALF, -_HALF, 0.0], [_HALF, _HALF, 0.0], [-_HALF, _HALF, 0.0]]
)


class CoverageError(ModelError):
    """The frames do not see every tag often enough, together with enough others, to build it."""


@dataclass(frozen=True)
class BuildConfig:
    """Settings of ``build_model``.

    Attributes:
        min_tags_per_frame: frames with fewer (pose-inlier) model tags are not used.
        min_frames_per_tag: every model tag must be seen in at least this many used frames.
        max_frames: at most this many frames are used (evenly spaced over the input).
        loss: ``least_squares`` robust loss (``soft_l1``, ``huber``, ``cauchy``, ``linear``).
        f_scale_px: residual (px) where the robust loss starts to flatten.
        prior_sigma_mm: sigma of the weak prior of tag centres toward the nominal (gauge only).
        outlier_px: after a first solve, a tag observation whose corner RMS exceeds this (and 5x the
            median) is dropped and the problem solved again.
        max_nfev: function evaluation budget of each solve.
    """

    min_tags_per_frame: int = 4
    min_frames_per_tag: int = 3
    max_frames: int = 400
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    prior_sigma_mm: float = 50.0
    outlier_px: float = 3.0
    max_nfev: int = 100

    def __post_init__(self) -> None:
        if self.min_tags_per_frame < 2:
            raise ConfigError(f"min_tags_per_frame must be >= 2, got {self.min_tags_per_frame}")
        if self.min_frames_per_tag < 1:
            raise ConfigError(f"min_frames_per_tag must be >= 1, got {self.min_frames_per_tag}")
        if self.max_frames < 2:
            raise ConfigError(f"max_frames must be >= 2, got {self.max_frames}")
        if self.loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
            raise ConfigError(f"unknown loss {self.loss!r}")
        for name in ("f_scale_px", "prior_sigma_mm", "outlier_px"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class TagDeviation:
    """How one as-built tag differs from the nominal one (cap frame, after the gauge alignment).

    Attributes:
        tag_id: the tag.
        offset_mm: built centre minus nominal centre (3,), cap frame, mm.
        rotation_deg: angle of the rotation from the nominal to the built tag, deg.
        about_normal_deg: its signed component about the tag normal (in-plane turn), deg.
        corner_rms_mm: RMS distance of the four corners from the nominal ones, mm.
        frames: used frames that saw the tag.
        rms_px: RMS reprojection error of its corners over those frames, px.
    """

    tag_id: int
    offset_mm: np.ndarray
    rotation_deg: float
    about_normal_deg: float
    corner_rms_mm: float
    frames: int
    rms_px: float

    def __post_init__(self) -> None:
        offset = np.array(self.offset_mm, dtype=np.float64).reshape(3)
        offset.setflags(write=False)
        object.__setattr__(self, "offset_mm", offset)

    @property
    def offset_norm_mm(self) -> float:
        return float(np.linalg.norm(self.offset_mm))


@dataclass(frozen=True)
class BuildResult:
    """An as-built cap model and how it was obtained.

    Attributes:
        model: the as-built model (same ids and corner order as the nominal), cap frame, mm.
        nominal: the model it started from.
        deviations: per tag, in model order.
        rms_px: RMS reprojection error of every used corner after the solve, px.
        frames_given: frames passed in.
        frames_used: frames used in the adjustment.
        frame_indices: positions (in the input) of the used frames.
        T_cam_cap: camera pose of each used frame in the as-built cap frame (translation in m).
        observations: tag observations used (frame x tag).
        observations_dropped: tag observations dropped as outliers.
        converged: the solver stopped on a tolerance (not on its budget).
    """

    model: CapModel
    nominal: CapModel = field(repr=False)
    deviations: tuple[TagDeviation, ...]
    rms_px: float
    frames_given: int
    frames_used: int
    frame_indices: tuple[int, ...] = field(repr=False)
    T_cam_cap: tuple[Transform, ...] = field(repr=False)
    observations: int
    observations_dropped: int
    converged: bool

    @property
    def corner_rms_mm(self) -> float:
        """RMS corner distance of the as-built model from the nominal one, mm."""
        d = self.model.corners_mm - self.nominal.corners_mm
        return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))

    def table(self) -> str:
        """A plain-text report: one line per tag, then the totals."""
        lines = [" id  frames  dx_mm  dy_mm  dz_mm  |d|_mm  rot_deg  about_n_deg  rms_px"]
        for d in self.deviations:
            lines.append(
                f"{d.tag_id:3d}  {d.frames:6d}  {d.offset_mm[0]:+5.2f}  {d.offset_mm[1]:+5.2f}  "
                f"{d.offset_mm[2]:+5.2f}  {d.offset_norm_mm:6.2f}  {d.rotation_deg:7.2f}  "
                f"{d.about_normal_deg:+11.2f}  {d.rms_px:6.2f}"
            )
        lines.append(
            f"frames used {self.frames_used}/{self.frames_given}, observations {self.observations} "
            f"(dropped {self.observations_dropped}), reprojection rms {self.rms_px:.3f} px, "
            f"corner rms from nominal {self.corner_rms_mm:.3f} mm"
            + ("" if self.converged else ", NOT CONVERGED (budget reached)")
        )
        return "\n".join(lines)

    def to_dict(self) -> dict[str, object]:
        """The report as plain data (JSON-ready)."""
        return {
            "rms_px": self.rms_px,
            "corner_rms_mm": self.corner_rms_mm,
            "frames_given": self.frames_given,
            "frames_used": self.frames_used,
            "observations": self.observations,
            "observations_dropped": self.observations_dropped,
            "converged": self.converged,
            "tags": [
                {
                    "id": d.tag_id,
                    "offset_mm": [float(v) for v in d.offset_mm],
                    "offset_norm_mm": d.offset_norm_mm,
                    "rotation_deg": d.rotation_deg,
                    "about_normal_deg": d.about_normal_deg,
                    "corner_rms_mm": d.corner_rms_mm,
                    "frames": d.frames,
                    "rms_px": d.rms_px,
                }
                for d in self.deviations
            ],
        }


# -- geometry helpers ---------------------------------------------------------------------------
def tag_frames(corners_mm: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """Best-fit rigid tag frames (R_cap_tag, centre mm) of corner sets (N, 4, 3).

    Each is the rotation that best maps ``LOCAL_CORNERS_MM`` onto the (centred) corners, so a
    slightly non-square measured tag gets its closest rigid square.
    """
    corners = np.asarray(corners_mm, dtype=np.float64)
    centres = corners.mean(axis=1)
    rotations = [Rotation.align_vectors(c - m, LOCAL_CORNERS_MM)[0] for c, m in zip(corners, centres)]
    return Rotation.concatenate(rotations), centres


def _corners_from_params(rotvec: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    r = Rotation.from_rotvec(rotvec)
    local = np.broadcast_to(LOCAL_CORNERS_MM, (len(t_mm), 4, 3))
    return np.einsum("nij,nkj->nki", r.as_matrix(), local) + t_mm[:, None, :]


def align_model(corners_mm: np.ndarray, reference_mm: np.ndarray) -> Transform:
    """Rigid ``T_ref_built`` (translation in mm here) that best maps corners onto the reference."""
    a = np.asarray(corners_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(reference_mm, dtype=np.float64).reshape(-1, 3)
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    rotation = Rotation.align_vectors(b - mb, a - ma)[0]
    return Transform(rotation, mb - rotation.apply(ma))


# -- the adjustment -----------------------------------------------------------------------------
@dataclass
class _Problem:
    """Observations in flat arrays: one row per tag observation (frame, tag, 4 corners)."""

    obs_frame: np.ndarray  # (M,) index into frames
    obs_tag: np.ndarray  # (M,) index into model tags
    obs_px: np.ndarray  # (M, 4, 2) undistorted corners
    intr: np.ndarray  # (M, 4) fx, fy, cx, cy of the observation's frame
    n_frames: int
    n_tags: int


def _residuals(x: np.ndarray, p: _Problem, prior_mm: np.ndarray, prior_sigma_mm: float) -> np.ndarray:
    tags = x[: 6 * p.n_tags].reshape(p.n_tags, 6)
    frames = x[6 * p.n_tags:].reshape(p.n_frames, 6)
    corners_cap = _corners_from_params(tags[:, :3], tags[:, 3:])  # (N, 4, 3)
    r_cam = Rotation.from_rotvec(frames[:, :3]).as_matrix()  # (F, 3, 3)
    pts = corners_cap[p.obs_tag]  # (M, 4, 3)
    cam = np.einsum("mij,mkj->mki", r_cam[p.obs_frame], pts) + frames[p.obs_frame, None, 3:]
    z = cam[..., 2]
    u = p.intr[:, None, 0] * cam[..., 0] / z + p.intr[:, None, 2]
    v = p.intr[:, None, 1] * cam[..., 1] / z + p.intr[:, None, 3]
    res = np.stack([u, v], axis=-1) - p.obs_px
    prior = (tags[:, 3:] - prior_mm) / prior_sigma_mm
    return np.concatenate([res.reshape(-1), prior.reshape(-1)])


def _sparsity(p: _Problem) -> coo_matrix:
    m = len(p.obs_tag)
    rows_per_obs = 8
    n_params = 6 * (p.n_tags + p.n_frames)
    rows, cols = [], []
    obs_rows = np.arange(m * rows_per_obs).reshape(m, rows_per_obs)
    for k in range(6):
        for cols_of, base in ((p.obs_tag, 0), (p.obs_frame, 6 * p.n_tags)):
            rows.append(obs_rows.reshape(-1))
            cols.append(np.repeat(base + 6 * cols_of + k, rows_per_obs))
    prior_rows = m * rows_per_obs + np.arange(3 * p.n_tags)
    rows.append(prior_rows)
    cols.append((6 * np.arange(p.n_tags)[:, None] + 3 + np.arange(3)[None, :]).reshape(-1))
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    return coo_matrix((np.ones(len(r)), (r, c)), shape=(m * rows_per_obs + 3 * p.n_tags, n_params))


def _solve(p: _Problem, x0: np.ndarray, prior_mm: np.ndarray, config: BuildConfig):  # type: ignore[no-untyped-def]
    return least_squares(
        _residuals, x0, args=(p, prior_mm, config.prior_sigma_mm), jac_sparsity=_sparsity(p),
        method="trf", loss=config.loss, f_scale=config.f_scale_px, x_scale="jac",
        max_nfev=config.max_nfev, xtol=1e-10, ftol=1e-10, gtol=1e-10,
    )


def _initial_pose(dets: Sequence[TagDetection], nominal: CapModel, camera: CameraModel,
                  min_tags: int) -> tuple[Transform, tuple[int, ...]] | None:
    """Camera pose from the nominal model and the tags that agree with it (pose inliers)."""
    from ficap_ros.pose import PoseConfig, estimate_cap_pose

    result = estimate_cap_pose(dets, nominal, camera, PoseConfig(method="joint", min_tags=min_tags))
    if result.pose is None:
        return None
    return result.pose.T_cam_cap, result.pose.used_ids


def build_model(
    frames: Sequence[Sequence[TagDetection]],
    camera: CameraModel | Sequence[CameraModel],
    nominal: CapModel | None = None,
    config: BuildConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> BuildResult:
    """Estimate the as-built cap from per-frame detections.

    Args:
        frames: the detections of each frame (ids outside the model are ignored; an id seen twice
            in one frame is ignored in that frame).
        camera: the intrinsics of every frame, or one per frame.
        nominal: the model to start from and align to (default: the cap-spec nominal).
        config: settings.
        progress: called with a one-line message at each stage.
    Returns:
        A ``BuildResult``; ``result.model.save(path)`` writes a normal cap model YAML.
    Raises:
        CoverageError: too few usable frames, or a tag not seen often enough with enough others.
        ConfigError: one camera per frame was expected but the counts differ.
    """
    config = config or BuildConfig()
    nominal = nominal or nominal_model()
    say = progress or (lambda _msg: None)
    cameras = [camera] * len(frames) if isinstance(camera, CameraModel) else list(camera)
    if len(cameras) != len(frames):
        raise ConfigError(f"{len(frames)} frames but {len(cameras)} cameras")

    # 1. Usable frames: enough distinct model tags, and an initial pose from the nominal model.
    candidates = []
    for index, dets in enumerate(frames):
        counts: dict[int, int] = {}
        for d in dets:
            if d.tag_id in nominal:
                counts[d.tag_id] = counts.get(d.tag_id, 0) + 1
        unique = [d for d in dets if counts.get(d.tag_id) == 1]
        if len(unique) >= config.min_tags_per_frame:
            candidates.append((index, unique))
    if len(candidates) > config.max_frames:
        pick = np.unique(np.linspace(0, len(candidates) - 1, config.max_frames).round().astype(int))
        candidates = [candidates[i] for i in pick]
    say(f"{len(candidates)} of {len(frames)} frames see >= {config.min_tags_per_frame} tags")
    used: list[tuple[int, Transform, list[TagDetection]]] = []
    for index, dets in candidates:
        start = _initial_pose(dets, nominal, cameras[index], config.min_tags_per_frame)
        if start is None:
            continue
        T, inlier_ids = start
        keep = [d for d in dets if d.tag_id in set(inlier_ids)]
        if len(keep) >= config.min_tags_per_frame:
            used.append((index, T, keep))
    if len(used) < 2:
        raise CoverageError(
            f"only {len(used)} frame(s) with a pose from >= {config.min_tags_per_frame} tags; "
            "record the cap from several angles so many tags are seen at once"
        )
    _check_coverage(nominal, [[d.tag_id for d in dets] for _, _, dets in used], config)
    say(f"adjusting {len(nominal)} tags over {len(used)} frames")

    # 2. Flat observation arrays (undistorted corners, per-observation intrinsics).
    obs_frame, obs_tag, obs_px, intr = [], [], [], []
    for f, (index, _, dets) in enumerate(used):
        cam = cameras[index]
        k = cam.K
        for d in dets:
            obs_frame.append(f)
            obs_tag.append(nominal.index_of(d.tag_id))
            obs_px.append(cam.undistort_px(d.corners_px))
            intr.append((k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
    problem = _Problem(np.array(obs_frame), np.array(obs_tag), np.array(obs_px), np.array(intr),
                       len(used), len(nominal))

    # 3. Initial values: nominal tag frames; camera poses from the nominal model (mm).
    r_tags, centres = tag_frames(nominal.corners_mm)
    x_tags = np.hstack([r_tags.as_rotvec(), centres])
    x_frames = np.array([np.hstack([T.rvec, T.translation_m * 1000.0]) for _, T, _ in used])
    x0 = np.concatenate([x_tags.reshape(-1), x_frames.reshape(-1)])
    prior_mm = centres.copy()

    solution = _solve(problem, x0, prior_mm, config)
    dropped = 0
    per_obs = _observation_rms_px(solution.x, problem, prior_mm, config)
    limit = max(config.outlier_px, 5.0 * float(np.median(per_obs)))
    bad = per_obs > limit
    if bad.any():
        dropped = int(bad.sum())
        say(f"dropping {dropped} tag observation(s) above {limit:.2f} px rms; solving again")
        keep = ~bad
        problem = _Problem(problem.obs_frame[keep], problem.obs_tag[keep], problem.obs_px[keep],
                           problem.intr[keep], problem.n_frames, problem.n_tags)
        _check_coverage(nominal, _ids_per_frame(problem, nominal), config)
        solution = _solve(problem, solution.x, prior_mm, config)
    per_obs = _observation_rms_px(solution.x, problem, prior_mm, config)

    # 4. Gauge: align the built corners to the nominal ones.
    tags = solution.x[: 6 * problem.n_tags].reshape(-1, 6)
    frames_x = solution.x[6 * problem.n_tags:].reshape(-1, 6)
    built = _corners_from_params(tags[:, :3], tags[:, 3:])
    T_nom_built = align_model(built, nominal.corners_mm)  # mm
    built = T_nom_built.apply(built)
    model = CapModel(nominal.ids, built)
    T_built_nom_m = Transform(T_nom_built.rotation, T_nom_built.translation_m / 1000.0).inv()
    poses = tuple(
        Transform(Rotation.from_rotvec(fx[:3]), fx[3:] / 1000.0) * T_built_nom_m for fx in frames_x
    )

    # 5. Report.
    r_nom, c_nom = tag_frames(nominal.corners_mm)
    r_built, c_built = tag_frames(built)
    delta = (r_nom.inv() * r_built).as_rotvec()  # in the nominal tag frame; z = inward normal
    deviations = []
    for i, tag_id in enumerate(nominal.ids):
        mine = problem.obs_tag == i
        d_corner = built[i] - nominal.corners_mm[i]
        deviations.append(TagDeviation(
            tag_id=tag_id,
            offset_mm=c_built[i] - c_nom[i],
            rotation_deg=float(np.degrees(np.linalg.norm(delta[i]))),
            # Tag z points into the cap: a positive turn about the outward normal is -z.
            about_normal_deg=float(np.degrees(-delta[i][2])),
            corner_rms_mm=float(np.sqrt(np.mean(np.sum(d_corner * d_corner, axis=-1)))),
            frames=int(mine.sum()),
            rms_px=float(np.sqrt(np.mean(per_obs[mine] ** 2))) if mine.any() else float("nan"),
        ))
    rms = float(np.sqrt(np.mean(per_obs ** 2)))
    say(f"reprojection rms {rms:.3f} px after {solution.nfev} evaluations")
    return BuildResult(
        model=model,
        nominal=nominal,
        deviations=tuple(deviations),
        rms_px=rms,
        frames_given=len(frames),
        frames_used=len(used),
        frame_indices=tuple(index for index, _, _ in used),
        T_cam_cap=poses,
        observations=len(problem.obs_tag),
        observations_dropped=dropped,
        converged=bool(solution.status > 0),
    )


def _observation_rms_px(x: np.ndarray, p: _Problem, prior_mm: np.ndarray,
                        config: BuildConfig) -> np.ndarray:
    res = _residuals(x, p, prior_mm, config.prior_sigma_mm)[: 8 * len(p.obs_tag)]
    return np.sqrt(np.mean(res.reshape(-1, 4, 2) ** 2, axis=(1, 2)) * 2.0)


def _ids_per_frame(p: _Problem, nominal: CapModel) -> list[list[int]]:
    out: list[list[int]] = [[] for _ in range(p.n_frames)]
    for f, t in zip(p.obs_frame, p.obs_tag):
        out[int(f)].append(nominal.ids[int(t)])
    return out


def _check_coverage(nominal: CapModel, ids_per_frame: list[list[int]], config: BuildConfig) -> None:
    """Every tag seen in enough frames (each with enough tags), all tags linked through frames."""
    counts = {tag_id: 0 for tag_id in nominal.ids}
    parent = {tag_id: tag_id for tag_id in nominal.ids}

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for ids in ids_per_frame:
        if len(ids) < config.min_tags_per_frame:
            continue
        for tag_id in ids:
            counts[tag_id] += 1
            parent[root(tag_id)] = root(ids[0])
    short = [f"{t} ({n})" for t, n in counts.items() if n < config.min_frames_per_tag]
    if short:
        raise CoverageError(
            f"tag(s) {', '.join(short)} seen in too few frames together with "
            f">= {config.min_tags_per_frame - 1} other tags (need {config.min_frames_per_tag}); "
            "record more views showing them"
        )
    groups = {root(t) for t in nominal.ids}
    if len(groups) > 1:
        raise CoverageError(
            f"the tags fall into {len(groups)} groups never seen together in one frame; "
            "record views that show tags of neighbouring groups at once"
        )
