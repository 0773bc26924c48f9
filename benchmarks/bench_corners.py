"""Corner accuracy against the truth, and what the photometric step costs on every tag.

Corners are what every pose rests on, and a camera biases them: its lens blurs linear light and
its tone curve then moves the grey midpoint of every black/white edge toward the black. Per
method, over every fully visible tag within 70 deg of head-on: the median and p95 corner error
(px) and the mean radial offset (px; negative = inside the tag), on

* every blender_dev set (independent path-traced renders with their own PSF, tone curve, light);
* ``ficap synth`` frames by condition: tone curve x PSF x lighting x resolution (6 frames each of
  one naturalistic drive, 1 s apart, seed 5, JPEG 95).

Methods, each frame searched alone (``TagDetector``, as ``ficap detect``): ours (the defaults:
unbiased edge-fit corners, the tag-level photometric step on the tags noise limits), ours with the
photometric step on every tag (``--photometric``), AprilTag 3 (its own corners) and the naive
peer's OpenCV sub-pixel corners. Then the step's cost on every tag: CPU ms per tracked frame of the
defaults and of ``--photometric`` (consecutive 30 fps synth frames through ``FrameProcessor``,
passes alternated, medians). Writes docs/benchmarks/corners.md and corners.png.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from _lib import cli, devsets, report
from _lib.methods import AT3_DETECTOR, OURS, OURS_PHOTOMETRIC, PEER
from _lib.synthdata import drive_frames
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import corner_errors_px
from ficap_ros.tools.synth import RenderConfig
from ficap_ros.vision.detector import TagDetector
from ficap_ros.vision.tracking import view_angles_deg

MAX_VIEW_DEG = 70.0
METHODS = {"ficap": OURS.detector, "ficap + photometric": OURS_PHOTOMETRIC.detector,
           "AprilTag 3": AT3_DETECTOR, "naive peer (OpenCV subpix)": PEER.detector}
#: ficap synth conditions: (resolution, tone, gamma, PSF sigma px or None for the default, lighting).
SYNTH_CONDITIONS = [
    ("540p", "srgb", 2.2, None, "neutral"),
    ("540p", "gamma", 1.8, 1.0, "high"),
    ("540p", "filmic", 2.2, 0.4, "neutral"),
    ("540p", "srgb", 2.2, 0.7, "low"),
    ("1080p", "srgb", 2.2, 1.0, "high"),
    ("1080p", "filmic", 2.2, 0.7, "neutral"),
    ("1080p", "gamma", 1.8, 0.4, "low"),
]

Frames = list[tuple[np.ndarray, dict[int, np.ndarray], list[int]]]


@dataclass
class CornerStats:
    err: list[np.ndarray] = field(default_factory=list)
    radial: list[np.ndarray] = field(default_factory=list)
    tags_true: int = 0

    def add(self, est: np.ndarray, true: np.ndarray) -> None:
        e, r = corner_errors_px(est, true)
        self.err.append(e.ravel())
        self.radial.append(r.ravel())

    def values(self) -> tuple[float, float, float, int]:
        e = np.concatenate(self.err) if self.err else np.zeros(0)
        r = np.concatenate(self.radial) if self.radial else np.zeros(0)
        if e.size == 0:
            return float("nan"), float("nan"), float("nan"), 0
        return float(np.median(e)), float(np.percentile(e, 95)), float(r.mean()), e.size // 4

    def cell(self) -> str:
        med, p95, rad, _n = self.values()
        return "-" if not np.isfinite(med) else f"{med:.3f} / {p95:.3f} / {rad:+.3f}"


def measure(frames: Frames) -> dict[str, CornerStats]:
    """frames: (image, true corners by id, clean ids) -> stats per method."""
    detectors = {name: TagDetector(cfg) for name, cfg in METHODS.items()}
    out = {name: CornerStats() for name in METHODS}
    for image, truth, clean in frames:
        for name, det in detectors.items():
            st = out[name]
            st.tags_true += len(clean)
            found = {d.tag_id: d.corners_px for d in det.detect(image) if d.tag_id in clean}
            if found:
                ids = sorted(found)
                st.add(np.array([found[i] for i in ids]), np.array([truth[i] for i in ids]))
    return out


def synth_condition(resolution: str, tone: str, gamma: float, psf: float | None, lighting: str,
                    n: int) -> Frames:
    import cv2

    cfg = RenderConfig(lighting=lighting, tone=tone, gamma=gamma, psf_sigma_px=psf)
    model = nominal_model()
    _camera, frames = drive_frames(resolution, n, step=30, seed=5, config=cfg, frontal_s=0.0)
    out = []
    for f in frames:
        angles = dict(zip(model.ids, view_angles_deg(model, f.T_cam_cap)))
        clean = [t for t in f.visible_ids if angles[t] <= MAX_VIEW_DEG]
        out.append((cv2.imdecode(f.jpeg, cv2.IMREAD_GRAYSCALE), f.corners_px, clean))
    return out


def photometric_cost(resolution: str, lighting: str, n: int, passes: int) -> list[str]:
    """[frames, ms per tracked frame without and with the step, the step's ms, tags, ms a tag]."""
    import cv2

    camera, frames = drive_frames(resolution, n, seed=3, config=RenderConfig(lighting=lighting), frontal_s=0.0)
    images = [(cv2.imdecode(f.jpeg, cv2.IMREAD_GRAYSCALE), f.stamp_ns) for f in frames]
    spent: dict[str, list[float]] = {OURS.name: [], OURS_PHOTOMETRIC.name: []}
    tags = 0
    for k in range(passes + 1):  # pass 0 warms the caches
        for m in ((OURS, OURS_PHOTOMETRIC) if k % 2 else (OURS_PHOTOMETRIC, OURS)):
            proc = m.processor()
            t0 = time.process_time()
            for image, stamp in images:
                r = proc.process(image, camera, stamp)
                tags += len(r.detections) if (k == 0 and m is OURS) else 0
            if k:
                spent[m.name].append(1e3 * (time.process_time() - t0) / len(images))
    base, photo = (float(np.median(v)) for v in spent.values())
    per_frame = tags / len(images)
    return [f"{resolution} {lighting}, {len(images)} frames", f"{base:.1f}", f"{photo:.1f}",
            f"{photo - base:.1f}", f"{per_frame:.1f}", f"{(photo - base) / per_frame:.2f}"]


def plot(labels: list[str], stats: list[dict[str, CornerStats]]) -> str:
    plt = report.pyplot()
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(13, 4.4))
    for k, name in enumerate(METHODS):
        ax.bar(x + (k - 1.5) * 0.2, [s[name].values()[0] for s in stats], 0.2, label=name)
    ax.set_yscale("log")
    ax.set_ylim(top=8.0)  # room for the legend above the bars
    ax.set_xticks(x, labels, rotation=40, ha="right", fontsize=7)
    ax.set_ylabel("corner error, median (px)")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8, ncol=4, loc="upper left")
    ax.set_title("Corner error by set and condition (clean tags within 70 deg)")
    fig.tight_layout()
    return report.save_figure(fig, "corners")


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="the first 5 frames of each blender_dev set, 2 synth frames a "
                                   "condition, 10 frames and 1 pass for the cost")
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    run = report.Run()
    labels, stats, rows = [], [], []
    for name in devsets.present(args.data):
        s = devsets.load_set(args.data, name, 5 if args.quick else None)
        st = measure([(f.image, f.corners_px, f.clean_ids(MAX_VIEW_DEG)) for f in s.frames])
        label = f"blender {name.replace('dev_', '')}"
        rows.append([label, f"{s.psf_sigma_px:.2f} {s.tone}, {s.lighting}", f"{st['ficap'].values()[3]}/"
                     f"{st['ficap'].tags_true}"] + [st[m].cell() for m in METHODS])
        labels.append(label), stats.append(st)
        print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    for res, tone, gamma, psf, light in SYNTH_CONDITIONS:
        st = measure(synth_condition(res, tone, gamma, psf, light, 2 if args.quick else 6))
        tone_s = f"gamma {gamma}" if tone == "gamma" else tone
        label = f"synth {res} {light}"
        rows.append([label, f"{'default' if psf is None else f'{psf:.2f}'} {tone_s}, {light}",
                     f"{st['ficap'].values()[3]}/{st['ficap'].tags_true}"] + [st[m].cell() for m in METHODS])
        labels.append(f"{label} {tone_s}"), stats.append(st)
        print(" | ".join(rows[-1]), file=sys.stderr, flush=True)
    table = report.md_table(["frames", "PSF px, tone, light", "clean tags found (ficap)"]
                            + [f"{m}: median / p95 / mean radial px" for m in METHODS], rows)
    n_cost, passes = (10, 1) if args.quick else (30, 3)
    cost_rows = [photometric_cost("1080p", "neutral", n_cost, passes),
                 photometric_cost("540p", "low", n_cost, passes)]
    cost = report.md_table(["tracked frames", "ficap ms/frame", "+ photometric ms/frame", "the step ms/frame",
                            "tags/frame", "ms a tag"], cost_rows)
    ours = [s["ficap"].values() for s in stats]
    photo = [s["ficap + photometric"].values() for s in stats]
    body = (f"{table}\n\n{plot(labels, stats)}\n\n"
            f"Ours: median {min(v[0] for v in ours):.3f}-{max(v[0] for v in ours):.3f} px, mean radial "
            f"within ±{max(abs(v[2]) for v in ours):.3f} px over every set and condition; with the "
            f"photometric step median {min(v[0] for v in photo):.3f}-{max(v[0] for v in photo):.3f} px. "
            "The grey-midpoint corners (AprilTag 3, OpenCV sub-pixel) sit inside the tag by a "
            "tenth of a pixel to over a pixel: the tone curve's bias, which the pose inherits.\n\n"
            "What the photometric step costs on every tag beyond the defaults (which run it on the "
            "tags noise limits only; CPU time per tracked frame, `FrameProcessor` as replay runs "
            "it; the two settings' passes alternated, medians):\n\n" + cost + "\n\n"
            "On every tag it is `ficap detect/replay --photometric` (the node's "
            "`detector.photometric`), for offline labels where accuracy matters more than rate.")
    what = ("What it measures: corner error against the projected truth (median, p95, mean radial "
            "offset; negative = inside the tag) of every fully visible tag within 70 deg of head-on, "
            "each frame searched alone (`TagDetector`, as `ficap detect`), on every blender_dev set "
            "and on `ficap synth` frames by tone curve, PSF, light and resolution; ours, ours + the "
            "photometric step, AprilTag 3 and the naive peer's OpenCV sub-pixel corners. Then the "
            "photometric step's CPU cost per tracked frame.")
    report.write_section("corners", what, report.how("bench_corners.py", "fewer frames per set and condition"),
                         body, run, report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
