"""Pose accuracy on the independent blender_dev renders: ours against the naive peer, per set.

Every set of ``<data>/blender_dev`` (the glance sets with motion blur and a rolling shutter
included) goes through ``FrameProcessor`` frame by frame in recording order, as ``ficap replay``
feeds it: ours (defaults, tracking on; the sets sampled 1.6-3.2 s apart are searched every frame),
ours with the photometric corner step on every tag, and the naive peer (OpenCV sub-pixel corners,
one SQPnP + LM, no tracking). Errors of the cap pose against the rendered truth: rotation (the
geodesic angle, and Phi3 = half of it, the paper's metric) and the cap origin's translation (mm);
``rms_px`` is the pose's reprojection rms, and beside it the same rms over the used tags fully
visible within 70 deg of head-on (those ``bench_corners`` scores): the difference is what the more
oblique tags the pose uses carry. The nominal cap model is used for every set (the as-built set's
cap differs from it by ~1 mm / ~1 deg a plate: what an unmeasured cap costs).
Writes docs/benchmarks/blender_pose.md and blender_pose.png.
"""

from __future__ import annotations

import sys

import numpy as np

from _lib import cli, devsets, report
from _lib.methods import OURS, OURS_PHOTOMETRIC, PEER
from _lib.stats import q
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pose import CapPose

METHODS = (OURS, OURS_PHOTOMETRIC, PEER)
#: The view angle within which a used tag counts in the clean tags' rms (as ``bench_corners``), deg.
CLEAN_VIEW_DEG = 70.0


def clean_rms_px(pose: CapPose, solved: tuple[TagDetection, ...], camera: CameraModel, model: CapModel,
                 frame: devsets.DevFrame) -> float:
    """The pose's reprojection rms (as ``rms_px``: the 2-D residuals' rms) over the used tags
    ``frame`` shows fully visible within ``CLEAN_VIEW_DEG`` of head-on; NaN without one."""
    used = {d.tag_id: d for d in solved if d.tag_id in pose.used_ids}
    clean = [t for t in frame.clean_ids(CLEAN_VIEW_DEG) if t in used]
    if not clean:
        return float("nan")
    at = {t: k for k, t in enumerate(model.ids)}
    corners_m = np.array([model.corners_mm[at[t]] for t in clean]).reshape(-1, 3) / 1000.0
    projected = camera.project(pose.T_cam_cap.apply(corners_m))
    seen = np.array([used[t].corners_px for t in clean]).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum((seen - projected) ** 2, axis=1))))


def run_set(data, name: str, max_frames: int | None) -> dict[str, dict[str, np.ndarray]]:  # noqa: ANN001
    """Per method: rotation error deg, translation error mm, rms_px and the clean tags' rms px per
    frame (NaN: no pose)."""
    s = devsets.load_set(data, name, max_frames)
    model = nominal_model()
    out = {}
    for m in METHODS:
        proc = m.processor(model)
        rot, trans, rms, clean = [], [], [], []
        for f in s.frames:
            pose = proc.process(f.image, s.camera, f.stamp_ns).pose
            if pose is None:
                rot.append(np.nan), trans.append(np.nan), rms.append(np.nan), clean.append(np.nan)
                continue
            solved = proc.last_solve.tags if proc.last_solve is not None else ()
            clean.append(clean_rms_px(pose, solved, s.camera, model, f))
            rot.append(float(angle_deg(pose.T_cam_cap.rotation, f.T_cam_cap.rotation)))
            trans.append(1e3 * float(np.linalg.norm(pose.T_cam_cap.translation_m - f.T_cam_cap.translation_m)))
            rms.append(float(pose.rms_px))
        out[m.name] = {"rot": np.array(rot), "trans": np.array(trans), "rms": np.array(rms),
                       "clean": np.array(clean)}
    return out


def plot(results: dict[str, dict[str, dict[str, np.ndarray]]]) -> str:
    plt = report.pyplot()
    names = list(results)
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for ax, key, label in ((axes[0], "rot", "rotation error, median (deg, geodesic)"),
                           (axes[1], "trans", "translation error, median (mm)")):
        for k, m in enumerate(METHODS):
            vals = [q(results[n][m.name][key], 50) for n in names]
            ax.bar(x + (k - 1) * 0.27, vals, 0.27, label=m.name)
        ax.set_yscale("log")
        ax.set_ylim(top=ax.get_ylim()[1] * 5)  # room for the legend above the bars
        ax.set_xticks(x, [n.replace("dev_", "") for n in names], rotation=40, ha="right", fontsize=8)
        ax.set_ylabel(label)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, ncol=3, loc="upper left")
    fig.suptitle("Pose error on blender_dev (nominal cap model)")
    fig.tight_layout()
    return report.save_figure(fig, "blender_pose")


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="the first 8 frames of each set")
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    if not devsets.available(args.data):
        print(f"blender_dev not found under {args.data} (--data)", file=sys.stderr)
        return 1
    run = report.Run()
    results, rows, bar = {}, [], []
    for name in devsets.present(args.data):
        res = run_set(args.data, name, 8 if args.quick else None)
        results[name] = res
        peer = res[PEER.name]
        for m in METHODS:
            r = res[m.name]
            ok = ""
            if m is not PEER:
                good = (q(r["rot"], 50) <= 0.5 * q(peer["rot"], 50) and q(r["rot"], 95) <= 0.5 * q(peer["rot"], 95)
                        and q(r["trans"], 50) <= 0.5 * q(peer["trans"], 50))
                ok = "yes" if good else "**no**"
                if m is OURS:
                    bar.append(good)
            rows.append([name.replace("dev_", ""), m.name,
                         f"{q(r['rot'], 50):.3f} / {q(r['rot'], 95):.3f}",
                         f"{q(r['rot'], 50) / 2:.3f} / {q(r['rot'], 95) / 2:.3f}",
                         f"{q(r['trans'], 50):.2f} / {q(r['trans'], 95):.2f}",
                         f"{q(r['rms'], 50):.3f} / {q(r['clean'], 50):.3f}",
                         f"{int(np.isfinite(r['rot']).sum())}/{len(r['rot'])}", ok])
            print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    table = report.md_table(["set", "method", "rotation median / p95 (deg, geodesic)", "Phi3 median / p95",
                             "translation median / p95 (mm)",
                             f"rms_px median: all used tags / those within {CLEAN_VIEW_DEG:.0f} deg",
                             "frames with a pose", "<= half the peer"], rows)
    body = (f"{table}\n\n{plot(results)}\n\n"
            f"'<= half the peer': rotation median and p95 and translation median each at most half the "
            f"naive peer's. Ours meets it on {sum(bar)} of {len(bar)} sets. The as-built set is rendered "
            "with a cap whose plates are moved and turned by ~1 mm / ~1 deg and replayed with the "
            "nominal model: its error is the unmeasured cap's (`ficap model build` measures it, see "
            "'As-built cap model'). The glance sets are 30 fps through a fast glance (up to 236 deg/s) "
            "with 1/60 s motion blur (`glance_blur`) or a 22 ms rolling-shutter readout (`glance_rs`): "
            "the pose is of a rigid cap at one instant, so both carry the motion's error.")
    what = ("What it measures: cap pose error on every blender_dev set (independent path-traced "
            "renders with exact truth; nothing in the package is tuned to them), ours, ours with the "
            "photometric corners on every tag (`--photometric`) and the naive peer, each set's frames in "
            "recording order as `ficap replay` feeds them (tracking on for ours), nominal cap model.")
    report.write_section("blender_pose", what, report.how("bench_blender_pose.py", "the first 8 frames of each set"),
                         body, run, report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
