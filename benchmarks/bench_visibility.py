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
``--hd-heights`` repeat part of the grid at 1080p. Writes docs/visibility_sweep.png with ``--record``.

Usage: .venv/bin/python benchmarks/bench_visibility.py [--frames 1800] [--stride 1]
    [--sweep-frames 1800] [--sweep-stride 20] [--record]

The section records which commit the imported ``ficap_ros`` modules match (``code_state``). To
measure committed code while the editable package is being changed, export it and run from outside
the repo: ``git archive HEAD ficap_ros | tar -x -C /tmp/snap; cd /tmp; PYTHONPATH=/tmp/snap
nice -n 10 /work/main/.venv/bin/python /work/main/benchmarks/bench_visibility.py --record``.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, Progress, load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.geometry.camera import CameraModel  # noqa: E402
from ficap_ros.geometry.cap_model import CapModel, nominal_model, write_atomic  # noqa: E402
from ficap_ros.geometry.metrics import angle_deg  # noqa: E402
from ficap_ros.geometry.transform import CAM_FROM_FORWARD  # noqa: E402
from ficap_ros.tools.synth import (  # noqa: E402
    RESOLUTIONS,
    DriveFrame,
    DriveScene,
    RenderConfig,
    RenderedFrame,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.pipeline import FrameProcessor  # noqa: E402

CAP_RADIUS_M = 0.092  # back of the cap to the cap origin (default_scene: 0.45 m + 0.092)
SECTION = "Visibility (paper section 6)"
PNG = ROOT / "docs" / "visibility_sweep.png"
PAPER_GE1_PCT, PAPER_GE4_PCT = 99.8, 99.2  # 246,643 frames, 68 min real drive (section 6)


def code_state() -> str:
    """Which commit the imported ``ficap_ros`` modules match, by git blob hash.

    The package is installed editable and may be edited while a benchmark runs; call this right
    after the imports so the section says which code produced it.
    """
    import ficap_ros

    def git(*cmd: str) -> str:
        return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True).stdout

    head = git("rev-parse", "--short", "HEAD").strip() or "unknown"
    blobs = {}  # path -> blob sha1 at HEAD ("<mode> blob <sha>\t<path>")
    for line in git("ls-tree", "-r", "HEAD", "ficap_ros").splitlines():
        meta, _, path = line.partition("\t")
        blobs[path] = meta.split()[2]
    pkg = Path(ficap_ros.__file__).resolve().parent
    changed, n = [], 0
    for name, mod in sorted(sys.modules.items()):
        f = getattr(mod, "__file__", None)
        if not (name == "ficap_ros" or name.startswith("ficap_ros.")) or not f:
            continue
        n += 1
        data = Path(f).read_bytes()
        sha = hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()
        rel = "ficap_ros/" + Path(f).resolve().relative_to(pkg).as_posix()
        if blobs.get(rel) != sha:
            changed.append(rel)
    where = "the repo" if pkg.parent == ROOT else "an export outside the repo"
    if not changed:
        return f"the {n} `ficap_ros` modules it imported (from {where}) are identical to commit {head}"
    return (f"`ficap_ros` imported from {where} DIFFERS from commit {head} in {', '.join(changed)} "
            "(uncommitted code)")


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
    prog = Progress(len(drive), label)
    for d in drive:
        f = render(model, scene.camera, d.T_cam_cap, cfg, seed=d.index)
        r = proc.process(f.image, scene.camera, d.stamp_ns)
        det.append(r.tags_detected)
        used.append(0 if r.pose is None else r.pose.tags_used)
        err.append(np.nan if r.pose is None else angle_deg(r.pose.T_cam_cap.rotation, d.T_cam_cap.rotation))
        seen.append(renderer_visible(f, model, args))
        prog.update()
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


def plot(grid: dict[tuple[float, float], Counts], dists: list[float], heights: list[float]) -> bytes:
    """Heat maps (distance x height) of the 540p sweep: >= 4 tags share, median / p95 error, tags used."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return buf.getvalue()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
    ap.add_argument("--record", action="store_true", help="write the section and docs/visibility_sweep.png")
    args = ap.parse_args()
    t_start = time.time()
    load_start, machine, code = load_avg(), machine_line(), code_state()
    print(f"{machine}; {code}", file=sys.stderr)
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
    print(md_table(["count", "frames", ">= 1 tag", ">= 4 tags", "with pose", "tags median / min",
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
    minutes = (time.time() - t_start) / 60.0
    flat = all(c.pct(c.detected, 4) == 100.0 for c in grid.values())

    text = "\n".join([
        f"Machine: {machine} (at the start); {load_start} at the start, {load_avg()} at the end; "
        f"{minutes:.1f} min (run with `nice -n 10`). Code: {code}.", "",
        "Every count is a detector result: frames rendered by `ficap_ros.tools.synth.render` (default `RenderConfig`: "
        "neutral light, the default image chain (PSF, sensor noise, sRGB), head and neck occluders, no headrest, seat, hands or other people) are run "
        "through `ficap_ros.vision.pipeline.FrameProcessor` with default settings; 'with pose' = the pipeline returned a "
        "cap pose; error = geodesic angle between the estimated and the rendered cap orientation "
        "(`ficap_ros.geometry.metrics.angle_deg`, twice the paper's Phi3); 'tags used' = tags kept by the pose. "
        "'Renderer visibility' (tags at least "
        f"{100 * args.min_visible:.1f} % visible, facing the camera within {args.max_angle_deg:.0f} deg, every side "
        f">= {args.min_side_px:.0f} px) is the renderer's upper bound with no detector in it.", "",
        f"Default placement (`default_scene`, 540p, 60 deg hfov, 0.45 m behind the back of the cap, 6 cm above its "
        f"centre, looking straight forward): naturalistic drive seed {args.seed}, "
        + (f"{dflt.n} consecutive frames ({args.frames / 30:.0f} s at 30 fps) with tracking on"
           if tracking else f"every {args.stride}th of {args.frames} frames, each searched independently")
        + f"; {int(glance.sum())} of the {dflt.n} frames are in mirror / cluster glances or moving to them "
        f"(|yaw| up to {yaw.max():.0f} deg, pitch {pitch.min():.0f} to {pitch.max():+.0f} deg). The paper's numbers "
        f"come from 68 min of real driving, with occlusions this renderer does not have; {args.frames / 30:.0f} s "
        "of simulated driving cannot show a 0.2 % effect.", "",
        md_table(["count", "frames", ">= 1 tag", ">= 4 tags", "with pose", "tags median / min", "mean tags used",
                  "error median / p95 / max (deg)"], rows), "",
        f"Sweep: camera distance behind the back of the cap x camera height above the cap centre, 60 deg hfov, "
        f"camera aimed at the frontal cap (`scene_at`; the default placement is 0.45 m / +0.06 m looking straight "
        f"forward, so it is not exactly a grid point). Per grid point: every {args.sweep_stride}th frame of a "
        f"{args.sweep_frames}-frame naturalistic drive (seed {args.seed}, {args.sweep_frames / 30:.0f} s; the same "
        f"{len(sweep_drive)} head poses at every point, {sweep_glance} of them in glances), each frame searched "
        "independently (`tracking=False`). A subset is repeated at 1080p. This is a small sample: one share step is "
        f"{100 / max(len(sweep_drive), 1):.1f} %.", "",
        md_table(["res", "distance (m)", "height (m)", "frames", ">= 1 tag", ">= 4 tags", "with pose",
                  "error median (deg)", "error p95 (deg)", "mean tags used", "renderer >= 4"], sweep_rows), "",
        f"Heat maps of the 540p sweep: `docs/{PNG.name}` (![sweep]({PNG.name})).", "",
        "Where to mount the camera (from this sweep, simulation only): " + recommendation(grid, dists, heights) + ".",
        ("Every grid point detected >= 4 tags in every sampled frame: the renderer has no headrest, seat, hands "
         "or passengers, so the shares cannot tell mount positions apart here; the error and the tags used do. "
         if flat else "")
        + "In a car the camera also has to see the cap past the headrest, which this sweep does not model.",
    ])
    print(text)
    if args.record:
        write_atomic(PNG, plot(grid, dists, heights))
        record_section(SECTION, text)
        print(f"recorded in docs/benchmarks.md and {PNG.relative_to(ROOT)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
