"""Accuracy on rendered drives by condition: ours, the paper's pose method and the naive peer
beside the paper's Table 1.

One naturalistic drive (``ficap_ros.tools.synth.naturalistic_drive``, seed 0, 30 fps, 60 s) at 540p and
1080p under neutral, high and low light, rendered through the realistic camera chain (lens PSF
in linear light, shot and read noise, clipping, sRGB, JPEG as ``ficap synth`` writes it). Every
rendered frame goes through three pipelines on the same image: ours (``FrameProcessor`` defaults,
tracking across the rendered frames), ours with the paper's pose method (section 3.2: per-tag
IPPE, Kabsch, corner rejection) and the naive peer (OpenCV sub-pixel corners, one SQPnP + LM).
Error: Phi3 = arccos(|q1.q2|) of the cap orientation against the rendered truth (the paper's
metric, half the geodesic angle), the geodesic angle itself, and the cap origin's translation
error (mm). Writes docs/benchmarks/accuracy.md and accuracy.png.
"""

from __future__ import annotations

import sys

import cv2
import numpy as np

from _lib import cli, report
from _lib.methods import OURS, OURS_PAPER, PEER
from _lib.stats import q
from _lib.synthdata import drive_frames
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.tools.synth import RenderConfig

#: The paper's Table 1 (Phi3, deg): median, p95.
PAPER = {
    ("540p", "neutral"): (1.18, 1.95), ("540p", "high"): (1.61, 2.10), ("540p", "low"): (0.95, 2.87),
    ("1080p", "neutral"): (0.36, 0.66), ("1080p", "high"): (1.15, 1.46), ("1080p", "low"): (1.01, 1.30),
}
METHODS = (OURS, OURS_PAPER, PEER)
DRIVE_FRAMES = 1800


def measure(resolution: str, lighting: str, stride: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Geodesic rotation error (deg) and translation error (mm) per method, per rendered frame
    (NaN without a pose)."""
    camera, frames = drive_frames(resolution, DRIVE_FRAMES // stride, step=stride,
                                  config=RenderConfig(lighting=lighting))
    procs = {m.name: m.processor() for m in METHODS}
    err: dict[str, list[float]] = {m.name: [] for m in METHODS}
    trans: dict[str, list[float]] = {m.name: [] for m in METHODS}
    for f in frames:
        gray = cv2.imdecode(f.jpeg, cv2.IMREAD_GRAYSCALE)
        for name, proc in procs.items():
            pose = proc.process(gray, camera, f.stamp_ns).pose
            if pose is None:
                err[name].append(np.nan), trans[name].append(np.nan)
                continue
            err[name].append(float(angle_deg(pose.T_cam_cap.rotation, f.T_cam_cap.rotation)))
            trans[name].append(1e3 * float(np.linalg.norm(pose.T_cam_cap.translation_m - f.T_cam_cap.translation_m)))
    return {k: np.array(v) for k, v in err.items()}, {k: np.array(v) for k, v in trans.items()}


def plot(errors: dict[tuple[str, str], dict[str, np.ndarray]]) -> str:
    plt = report.pyplot()
    conds = list(errors)
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.4), squeeze=False)
    for ax, cond in zip(axes.ravel(), conds):
        for name, e in errors[cond].items():
            e = np.sort(e[np.isfinite(e)] / 2.0)
            if e.size:
                ax.plot(e, np.arange(1, e.size + 1) / e.size, label=name)
        ax.axvline(PAPER[cond][0], color="grey", ls=":", label="paper's median")
        ax.set_xscale("log")
        ax.set_title(f"{cond[0]} {cond[1]} light")
        ax.set_xlabel("Phi3 error (deg)")
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel("fraction of frames")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Cap orientation error on synth drives (CDF)")
    fig.tight_layout()
    return report.save_figure(fig, "accuracy")


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="every 60th frame (30 a condition) instead of every 12th (150)")
    ap.add_argument("--stride", type=int, default=None, help="render every N-th frame of the drive (default 12)")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    run = report.Run()
    stride = args.stride or (60 if args.quick else 12)
    errors, rows, bar_ok = {}, [], []
    for res in ("540p", "1080p"):
        for light in ("neutral", "high", "low"):
            err, trans = measure(res, light, stride)
            errors[(res, light)] = err
            ours, peer = err[OURS.name], err[PEER.name]
            ok = q(ours, 50) <= 0.5 * q(peer, 50) and q(ours, 95) <= 0.5 * q(peer, 95)
            bar_ok.append(ok)
            cells = [f"{q(err[m.name], 50) / 2:.3f} / {q(err[m.name], 95) / 2:.3f}" for m in METHODS]
            posed = "/".join(str(int(np.isfinite(err[m.name]).sum())) for m in METHODS)
            geo = [f"{q(err[m.name], 50):.3f} / {q(err[m.name], 95):.3f}" for m in (OURS, PEER)]
            mm = [f"{q(trans[m.name], 50):.2f}" for m in (OURS, PEER)]
            rows.append([res, light, *cells, f"{PAPER[(res, light)][0]:.2f} / {PAPER[(res, light)][1]:.2f}",
                         *geo, " / ".join(mm), f"{posed} of {len(ours)}", "yes" if ok else "**no**"])
            print(" | ".join(str(c) for c in rows[-1]), file=sys.stderr, flush=True)
    table = report.md_table(["res", "light", "ficap (Phi3 median / p95, deg)", "ficap, paper's pose",
                             "naive peer", "paper's Table 1", "ficap geodesic median / p95 (deg)",
                             "naive peer geodesic", "translation median, ficap / peer (mm)",
                             "frames with a pose (ficap/paper/peer)", "ficap <= half the peer"], rows)
    n = DRIVE_FRAMES // stride
    body = (f"{table}\n\n{plot(errors)}\n\n"
            f"Ours meets half the naive peer's median and p95 in {sum(bar_ok)} of {len(bar_ok)} conditions. "
            "The paper's pose method, re-implemented, is a reproduction baseline: its per-tag poses "
            "and corner rejection lose to one joint fit over every corner. The paper's figures come "
            "from real drives and are shown for scale, not as a like-for-like comparison.")
    what = ("What it measures: cap-orientation error (Phi3, the paper's metric: half the geodesic "
            f"angle) on {n} frames per condition (every {stride}th frame of a 60 s naturalistic drive, "
            "seed 0) rendered at 540p and 1080p under neutral, high and low light through the "
            "realistic camera chain (PSF, sensor noise, sRGB, JPEG q95); ours, ours with the "
            "paper's pose method and the naive peer (OpenCV sub-pixel corners + one SQPnP/LM) on the "
            "same images.")
    report.write_section("accuracy", what, report.how("bench_accuracy.py", "every 60th frame"),
                         body, run, report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
