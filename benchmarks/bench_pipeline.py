"""Detection and pose time per frame at 540p and 1080p (one process, one thread).

Usage: .venv/bin/python benchmarks/bench_pipeline.py [--frames N] [--record]
Prints a table; with --record writes it (machine, date, commit) into docs/benchmarks.md, replacing its section.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from _common import machine_line  # noqa: E402  (benchmarks/ is the script folder)

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import FrameProcessor
from ficap_ros.vision.pose import PoseConfig

ROOT = Path(__file__).resolve().parents[1]

CONFIGS = {
    "ficap (opencv+edge, joint)": (DetectorConfig(), PoseConfig()),
    "ficap (opencv+edge, paper)": (DetectorConfig(), PoseConfig(method="paper")),
    "naive peer (opencv+subpix, naive)": (DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive")),
    "apriltag3 backend (joint)": (DetectorConfig(backend="apriltag"), PoseConfig()),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--record", action="store_true", help="write the table into docs/benchmarks.md")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    model = nominal_model()
    rows = []
    for resolution in ("540p", "1080p"):
        scene = default_scene(resolution)
        drive = naturalistic_drive(args.frames * 5, fps=30.0, seed=3, scene=scene)[::5]
        frames = [(render(model, scene.camera, d.T_cam_cap, RenderConfig(), seed=k), d) for k, d in enumerate(drive)]
        for name, (det, pose) in CONFIGS.items():
            proc = FrameProcessor(model, det, pose)
            detect_ms, pose_ms, errs = [], [], []
            for frame, truth in frames:
                r = proc.process(frame.image, scene.camera)
                detect_ms.append(r.detect_ms)
                pose_ms.append(r.pose_ms)
                errs.append(angle_deg(r.pose.T_cam_cap.rotation, truth.T_cam_cap.rotation) if r.pose else np.nan)
            rows.append((resolution, name, np.median(detect_ms), np.median(pose_ms),
                         np.nanmedian(errs), np.nanpercentile(errs, 95), int(np.sum(np.isfinite(errs)))))
            print(f"{resolution:6} {name:36} detect {rows[-1][2]:6.2f} ms  pose {rows[-1][3]:5.2f} ms  "
                  f"median {rows[-1][4]:.3f} deg  p95 {rows[-1][5]:.3f} deg", file=sys.stderr)
    table = [
        f"bench_pipeline ({args.frames} rendered neutral frames per resolution)",
        "",
        f"Machine: {machine_line()}",
        "",
        "| resolution | pipeline | detect ms/frame (median) | pose ms/frame (median) | rotation error median (deg) | p95 (deg) | frames with pose |",
        "|---|---|---|---|---|---|---|",
    ]
    table += [f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.3f} | {r[5]:.3f} | {r[6]}/{args.frames} |" for r in rows]
    text = "\n".join(table) + "\n"
    print(text)
    if args.record:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from _common import load_avg, record_section

        record_section("Pipeline (detect/pose ms and error)", text + f"\n{load_avg()} at the end.\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
