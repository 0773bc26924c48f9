"""``ficap synth``: a rendered drive as a rosbag2 MCAP bag with exact ground truth."""

from __future__ import annotations

import argparse

from ficap_ros.cli import positive_int

HELP = ("render a naturalistic drive of the cap into a rosbag2 MCAP bag: CompressedImage (JPEG), "
        "CameraInfo and ground-truth cap and head poses")

#: Topics of a synth bag.
IMAGE_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
TRUTH_CAP_TOPIC = "/ficap/truth/cap_pose"
TRUTH_HEAD_TOPIC = "/ficap/truth/head_pose"
TRUTH_HEAD_CAMERA_TOPIC = "/ficap/truth/head_pose_camera"
TRUTH_FRONTAL_TOPIC = "/ficap/truth/frontal"
CAMERA_FRAME = "camera_optical_frame"
FRONTAL_FRAME = "frontal"
#: First stamp of a synth bag (2023-11-14 22:13:20 UTC): a realistic epoch, fixed so bags are
#: reproducible.
START_NS = 1_700_000_000_000_000_000


def _resolution(text: str) -> str | tuple[int, int]:
    if "x" in text.lower():
        w, _, h = text.lower().partition("x")
        try:
            size = (int(w), int(h))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from None
        if min(size) < 64:
            raise argparse.ArgumentTypeError(f"resolution {text} is too small")
        return size
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="BAG", help="output rosbag2 folder")
    parser.add_argument("--resolution", type=_resolution, default="540p",
                        help="540p, 1080p (also 360p, 720p) or WxH (default 540p)")
    parser.add_argument("--lighting", choices=("neutral", "high", "low"), default="neutral",
                        help="the paper's illumination conditions (default neutral)")
    parser.add_argument("--frames", type=positive_int, default=300, help="frames (default 300)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--frontal-s", type=float, default=3.0,
                        help="initial looking-straight-ahead segment, s (default 3)")
    parser.add_argument("--jpeg-quality", type=int, default=95, help="JPEG quality (default 95)")
    parser.add_argument("--model", help="cap model YAML to render (default: nominal)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ficap_ros.cap_model import load_model, nominal_model
    from ficap_ros.errors import BagError, ConfigError

    if not 1 <= args.jpeg_quality <= 100:
        raise ConfigError(f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    if not args.frontal_s >= 0:
        raise ConfigError(f"--frontal-s must be >= 0, got {args.frontal_s}")
    if not args.fps > 0:
        raise ConfigError(f"--fps must be positive, got {args.fps}")
    out = Path(args.out)
    if out.exists():
        raise BagError(f"{out} exists already; choose a new --out")
    model = load_model(args.model) if args.model else nominal_model()
    info = write_synth_bag(out, model, args.resolution, args.lighting, args.frames, args.fps,
                           args.seed, args.jpeg_quality, progress=not args.quiet,
                           frontal_s=args.frontal_s)
    print(f"{args.frames} frames {info['width']}x{info['height']} {args.lighting} -> {out} "
          f"({info['fps_rendered']:.1f} frames/s rendered)")
    return 0


def write_synth_bag(
    out, model, resolution="540p", lighting="neutral", frames=300, fps=30.0, seed=0,
    jpeg_quality=95, progress=True, frontal_s=3.0,
) -> dict:
    """Render ``ficap_ros.synth.naturalistic_drive`` into a rosbag2 MCAP folder at ``out``.

    Topics (all stamped START_NS + the drive's stamp; header stamp = bag receive time):
        ``/camera/image_raw/compressed`` CompressedImage (JPEG), frame ``camera_optical_frame``;
        ``/camera/camera_info`` CameraInfo, one per image;
        ``/ficap/truth/cap_pose`` PoseStamped: true T_cam_cap (camera optical frame);
        ``/ficap/truth/head_pose`` PoseStamped, frame ``frontal``: true head pose in the frontal
            frame F (orientation R_frontal_head, position the cap origin in F), what
            ``ficap evaluate`` compares against labels.csv's head_q*;
        ``/ficap/truth/head_pose_camera`` PoseStamped: true T_cam_head (as the node's head_pose);
        ``/ficap/truth/frontal`` std_msgs/Bool: inside the initial looking-ahead segment.
    The scene's true R_cap_head and R_cam_frontal go into the bag's custom metadata
    (``ficap.R_cap_head_q_wxyz`` ...).

    Returns:
        dict with width, height, frames, fps_rendered.
    """
    import json
    import time

    import cv2
    import numpy as np

    from ficap_ros import synth
    from ficap_ros.bag_io import (
        CAMERA_INFO_TYPE,
        COMPRESSED_TYPE,
        BagWriter,
        camera_info_msg,
        compressed_image_msg,
        jazzy_typestore,
        pose_stamped_msg,
    )
    from ficap_ros.replay import Progress
    from ficap_ros.transform import Transform

    scene = synth.default_scene(resolution)
    camera = scene.camera
    drive = synth.naturalistic_drive(frames, fps, seed, scene, frontal_s=frontal_s)
    config = synth.RenderConfig(lighting=lighting, background_seed=seed)
    bool_type = jazzy_typestore().types["std_msgs/msg/Bool"]
    bar = Progress(len(drive), "frames rendered", enabled=progress)
    t0 = time.perf_counter()

    def q_wxyz(r) -> str:
        x, y, z, w = r.as_quat(canonical=True)
        return json.dumps([round(float(v), 12) for v in (w, x, y, z)])

    with BagWriter(out, storage="mcap", layout="folder") as bag:
        bag.set_custom_data("ficap.R_cap_head_q_wxyz", q_wxyz(scene.R_cap_head))
        bag.set_custom_data("ficap.R_cam_frontal_q_wxyz", q_wxyz(scene.R_cam_frontal))
        bag.set_custom_data("ficap.synth", json.dumps(
            {"resolution": [camera.width_px, camera.height_px], "lighting": lighting,
             "frames": frames, "fps": fps, "seed": seed, "jpeg_quality": jpeg_quality,
             "frontal_s": frontal_s}))
        bag.add_topic(IMAGE_TOPIC, COMPRESSED_TYPE)
        bag.add_topic(CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE)
        bag.add_topic(TRUTH_CAP_TOPIC, "geometry_msgs/msg/PoseStamped")
        bag.add_topic(TRUTH_HEAD_TOPIC, "geometry_msgs/msg/PoseStamped")
        bag.add_topic(TRUTH_HEAD_CAMERA_TOPIC, "geometry_msgs/msg/PoseStamped")
        bag.add_topic(TRUTH_FRONTAL_TOPIC, "std_msgs/msg/Bool")
        R_frontal_cam = Transform(scene.R_cam_frontal.inv(), np.zeros(3))
        for f in drive:
            stamp = START_NS + f.stamp_ns
            rendered = synth.render(model, camera, f.T_cam_cap, config, seed=seed * 100003 + f.index)
            ok, jpg = cv2.imencode(".jpg", rendered.image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
            if not ok:  # pragma: no cover - OpenCV always encodes a uint8 image
                raise RuntimeError("JPEG encoding failed")
            T_cam_head = Transform(f.T_cam_cap.rotation * scene.R_cap_head,
                                   f.T_cam_cap.translation_m)
            bag.write(CAMERA_INFO_TOPIC, stamp, camera_info_msg(stamp, CAMERA_FRAME, camera))
            bag.write(IMAGE_TOPIC, stamp, compressed_image_msg(stamp, CAMERA_FRAME, jpg.tobytes()))
            bag.write(TRUTH_CAP_TOPIC, stamp, pose_stamped_msg(stamp, CAMERA_FRAME, f.T_cam_cap))
            bag.write(TRUTH_HEAD_TOPIC, stamp,
                      pose_stamped_msg(stamp, FRONTAL_FRAME, R_frontal_cam * T_cam_head))
            bag.write(TRUTH_HEAD_CAMERA_TOPIC, stamp,
                      pose_stamped_msg(stamp, CAMERA_FRAME, T_cam_head))
            bag.write(TRUTH_FRONTAL_TOPIC, stamp, bool_type(data=bool(f.frontal)))
            bar.update()
    bar.close()
    elapsed = time.perf_counter() - t0
    return {"width": camera.width_px, "height": camera.height_px, "frames": len(drive),
            "fps_rendered": len(drive) / elapsed if elapsed > 0 else float("inf")}
