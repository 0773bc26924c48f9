"""The cap as built, by bundle adjustment over frames that see many tags at once.

Unknowns: every tag is a rigid 32 mm square with its own 6-DoF pose in the cap frame (``R_cap_tag``,
``t_cap_tag_mm``); every frame has its camera pose ``T_cam_cap``; and one global nuisance, the
*edge offset* of the detected corners (px, positive outward). Residuals are the reprojection errors
of the detected corners (undistorted with the frame's intrinsics, so every lens model shares one
pinhole projection), minimised with ``scipy.optimize.least_squares`` (TRF, sparse Jacobian from
``jac_sparsity``, robust ``soft_l1`` loss so a bad corner cannot drag a tag).

Why the edge offset. A corner detector that fits the tag's border lines finds them displaced by a
roughly constant fraction of a pixel when the image chain (lens blur, tone curve, JPEG) is not
symmetric about the black-white edge: on real images the corners sit ~0.2-0.9 px inside each tag.
If the printed 32 mm side were the only metric reference, every tag would look ~1 % small and the
solver would grow the whole cap by ~1 % to fit (a replay with that model then puts the cap ~7 mm
too far away). So the predicted corner of a tag is its projected corner moved so that both of its
border lines shift by the same ``edge_offset_px`` along their outward normals in the image (the
intersection of the two shifted lines), the way a border-line detector errs.

Why the size is anchored to the nominal layout. An edge offset and a uniform scale of the cap are
nearly interchangeable in the images (both change how large a tag looks), and only the spread of
distances and view angles separates them (and a bias that is not exactly an edge offset leaks
into the size). Hand assembly moves and turns plates; it does not grow the cap. So the RMS radius
of the tag centres is held at the nominal's (``anchor_size``, a stiff prior), and every tag has a
prior toward its nominal place (``assembly_sigma_mm``, about the accuracy of gluing a plate by
hand) and orientation (``assembly_sigma_deg``), which fix the gauge (the rigid motion of the whole
cap the images cannot see) and hold a tag the images barely see. Each plate's own deviation is
measured by the images (its prior weighs about (0.05 mm / 1 mm)^2 against the data).

The anchor costs what hand assembly does to the size (``assembly_size_sigma``: about 0.3 % for
1 mm plates). So with ``size="auto"`` (the default) the edge offset of the same fit with the size
free decides: when the size change it implies (2 |offset| / median tag side) is below that, the
corners are unbiased enough for the printed side to be the better scale, and the model is solved
again with the offset held at 0 and the size free. After the solve the model is Kabsch-aligned
to the nominal corners, so the as-built cap frame is the nominal one in the least-squares sense,
and per-tag deviations are relative to it.

Trust. Each tag's deviation comes with a standard deviation from the Gauss-Newton covariance (the
Schur complement over the camera poses, the whole-cap rigid motion projected out), with its
observation count and the spread of the directions it was seen from. ``BuildResult.problems`` lists
every reason not to trust the model (solver budget reached, a tag seen too rarely or with a large
uncertainty; optionally from too narrow a spread of directions); ``replay_check`` re-estimates
every frame's pose with the nominal and the built model, the pose code replay uses, and adds a
warning when the built model fits the recording worse, a problem when it moves the cap along the
line of sight by more than hand assembly can (``depth_change_limit``).

Tag frame (local): x along the tag's top edge (TL -> TR), y down (TL -> BL), z = x cross y (into
the cap); local corners (-16, -16, 0), (16, -16, 0), (16, 16, 0), (-16, 16, 0) mm = TL, TR, BR, BL.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError, ModelError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel, nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.detector import TagDetection

__all__ = [
    "CoverageError",
    "BuildConfig",
    "TagDeviation",
    "BuildResult",
    "ReplayCheck",
    "build_model",
    "replay_check",
    "depth_change_limit",
    "assembly_size_sigma",
    "tag_frames",
    "align_model",
    "size_ratio",
    "edge_shift_px",
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
    """Settings of ``build_model`` and ``replay_check``.

    Attributes:
        min_tags_per_frame: frames with fewer (pose-inlier) model tags are not used.
        min_frames_per_tag: every model tag must be seen in at least this many used frames.
        max_frames: at most this many frames are used (evenly spaced over the input).
        loss: ``least_squares`` robust loss (``soft_l1``, ``huber``, ``cauchy``, ``linear``).
        f_scale_px: residual (px) where the robust loss starts to flatten.
        assembly_sigma_mm: how far (per axis, 1 sigma) a plate may sit from its nominal place: the
            prior that anchors the cap's overall size and the gauge.
        assembly_sigma_deg: the same for its orientation (each rotation axis).
        fit_edge_offset: estimate the global edge offset of the detected corners; ``False`` holds it
            at ``edge_offset_px`` (the printed tag side is then the only scale reference).
        edge_offset_px: start (or fixed) value of the edge offset, px, positive outward.
        anchor_size: hold the RMS radius of the tag centres (about their centroid) at the
            nominal's (a stiff prior, 1e-4 relative): the cap's overall size comes from the
            nominal layout, the plates' moves and turns from the images. ``False`` leaves the size
            to the images and the per-plate priors.
        size: ``auto`` (default): the anchored, edge-offset model is solved first; when the size
            change its fitted edge offset implies (2 |offset| / median tag side, with the size
            free) is smaller than what hand assembly does to the size (``assembly_sigma_mm /
            (sqrt(N) r)``, r the RMS radius of the tag centres), the corners are unbiased enough
            for the printed side to be the better scale reference, and the model is solved again
            with the offset held at 0 and the size free. ``fixed``: ``fit_edge_offset`` and
            ``anchor_size`` as given.
        outlier_px: after a first solve, a tag observation whose corner RMS exceeds this (and 5x the
            median) is dropped and the problem solved again.
        max_nfev: function evaluation budget of each solve.
        max_corner_sigma_mm: a tag whose corners are less certain than this (1 sigma, rms over the
            four, after the gauge) is poorly observed: at a quarter of the ~1 mm a plate is off
            by hand, a built tag is clearly closer to the truth than its nominal place.
        min_view_spread_deg: a tag seen from directions spanning less than this is poorly observed
            (its distance along the one line of sight rests on its apparent size alone). Default 0
            (reported, not judged): the uncertainty already carries the geometry, and a 1080p
            synth drive had a tag seen within 6 deg that was built to 0.05 mm.
        max_depth_change: ``replay_check``: the largest median relative change of the camera-cap
            distance between the built and the nominal model's poses (a fraction). A correct
            as-built model moves it by what the nominal model gets wrong, about 0.1 % (0.01 % on
            blender_dev's hand-built cap, 0.11 % on a rendered one); a cap grown by the corner
            bias moves it by 0.5-1 %.
    """

    min_tags_per_frame: int = 4
    min_frames_per_tag: int = 3
    max_frames: int = 400
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    assembly_sigma_mm: float = 1.0
    assembly_sigma_deg: float = 2.0
    fit_edge_offset: bool = True
    edge_offset_px: float = 0.0
    anchor_size: bool = True
    size: str = "auto"
    outlier_px: float = 3.0
    max_nfev: int = 100
    max_corner_sigma_mm: float = 0.25
    min_view_spread_deg: float = 0.0
    max_depth_change: float = 0.003

    def __post_init__(self) -> None:
        if self.min_tags_per_frame < 2:
            raise ConfigError(f"min_tags_per_frame must be >= 2, got {self.min_tags_per_frame}")
        if self.min_frames_per_tag < 1:
            raise ConfigError(f"min_frames_per_tag must be >= 1, got {self.min_frames_per_tag}")
        if self.max_frames < 2:
            raise ConfigError(f"max_frames must be >= 2, got {self.max_frames}")
        if self.max_nfev < 1:
            raise ConfigError(f"max_nfev must be >= 1, got {self.max_nfev}")
        if self.size not in ("auto", "fixed"):
            raise ConfigError(f"size must be 'auto' or 'fixed', got {self.size!r}")
        if self.loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
            raise ConfigError(f"unknown loss {self.loss!r}")
        for name in ("f_scale_px", "assembly_sigma_mm", "assembly_sigma_deg", "outlier_px",
                     "max_corner_sigma_mm", "max_depth_change"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if not np.isfinite(self.edge_offset_px) or abs(self.edge_offset_px) > 5.0:
            raise ConfigError(f"edge_offset_px must be within +-5 px, got {self.edge_offset_px}")
        if not 0.0 <= self.min_view_spread_deg < 180.0:
            raise ConfigError(f"min_view_spread_deg must be in [0, 180), got {self.min_view_spread_deg}")


@dataclass(frozen=True)
class TagDeviation:
    """How one as-built tag differs from the nominal one (cap frame, after the gauge alignment).

    Attributes:
        tag_id: the tag.
        offset_mm: built centre minus nominal centre (3,), cap frame, mm.
        offset_sigma_mm: 1-sigma uncertainty of that offset (root of the covariance's trace), mm.
        rotation_deg: angle of the rotation from the nominal to the built tag, deg.
        about_normal_deg: its signed component about the tag normal (in-plane turn), deg.
        about_normal_sigma_deg: 1-sigma uncertainty of that turn, deg.
        corner_rms_mm: RMS distance of the four corners from the nominal ones, mm.
        corner_sigma_mm: 1-sigma uncertainty of the corners (rms over the four), mm.
        frames: used frames that saw the tag (observations).
        view_angle_min_deg, view_angle_max_deg: range of its angle between the line of sight and
            the tag normal over those frames, deg.
        view_spread_deg: largest angle between two directions it was seen from, deg.
        rms_px: RMS reprojection error of its corners over those frames, px.
        problem: why it is poorly observed ("" when it is not).
    """

    tag_id: int
    offset_mm: np.ndarray
    offset_sigma_mm: float
    rotation_deg: float
    about_normal_deg: float
    about_normal_sigma_deg: float
    corner_rms_mm: float
    corner_sigma_mm: float
    frames: int
    view_angle_min_deg: float
    view_angle_max_deg: float
    view_spread_deg: float
    rms_px: float
    problem: str = ""

    def __post_init__(self) -> None:
        offset = np.array(self.offset_mm, dtype=np.float64).reshape(3)
        offset.setflags(write=False)
        object.__setattr__(self, "offset_mm", offset)

    @property
    def offset_norm_mm(self) -> float:
        return float(np.linalg.norm(self.offset_mm))


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


@dataclass(frozen=True)
class BuildResult:
    """An as-built cap model and how it was obtained.

    Attributes:
        model: the as-built model (same ids and corner order as the nominal), cap frame, mm.
        nominal: the model it started from.
        deviations: per tag, in model order.
        rms_px: RMS reprojection error of every used corner after the solve, px.
        edge_offset_px: the fitted (or held) edge offset of the detected corners, px, + outward.
        edge_offset_sigma_px: its 1-sigma uncertainty (0 when held).
        median_side_px: median apparent tag side over the observations, px.
        size_ratio: size of the built cap over the nominal one (``size_ratio``), 1 = same size.
        size_ratio_images: the size the images alone give (the same adjustment with the size free;
            NaN when the size was not anchored): it differs from the nominal by the cap's true
            size change plus what the edge-offset model misses of the detector's bias.
        edge_offset_images_px: the edge offset of that size-free adjustment (NaN when not run).
        size_source: where the cap's size came from: ``nominal layout`` (anchored), ``tag side``
            (offset held, size free: the printed side is the scale) or ``images`` (offset fitted,
            size free).
        frames_given: frames passed in.
        frames_used: frames used in the adjustment.
        frame_indices: positions (in the input) of the used frames.
        T_cam_cap: camera pose of each used frame in the as-built cap frame (translation in m).
        observations: tag observations used (frame x tag).
        observations_dropped: tag observations dropped as outliers.
        converged: the solver stopped on a tolerance (not on its budget).
        nfev: function evaluations of the last solve.
        problems: every reason not to trust the model ("" free; empty when trusted).
    """

    model: CapModel
    nominal: CapModel = field(repr=False)
    deviations: tuple[TagDeviation, ...]
    rms_px: float
    edge_offset_px: float
    edge_offset_sigma_px: float
    median_side_px: float
    size_ratio: float
    size_ratio_images: float
    edge_offset_images_px: float
    size_source: str
    frames_given: int
    frames_used: int
    frame_indices: tuple[int, ...] = field(repr=False)
    T_cam_cap: tuple[Transform, ...] = field(repr=False)
    observations: int
    observations_dropped: int
    converged: bool
    nfev: int
    problems: tuple[str, ...] = ()

    @property
    def trusted(self) -> bool:
        return not self.problems

    @property
    def corner_rms_mm(self) -> float:
        """RMS corner distance of the as-built model from the nominal one, mm."""
        d = self.model.corners_mm - self.nominal.corners_mm
        return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))

    @property
    def effective_side_mm(self) -> float:
        """The tag side a side-only scale would have seen: 32 mm grown by twice the edge offset at
        the median apparent side (what the edge offset would have done to the cap's size)."""
        return TAG_SIDE_MM * (1.0 + 2.0 * self.edge_offset_px / self.median_side_px)

    def table(self) -> str:
        """A plain-text report: one line per tag, then the totals."""
        lines = [" id  obs  view_deg  spread  dx_mm  dy_mm  dz_mm  |d|_mm  +-sd_mm  rot_deg  "
                 "about_n_deg  +-sd_deg  rms_px  flag"]
        for d in self.deviations:
            lines.append(
                f"{d.tag_id:3d}  {d.frames:3d}  {d.view_angle_min_deg:3.0f}-{d.view_angle_max_deg:<3.0f}  "
                f"{d.view_spread_deg:6.1f}  {d.offset_mm[0]:+5.2f}  {d.offset_mm[1]:+5.2f}  "
                f"{d.offset_mm[2]:+5.2f}  {d.offset_norm_mm:6.2f}  {d.offset_sigma_mm:7.3f}  "
                f"{d.rotation_deg:7.2f}  {d.about_normal_deg:+11.2f}  {d.about_normal_sigma_deg:8.3f}  "
                f"{d.rms_px:6.2f}  {'POOR' if d.problem else 'ok'}"
            )
        lines.append(
            f"frames used {self.frames_used}/{self.frames_given}, observations {self.observations} "
            f"(dropped {self.observations_dropped}), reprojection rms {self.rms_px:.3f} px, "
            f"corner rms from nominal {self.corner_rms_mm:.3f} mm"
        )
        lines.append(
            f"edge offset of the detected corners {self.edge_offset_px:+.3f} +- "
            f"{self.edge_offset_sigma_px:.3f} px (+ outward; at the median tag side "
            f"{self.median_side_px:.0f} px a side-only scale would have read the tags as "
            f"{self.effective_side_mm:.2f} mm)"
        )
        lines.append(
            f"cap size vs nominal {100.0 * (self.size_ratio - 1.0):+.3f} %, from the {self.size_source}"
            + ("" if np.isnan(self.size_ratio_images) else
               f" (the images with the edge offset fitted and the size free: "
               f"{100.0 * (self.size_ratio_images - 1.0):+.3f} %, offset {self.edge_offset_images_px:+.3f} px)")
        )
        lines.append("solver " + ("converged" if self.converged else "NOT CONVERGED (budget reached)")
                     + f" after {self.nfev} evaluations")
        lines += [f"PROBLEM: {p}" for p in self.problems]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, object]:
        """The report as plain data (JSON-ready)."""
        return {
            "rms_px": self.rms_px,
            "corner_rms_mm": self.corner_rms_mm,
            "edge_offset_px": self.edge_offset_px,
            "edge_offset_sigma_px": self.edge_offset_sigma_px,
            "median_side_px": self.median_side_px,
            "effective_side_mm": self.effective_side_mm,
            "size_ratio": self.size_ratio,
            "size_ratio_images": None if np.isnan(self.size_ratio_images) else self.size_ratio_images,
            "edge_offset_images_px": None if np.isnan(self.edge_offset_images_px) else self.edge_offset_images_px,
            "size_source": self.size_source,
            "frames_given": self.frames_given,
            "frames_used": self.frames_used,
            "observations": self.observations,
            "observations_dropped": self.observations_dropped,
            "converged": self.converged,
            "nfev": self.nfev,
            "trusted": self.trusted,
            "problems": list(self.problems),
            "tags": [
                {
                    "id": d.tag_id,
                    "offset_mm": [float(v) for v in d.offset_mm],
                    "offset_norm_mm": d.offset_norm_mm,
                    "offset_sigma_mm": d.offset_sigma_mm,
                    "rotation_deg": d.rotation_deg,
                    "about_normal_deg": d.about_normal_deg,
                    "about_normal_sigma_deg": d.about_normal_sigma_deg,
                    "corner_rms_mm": d.corner_rms_mm,
                    "corner_sigma_mm": d.corner_sigma_mm,
                    "frames": d.frames,
                    "view_angle_min_deg": d.view_angle_min_deg,
                    "view_angle_max_deg": d.view_angle_max_deg,
                    "view_spread_deg": d.view_spread_deg,
                    "rms_px": d.rms_px,
                    "problem": d.problem,
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


def size_ratio(corners_mm: np.ndarray, reference_mm: np.ndarray) -> float:
    """Size of a cap relative to another: ratio of the RMS distances of their corners from their
    centroids (rotation and translation do not change it)."""
    a = np.asarray(corners_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(reference_mm, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(np.sum((a - a.mean(0)) ** 2) / np.sum((b - b.mean(0)) ** 2)))


def edge_shift_px(quads_px: np.ndarray, offset_px: float) -> np.ndarray:
    """Where a border-line detector puts the corners of quads whose edges it finds ``offset_px``
    outside the true ones (negative: inside).

    Args:
        quads_px: (..., 4, 2) true image corners, in order around the quad (either sense).
        offset_px: the edge offset, px, positive outward.
    Returns:
        (..., 4, 2) corners where both lines through each corner are moved by the offset along
        their outward normals (the corners of the offset quad).
    """
    q = np.asarray(quads_px, dtype=np.float64)
    edge = np.roll(q, -1, axis=-2) - q  # edge k runs from corner k to k+1
    normal = np.stack([edge[..., 1], -edge[..., 0]], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mid = q + 0.5 * edge
    outward = np.sign(np.sum((mid - q.mean(axis=-2, keepdims=True)) * normal, axis=-1))
    normal *= outward[..., None]
    a = normal  # corner k is on edge k ...
    b = np.roll(normal, 1, axis=-2)  # ... and on edge k-1
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    # Solve [a; b] d = [offset, offset] per corner.
    d = np.stack([b[..., 1] - a[..., 1], a[..., 0] - b[..., 0]], axis=-1) / det[..., None]
    return q + float(offset_px) * d


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

    def subset(self, keep: np.ndarray) -> _Problem:
        return _Problem(self.obs_frame[keep], self.obs_tag[keep], self.obs_px[keep], self.intr[keep],
                        self.n_frames, self.n_tags)


#: Relative sigma of the size anchor: stiff enough to hold the size to a few parts per million
#: (on blender_dev's as-built set: 2 ppm),
#: soft enough to keep the problem well conditioned.
_SIZE_SIGMA = 1e-4


@dataclass(frozen=True)
class _Priors:
    centres_mm: np.ndarray  # (N, 3) nominal tag centres
    rotations: Rotation  # (N,) nominal tag orientations
    sigma_mm: float
    sigma_rad: float

    @property
    def radius_mm(self) -> float:
        return _rms_radius(self.centres_mm)


def _rms_radius(centres_mm: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((centres_mm - centres_mm.mean(axis=0)) ** 2, axis=1))))


def _unpack(x: np.ndarray, p: _Problem, config: BuildConfig) -> tuple[np.ndarray, float, np.ndarray]:
    n_tag = 6 * p.n_tags
    tags = x[:n_tag].reshape(p.n_tags, 6)
    if config.fit_edge_offset:
        offset, frames = float(x[n_tag]), x[n_tag + 1:]
    else:
        offset, frames = config.edge_offset_px, x[n_tag:]
    return tags, offset, frames.reshape(p.n_frames, 6)


def _project(tags: np.ndarray, frames: np.ndarray, p: _Problem) -> np.ndarray:
    corners_cap = _corners_from_params(tags[:, :3], tags[:, 3:])  # (N, 4, 3)
    r_cam = Rotation.from_rotvec(frames[:, :3]).as_matrix()  # (F, 3, 3)
    pts = corners_cap[p.obs_tag]  # (M, 4, 3)
    cam = np.einsum("mij,mkj->mki", r_cam[p.obs_frame], pts) + frames[p.obs_frame, None, 3:]
    z = cam[..., 2]
    u = p.intr[:, None, 0] * cam[..., 0] / z + p.intr[:, None, 2]
    v = p.intr[:, None, 1] * cam[..., 1] / z + p.intr[:, None, 3]
    return np.stack([u, v], axis=-1)


def _residuals(x: np.ndarray, p: _Problem, priors: _Priors, config: BuildConfig) -> np.ndarray:
    tags, offset, frames = _unpack(x, p, config)
    predicted = edge_shift_px(_project(tags, frames, p), offset)
    res = predicted - p.obs_px
    # Priors: where hand assembly puts a plate (anchors the cap's size and the gauge).
    prior_t = (tags[:, 3:] - priors.centres_mm) / priors.sigma_mm
    prior_r = (priors.rotations.inv() * Rotation.from_rotvec(tags[:, :3])).as_rotvec() / priors.sigma_rad
    parts = [res.reshape(-1), prior_t.reshape(-1), prior_r.reshape(-1)]
    if config.anchor_size:
        size = _rms_radius(tags[:, 3:]) / priors.radius_mm - 1.0
        parts.append(np.array([size / _SIZE_SIGMA]))
    return np.concatenate(parts)


def _n_params(p: _Problem, config: BuildConfig) -> int:
    return 6 * (p.n_tags + p.n_frames) + int(config.fit_edge_offset)


def _jacobian(x: np.ndarray, p: _Problem, priors: _Priors, config: BuildConfig) -> csr_matrix:
    """Sparse Jacobian of ``_residuals``: forward differences in 13 grouped evaluations, the size
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
    f0 = _residuals(x, p, priors, config)
    obs_rows = np.arange(m8).reshape(-1, 8)
    rows, cols, vals = [], [], []

    def stepped(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(h, change of the residuals) with the parameters ``idx`` stepped by h together."""
        h = 1.49e-8 * np.maximum(1.0, np.abs(x[idx]))
        xs = x.copy()
        xs[idx] += h
        return h, _residuals(xs, p, priors, config) - f0

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
        radius = _rms_radius(t)
        grad = (t - t.mean(axis=0)) / (len(t) * radius) / priors.radius_mm / _SIZE_SIGMA
        rows.append(np.full(3 * p.n_tags, n_rows - 1))
        cols.append((6 * np.arange(p.n_tags)[:, None] + 3 + np.arange(3)[None, :]).reshape(-1))
        vals.append(grad.reshape(-1))
    return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_rows, _n_params(p, config))).tocsr()


def _solve(p: _Problem, x0: np.ndarray, priors: _Priors, config: BuildConfig):  # type: ignore[no-untyped-def]
    return least_squares(
        _residuals, x0, jac=_jacobian, args=(p, priors, config),
        method="trf", loss=config.loss, f_scale=config.f_scale_px, x_scale="jac",
        # scipy's default tolerances: 1e-10 changed no result in the 5th digit on blender_dev and
        # a 1080p synth drive but took 365 instead of 24 evaluations on the latter.
        max_nfev=config.max_nfev, xtol=1e-8, ftol=1e-8, gtol=1e-8,
    )


def _initial_pose(dets: Sequence[TagDetection], nominal: CapModel, camera: CameraModel,
                  min_tags: int) -> tuple[Transform, tuple[int, ...]] | None:
    """Camera pose from the nominal model and the tags that agree with it (pose inliers)."""
    from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose

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
    problems: list[str] = []
    coverage = _coverage_problems(nominal, [[d.tag_id for d in dets] for _, _, dets in used], config)
    if coverage and not allow_partial:
        raise CoverageError(coverage[0])
    problems += coverage
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
    priors = _Priors(centres.copy(), r_tags, config.assembly_sigma_mm,
                     np.radians(config.assembly_sigma_deg))
    x_tags = np.hstack([r_tags.as_rotvec(), centres])
    x_frames = np.array([np.hstack([T.rvec, T.translation_m * 1000.0]) for _, T, _ in used])
    x_offset = [config.edge_offset_px] if config.fit_edge_offset else []
    x0 = np.concatenate([x_tags.reshape(-1), x_offset, x_frames.reshape(-1)])

    solution = _solve(problem, x0, priors, config)
    dropped = 0
    per_obs = _observation_rms_px(solution.x, problem, priors, config)
    limit = max(config.outlier_px, 5.0 * float(np.median(per_obs)))
    bad = per_obs > limit
    if bad.any():
        dropped = int(bad.sum())
        say(f"dropping {dropped} tag observation(s) above {limit:.2f} px rms; solving again")
        problem = problem.subset(~bad)
        after = _coverage_problems(nominal, _ids_per_frame(problem, nominal), config)
        if after and not allow_partial:
            raise CoverageError(after[0] + f" (after dropping {dropped} outlier observation(s))")
        problems += [p for p in after if p not in problems]
        solution = _solve(problem, solution.x, priors, config)
    # What the images alone say about the size (a diagnostic beside the anchored model, and the
    # ``auto`` decision): the same problem with the size free, from the anchored solution.
    size_images = offset_images = float("nan")
    if config.anchor_size and config.fit_edge_offset:
        free = replace(config, anchor_size=False)
        x_free = _solve(problem, solution.x, priors, free).x
        t_free, offset_images, _ = _unpack(x_free, problem, free)
        size_images = size_ratio(_corners_from_params(t_free[:, :3], t_free[:, 3:]), nominal.corners_mm)
    quads = problem.obs_px
    side_px = float(np.median(np.linalg.norm(np.roll(quads, -1, axis=1) - quads, axis=-1)))
    if config.size == "auto" and config.anchor_size and config.fit_edge_offset:
        bias_size = 2.0 * abs(offset_images) / side_px
        assembly_size = assembly_size_sigma(nominal, config)
        if bias_size < assembly_size:
            say(f"edge offset {offset_images:+.3f} px changes the size by {100 * bias_size:.3f} %, less "
                f"than hand assembly's {100 * assembly_size:.3f} %: the printed tag side sets the size")
            anchored = config
            config = replace(config, fit_edge_offset=False, edge_offset_px=0.0, anchor_size=False)
            x_side = np.delete(solution.x, 6 * problem.n_tags) if anchored.fit_edge_offset else solution.x
            solution = _solve(problem, x_side, priors, config)
        else:
            say(f"edge offset {offset_images:+.3f} px changes the size by {100 * bias_size:.3f} %, more "
                f"than hand assembly's {100 * assembly_size:.3f} %: the nominal layout sets the size")
    size_source = ("nominal layout" if config.anchor_size else
                   "images" if config.fit_edge_offset else "tag side")
    per_obs = _observation_rms_px(solution.x, problem, priors, config)
    converged = bool(solution.status > 0)
    if not converged:
        problems.append(f"the solver stopped at its budget of {config.max_nfev} evaluations "
                        "without converging")

    # 4. Uncertainty (before the gauge alignment; the covariance is projected onto it below).
    tags, offset, frames_x = _unpack(solution.x, problem, config)
    raw = _corners_from_params(tags[:, :3], tags[:, 3:])
    cov_corners, offset_var = _structure_covariance(solution, problem, config, raw)

    # 5. Gauge: align the built corners to the nominal ones.
    T_nom_built = align_model(raw, nominal.corners_mm)  # mm
    built = T_nom_built.apply(raw)
    model = CapModel(nominal.ids, built)
    R_nb = T_nom_built.rotation.as_matrix()
    cov_corners = _rotate_covariance(cov_corners, R_nb)
    T_built_nom_m = Transform(T_nom_built.rotation, T_nom_built.translation_m / 1000.0).inv()
    poses = tuple(
        Transform(Rotation.from_rotvec(fx[:3]), fx[3:] / 1000.0) * T_built_nom_m for fx in frames_x
    )

    # 6. Report.
    deviations = _deviations(nominal, built, cov_corners, problem, per_obs, poses, config)
    for d in deviations:
        if d.problem:
            problems.append(f"tag {d.tag_id}: {d.problem}")
    rms = float(np.sqrt(np.mean(per_obs ** 2)))
    say(f"reprojection rms {rms:.3f} px after {solution.nfev} evaluations, edge offset {offset:+.3f} px")
    return BuildResult(
        model=model,
        nominal=nominal,
        deviations=tuple(deviations),
        rms_px=rms,
        edge_offset_px=float(offset),
        edge_offset_sigma_px=float(np.sqrt(offset_var)),
        median_side_px=side_px,
        size_ratio=size_ratio(built, nominal.corners_mm),
        size_ratio_images=size_images,
        edge_offset_images_px=float(offset_images),
        size_source=size_source,
        frames_given=len(frames),
        frames_used=len(used),
        frame_indices=tuple(index for index, _, _ in used),
        T_cam_cap=poses,
        observations=len(problem.obs_tag),
        observations_dropped=dropped,
        converged=converged,
        nfev=int(solution.nfev),
        problems=tuple(problems),
    )


def _rotate_covariance(cov: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Covariance (K, 3, K, 3) of points, expressed after rotating every point by ``R``."""
    return np.einsum("ab,ibjc,dc->iajd", R, cov, R)


def _structure_covariance(solution, p: _Problem, config: BuildConfig,  # type: ignore[no-untyped-def]
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
            dc = (_corners_from_params(hi[None, :3], hi[None, 3:]) -
                  _corners_from_params(lo[None, :3], lo[None, 3:]))[0] / (2 * step)
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


def _deviations(nominal: CapModel, built: np.ndarray, cov: np.ndarray, p: _Problem,
                per_obs: np.ndarray, poses: Sequence[Transform], config: BuildConfig) -> list[TagDeviation]:
    r_nom, c_nom = tag_frames(nominal.corners_mm)
    r_built, c_built = tag_frames(built)
    delta = (r_nom.inv() * r_built).as_rotvec()  # in the nominal tag frame; z = inward normal
    normals = CapModel(nominal.ids, built).normals
    cam_centres_mm = np.array([T.inv().translation_m * 1000.0 for T in poses])
    out = []
    for i, tag_id in enumerate(nominal.ids):
        mine = p.obs_tag == i
        d_corner = built[i] - nominal.corners_mm[i]
        block = cov[4 * i: 4 * i + 4, :, 4 * i: 4 * i + 4, :]  # (4, 3, 4, 3)
        corner_var = np.array([np.trace(block[k, :, k, :]) for k in range(4)])
        centre_cov = block.sum(axis=(0, 2)) / 16.0
        # In-plane turn: tangential corner motion over the corner radius, averaged over corners.
        radial = built[i] - built[i].mean(axis=0)
        w = np.cross(normals[i], radial) / np.sum(radial * radial, axis=1, keepdims=True) / 4.0
        turn_var = float(np.einsum("ka,kalb,lb->", w, block, w))
        views = cam_centres_mm[p.obs_frame[mine]] - c_built[i]
        views /= np.linalg.norm(views, axis=1, keepdims=True)
        if len(views):
            angles = np.degrees(np.arccos(np.clip(views @ normals[i], -1.0, 1.0)))
            pairwise = np.degrees(np.arccos(np.clip(views @ views.T, -1.0, 1.0)))
            a_min, a_max, spread = float(angles.min()), float(angles.max()), float(pairwise.max())
        else:
            a_min = a_max = spread = float("nan")
        corner_sigma = float(np.sqrt(np.mean(corner_var)))
        frames_seen = int(mine.sum())
        why = []
        if frames_seen < config.min_frames_per_tag:
            why.append(f"seen in {frames_seen} frame(s) (need {config.min_frames_per_tag})")
        elif spread < config.min_view_spread_deg:
            why.append(f"seen from directions only {spread:.1f} deg apart (need {config.min_view_spread_deg:g})")
        if corner_sigma > config.max_corner_sigma_mm:
            why.append(f"corner uncertainty {corner_sigma:.3f} mm (limit {config.max_corner_sigma_mm:g})")
        out.append(TagDeviation(
            tag_id=tag_id,
            offset_mm=c_built[i] - c_nom[i],
            offset_sigma_mm=float(np.sqrt(max(np.trace(centre_cov), 0.0))),
            rotation_deg=float(np.degrees(np.linalg.norm(delta[i]))),
            # Tag z points into the cap: a positive turn about the outward normal is -z.
            about_normal_deg=float(np.degrees(-delta[i][2])),
            about_normal_sigma_deg=float(np.degrees(np.sqrt(max(turn_var, 0.0)))),
            corner_rms_mm=float(np.sqrt(np.mean(np.sum(d_corner * d_corner, axis=-1)))),
            corner_sigma_mm=corner_sigma,
            frames=frames_seen,
            view_angle_min_deg=a_min,
            view_angle_max_deg=a_max,
            view_spread_deg=spread,
            rms_px=float(np.sqrt(np.mean(per_obs[mine] ** 2))) if mine.any() else float("nan"),
            problem="; ".join(why),
        ))
    return out


def _observation_rms_px(x: np.ndarray, p: _Problem, priors: _Priors, config: BuildConfig) -> np.ndarray:
    res = _residuals(x, p, priors, config)[: 8 * len(p.obs_tag)]
    return np.sqrt(np.mean(res.reshape(-1, 4, 2) ** 2, axis=(1, 2)) * 2.0)


def _ids_per_frame(p: _Problem, nominal: CapModel) -> list[list[int]]:
    out: list[list[int]] = [[] for _ in range(p.n_frames)]
    for f, t in zip(p.obs_frame, p.obs_tag):
        out[int(f)].append(nominal.ids[int(t)])
    return out


def _coverage_problems(nominal: CapModel, ids_per_frame: list[list[int]], config: BuildConfig) -> list[str]:
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
    out = []
    short = [f"{t} ({n})" for t, n in counts.items() if n < config.min_frames_per_tag]
    if short:
        out.append(
            f"tag(s) {', '.join(short)} seen in too few frames together with "
            f">= {config.min_tags_per_frame - 1} other tags (need {config.min_frames_per_tag}); "
            "record more views showing them"
        )
    groups = {root(t) for t in nominal.ids}
    if len(groups) > 1:
        out.append(
            f"the tags fall into {len(groups)} groups never seen together in one frame; "
            "record views that show tags of neighbouring groups at once"
        )
    return out


# -- the replay check ---------------------------------------------------------------------------
def assembly_size_sigma(nominal: CapModel, config: BuildConfig) -> float:
    """How much (relative, 1 sigma) hand assembly changes the cap's size: the mean of N independent
    radial plate errors of ``assembly_sigma_mm`` over the RMS radius of the tag centres."""
    return config.assembly_sigma_mm / (np.sqrt(len(nominal)) * _rms_radius(nominal.centres_mm))


def depth_change_limit(result: BuildResult, config: BuildConfig) -> float:
    """The ``replay_check`` distance limit for a build result.

    A size anchored to the nominal layout leaves the nominal model's pose distances alone, so
    ``config.max_depth_change`` applies. A size measured from the printed tag side (``auto``
    found the corners unbiased) is a real measurement of a cap that may be larger or smaller
    than nominal by what hand assembly does, so up to three of its sigmas are allowed: on a
    rendered cap 0.21 % smaller than nominal the nominal model itself was 0.31 % off in distance.
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
