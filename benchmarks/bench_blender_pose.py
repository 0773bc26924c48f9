"""Pose accuracy on the independent blender_dev renders: ours against the naive peer, per set.

Every set's frames go through ``FrameProcessor`` in recording order, as ``ficap replay`` feeds
them (tracking on for ours; the sets other than ``dev_540p_drive30`` are 1.6-3.2 s apart, so
their frames are searched). Errors of the cap pose against the rendered truth: rotation (Phi3 =
half the geodesic angle, the paper's metric, and the geodesic angle) and the cap origin's
translation (mm); ``rms_px`` is the pose's reprojection rms (unweighted, over the corners of the
tags the pose used); beside it the same rms over every detected model tag at that pose, the tags
the pose left out included. The nominal cap model is used for every set (the as-built set's cap
differs from it by ~1 mm / ~1 deg per plate: that set shows what an unmeasured cap costs).

``--rms-sources``: what makes each frame's rms_px, from the truth (``ground_truth.json``): every
used corner's residual by its tag's class (partly hidden: fewer than 4 corners visible to the
renderer's ray cast; fully visible by view angle), with its error against the projected truth and
the share of the frame's sum of squares; with the partly-hidden check (``DetectorConfig.hidden_check``)
off and on.

Usage: .venv/bin/python benchmarks/bench_blender_pose.py [--sets all|a,b] [--methods 'a;b'] [--record] [--rms-sources]
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
    "ficap, no hidden check": (DetectorConfig(hidden_check=False), PoseConfig(), True),
    "naive peer": (DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive"), False),
    # Opt-in (issue 10): the tag-level photometric fit as the corner stage's last step.
    "ficap + photometric corners": (DetectorConfig(edge_photometric=True), PoseConfig(), True),
}
#: Run unless --methods says otherwise (the table recorded in docs/benchmarks.md).
DEFAULT_METHODS = ("ficap", "ficap, equal tag weights", "ficap, biased corners", "ficap, no hidden check",
                   "naive peer")


def _residuals_px(pose, detections, camera, model) -> dict[int, np.ndarray]:
    """Tag id -> (4,) reprojection distances, px, of its detected corners at ``pose`` (first copy)."""
    out: dict[int, np.ndarray] = {}
    for d in detections:
        if d.tag_id in model and d.tag_id not in out:
            proj = camera.project(pose.T_cam_cap.apply(model.corners_of(d.tag_id) / 1000.0)).reshape(4, 2)
            out[d.tag_id] = np.linalg.norm(camera.undistort_px(d.corners_px) - camera.undistort_px(proj), axis=1)
    return out


def run_set(name: str, methods: list[str]) -> dict[str, dict[str, np.ndarray]]:
    s = blender_dev.load_set(name)
    model = nominal_model()
    out = {}
    for m in methods:
        det, pose, tracking = METHODS[m]
        proc = FrameProcessor(model, det, pose, tracking=tracking)
        rot, trans, rms, rms_all = [], [], [], []
        for f in s.frames:
            r = proc.process(f.image, s.camera, f.stamp_ns)
            if r.pose is None:
                rot.append(np.nan), trans.append(np.nan), rms.append(np.nan), rms_all.append(np.nan)
                continue
            rot.append(float(angle_deg(r.pose.T_cam_cap.rotation, f.T_cam_cap.rotation)))
            trans.append(1000.0 * float(np.linalg.norm(r.pose.T_cam_cap.translation_m - f.T_cam_cap.translation_m)))
            rms.append(float(r.pose.rms_px))
            every = np.concatenate(list(_residuals_px(r.pose, r.detections, s.camera, model).values()))
            rms_all.append(float(np.sqrt(np.mean(every**2))))
        out[m] = {"rot": np.array(rot), "trans": np.array(trans), "rms": np.array(rms), "rms_all": np.array(rms_all)}
    return out


#: Tag classes of ``--rms-sources`` (from the truth: the renderer's ray cast and view angle).
CLASSES = ("partly hidden (< 4 corners visible)", "fully visible, > 70 deg", "fully visible, 50-70 deg",
           "fully visible, <= 50 deg")


def _tag_class(t: blender_dev.TagTruth) -> str:
    if t.corners_visible < 4:
        return CLASSES[0]
    return CLASSES[1] if t.view_angle_deg > 70.0 else CLASSES[2] if t.view_angle_deg > 50.0 else CLASSES[3]


def rms_sources(name: str) -> list[list[str]]:
    """Rows of the ``--rms-sources`` table for one set: per check setting and tag class, the used
    tags / detected ones, the rms of their residuals, their corners' median error against the
    truth, their share of the frames' summed squared residuals, and the frames' median rms_px with
    that class's corners taken out at the same pose (a what-if, not a new pose)."""
    s = blender_dev.load_set(name)
    model = nominal_model()
    rows = []
    for label, det in (("off", DetectorConfig(hidden_check=False)), ("on", DetectorConfig())):
        proc = FrameProcessor(model, det, PoseConfig(), tracking=True)
        res: dict[str, list[np.ndarray]] = {c: [] for c in CLASSES}
        err: dict[str, list[np.ndarray]] = {c: [] for c in CLASSES}
        counts = {c: [0, 0] for c in CLASSES}  # used, detected
        per_frame: list[dict[str, float]] = []  # summed squares per class
        n_corners: list[dict[str, int]] = []
        for f in s.frames:
            r = proc.process(f.image, s.camera, f.stamp_ns)
            if r.pose is None:
                continue
            by_id = _residuals_px(r.pose, r.detections, s.camera, model)
            first = {}
            for d in r.detections:
                first.setdefault(d.tag_id, d.corners_px)
            used = set(r.pose.used_ids)
            sq = {c: 0.0 for c in CLASSES}
            nc = {c: 0 for c in CLASSES}
            for i, rr in by_id.items():
                c = _tag_class(f.tags[i])
                counts[c][1] += 1
                if i not in used:
                    continue
                counts[c][0] += 1
                res[c].append(rr)
                err[c].append(np.linalg.norm(first[i] - f.corners_px[i], axis=1))
                sq[c] += float(np.sum(rr**2))
                nc[c] += 4
            per_frame.append(sq)
            n_corners.append(nc)
        total_sq = sum(sum(q.values()) for q in per_frame)
        frame_rms = [np.sqrt(sum(q.values()) / max(sum(n.values()), 1)) for q, n in zip(per_frame, n_corners)]
        rows.append([name, label, "all used tags", f"{sum(v[0] for v in counts.values())} / "
                     f"{sum(v[1] for v in counts.values())}",
                     f"{np.sqrt(np.mean(np.concatenate([np.concatenate(v) for v in res.values() if v]) ** 2)):.3f}",
                     f"{np.median(np.concatenate([np.concatenate(v) for v in err.values() if v])):.3f}", "100 %",
                     f"{np.median(frame_rms):.3f}"])
        for c in CLASSES:
            if not counts[c][1]:
                continue
            without = [np.sqrt((sum(q.values()) - q[c]) / max(sum(n.values()) - n[c], 1))
                       for q, n in zip(per_frame, n_corners)]
            r_c = np.concatenate(res[c]) if res[c] else np.zeros(0)
            e_c = np.concatenate(err[c]) if err[c] else np.zeros(0)
            rows.append([name, label, c, f"{counts[c][0]} / {counts[c][1]}",
                         f"{np.sqrt(np.mean(r_c**2)):.3f}" if r_c.size else "-",
                         f"{np.median(e_c):.3f}" if e_c.size else "-",
                         f"{100.0 * sum(q[c] for q in per_frame) / total_sq:.0f} %", f"{np.median(without):.3f}"])
    return rows


RMS_HEADER = ["set", "hidden check", "tags (truth)", "used / detected", "residual rms px",
              "corner error median px (truth)", "share of squared residuals", "rms_px median without them"]


def _q(x: np.ndarray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else float("nan")


HEADER = ["set", "method", "Phi3 median / p95 deg", "geodesic median / p95 deg", "translation median / p95 mm",
          "rms_px median", "rms_px median, every detected tag", "frames with pose", "bar (<= 1/2 peer)"]


#: Written under the table (measured on 2026-11-23).
READING = """Reading it: against the run before (6a6167d+dirty, 21:32) the change is the partly-hidden
check (issue 10: `detection.partly_hidden` reads each tag's white quiet zone, the pose drops a tag
it flags at twice the median tag residual, `PoseConfig.hidden_ratio`; row 'no hidden check' is the
same code without it; the 'equal tag weights' and 'biased corners' rows have the check too, which
is what moved them, e.g. 1080p high equal weights p95 0.068 -> 0.061 deg). rms_px median: 1080p high 0.237 -> 0.217, 1080p neutral 0.183 -> 0.178,
540p high 0.258 -> 0.242, 540p neutral 0.232 -> 0.226, drive30 0.182 -> 0.179; 540p low and the
as-built set unchanged. Pose: 1080p high geodesic median / p95 0.030 / 0.044 -> 0.028 / 0.043 deg,
translation median 0.09 -> 0.08 mm; as-built p95 0.554 -> 0.508 deg and translation p95 1.68 ->
1.41 mm; 1080p neutral p95 0.028 -> 0.030 deg; the others within 0.001 deg and 0.01 mm; the bar
against the peer as before. Issue 10's rms_px target (<= 0.2 px median on clean 1080p frames):
1080p neutral 0.178 (met), 1080p high 0.217 (not met; what is left: 'What makes rms_px on
blender_dev'). rms_px is unweighted over every corner of the tags the pose used; 'every detected
tag' is the same rms over all detected model tags at that pose, those it left out (partly hidden,
beyond 78 deg, outliers) included: on 1080p high 0.334 with or without the check."""


#: Written under the --rms-sources table (measured on 2026-11-23).
RMS_READING = """Reading it. With the check off, 1080p high's rms_px (0.237) came a quarter from 12
partly hidden tags (residual rms 0.56 px, their corners 0.36 px median from the truth against 0.13
for fully visible tags within 50 deg), a quarter from the 22 tags seen beyond 70 deg (0.43 px) and
half from the rest. The check drops the partly hidden tags whose quiet zone shows the cover and
whose residual is over twice the median (2 of the 12, and 5 tags at 50-70 deg the ray cast calls
fully visible, which tests corners only, whose margin something covers: one of them 1.2 px off). The 10 partly hidden tags still used (0.48 px)
are mostly seen at 70-76 deg with one corner hidden and a quiet zone that reads clean (the darkest
half side 0.1-0.3 of the contrast for all but one): the image does not show them as covered. What keeps 1080p
high above 0.2 is the oblique tags: their corners' error grows with the view angle (0.13, 0.16, 0.28
px median below 50, at 50-70 and beyond 70 deg), and without the beyond-70 deg tags' corners the
same poses would give 0.189. Leaving those tags out of the pose (`TrackConfig.pose_max_view_angle_deg`
70 instead of 78, tried, not kept) gives rms_px 0.174 but worse poses: 1080p high geodesic p95
0.043 -> 0.054 deg and translation median 0.08 -> 0.10 mm, 540p low median 0.074 -> 0.093 deg: they
carry information, only their corners are worse. Nor kept: the general 1 px outlier floor at 0.5 px
(1080p high 0.207, poses unchanged). So the target needs better corners on oblique tags (the
cell-edge fit), not more dropping.

Uncertainty (`bench_uncertainty.py --frames 60`, before: 2e52b41's tree, after: with the check,
same machine, load 3-4): every synth row unchanged (the check flags no fully visible synth tag);
blender ours ('ficap joint'): 540p neutral rotation 0.046 -> 0.047 deg, coverage 92 % both,
translation coverage 52 -> 56 %; 540p high translation sharpness 4.31 -> 4.50; 1080p neutral
translation sharpness 4.49 -> 4.07; 1080p high rotation 0.030 -> 0.028 deg (coverage 92 % both),
translation bound 0.28 -> 0.30 mm (sharpness 3.15 -> 3.65, coverage 100 % both); drive30 rotation
coverage 96 -> 99 %; 540p low unchanged, as-built but for Spearman 0.45 -> 0.42.

Cost: `partly_hidden` on a tracked 1080p frame of 22 tags, 0.13-0.18 ms CPU (one 100-point remap a
tag and two sorts; synth drive, load 2-4.6), about 2 % of the frame's 8 ms after the JPEG decode."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="all")
    ap.add_argument("--methods", default=";".join(DEFAULT_METHODS),
                    help=f"';'-separated list of {'; '.join(METHODS)} (must include 'naive peer'; "
                         "default: all but the photometric corners)")
    ap.add_argument("--record", action="store_true")
    ap.add_argument("--rms-sources", action="store_true", help="what makes rms_px (default sets: the 1080p ones)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if not blender_dev.available():
        print(f"blender_dev not found at {blender_dev.BLENDER_DEV}", file=sys.stderr)
        return 1
    sets = list(blender_dev.SETS) if args.sets == "all" else args.sets.split(",")
    t0 = time.time()
    if args.rms_sources:
        if args.sets == "all":
            sets = ["dev_1080p_high", "dev_1080p_neutral"]
        rows = [row for name in sets for row in rms_sources(name)]
        table = md_table(RMS_HEADER, rows)
        print(table)
        if args.record:
            record_section("What makes rms_px on blender_dev", (
                f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s. "
                "`benchmarks/bench_blender_pose.py --rms-sources --record`.\n\n"
                "Each set's frames through `FrameProcessor` as replay runs them, with the partly-hidden "
                "check (`DetectorConfig.hidden_check`) off and on. rms_px is the unweighted rms of the "
                "residuals of every corner of the tags the pose used, at the final (tag-weighted) pose. "
                "Its residuals by the class of their tag (from the truth: the renderer's ray cast, the "
                "view angle); 'used / detected': tags the pose used of the detected ones of that class; "
                "corner error: the used corners against the projected truth; the last column: each "
                "frame's rms_px with that class's corners taken out at the same pose (a what-if).\n\n"
                + table + "\n\n" + RMS_READING))
        return 0
    rows = []
    for name in sets:
        res = run_set(name, [m.strip() for m in args.methods.split(";")])
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
                         f"{_q(r['rms_all'], 50):.3f}", f"{n}/{len(r['rot'])}", bar])
            print(" | ".join(rows[-1]), flush=True)
    table = md_table(HEADER, rows)
    print(table)
    if args.record and args.methods != ";".join(DEFAULT_METHODS):
        print("--record writes the default methods' table only", file=sys.stderr)
    elif args.record:
        body = (f"Machine: {machine_line()}; {load_avg()}; {time.time() - t0:.0f} s.\n\n"
                "Each set's frames through `FrameProcessor` in recording order (ours: default settings, "
                "tracking on, as `ficap replay`; 'equal tag weights': every tag weighted alike in the pose, "
                "as before the per-tag corner-noise weights; 'biased corners': the line fit alone, as before the "
                "tone-curve work; 'no hidden check': without the partly-hidden check (`DetectorConfig."
                "hidden_check`); naive peer: OpenCV sub-pixel corners + one SQPnP/LM, no tracking). Nominal "
                "cap model everywhere. Errors of the cap pose against the rendered truth. 'bar' = rotation "
                "median and p95 and translation median each at most half the peer's.\n\n" + table
                + "\n\n" + READING)
        record_section("Pose on blender_dev (independent renders)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
