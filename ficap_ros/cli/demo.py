"""``ficap demo``: the sample drive recording through a live ficap_node, against its ground truth.

The sample recording is a ``ficap synth`` drive (by default 540p, neutral light, seed 1, 240
frames: 3 s looking ahead, then glances to the mirrors and the instrument cluster), built once per
set of options into a cache folder (``$FICAP_CACHE`` or ``~/.cache/ficap_ros``) and replayed from
there. ``--offline`` renders the same kind of drive through the core without ROS. Every option
applies to both modes (``--resolution``, ``--lighting``, ``--seed``, ``--frames`` choose the
drive, ``--method`` the node's ``pose.method`` or the core's estimator, ``--every`` the printing).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

HELP = "play the sample drive into a live ficap_node, calibrate, print head pose against ground truth"

#: The embedded default: what ``ficap synth`` renders for the sample recording.
SAMPLE = {"resolution": "540p", "lighting": "neutral", "frames": 240, "fps": 30.0, "seed": 1,
          "jpeg_quality": 90, "frontal_s": 3.0}


def sample_recording(progress: bool = True, **options: object) -> Path:
    """The sample drive recording (a rosbag2 MCAP folder), rendered on first use.

    ``options`` override ``SAMPLE`` (resolution, lighting, frames, seed); each set of options has
    its own cache folder.
    """
    from ficap_ros.cli.synth import write_synth_bag
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.synth import RENDER_VERSION

    sample = {**SAMPLE, **options}
    cache = Path(os.environ.get("FICAP_CACHE", Path.home() / ".cache" / "ficap_ros"))
    # A new renderer, a new key ("chain2": synth's camera chain; 3: the neutral lamp).
    key = ("_".join(str(v).replace(" ", "").replace(",", "x").strip("()") for v in sample.values())
           + f"_chain{RENDER_VERSION}")
    bag = cache / f"sample_drive_{key}"
    if not (bag / "metadata.yaml").exists():
        from ficap_ros.files import OutputLock, check_not_in_recording

        check_not_in_recording(bag, "sample recording")  # $FICAP_CACHE inside a recording
        # One demo renders it; another one started meanwhile waits and then uses it.
        with OutputLock(bag, "sample recording", wait=True):
            if not (bag / "metadata.yaml").exists():
                print(f"ficap demo: rendering the sample drive recording once into {bag} ...",
                      flush=True)
                write_synth_bag(bag, nominal_model(), progress=progress, **sample)
    return bag


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ficap_ros.cli.args import frame_count, positive_int, seed
    from ficap_ros.cli.synth import _resolution

    parser.add_argument("--offline", action="store_true",
                        help="run the core on freshly rendered frames instead (no ROS)")
    parser.add_argument("--frames", type=frame_count, default=None,
                        help=f"frames of the drive at 30 fps (default {SAMPLE['frames']}; "
                             "--offline 150); live, more than the 3 s (90 frames) of looking "
                             "ahead that the calibration uses")
    parser.add_argument("--resolution", type=_resolution, default=SAMPLE["resolution"],
                        help="360p, 540p, 720p, 1080p or WxH (default %(default)s)")
    parser.add_argument("--lighting", default=SAMPLE["lighting"], choices=("neutral", "high", "low"),
                        help="the paper's illumination conditions (default %(default)s)")
    parser.add_argument("--method", default="joint", choices=("joint", "paper", "naive"),
                        help="cap pose estimator (live: the node's pose.method; default %(default)s)")
    parser.add_argument("--seed", type=seed, default=SAMPLE["seed"],
                        help="drive and noise seed (default %(default)s)")
    parser.add_argument("--every", type=positive_int, default=6,
                        help="print every Nth frame (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    if not args.offline:
        from ficap_ros.errors import ConfigError
        from ficap_ros.ros.demo import run_demo

        frames = args.frames if args.frames is not None else int(SAMPLE["frames"])
        frontal_frames = int(float(SAMPLE["frontal_s"]) * float(SAMPLE["fps"]))
        if frames <= frontal_frames:
            raise ConfigError(f"--frames {frames}: the live demo calibrates on the first "
                              f"{frontal_frames} frames and needs more after them")
        bag = sample_recording(resolution=args.resolution, lighting=args.lighting,
                               frames=frames, seed=args.seed)
        return run_demo(bag, frontal_s=float(SAMPLE["frontal_s"]), every=args.every,
                        method=args.method)
    return run_offline(args)


def run_offline(args: argparse.Namespace) -> int:
    import numpy as np

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.geometry.metrics import (
        angle_deg,
        phi3_deg,
        summarize_errors,
        yaw_pitch_roll_deg,
    )
    from ficap_ros.io.labels import FrameRecord
    from ficap_ros.tools.synth import (
        RenderConfig,
        default_scene,
        naturalistic_drive,
        render,
    )
    from ficap_ros.vision.pipeline import FrameProcessor
    from ficap_ros.vision.pose import PoseConfig

    frames = args.frames if args.frames is not None else 150
    model = nominal_model()
    scene = default_scene(args.resolution)
    drive = naturalistic_drive(frames, fps=30.0, seed=args.seed, scene=scene)
    processor = FrameProcessor(model, pose=PoseConfig(method=args.method))
    config = RenderConfig(lighting=args.lighting)
    cam = scene.camera
    print(f"ficap demo: {frames} frames, {cam.width_px}x{cam.height_px}, {args.lighting} light, "
          f"method {args.method}; cap pose T_cam_cap vs ground truth")
    print(f"{'frame':>5} {'t_s':>6} {'tags':>5} {'used':>4} {'rms_px':>6} {'rel':>5} "
          f"{'yaw':>7} {'pitch':>7} {'roll':>7} {'x_m':>7} {'y_m':>7} {'z_m':>6} {'err_deg':>8}")
    errors, phi3, detect_ms, pose_ms = [], [], [], []
    for k, truth in enumerate(drive):
        frame = render(model, cam, truth.T_cam_cap, config, seed=args.seed * 100_000 + k)
        result = processor.process(frame.image, cam, stamp_ns=truth.stamp_ns)
        detect_ms.append(result.detect_ms)
        pose_ms.append(result.pose_ms)
        if result.pose is None:
            errors.append(np.nan)
            phi3.append(np.nan)
            if k % args.every == 0:
                print(f"{k:>5} {truth.stamp_ns / 1e9:>6.2f} {result.tags_detected:>5}    - no pose: {result.reason}")
            continue
        T = result.pose.T_cam_cap
        err = angle_deg(T.rotation, truth.T_cam_cap.rotation)
        errors.append(err)
        phi3.append(phi3_deg(T.rotation, truth.T_cam_cap.rotation))
        if k % args.every == 0:
            # Head angles of the cap seen as the head (uncalibrated): readable, not the truth's axes.
            head = FrameRecord.of(result, k, truth.stamp_ns, "").T_frontal_head
            assert head is not None
            ypr = yaw_pitch_roll_deg(head.rotation)
            x, y, z = T.translation_m
            print(f"{k:>5} {truth.stamp_ns / 1e9:>6.2f} {result.tags_detected:>5} {result.pose.tags_used:>4} "
                  f"{result.pose.rms_px:>6.2f} {result.pose.reliability:>5.2f} {ypr[0]:>7.2f} {ypr[1]:>7.2f} "
                  f"{ypr[2]:>7.2f} {x:>7.3f} {y:>7.3f} {z:>6.3f} {err:>8.3f}")
    s = summarize_errors(np.array(errors))
    p = summarize_errors(np.array(phi3))
    with_pose = int(np.sum(np.isfinite(errors)))
    print(f"\nframes with pose: {with_pose}/{len(errors)}")
    print(f"cap rotation error, geodesic angle: mean {s['mean']:.3f}  median {s['median']:.3f}  "
          f"p95 {s['p95']:.3f}  max {s['max']:.3f} deg")
    print(f"cap rotation error, paper's Phi3:   mean {p['mean']:.3f}  median {p['median']:.3f}  "
          f"p95 {p['p95']:.3f} deg")
    print(f"time per frame: detect {np.median(detect_ms):.1f} ms, pose {np.median(pose_ms):.1f} ms (median)")
    return 0
