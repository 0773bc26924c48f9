"""Corner accuracy against the truth: ours, AprilTag 3 and OpenCV sub-pixel, by condition.

Corners are what every pose rests on, and a tone curve biases them (a lens blurs linear light, the
camera's tone curve then moves the 50 % grey point of every black/white edge toward the black), so
this measures corners directly: per method, the median and p95 corner error (px) and the mean
*radial* offset (px, negative = inside the tag) of every fully visible tag within 70 deg of
head-on, on

* ``blender_dev``: independent path-traced renders (../shared/data/blender_dev; sets with their own
  PSF, tone curve and lighting), and
* ``ficap synth`` frames: tone curve x PSF x lighting x resolution on one naturalistic drive.

Each frame is searched independently (``TagDetector``, the detector replay starts from).

``--cost``: what the corner stage costs per tracked frame (40 consecutive 1080p ``ficap synth``
frames at 30 fps, ~21 tags, through ``FrameProcessor`` as replay runs them; process time, 3 passes,
medians): the line pass, the border unbias, the cell-edge fit, the small tags' line bias.

Usage: .venv/bin/python benchmarks/bench_corners.py [--sets all|none|a,b] [--cost] [--record]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_dev  # noqa: E402
from _common import load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.detection import DetectorConfig, TagDetector  # noqa: E402
from ficap_ros.metrics import corner_errors_px  # noqa: E402

#: The corner methods compared: name -> detector settings.
METHODS: dict[str, DetectorConfig] = {
    "ficap edge": DetectorConfig(),
    "ficap lines + border unbias": DetectorConfig(edge_fit=False),
    "ficap lines (before)": DetectorConfig(edge_unbias=False, edge_fit=False),
    "AprilTag 3": DetectorConfig(backend="apriltag", corner_refine="apriltag"),
    "OpenCV subpix": DetectorConfig(corner_refine="subpix"),
}
MAX_VIEW_DEG = 70.0


@dataclass
class CornerStats:
    err: list[np.ndarray] = field(default_factory=list)
    radial: list[np.ndarray] = field(default_factory=list)
    tags_true: int = 0

    def add(self, est: np.ndarray, true: np.ndarray) -> None:
        e, r = corner_errors_px(est, true)
        self.err.append(e.ravel())
        self.radial.append(r.ravel())

    def row(self) -> list[str]:
        e = np.concatenate(self.err) if self.err else np.zeros(0)
        r = np.concatenate(self.radial) if self.radial else np.zeros(0)
        if e.size == 0:
            return ["0", "-", "-", "-", "-"]
        found = f"{e.size // 4}/{self.tags_true}"
        return [found, f"{np.median(e):.3f}", f"{np.percentile(e, 95):.3f}", f"{r.mean():+.3f}",
                f"{np.sqrt(np.mean(e ** 2)):.3f}"]


def measure(frames: list[tuple[np.ndarray, dict[int, np.ndarray], list[int]]],
            detectors: dict[str, TagDetector]) -> dict[str, CornerStats]:
    """frames: (image, true corners by id, clean ids) -> stats per method."""
    out = {name: CornerStats() for name in detectors}
    for image, truth, clean in frames:
        for name, det in detectors.items():
            st = out[name]
            st.tags_true += len(clean)
            found = {d.tag_id: d.corners_px for d in det.detect(image) if d.tag_id in clean}
            if found:
                ids = sorted(found)
                st.add(np.array([found[i] for i in ids]), np.array([truth[i] for i in ids]))
    return out


def blender_frames(name: str) -> list[tuple[np.ndarray, dict[int, np.ndarray], list[int]]]:
    s = blender_dev.load_set(name)
    return [(f.image, f.corners_px, f.clean_ids(MAX_VIEW_DEG)) for f in s.frames]


#: Corner-stage functions timed by ``--cost``: label -> name in ficap_ros.detection.
STAGE_FUNCS = {
    "line pass (refine_corners_edge_ok)": "refine_corners_edge_ok",
    "border unbias (unbias_corners_edge)": "unbias_corners_edge",
    "cell-edge fit (fit_tag_edges)": "fit_tag_edges",
    "small tags' line bias (_line_bias)": "_line_bias",
}


def cost_table(n_frames: int = 40, passes: int = 3) -> tuple[list[list[str]], str]:
    """Per-frame process time of the corner stage on consecutive tracked 1080p frames."""
    import ficap_ros.detection as det
    from ficap_ros.cap_model import nominal_model
    from ficap_ros.pipeline import FrameProcessor
    from ficap_ros.synth import RenderConfig, default_scene, naturalistic_drive, render

    model, scene = nominal_model(), default_scene("1080p")
    drive = naturalistic_drive(n_frames, fps=30.0, seed=3, scene=scene, frontal_s=0.0)
    images = [render(model, scene.camera, d.T_cam_cap, RenderConfig(jpeg_quality=95), seed=d.index).image
              for d in drive]
    spent = {name: 0.0 for name in STAGE_FUNCS.values()}
    originals = {name: getattr(det, name) for name in STAGE_FUNCS.values() if hasattr(det, name)}

    def timed(name, fn):  # noqa: ANN001, ANN202
        def wrapper(*a, **k):  # noqa: ANN002, ANN003, ANN202
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.process_time() - t0
        return wrapper

    rows, tags = [], 0
    import ficap_ros.pipeline as pipe
    import ficap_ros.tracking as trk

    imported = [(mod, name, getattr(mod, name)) for mod in (pipe, trk) for name in originals if hasattr(mod, name)]
    try:
        for name, fn in originals.items():
            setattr(det, name, timed(name, fn))
        for mod, name, fn in imported:  # the names the pipeline and the tracker imported
            setattr(mod, name, timed(name, fn))
        per_pass = []
        for k in range(passes + 1):  # the first pass warms the caches
            for name in spent:
                spent[name] = 0.0
            proc = FrameProcessor(model)
            t0 = time.process_time()
            for d, image in zip(drive, images):
                r = proc.process(image, scene.camera, d.stamp_ns)
                tags += len(r.detections) if k == 1 else 0
            total = time.process_time() - t0
            if k:
                per_pass.append([spent[n] for n in STAGE_FUNCS.values()] + [total])
        ms = np.median(np.array(per_pass), axis=0) * 1e3 / len(images)
        # The unbias and the line bias run inside refine_tag_corners: the stage is the sum of
        # the leaf functions.
        rows.append(["as committed"] + [f"{v:.2f}" for v in ms[:-1]] + [f"{ms[:-1].sum():.2f}", f"{ms[-1]:.2f}",
                                                             f"{proc.tracker.tracked_frames}/{len(images)}"])
        print(" | ".join(rows[-1]), flush=True)
    finally:
        for name, fn in originals.items():
            setattr(det, name, fn)
        for mod, name, fn in imported:
            setattr(mod, name, fn)
    header = ["variant"] + list(STAGE_FUNCS) + ["corner stage", "whole frame (raw)", "tracked frames"]
    note = f"{len(images)} frames, {tags / len(images):.1f} tags per frame"
    return [header] + rows, note


#: What the table shows (written under it by --record; the causes were measured on 2026-11-23).
READING = """Reading it: `ficap edge` is what `ficap detect --json` and replay return. Issue 10's targets
(median <= 0.15 px, p95 <= 0.5 px, |mean radial| <= 0.05 px) hold on every set but dev_540p_low.
Its miss is noise, not bias (mean radial ~0): its frames carry grey-level noise of sd ~10 on the
white and ~5 on the black against ~75 levels of contrast (path tracing at 8 samples per pixel on
top of shot noise; `ficap synth`'s low light has a similar noise-to-contrast ratio, 0.11-0.15), and
its tags are small (cells of 2-4 px at 540p): the 94 % of clean tags the cell-edge fit takes have
median 0.17 / p95 0.47 px; the same estimator on synth frames without sensor noise gives
0.03-0.04 px median. The rest of its p95 is a few tags (8 of 245) whose line fit latched onto the
wrong edge and whose cell-edge fit then refused them (errors of 1-5 px; the pose's tag-level
outlier rejection drops such tags). Tags too small or oblique to fit (cells under 2 px across one
axis, 2-6 % of clean tags at 540p) carry the line estimator's bias measured on the frame's fitted
tags with their own windows (before: none in `ficap detect`, radial -0.3 to -0.5 px on them)."""

#: Written under the --cost table: the run of the code before the corner-stage work, and what
#: the table shows (measured on 2026-11-23).
COST_READING = """Before this branch (0650613's `ficap_ros`, the same script and frames, run at 19:31 just before
the table above; load average 4.4 (1 min)): line pass 1.57, border unbias 1.02, cell-edge fit 1.46,
corner stage 4.05 ms, whole frame 8.79 ms, 39/40 tracked.

Reading it: the corner stage of a tracked frame costs about 4.0 ms before and after the changes
that keep it identical (closed-form tag homographies, a cached group layout, one sampling call for
the unbias's first look: -0.2 ms); the small tags' line bias, new, adds 0.2 ms (0.15 ms on a frame
with one small tag). A structural saving was measured and not kept: a tracked tag's prediction
already has the true geometry, so one cell-edge fit round from it (a second round where it moved
> 0.2 px; the line pass + unbias only for tags the fit cannot take; commit 9f23cef) replaces the
line pass and the unbias: 4.0 -> 3.0-3.2 ms (two runs), with the tracked corners as accurate (blender_dev
drive30 through `FrameProcessor`, tags <= 70 deg: median 0.112 -> 0.107 px, p95 0.348 -> 0.370,
radial -0.011 -> -0.004; 60-frame 30 fps synth drives, median / p95: 540p low light sRGB PSF 0.4
0.110 / 0.285 -> 0.107 / 0.291, 1080p high light PSF 1.0 0.100 / 0.354 -> 0.100 / 0.354, 540p
neutral gamma 1.8 0.033 / 0.121 -> 0.028 / 0.109). Most of what remains is the fit's per-tag normal equations (about 40 %) and its
profile sampling (about 25 %). It was reverted (e7792d2): corners started at the model's
projection keep a pull toward it, the residuals shrink, and the 95 % rotation bound covered 53 % of
`test_bag_replay`'s synth drive instead of >= 85 %. The whole-frame column moves with the machine's load between the
passes; the corner stage is what the changes touch."""

HEADER = ["set", "PSF px", "tone", "lighting", "method", "tags found", "median px", "p95 px",
          "mean radial px", "rms px"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="all", help="blender_dev sets: all, none or a comma list")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--cost", action="store_true", help="time the corner stage per tracked 1080p frame instead")
    ap.add_argument("--record", action="store_true", help="write the tables into docs/benchmarks.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.cost:
        load_before = load_avg()
        table, note = cost_table()
        text = md_table(table[0], table[1:])
        print(text)
        if args.record:
            body = (f"Machine: {machine_line()}; {load_before} at the start, {load_avg()} at the end. "
                    f"`benchmarks/bench_corners.py --cost` (see its docstring): {note}; mean ms per frame "
                    "(process time, median of 3 passes).\n\n" + text + "\n\n" + COST_READING)
            record_section("Corner stage cost per tracked 1080p frame", body)
        return 0
    names = [m for m in args.methods.split(",") if m]
    detectors = {n: TagDetector(METHODS[n]) for n in names}
    sets = (list(blender_dev.SETS) if args.sets == "all" else
            [] if args.sets == "none" else args.sets.split(","))
    t0 = time.time()
    rows = []
    if sets and not blender_dev.available():
        print(f"blender_dev not found at {blender_dev.BLENDER_DEV}; skipping", file=sys.stderr)
        sets = []
    for name in sets:
        s = blender_dev.load_set(name)
        frames = [(f.image, f.corners_px, f.clean_ids(MAX_VIEW_DEG)) for f in s.frames]
        res = measure(frames, detectors)
        for m in names:
            rows.append([name, f"{s.psf_sigma_px:.2f}", s.tone, s.lighting, m] + res[m].row())
            print(" | ".join(rows[-1]), flush=True)
    table = md_table(HEADER, rows)
    print(table)
    if args.record and rows:
        body = (f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s.\n\n"
                f"Every frame of each set searched independently (`TagDetector`); tags fully visible "
                f"(4 corners), facing, within {MAX_VIEW_DEG:.0f} deg of head-on. 'tags found' = clean "
                "tags the method returned / clean tags. Radial offset: the error's component along the "
                "tag centre -> corner direction (negative = inside the tag).\n\n" + table + "\n\n" + READING)
        record_section("Corners on blender_dev (independent renders)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
