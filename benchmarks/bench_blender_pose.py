"""Pose accuracy on the independent blender_dev renders: ours against the naive peer, per set.

Every set's frames go through ``FrameProcessor`` in recording order, as ``ficap replay`` feeds
them (tracking on for ours; the sets other than ``dev_540p_drive30`` are 1.6-3.2 s apart, so
their frames are searched). Errors of the cap pose against the rendered truth: rotation (Phi3 =
half the geodesic angle, the paper's metric, and the geodesic angle) and the cap origin's
translation (mm); ``rms_px`` is the pose's reprojection rms. The nominal cap model is used for
every set (the as-built set's cap differs from it by ~1 mm / ~1 deg per plate: that set shows
what an unmeasured cap costs).

Usage: .venv/bin/python benchmarks/bench_blender_pose.py [--sets all|a,b] [--record]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_dev  # noqa: E402
from _common import load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.cap_model import nominal_model  # noqa: E402
from ficap_ros.detection import DetectorConfig  # noqa: E402
from ficap_ros.metrics import angle_deg  # noqa: E402
from ficap_ros.pipeline import FrameProcessor  # noqa: E402
from ficap_ros.pose import PoseConfig, UncertaintyConfig  # noqa: E402

#: name -> (detector, pose, tracking)
METHODS = {
    "ficap": (DetectorConfig(), PoseConfig(), True),
    "ficap, equal tag weights": (DetectorConfig(), PoseConfig(uncertainty=UncertaintyConfig(weight_tags=False)),
                                 True),
    "ficap, biased corners": (DetectorConfig(edge_unbias=False, edge_fit=False), PoseConfig(), True),
    "naive peer": (DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive"), False),
}


def run_set(name: str, methods: list[str]) -> dict[str, dict[str, np.ndarray]]:
    s = blender_dev.load_set(name)
    model = nominal_model()
    out = {}
    for m in methods:
        det, pose, tracking = METHODS[m]
        proc = FrameProcessor(model, det, pose, tracking=tracking)
        rot, trans, rms = [], [], []
        for f in s.frames:
            r = proc.process(f.image, s.camera, f.stamp_ns)
            if r.pose is None:
                rot.append(np.nan), trans.append(np.nan), rms.append(np.nan)
                continue
            rot.append(float(angle_deg(r.pose.T_cam_cap.rotation, f.T_cam_cap.rotation)))
            trans.append(1000.0 * float(np.linalg.norm(r.pose.T_cam_cap.translation_m - f.T_cam_cap.translation_m)))
            rms.append(float(r.pose.rms_px))
        out[m] = {"rot": np.array(rot), "trans": np.array(trans), "rms": np.array(rms)}
    return out


def _q(x: np.ndarray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else float("nan")


HEADER = ["set", "method", "Phi3 median / p95 deg", "geodesic median / p95 deg", "translation median / p95 mm",
          "rms_px median", "frames with pose", "bar (<= 1/2 peer)"]


#: Written under the table (measured on 2026-11-23).
READING = """Reading it: against the run before (3f45e07, 20:37) only the searched tags whose corners were
led a cell astray changed (`detection._refit`, issue 10): dev_540p_low Phi3 p95 0.197 -> 0.10 deg
(geodesic 0.394 -> 0.20, translation p95 0.71 -> 0.66 mm), rms_px 0.352 both; every other set within a few thousandths of a
degree. Replay's rms_px on clean 1080p frames stays 0.183 (neutral) and 0.237 (high light; issue 10's
target 0.2 not met): on dev_1080p_high the fitted corners' error is mostly noise (`bench_corners.py
--noise`: 0.131 of 0.141 px median), and doubling the pixels each edge profile reads did not lower
rms_px (0.237 -> 0.246, see 'Corner noise')."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="all")
    ap.add_argument("--record", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if not blender_dev.available():
        print(f"blender_dev not found at {blender_dev.BLENDER_DEV}", file=sys.stderr)
        return 1
    sets = list(blender_dev.SETS) if args.sets == "all" else args.sets.split(",")
    t0 = time.time()
    rows = []
    for name in sets:
        res = run_set(name, list(METHODS))
        peer = res["naive peer"]
        for m, r in res.items():
            bar = ""
            if m != "naive peer":
                ok = (_q(r["rot"], 50) <= 0.5 * _q(peer["rot"], 50) and _q(r["rot"], 95) <= 0.5 * _q(peer["rot"], 95)
                      and _q(r["trans"], 50) <= 0.5 * _q(peer["trans"], 50))
                bar = "yes" if ok else "**NO**"
            n = int(np.isfinite(r["rot"]).sum())
            rows.append([name, m, f"{_q(r['rot'], 50) / 2:.3f} / {_q(r['rot'], 95) / 2:.3f}",
                         f"{_q(r['rot'], 50):.3f} / {_q(r['rot'], 95):.3f}",
                         f"{_q(r['trans'], 50):.2f} / {_q(r['trans'], 95):.2f}", f"{_q(r['rms'], 50):.3f}",
                         f"{n}/{len(r['rot'])}", bar])
            print(" | ".join(rows[-1]), flush=True)
    table = md_table(HEADER, rows)
    print(table)
    if args.record:
        body = (f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s.\n\n"
                "Each set's frames through `FrameProcessor` in recording order (ours: default settings, "
                "tracking on, as `ficap replay`; 'equal tag weights': every tag weighted alike in the pose, "
                "as before the per-tag corner-noise weights; 'biased corners': the line fit alone, as before the "
                "tone-curve work; naive peer: OpenCV sub-pixel corners + one SQPnP/LM, no tracking). Nominal "
                "cap model everywhere. Errors of the cap pose against the rendered truth. 'bar' = rotation "
                "median and p95 and translation median each at most half the peer's.\n\n" + table
                + "\n\n" + READING)
        record_section("Pose on blender_dev (independent renders)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
