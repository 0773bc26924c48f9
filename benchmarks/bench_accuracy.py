"""The paper's Table 1: cap-rotation error on rendered naturalistic drives, ours vs paper vs naive peer.

One naturalistic drive (``ficap_ros.tools.synth.naturalistic_drive``, seed 0, 30 fps, ``--frames`` frames,
every ``--stride``-th frame rendered) at 540p and 1080p x neutral/high/low lighting. Every frame is
processed by three pipelines on the same image: ours with the ``joint`` and the ``paper`` pose method
(opencv tuned + edge-fit corners), and the naive peer (OpenCV sub-pixel corners + one SQPnP/LM).
Error: Phi3 = arccos(|q1.q2|) (the paper's metric, half the geodesic angle) and the geodesic angle,
of the cap orientation against the rendered truth.

Usage: .venv/bin/python benchmarks/bench_accuracy.py [--frames 1800] [--stride 1] [--record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    DOC,
    ROOT,
    Progress,
    load_avg,
    machine_line,
    md_table,
    record_section,
)

from ficap_ros.geometry.cap_model import nominal_model  # noqa: E402
from ficap_ros.geometry.metrics import angle_deg  # noqa: E402
from ficap_ros.tools.synth import (  # noqa: E402
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import DetectorConfig  # noqa: E402
from ficap_ros.vision.pipeline import FrameProcessor  # noqa: E402
from ficap_ros.vision.pose import PoseConfig  # noqa: E402

#: Paper Table 1 (Phi3, deg): mean, median, p95.
PAPER = {
    ("540p", "neutral"): (1.17, 1.18, 1.95), ("540p", "high"): (1.45, 1.61, 2.10),
    ("540p", "low"): (1.17, 0.95, 2.87), ("1080p", "neutral"): (0.39, 0.36, 0.66),
    ("1080p", "high"): (1.12, 1.15, 1.46), ("1080p", "low"): (0.93, 1.01, 1.30),
}
METHODS = {
    "ficap joint": (DetectorConfig(), PoseConfig(method="joint")),
    "ficap paper": (DetectorConfig(), PoseConfig(method="paper")),
    "naive peer": (DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive")),
}


def stats(err: np.ndarray) -> tuple[float, float, float]:
    e = err[np.isfinite(err)]
    if e.size == 0:
        return (float("nan"),) * 3
    return float(e.mean()), float(np.median(e)), float(np.percentile(e, 95))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1800, help="drive length in frames at 30 fps (default 1800)")
    ap.add_argument("--stride", type=int, default=1, help="render every N-th frame (default 1)")
    ap.add_argument("--resolutions", default="540p,1080p")
    ap.add_argument("--lightings", default="neutral,high,low")
    ap.add_argument("--record", action="store_true", help="write the table into docs/benchmarks.md")
    ap.add_argument("--save-worst", type=Path, default=None,
                    help="folder for PNGs of each condition's worst 'ficap joint' frame")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    model = nominal_model()
    load_before = load_avg()
    rows, md_rows, all_err = [], [], {}
    t_start = time.time()
    for res in args.resolutions.split(","):
        scene = default_scene(res)
        drive = naturalistic_drive(args.frames, fps=30.0, seed=0, scene=scene)[:: args.stride]
        procs = {name: FrameProcessor(model, det, pose) for name, (det, pose) in METHODS.items()}
        for light in args.lightings.split(","):
            cfg = RenderConfig(lighting=light)
            err = {name: np.full(len(drive), np.nan) for name in METHODS}
            worst = (-1.0, None, None)
            prog = Progress(len(drive), f"{res} {light}")
            for k, d in enumerate(drive):
                frame = render(model, scene.camera, d.T_cam_cap, cfg, seed=d.index)
                for name, proc in procs.items():
                    r = proc.process(frame.image, scene.camera, d.stamp_ns)
                    if r.pose is not None:
                        err[name][k] = float(angle_deg(r.pose.T_cam_cap.rotation, d.T_cam_cap.rotation))
                if args.save_worst is not None and np.nan_to_num(err["ficap joint"][k], nan=99) > worst[0]:
                    worst = (float(np.nan_to_num(err["ficap joint"][k], nan=99)), frame, d)
                prog.update()
            if args.save_worst is not None and worst[1] is not None:
                args.save_worst.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(args.save_worst / f"worst_{res}_{light}_f{worst[2].index}.png"), worst[1].image)
            paper = PAPER.get((res, light), (float("nan"),) * 3)
            peer_geo = stats(err["naive peer"])
            for name in METHODS:
                geo = stats(err[name])
                phi = tuple(v / 2 for v in geo)
                n_pose = int(np.isfinite(err[name]).sum())
                bar = ""
                if name != "naive peer":
                    ok = geo[1] <= 0.5 * peer_geo[1] and geo[2] <= 0.5 * peer_geo[2]
                    bar = "yes" if ok else "**NO**"
                rows.append((res, light, name, phi, geo, n_pose, len(drive)))
                md_rows.append([res, light, name, f"{phi[0]:.3f} / {phi[1]:.3f} / {phi[2]:.3f}",
                                f"{geo[0]:.3f} / {geo[1]:.3f} / {geo[2]:.3f}",
                                f"{paper[0]:.2f} / {paper[1]:.2f} / {paper[2]:.2f}",
                                f"{n_pose}/{len(drive)}", bar])
                print(f"{res:6} {light:8} {name:12} phi3 {phi[0]:.3f}/{phi[1]:.3f}/{phi[2]:.3f}  "
                      f"geodesic {geo[0]:.3f}/{geo[1]:.3f}/{geo[2]:.3f}  pose {n_pose}/{len(drive)}  {bar}",
                      file=sys.stderr)
                all_err[(res, light, name)] = err[name]
    elapsed = time.time() - t_start
    n = len(naturalistic_drive(args.frames, fps=30.0, seed=0)[:: args.stride])
    body = [
        f"Machine: {machine_line()}; {load_avg()} at the end ({load_before} at the start); "
        f"{elapsed / 60:.1f} min.",
        "",
        f"One naturalistic drive (seed 0) of {args.frames} frames at 30 fps ({args.frames / 30:.0f} s), "
        + (f"every {args.stride}th frame rendered: {n} frames per condition"
           if args.stride > 1 else f"all {n} frames rendered")
        + " (`ficap_ros.tools.synth.render`, default camera and image chain: PSF, sensor noise, sRGB). Same frames for every method. "
        "Errors of the cap orientation against the rendered truth, mean / median / p95 in degrees: "
        "Phi3 = arccos(|q1.q2|) (the paper's metric, half the geodesic angle) and the geodesic angle. "
        "'bar' = median and p95 at most half the naive peer's.",
        "",
        md_table(["res", "lighting", "method", "Phi3 mean / median / p95", "geodesic mean / median / p95",
                  "paper Table 1 (Phi3)", "frames with pose", "bar (<= 1/2 peer)"], md_rows),
    ]
    if args.stride > 1:
        body.append("")
        body.append("Fewer frames than the paper's 1800 per condition because rendering takes 0.1-0.5 s "
                    "per frame on this machine; run with `--stride 1` for the full sequence.")
    text = "\n".join(body)
    print(text)
    png = ROOT / "docs" / "bench_accuracy.png"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        res_list, lights = args.resolutions.split(","), args.lightings.split(",")
        fig, axes = plt.subplots(len(res_list), len(lights), figsize=(4 * len(lights), 3.2 * len(res_list)),
                                 squeeze=False)
        for i, res in enumerate(res_list):
            for j, light in enumerate(lights):
                ax = axes[i][j]
                for name in METHODS:
                    e = np.sort(all_err[(res, light, name)] / 2)
                    e = e[np.isfinite(e)]
                    if e.size:
                        ax.plot(e, np.arange(1, e.size + 1) / e.size, label=name)
                ax.set_xscale("log")
                ax.set_title(f"{res} {light}")
                ax.set_xlabel("Phi3 error (deg)")
                ax.grid(True, alpha=0.3)
        axes[0][0].set_ylabel("fraction of frames")
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        if args.record:
            fig.savefig(png, dpi=80)
        plt.close(fig)
    except ImportError:
        pass
    if args.record:
        record_section("Accuracy (paper Table 1)", text + f"\n\nCDF plot: `{png.relative_to(ROOT)}`.")
        print(f"recorded in {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
