"""Section 6: share of frames with >= 1 and >= 4 tags detected, pose error, and where to mount the camera.

Every count here is a *detector* result: rendered frames (``ficap_ros.tools.synth.render``, default
``RenderConfig``: neutral light, the default image chain) go through ``ficap_ros.vision.pipeline.FrameProcessor``
with its default settings, and the cap orientation is compared with the render's exact truth
(geodesic angle, ``ficap_ros.geometry.metrics.angle_deg``). The renderer's own visibility (a tag counts when
at least ``--min-visible`` of it is in the image and not hidden by the head or neck, it faces the
camera within ``--max-angle-deg`` and every side is at least ``--min-side-px``) is kept as a
secondary column: it is an upper bound with no detector in it.

Default placement: ``default_scene`` (0.45 m behind the back of the cap, 6 cm above its centre,
60 deg hfov, looking straight forward) over ``--frames`` frames of a naturalistic drive with mirror
and cluster glances. With ``--stride 1`` the frames are consecutive and tracking is on (as in the
node); with a stride every frame is searched independently (``tracking=False``).

Sweep: camera distance behind the back of the cap x height above the cap centre, camera aimed at
the frontal cap (``scene_at``); every ``--sweep-stride``th frame of a ``--sweep-frames`` drive (the
same head motion at every grid point), searched independently. ``--hd-distances`` /
``--hd-heights`` repeat part of the grid at 1080p. Heat maps of the 540p sweep go to docs/benchmarks/visibility.png.

Writes docs/benchmarks/visibility.md and visibility.png.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from _lib import cli, report
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD
from ficap_ros.tools.synth import (
    RESOLUTIONS,
    DriveFrame,
    DriveScene,
    RenderConfig,
    RenderedFrame,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.pipeline import FrameProcessor

CAP_RADIUS_M = 0.092  # back of the cap to the cap origin (default_scene: 0.45 m + 0.092)
PAPER_GE1_PCT, PAPER_GE4_PCT = 99.8, 99.2  # 246,643 frames, 68 min real drive (section 6)


def scene_at(distance_m: float, height_m: float, resolution: tuple[int, int]) -> DriveScene:
    """Camera ``distance_m`` behind the back of the cap, ``height_m`` above the cap origin, aimed at it."""
    camera = CameraModel.pinhole(*resolution, hfov_deg=60.0)
    neck_to_cap = np.array([-0.04, 0.0, 0.13])
    p_frontal_cap = np.array([distance_m + CAP_RADIUS_M, 0.0, -height_m])  # cap seen from the camera
    pitch = np.degrees(np.arctan2(height_m, distance_m + CAP_RADIUS_M))
    # Camera body frame pitched down by `pitch` (looks at the cap); frontal frame F expressed in it.
    R_forward_body = Rotation.from_euler("y", pitch, degrees=True)  # body x tilted down (y left)
    R_cam_frontal = CAM_FROM_FORWARD * R_forward_body.inv()
    p_cam_neck = R_cam_frontal.apply(p_frontal_cap - neck_to_cap)
    return DriveScene(camera=camera, R_cam_frontal=R_cam_frontal, p_cam_neck_m=p_cam_neck, neck_to_cap_m=neck_to_cap)


@dataclass(frozen=True)
class Counts:
    """Per-frame results of one placement.

    Attributes:
        detected: distinct model tags detected per frame.
        used: tags used by the pose per frame (0 without a pose).
        err_deg: geodesic cap-orientation error per frame, deg (NaN without a pose).
        seen: tags the renderer counts as visible per frame (cheap pass, no detector).
    """

    detected: np.ndarray
    used: np.ndarray
    err_deg: np.ndarray
    seen: np.ndarray

    @property
    def n(self) -> int:
        return int(self.detected.size)

    def pct(self, values: np.ndarray, k: int) -> float:
        return 100.0 * float(np.mean(values >= k))

    @property
    def pose_pct(self) -> float:
        return 100.0 * float(np.mean(np.isfinite(self.err_deg)))

    def err(self, q: float) -> float:
        e = self.err_deg[np.isfinite(self.err_deg)]
        return float(np.percentile(e, q)) if e.size else float("nan")


def renderer_visible(frame: RenderedFrame, model: CapModel, args: argparse.Namespace) -> int:
    """Tags the renderer says are visible, face the camera enough and are big enough (no detector)."""
    T = frame.T_cam_cap
    n_cam = T.rotation.apply(model.normals)
    c_cam = T.apply(model.centres_mm / 1000.0)
    cosang = -np.sum(n_cam * c_cam, 1) / np.linalg.norm(c_cam, axis=1)
    ok_angle = {t for t, c in zip(model.ids, cosang) if c > np.cos(np.radians(args.max_angle_deg))}
    big = {t for t, c in frame.corners_px.items()
           if np.linalg.norm(c - np.roll(c, -1, 0), axis=1).min() >= args.min_side_px}
    return sum(1 for t in frame.visible_ids(args.min_visible) if t in ok_angle and t in big)


def run(scene: DriveScene, drive: list[DriveFrame], tracking: bool, label: str,
        args: argparse.Namespace) -> Counts:
    """Render ``drive`` in ``scene`` and run every frame through a default ``FrameProcessor``."""
    model = nominal_model()
    proc = FrameProcessor(model, tracking=tracking)
    cfg = RenderConfig()
    det, used, err, seen = [], [], [], []
    for d in drive:
        f = render(model, scene.camera, d.T_cam_cap, cfg, seed=d.index)
        r = proc.process(f.image, scene.camera, d.stamp_ns)
        det.append(r.tags_detected)
        used.append(0 if r.pose is None else r.pose.tags_used)
        err.append(np.nan if r.pose is None else angle_deg(r.pose.T_cam_cap.rotation, d.T_cam_cap.rotation))
        seen.append(renderer_visible(f, model, args))
    print(f"  {label}: {len(det)} frames", file=sys.stderr, flush=True)
    return Counts(np.array(det), np.array(used), np.array(err, dtype=np.float64), np.array(seen))


def floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def sweep_row(res: str, dist: float, h: float, c: Counts) -> list[object]:
    return [res, f"{dist:.2f}", f"{h:+.2f}", c.n, f"{c.pct(c.detected, 1):.1f} %", f"{c.pct(c.detected, 4):.1f} %",
            f"{c.pose_pct:.1f} %", f"{c.err(50):.3f}", f"{c.err(95):.3f}", f"{c.used.mean():.1f}",
            f"{c.pct(c.seen, 4):.1f} %"]


def recommendation(grid: dict[tuple[float, float], Counts], dists: list[float], heights: list[float]) -> str:
    """Sentences from the 540p sweep: where >= 4 tags held at the paper's rate, how the error moves."""
    good = {k for k, c in grid.items() if c.pct(c.detected, 4) >= PAPER_GE4_PCT and c.pose_pct >= 100.0}
    if len(good) == len(grid):
        where = "at every distance and height tried"
    elif good:
        ok_d = [d for d in dists if all((d, h) in good for h in heights)]
        where = (f"at every height at {', '.join(f'{d:.2f}' for d in ok_d)} m" if ok_d
                 else f"at {len(good)} of {len(grid)} grid points")
    else:
        where = ""
    out = [(f"at 540p, >= 4 tags were detected with a pose in at least the paper's {PAPER_GE4_PCT} % of the "
            f"sampled frames {where}" if where else
            f"at 540p no grid point reached the paper's {PAPER_GE4_PCT} % of frames with >= 4 tags")]
    per_d = {d: [grid[(d, h)].err(50) for h in heights] for d in dists}
    out.append("median error (lowest-highest over the heights) "
               + ", ".join(f"{min(v):.3f}-{max(v):.3f} deg at {d:.2f} m" for d, v in per_d.items()))
    best_h = {d: min(heights, key=lambda h: grid[(d, h)].err(50)) for d in dists}
    top_h = max(heights, key=lambda h: sum(v == h for v in best_h.values()))
    out.append(f"the lowest median error at {sum(v == top_h for v in best_h.values())} of the {len(dists)} "
               f"distances was at height {top_h:+.2f} m")
    pool = good or set(grid)
    best_k = min(pool, key=lambda k: grid[k].err(95))
    worst_k = max(grid, key=lambda k: grid[k].err(95))
    best, worst = grid[best_k], grid[worst_k]
    out.append(f"lowest p95 {best.err(95):.3f} deg at {best_k[0]:.2f} m / {best_k[1]:+.2f} m "
               f"({best.used.mean():.1f} tags used on average), highest p95 {worst.err(95):.3f} deg at "
               f"{worst_k[0]:.2f} m / {worst_k[1]:+.2f} m ({worst.used.mean():.1f} tags used)")
    return "; ".join(out)


def plot(grid: dict[tuple[float, float], Counts], dists: list[float], heights: list[float]) -> str:
    """Heat maps (distance x height) of the 540p sweep: >= 4 tags share, median / p95 error, tags used."""
    plt = report.pyplot()
    panels = [
        ("frames with >= 4 tags detected (%)", lambda c: c.pct(c.detected, 4), "viridis", "{:.1f}", (90.0, 100.0)),
        ("mean tags used by the pose", lambda c: float(c.used.mean()), "viridis", "{:.1f}", None),
        ("median rotation error (deg)", lambda c: c.err(50), "magma_r", "{:.3f}", None),
        ("p95 rotation error (deg)", lambda c: c.err(95), "magma_r", "{:.3f}", None),
    ]
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    for ax, (title, fn, cmap, fmt, limits) in zip(axes.ravel(), panels):
        m = np.array([[fn(grid[(d, h)]) for d in dists] for h in heights])
        # Shares: a fixed 90-100 % scale, so a constant 100 % does not read as a spread.
        lo, hi = (min(limits[0], float(np.nanmin(m))), limits[1]) if limits else (np.nanmin(m), np.nanmax(m))
        im = ax.imshow(m, origin="lower", cmap=cmap, aspect="auto", vmin=lo, vmax=hi)
        for i in range(len(heights)):
            for j in range(len(dists)):
                v = m[i, j]
                frac = 0.5 if hi <= lo else (v - lo) / (hi - lo)
                dark = frac < 0.5 if cmap == "viridis" else frac > 0.5
                ax.text(j, i, fmt.format(v), ha="center", va="center", fontsize=8,
                        color="white" if dark else "black")
        ax.set_xticks(range(len(dists)), [f"{d:.2f}" for d in dists])
        ax.set_yticks(range(len(heights)), [f"{h:+.2f}" for h in heights])
        ax.set_xlabel("camera distance behind the cap (m)")
        ax.set_ylabel("camera height above cap centre (m)")
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, ax=ax, shrink=0.85)
    fig.suptitle("Camera placement sweep, 540p 60 deg hfov, detector results (FrameProcessor)", fontsize=11)
    fig.tight_layout()
    return report.save_figure(fig, "visibility")


QUICK = {"frames": 150, "sweep_stride": 180, "distances": "0.45,0.9", "heights": "0.0,0.1",
         "hd_distances": "", "hd_heights": ""}


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="150 frames at the default placement, a 2 x 2 sweep of 10 frames a "
                                   "point, no 1080p points")
    ap.add_argument("--frames", type=int, default=1800, help="default placement: drive length, 30 fps frames")
    ap.add_argument("--stride", type=int, default=1, help="default placement: every Nth frame (1 = tracking)")
    ap.add_argument("--sweep-frames", type=int, default=1800, help="sweep: drive length, 30 fps frames")
    ap.add_argument("--sweep-stride", type=int, default=20, help="sweep: every Nth frame")
    ap.add_argument("--distances", default="0.3,0.45,0.6,0.75,0.9,1.2", help="sweep: m behind the back of the cap")
    ap.add_argument("--heights", default="-0.1,0.0,0.1,0.2", help="sweep: m above the cap centre")
    ap.add_argument("--hd-distances", default="0.45,0.9,1.2", help="1080p subset (empty = none)")
    ap.add_argument("--hd-heights", default="0.0,0.2", help="1080p subset")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--min-visible", type=float, default=0.999)
    ap.add_argument("--max-angle-deg", type=float, default=75.0)
    ap.add_argument("--min-side-px", type=float, default=12.0, help="shortest projected tag side counted")
    args = ap.parse_args(argv)
    if args.quick:
        for k, v in QUICK.items():
            setattr(args, k, v)
    import cv2

    cv2.setNumThreads(1)
    run_info = report.Run()
    dists, heights = floats(args.distances), floats(args.heights)
    hd_dists, hd_heights = floats(args.hd_distances), floats(args.hd_heights)

    # Default placement.
    scene = default_scene("540p")
    drive = naturalistic_drive(args.frames, fps=30.0, seed=args.seed, scene=scene)[::args.stride]
    tracking = args.stride == 1
    dflt = run(scene, drive, tracking, "default placement", args)
    glance = np.array([d.target != "frontal" for d in drive])
    yaw = np.array([abs(d.ypr_deg[0]) for d in drive])
    pitch = np.array([d.ypr_deg[1] for d in drive])
    rows = [
        ["detected, 540p (`FrameProcessor`, " + ("tracking" if tracking else "no tracking") + ")", dflt.n,
         f"{dflt.pct(dflt.detected, 1):.1f} %", f"{dflt.pct(dflt.detected, 4):.1f} %", f"{dflt.pose_pct:.1f} %",
         f"{np.median(dflt.detected):.0f} / {dflt.detected.min()}", f"{dflt.used.mean():.1f}",
         f"{dflt.err(50):.3f} / {dflt.err(95):.3f} / {np.nanmax(dflt.err_deg):.3f}"],
        ["renderer visibility (no detector)", dflt.n, f"{dflt.pct(dflt.seen, 1):.1f} %",
         f"{dflt.pct(dflt.seen, 4):.1f} %", "-", f"{np.median(dflt.seen):.0f} / {dflt.seen.min()}", "-", "-"],
        ["paper (real drive, 68 min, 60 fps)", 246643, f"{PAPER_GE1_PCT} %", f"{PAPER_GE4_PCT} %", "-", "-", "-",
         "-"],
    ]
    print(report.md_table(["count", "frames", ">= 1 tag", ">= 4 tags", "with pose", "tags median / min",
                    "mean tags used", "error median / p95 / max (deg)"], rows), file=sys.stderr)

    # Sweep (frames not consecutive: every frame searched over the whole image).
    grid: dict[tuple[float, float], Counts] = {}
    sweep_rows: list[list[object]] = []
    for res, ds, hs in (("540p", dists, heights), ("1080p", hd_dists, hd_heights)):
        for dist in ds:
            for h in hs:
                sc = scene_at(dist, h, RESOLUTIONS[res])
                dr = naturalistic_drive(args.sweep_frames, fps=30.0, seed=args.seed, scene=sc)[::args.sweep_stride]
                c = run(sc, dr, False, f"{res} d {dist:.2f} h {h:+.2f}", args)
                if res == "540p":
                    grid[(dist, h)] = c
                sweep_rows.append(sweep_row(res, dist, h, c))
                print("  " + " | ".join(str(v) for v in sweep_rows[-1]), file=sys.stderr)
    sweep_drive = naturalistic_drive(args.sweep_frames, fps=30.0, seed=args.seed)[::args.sweep_stride]
    sweep_glance = sum(d.target != "frontal" for d in sweep_drive)
    flat = all(c.pct(c.detected, 4) == 100.0 for c in grid.values())

    what = ("What it measures: how often the detector finds at least 1 and at least 4 tags, how often "
            "there is a pose and its error (geodesic, twice Phi3), on rendered drives (`ficap synth`'s "
            "renderer, neutral light, the default chain, head and neck occluders; no headrest, seat, "
            "hands or passengers), at the default camera placement and over a sweep of camera "
            "distance x height; every count is a detector result (`FrameProcessor`, defaults). "
            "'Renderer visibility' (tags at least "
            f"{100 * args.min_visible:.1f} % visible, facing within {args.max_angle_deg:.0f} deg, every "
            f"side >= {args.min_side_px:.0f} px) is the upper bound with no detector in it.")
    body = "\n".join([
        f"Default placement (`default_scene`, 540p, 60 deg hfov, 0.45 m behind the back of the cap, 6 cm "
        f"above its centre, looking straight forward): naturalistic drive seed {args.seed}, "
        + (f"{dflt.n} consecutive frames ({args.frames / 30:.0f} s at 30 fps) with tracking on"
           if tracking else f"every {args.stride}th of {args.frames} frames, each searched alone")
        + f"; {int(glance.sum())} of the {dflt.n} frames are in mirror / cluster glances or moving to them "
        f"(|yaw| up to {yaw.max():.0f} deg, pitch {pitch.min():.0f} to {pitch.max():+.0f} deg). The "
        "paper's figures come from 68 min of real driving, with occlusions this renderer does not have.", "",
        report.md_table(["count", "frames", ">= 1 tag", ">= 4 tags", "with pose", "tags median / min",
                         "mean tags used", "error median / p95 / max (deg)"], rows), "",
        f"Sweep: camera distance behind the back of the cap x height above the cap centre, 60 deg hfov, "
        f"aimed at the frontal cap. Per point: every {args.sweep_stride}th frame of a "
        f"{args.sweep_frames}-frame drive (the same {len(sweep_drive)} head poses at every point, "
        f"{sweep_glance} in glances), each searched alone; part of the grid again at 1080p. One share "
        f"step is {100 / max(len(sweep_drive), 1):.1f} %.", "",
        report.md_table(["res", "distance (m)", "height (m)", "frames", ">= 1 tag", ">= 4 tags", "with pose",
                         "error median (deg)", "error p95 (deg)", "mean tags used", "renderer >= 4"],
                        sweep_rows), "",
        plot(grid, dists, heights), "",
        "Where to mount the camera (from this sweep, simulation only): " + recommendation(grid, dists, heights)
        + ". " + ("Every grid point detected >= 4 tags in every sampled frame: without headrest, seat "
                  "or hands the shares cannot tell mount positions apart; the error and the tags used "
                  "do. " if flat else "")
        + "In a car the camera also has to see the cap past the headrest, which this sweep does not model.",
    ])
    report.write_section("visibility", what, report.how("bench_visibility.py", "a short drive and a 2 x 2 sweep"),
                         body, run_info, report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
