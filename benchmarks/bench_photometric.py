"""The tag-level photometric corner fit (``DetectorConfig(edge_photometric=True)``): accuracy and cost.

Issue 10's last open corner target (blender_dev dev_540p_low median <= 0.15 px) is missed by the
cell-edge fit (``ficap edge``); ``detection.fit_tags_photometric`` (``ficap_ros.vision.photometric``) fits each tag's
printed pattern, blurred in linear light and put through an sRGB curve, to its pixels near the
cell boundaries, as the corner stage's last step. This measures, with the same detector
otherwise (``TagDetector``, every frame searched, as ``ficap detect --json``):

* corners on every blender_dev set (median, p95, mean radial, rms over fully visible tags within
  70 deg of head-on; tags as in bench_corners.py), ``ficap edge`` and ``+ photometric`` and the
  naive peer (OpenCV sub-pixel) on the same frames;
* the same on ``ficap synth`` conditions (``bench_corners.SYNTH_CONDITIONS``, 6 frames each);
* ``--cost``: process time per tracked frame (40 consecutive 30 fps synth frames through
  ``FrameProcessor``, as replay runs them; the two settings alternated, 3 passes each, medians),
  and per tag: 1080p in neutral light, and 540p in low light (the fit's other end: small tags,
  a wide blur in cell units, every pixel of a tag kept).

Usage: .venv/bin/python benchmarks/bench_photometric.py [--sets all|none|a,b] [--no-synth] [--cost] [--record]
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
from bench_corners import SYNTH_CONDITIONS, blender_frames, measure, synth_frames  # noqa: E402

from ficap_ros.vision.detector import DetectorConfig, TagDetector  # noqa: E402

METHODS = {
    "ficap edge": DetectorConfig(),
    "ficap edge + photometric": DetectorConfig(edge_photometric=True),
    "OpenCV subpix": DetectorConfig(corner_refine="subpix"),
}


#: Written under the accuracy table (measured 2026-11-23 23:38).
READING = """Reading it: as the corner stage's last step, the photometric fit lowers the median corner
error on every blender_dev set and every synth condition, keeps every mean radial offset within
+-0.025 px, and meets issue 10's corner targets on all of them, dev_540p_low included (0.170 / 0.488
-> 0.140 / 0.387 px, target 0.15 / 0.5). The gain is largest where noise limits the cell-edge fit
(synth low light 0.098-0.147 -> 0.051-0.088 px) and smallest on blender_dev 540p high (0.147 ->
0.134, p95 0.429 -> 0.436: a filmic curve with clipped whites, which an sRGB curve to a free power
describes least well). Its constants were set on synth frames (blur and tone exponent fitted per
tag, the sRGB family assumed); blender_dev was the check. Not the default: it costs ~1 ms a tag
(next section)."""
COST_READING = """Reading it: ~1 ms of CPU per tag at 1080p, ~0.8 ms at 540p in low light (1500 pixels at most
per tag, 3 Gauss-Newton steps of a 16-parameter model per tag). Earlier: 2.98 ms a tag in the first
version (2026-11-23 23:39, 65.5 ms a 1080p frame), 1.31 ms (2026-11-24 00:27, 28.9 ms). Run interleaved
with that version (main at 2fb5529, its own `--cost`, 3 rounds each, load 2.1-3.6): 1080p 27.2 / 33.2 /
34.0 -> 21.5 / 21.1 / 21.1 ms a frame; 540p low light (the same 40-frame drive through `FrameProcessor`,
a script outside the repo, 2 rounds) 34.1 / 35.5 -> 16.6 / 16.5 ms. The old version's spread is fresh
memory: it needed 35-41 MB a call and, whenever the allocator had handed the last call's pages back,
paid 2-8 k page faults a frame (a third of its time at 540p); fitting at most 12 tags at once and
dropping each step's arrays keeps the fit's peak at 11-12 MB, and these runs saw no faults. User time
alone, 1080p ~27 -> ~20 ms, 540p ~22 -> ~16.5 ms. Same corners as that version, bit for bit
(docs/detection.md). Still about 5x the corner stage it follows (~4.4 ms) and 40x the ~0.5 ms a
tracked 1080p frame could spare: hence opt-in (`ficap detect/replay --photometric`, the node's
`detector.photometric`). Fewer pixels per tag cost accuracy at once (dev_1080p_high median 0.125 px at
1500 pixels, 0.137 at 600, 0.162 at 300, 4 steps; a narrower band around the boundaries instead loses
the levels and the fit fails), so the way to the tracked path's budget is compiled code, not a smaller
problem."""


def cost(n_frames: int = 40, passes: int = 3, resolution: str = "1080p",
         lighting: str = "neutral") -> list[list[str]]:
    """ms of process time per tracked frame, without and with the photometric fit."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.synth import (
        RenderConfig,
        default_scene,
        naturalistic_drive,
        render,
    )
    from ficap_ros.vision.pipeline import FrameProcessor

    model, scene = nominal_model(), default_scene(resolution)
    drive = naturalistic_drive(n_frames, fps=30.0, seed=3, scene=scene, frontal_s=0.0)
    images = [render(model, scene.camera, d.T_cam_cap, RenderConfig(jpeg_quality=95, lighting=lighting),
                     seed=d.index).image for d in drive]
    spent: dict[str, list[float]] = {"ficap edge": [], "ficap edge + photometric": []}
    tags = 0
    for k in range(passes + 1):  # the first pass warms the caches
        for name in spent:
            proc = FrameProcessor(model, detector=METHODS[name])
            t0 = time.process_time()
            for d, image in zip(drive, images):
                r = proc.process(image, scene.camera, d.stamp_ns)
                tags += len(r.detections) if (k == 1 and name == "ficap edge") else 0
            if k:
                spent[name].append(1000.0 * (time.process_time() - t0) / n_frames)
    base, photo = (float(np.median(v)) for v in spent.values())
    per_tag = (photo - base) / (tags / n_frames)
    return [[f"{resolution} {lighting}", f"{base:.1f}", f"{photo:.1f}", f"{photo - base:.1f}",
             f"{tags / n_frames:.1f}", f"{per_tag:.2f}"]]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="all", help="blender_dev sets: all, none or a comma list")
    ap.add_argument("--no-synth", action="store_true")
    ap.add_argument("--cost", action="store_true", help="time tracked 1080p frames instead")
    ap.add_argument("--record", action="store_true", help="write the tables into docs/benchmarks.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0 = time.time()
    if args.cost:
        load_before = load_avg()
        rows = cost() + cost(resolution="540p", lighting="low")
        text = md_table(["frames", "ficap edge ms/frame", "+ photometric ms/frame", "photometric fit ms/frame",
                         "tags/frame", "ms/tag"], rows)
        print(text)
        if args.record:
            record_section("Photometric corner fit: cost per tracked frame", (
                f"Machine: {machine_line()}; {load_before} at the start, {load_avg()} at the end. "
                "`benchmarks/bench_photometric.py --cost --record`: 40 consecutive 30 fps `ficap synth` "
                "frames (1080p neutral light, 540p low light) through `FrameProcessor` (tracking on), the two "
                "settings alternated, 3 passes each; process time per frame, medians.\n\n" + text + "\n\n" + COST_READING))
        return 0
    detectors = {n: TagDetector(c) for n, c in METHODS.items()}
    header = ["frames", "method", "tags found", "median px", "p95 px", "mean radial px", "rms px"]
    rows = []
    sets = list(blender_dev.SETS) if args.sets == "all" else [x for x in args.sets.split(",") if x and x != "none"]
    for name in sets:
        stats = measure(blender_frames(name), detectors)
        for m, st in stats.items():
            rows.append([f"blender_dev {name}", m] + st.row())
            print(" | ".join(rows[-1]), flush=True)
    if not args.no_synth:
        for res, tone, gamma, psf, light in SYNTH_CONDITIONS:
            stats = measure(synth_frames(res, tone, gamma, psf, light), detectors)
            label = f"synth {res} {tone if tone != 'gamma' else f'gamma {gamma}'} PSF {psf or 'default'} {light}"
            for m, st in stats.items():
                rows.append([label, m] + st.row())
                print(" | ".join(rows[-1]), flush=True)
    text = md_table(header, rows)
    print(text)
    if args.record:
        record_section("Photometric corner fit: accuracy", (
            f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s. "
            "`benchmarks/bench_photometric.py --record` (see its docstring): every frame searched "
            "(`TagDetector`, as `ficap detect --json`); tags fully visible, facing, within 70 deg "
            "of head-on; radial: negative = inside the tag.\n\n" + text + "\n\n" + READING))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
