"""What ``build_model`` reports: each tag's deviation from the nominal with its uncertainty and
how it was seen (``TagDeviation``), and the whole result (``BuildResult``: the model, the fit, the
size's source, every reason not to trust it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.model_build.adjustment import Problem
from ficap_ros.tools.model_build.config import BuildConfig
from ficap_ros.tools.model_build.geometry import tag_frames

__all__ = ["TagDeviation", "BuildResult", "deviations"]


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


def deviations(nominal: CapModel, built: np.ndarray, cov: np.ndarray, p: Problem,
                per_obs: np.ndarray, poses: Sequence[Transform], config: BuildConfig) -> list[TagDeviation]:
    """Each tag's deviation from the nominal (built corners ``built`` aligned to the nominal cap
    frame, their covariance ``cov``), how it was seen (``per_obs`` rms px per observation, the
    frames' camera poses) and why it is poorly observed."""
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
