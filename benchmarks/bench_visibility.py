"""Section 6: share of frames with >= 1 and >= 4 tags, and where to mount the camera.

Cheap first pass (labelled as such in the table): a tag counts as seen when the renderer's
``visible_fraction`` (share of the tag square inside the image and not hidden by the head, neck
or other faces) is at least ``--min-visible`` and it faces the camera at less than ``--max-angle-deg``
(ArUco stops decoding very oblique tags). With ``--detect`` the frames are also run through the
detector (``FrameProcessor``) and the detected counts are reported (slower).

Default placement: ``ficap_ros.synth.default_scene`` (0.45 m behind the cap, 6 cm above, 60 deg hfov)
over a long naturalistic drive. Sweep: camera distance behind the back of the cap x height above the
cap centre, the camera aimed at the cap of the frontal head.

Usage: .venv/bin/python benchmarks/bench_visibility.py [--frames 3600] [--stride 4] [--detect] [--record]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Progress, load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.camera import CameraModel  # noqa: E402
from ficap_ros.cap_model import nominal_model  # noqa: E402
from ficap_ros.pipeline import FrameProcessor  # noqa: E402
from ficap_ros.synth import DriveScene, RenderConfig, default_scene, naturalistic_drive, render  # noqa: E402
from ficap_ros.transform import CAM_FROM_FORWARD  # noqa: E402

CAP_RADIUS_M = 0.092  # back of the cap to the cap origin (default_scene: 0.45 m + 0.092)


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


def counts(scene: DriveScene, frames: int, stride: int, args: argparse.Namespace, label: str,
           detect: bool) -> tuple[np.ndarray, np.ndarray | None]:
    model = nominal_model()
    drive = naturalistic_drive(frames, fps=30.0, seed=args.seed, scene=scene)[::stride]
    cfg = RenderConfig(noise_sigma=2.0, supersample=2 if not detect else 4)
    proc = FrameProcessor(model, tracking=False) if detect else None
    seen, det = [], []
    prog = Progress(len(drive), label)
    for d in drive:
        f = render(model, scene.camera, d.T_cam_cap, cfg, seed=d.index)
        rot = d.T_cam_cap.rotation
        n_cam = rot.apply(model.normals)
        c_cam = d.T_cam_cap.apply(model.centres_mm / 1000.0)
        cosang = -np.sum(n_cam * c_cam, 1) / np.linalg.norm(c_cam, axis=1)
        ok_angle = {t for t, c in zip(model.ids, cosang) if c > np.cos(np.radians(args.max_angle_deg))}
        big = {t for t, c in f.corners_px.items()
               if np.linalg.norm(c - np.roll(c, -1, 0), axis=1).min() >= args.min_side_px}
        seen.append(sum(1 for t in f.visible_ids(args.min_visible) if t in ok_angle and t in big))
        if proc is not None:
            det.append(proc.process(f.image, scene.camera).tags_detected)
        prog.update()
    return np.array(seen), (np.array(det) if detect else None)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=3600, help="drive length, 30 fps frames (default 2 min)")
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--sweep-frames", type=int, default=1800)
    ap.add_argument("--sweep-stride", type=int, default=15)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--min-visible", type=float, default=0.999)
    ap.add_argument("--max-angle-deg", type=float, default=75.0)
    ap.add_argument("--min-side-px", type=float, default=12.0, help="shortest projected tag side counted")
    ap.add_argument("--detect", action="store_true", help="also run detection on the default placement")
    ap.add_argument("--record", action="store_true")
    args = ap.parse_args()
    res = (960, 540)
    seen, det = counts(default_scene("540p"), args.frames, args.stride, args, "default placement", args.detect)
    rows = [["renderer visibility (cheap pass)", len(seen), f"{100 * np.mean(seen >= 1):.1f} %",
             f"{100 * np.mean(seen >= 4):.1f} %", f"{np.median(seen):.0f}", f"{seen.min()}"]]
    if det is not None:
        rows.append(["detected (540p, FrameProcessor)", len(det), f"{100 * np.mean(det >= 1):.1f} %",
                     f"{100 * np.mean(det >= 4):.1f} %", f"{np.median(det):.0f}", f"{det.min()}"])
    rows.append(["paper (real drive, 68 min)", 246643, "99.8 %", "99.2 %", "-", "-"])
    sweep = []
    for dist in (0.3, 0.45, 0.7, 1.0):
        for h in (-0.1, 0.06, 0.2, 0.35):
            s, _ = counts(scene_at(dist, h, res), args.sweep_frames, args.sweep_stride, args,
                          f"d {dist} h {h}", False)
            sweep.append([f"{dist:.2f}", f"{h:+.2f}", f"{100 * np.mean(s >= 1):.1f} %",
                          f"{100 * np.mean(s >= 4):.1f} %", f"{np.median(s):.0f}", f"{np.percentile(s, 5):.0f}"])
            print(sweep[-1], file=sys.stderr)
    text = "\n".join([
        f"Machine: {machine_line()}; {load_avg()}.", "",
        f"Default placement (`default_scene`, 540p): naturalistic drive seed {args.seed}, {args.frames} frames "
        f"({args.frames / 1800:.1f} min at 30 fps), every {args.stride}th frame. 'Renderer visibility' is the "
        f"cheap pass: tags at least {100 * args.min_visible:.1f} % visible (not cut by the image border, the head "
        f"or the neck), facing the camera within {args.max_angle_deg:.0f} deg and with every side at least "
        f"{args.min_side_px:.0f} px; not a detector result.", "",
        md_table(["count", "frames", ">= 1 tag", ">= 4 tags", "median tags", "min tags"], rows), "",
        f"Sweep (renderer visibility, cheap pass; {args.sweep_frames} frames, every {args.sweep_stride}th; 540p "
        "60 deg hfov; camera aimed at the frontal cap): distance = camera to the back of the cap, height = camera "
        "above the cap centre (the default is 0.45 m / +0.06 m).", "",
        md_table(["distance (m)", "height (m)", ">= 1 tag", ">= 4 tags", "median tags", "5th pct tags"], sweep),
    ])
    print(text)
    if args.record:
        record_section("Visibility (paper section 6)", text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
