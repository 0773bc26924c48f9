"""``ficap synth``: a rendered drive as a rosbag2 MCAP bag with exact ground truth."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from ficap_ros.cli.args import (
    ROW_ORDERS,
    duration_ms,
    float_in,
    frame_count,
    frame_rate,
    seed,
)

if TYPE_CHECKING:
    import numpy as np
    from scipy.spatial.transform import Rotation

    from ficap_ros.geometry.cap_model import CapModel
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.tools.synth import DriveFrame, DriveMotion, DriveScene, RenderConfig

HELP = ("render a naturalistic drive of the cap into a rosbag2 MCAP bag: CompressedImage (JPEG), "
        "CameraInfo and ground-truth cap and head poses")

#: Topics of a synth bag.
IMAGE_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
TRUTH_CAP_TOPIC = "/ficap/truth/cap_pose"
TRUTH_HEAD_TOPIC = "/ficap/truth/head_pose"
TRUTH_HEAD_CAMERA_TOPIC = "/ficap/truth/head_pose_camera"
TRUTH_FRONTAL_TOPIC = "/ficap/truth/frontal"
TRUTH_TWIST_TOPIC = "/ficap/truth/cap_twist"
#: Head motions of ``--motion`` (``synth.MOTIONS``, named here so parsing needs no OpenCV).
MOTIONS = ("naturalistic", "glances")
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
        from ficap_ros.errors import ImageError
        from ficap_ros.io.image_codec import check_pixel_budget

        try:
            check_pixel_budget(*size, what="rendered image")
        except ImageError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
        return size
    return text


def _jpeg_quality(text: str) -> int:
    """argparse type for a JPEG quality: an integer in 1..100."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in 1..100, got {text!r}") from None
    if not 1 <= value <= 100:
        raise argparse.ArgumentTypeError(f"expected an integer in 1..100, got {value}")
    return value


def _limited(name: str, low_open: bool = False):  # noqa: ANN202 - an argparse type
    """argparse type for a camera knob, in [0, the RenderConfig limit ``name``]."""
    def parse(text: str) -> float:
        from ficap_ros.tools.synth import config

        return float_in(0.0, float(getattr(config, name)), low_open=low_open)(text)

    parse.__name__ = "number"
    return parse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="BAG", help="output rosbag2 folder")
    parser.add_argument("--resolution", type=_resolution, default="540p",
                        help="540p, 1080p (also 360p, 720p) or WxH (default 540p)")
    parser.add_argument("--lighting", choices=("neutral", "high", "low"), default="neutral",
                        help="the paper's illumination conditions (default neutral)")
    parser.add_argument("--frames", type=frame_count, default=300,
                        help="frames, at most 108000 (default 300)")
    parser.add_argument("--fps", type=frame_rate, default=30.0,
                        help="frame rate, Hz, 0.01 to 1000 (default 30)")
    parser.add_argument("--seed", type=seed, default=0, help="random seed, 0 to 2^32-1 (default 0)")
    parser.add_argument("--frontal-s", type=float_in(0.0, 3600.0), default=3.0,
                        help="initial looking-straight-ahead segment, s, at most 3600 (default 3)")
    parser.add_argument("--motion", choices=MOTIONS, default="naturalistic",
                        help="head motion: naturalistic (looking ahead, glances now and then) or "
                             "glances (glances back to back, every turn peaking at 150-250 deg/s) "
                             "(default naturalistic)")
    parser.add_argument("--jpeg-quality", type=_jpeg_quality, default=95,
                        help="JPEG quality, 1..100 (default 95)")
    cam = parser.add_argument_group(
        "camera", "the image formation chain (linear light -> lens PSF -> motion blur -> sensor -> "
        "tone curve -> 8 bit -> JPEG; see ficap_ros.tools.synth)")
    cam.add_argument("--psf-sigma-px", type=_limited("MAX_BLUR_PX"), default=None,
                     help="Gaussian lens PSF sigma, px, in linear light, at most 50 (default 0.7 "
                     "px at 1080p, times sqrt(height/1080); 0 = none)")
    cam.add_argument("--defocus-px", type=_limited("MAX_BLUR_PX"), default=0.0,
                     help="radius of a defocus disc PSF, px, at most 50 (default 0 = in focus)")
    cam.add_argument("--tone", choices=("srgb", "gamma", "filmic", "linear"), default="srgb",
                     help="the camera's tone curve (default srgb; linear = an idealised camera)")
    cam.add_argument("--gamma", type=_limited("MAX_GAMMA", low_open=True), default=2.2,
                     help="exponent of --tone gamma: value ** (1/GAMMA) (default 2.2)")
    cam.add_argument("--exposure-ms", type=_limited("MAX_EXPOSURE_MS", low_open=True), default=None,
                     help="exposure time, ms (default: the lighting's auto-exposure: neutral 8, high 4, "
                     "low 20); the gain follows unless --gain is given")
    cam.add_argument("--gain", type=_limited("MAX_GAIN", low_open=True), default=None,
                     help="sensor gain (default auto: keeps the lighting's brightness)")
    cam.add_argument("--motion-blur", action="store_true",
                     help="integrate the head motion over the exposure (truth = mid-exposure pose)")
    cam.add_argument("--readout-ms", type=duration_ms, default=0.0, metavar="MS",
                     help="rolling shutter: rows exposed one after another, the first and the last "
                          "row's exposure centres MS apart, the middle row's at the stamp (truth = "
                          "the pose at the stamp); without --motion-blur each row is an instant "
                          "(default 0: a global shutter)")
    cam.add_argument("--row-order", choices=ROW_ORDERS, default="top_to_bottom",
                     help="order in which the rolling shutter reads its rows (default top_to_bottom)")
    cam.add_argument("--no-noise", action="store_true", help="no shot or read noise")
    parser.add_argument("--model", help="cap model YAML to render (default: nominal)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    from ficap_ros.errors import BagError
    from ficap_ros.files import OutputLock, check_output_folder
    from ficap_ros.geometry.cap_model import load_model, nominal_model
    from ficap_ros.tools.synth import RenderConfig

    # Knobs out of range are argparse's (exit 2, as every verb's numbers).
    out = Path(args.out)
    if os.path.lexists(out):
        raise BagError(f"{out} exists already; choose a new --out")
    # Before anything is rendered: never an input or inside a recording, and one writer at a
    # time (the bag is written beside its place and renamed into it when complete).
    check_output_folder(out, [args.model])
    # Built here so a bad knob fails before anything is written.
    config = RenderConfig(lighting=args.lighting, background_seed=args.seed, psf_sigma_px=args.psf_sigma_px,
                          defocus_radius_px=args.defocus_px, tone=args.tone, gamma=args.gamma,
                          exposure_ms=args.exposure_ms, gain=args.gain, noise=not args.no_noise,
                          readout_ms=args.readout_ms, row_order=args.row_order)
    model = load_model(args.model) if args.model else nominal_model()
    with OutputLock(out, "output bag"):
        info = write_synth_bag(out, model, args.resolution, args.lighting, args.frames, args.fps,
                               args.seed, args.jpeg_quality, progress=not args.quiet,
                               frontal_s=args.frontal_s, config=config,
                               motion_blur=args.motion_blur, motion=args.motion)
    print(f"{args.frames} frames {info['width']}x{info['height']} {args.lighting} -> {out} "
          f"({info['fps_rendered']:.1f} frames/s rendered)")
    return 0


def write_synth_bag(
    out: str | Path, model: CapModel, resolution: str | tuple[int, int] = "540p",
    lighting: str = "neutral", frames: int = 300, fps: float = 30.0, seed: int = 0,
    jpeg_quality: int = 95, progress: bool = True, frontal_s: float = 3.0,
    config: RenderConfig | None = None, motion_blur: bool = False, motion: str = "naturalistic",
) -> dict[str, float]:
    """Render a drive (``synth.drive_motion(motion, ...)``: ``naturalistic`` or ``glances``) into
    a rosbag2 MCAP folder at ``out``.

    ``config`` (a ``synth.RenderConfig``; default: the realistic chain for ``lighting``) sets the
    camera; with ``motion_blur`` each frame integrates the motion over its exposure, centred on
    the frame's stamp (the truth is the pose at the stamp); with ``config.readout_ms`` a rolling
    shutter exposes each row at its own time (``CameraTiming``'s convention: the middle row's
    mid-exposure at the stamp, the truth the pose at the stamp), blurred or not.

    Topics (all stamped START_NS + the drive's stamp; header stamp = bag receive time):
        ``/camera/image_raw/compressed`` CompressedImage (JPEG), frame ``camera_optical_frame``;
        ``/camera/camera_info`` CameraInfo, one per image;
        ``/ficap/truth/cap_pose`` PoseStamped: true T_cam_cap (camera optical frame);
        ``/ficap/truth/head_pose`` PoseStamped, frame ``frontal``: true head pose in the frontal
            frame F (orientation R_frontal_head, position the cap origin in F), what
            ``ficap evaluate`` compares against labels.csv's head_q*;
        ``/ficap/truth/head_pose_camera`` PoseStamped: true T_cam_head (as the node's head_pose);
        ``/ficap/truth/frontal`` std_msgs/Bool: inside the initial looking-ahead segment;
        ``/ficap/truth/cap_twist`` TwistStamped: the cap's true velocity at the stamp, as
            ``CapPose.velocity`` (camera axes: the cap origin's m/s, then rad/s).
    The scene's true R_cap_head and R_cam_frontal go into the bag's custom metadata
    (``ficap.R_cap_head_q_wxyz`` ...), and the camera's timing (``ficap.camera_timing``, what
    ``ficap replay`` reads: ``CameraTiming.to_dict``; all zeros for still frames).

    Returns:
        dict with width, height, frames, fps_rendered.
    """
    import dataclasses
    import time

    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.tools import synth
    from ficap_ros.tools.replay import Progress

    scene = synth.default_scene(resolution)
    drive_motion = synth.drive_motion(motion, frames / fps, seed, scene, frontal_s=frontal_s)
    drive = [drive_motion.frame(i, fps) for i in range(frames)]
    config = dataclasses.replace(_render_config(config, lighting, seed), motion_blur=motion_blur)
    moving = motion_blur or config.readout_ms > 0.0
    bar = Progress(len(drive), "frames rendered", enabled=progress)
    t0 = time.perf_counter()
    with BagWriter(out, storage="mcap", layout="folder") as bag:
        _write_metadata(bag, scene, config, {
            "lighting": lighting, "frames": frames, "fps": fps, "seed": seed,
            "jpeg_quality": jpeg_quality, "frontal_s": frontal_s, "motion_blur": motion_blur,
            "motion": motion})
        _add_topics(bag)
        for f in drive:
            pose = drive_motion.around(f.stamp_ns / 1e9) if moving else f.T_cam_cap
            rendered = synth.render(model, scene.camera, pose, config, seed=seed * 100003 + f.index)
            _write_frame(bag, scene, f, rendered.image, jpeg_quality, drive_motion)
            bar.update()
    bar.close()
    elapsed = time.perf_counter() - t0
    return {"width": scene.camera.width_px, "height": scene.camera.height_px, "frames": len(drive),
            "fps_rendered": len(drive) / elapsed if elapsed > 0 else float("inf")}


def _render_config(config: RenderConfig | None, lighting: str, seed: int) -> RenderConfig:
    """The camera of a synth bag: ``config`` in ``lighting``, or the realistic chain."""
    import dataclasses

    from ficap_ros.tools import synth

    if config is None:
        return synth.RenderConfig(lighting=lighting, background_seed=seed, **synth.REALISTIC)
    if config.lighting != lighting:
        return dataclasses.replace(config, lighting=lighting)
    return config


def _q_wxyz_json(r: Rotation) -> str:
    x, y, z, w = r.as_quat(canonical=True)
    return json.dumps([round(float(v), 12) for v in (w, x, y, z)])


def _write_metadata(bag: BagWriter, scene: DriveScene, config: RenderConfig,
                    options: dict[str, object]) -> None:
    """The bag's custom metadata: the scene's true rotations, the camera's timing and how the
    drive was rendered (``options``: lighting, frames, fps, seed, jpeg_quality, frontal_s,
    motion_blur, motion)."""
    from ficap_ros.io.sources import TIMING_METADATA_KEY

    camera = scene.camera
    exposure_ms, gain = config.exposure_and_gain()
    bag.set_custom_data(TIMING_METADATA_KEY, json.dumps(config.timing.to_dict()))
    bag.set_custom_data("ficap.R_cap_head_q_wxyz", _q_wxyz_json(scene.R_cap_head))
    bag.set_custom_data("ficap.R_cam_frontal_q_wxyz", _q_wxyz_json(scene.R_cam_frontal))
    bag.set_custom_data("ficap.synth", json.dumps(
        {"resolution": [camera.width_px, camera.height_px], "lighting": options["lighting"],
         "frames": options["frames"], "fps": options["fps"], "seed": options["seed"],
         "jpeg_quality": options["jpeg_quality"], "frontal_s": options["frontal_s"],
         "psf_sigma_px": config.psf_sigma_for(camera.height_px),
         "defocus_radius_px": config.defocus_radius_px, "tone": config.tone, "gamma": config.gamma,
         "exposure_ms": exposure_ms, "gain": gain, "noise": config.noise,
         "motion_blur": bool(options["motion_blur"]), "motion": options["motion"],
         "readout_ms": config.readout_ms, "row_order": config.row_order}))


def _add_topics(bag: BagWriter) -> None:
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE

    bag.add_topic(IMAGE_TOPIC, COMPRESSED_TYPE)
    bag.add_topic(CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE)
    bag.add_topic(TRUTH_CAP_TOPIC, "geometry_msgs/msg/PoseStamped")
    bag.add_topic(TRUTH_HEAD_TOPIC, "geometry_msgs/msg/PoseStamped")
    bag.add_topic(TRUTH_HEAD_CAMERA_TOPIC, "geometry_msgs/msg/PoseStamped")
    bag.add_topic(TRUTH_FRONTAL_TOPIC, "std_msgs/msg/Bool")
    bag.add_topic(TRUTH_TWIST_TOPIC, "geometry_msgs/msg/TwistStamped")


def _write_frame(bag: BagWriter, scene: DriveScene, f: DriveFrame, image: np.ndarray,
                 jpeg_quality: int, motion: DriveMotion) -> None:
    """One frame's messages: CameraInfo, the JPEG image, the true poses and the true twist, at
    the frame's stamp."""
    import cv2
    import numpy as np

    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io.messages import (
        ROSBAGS,
        camera_info,
        compressed_image,
        header,
        jazzy_typestore,
        pose_stamped,
        twist_stamped,
    )

    stamp = START_NS + f.stamp_ns
    ok, jpg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:  # pragma: no cover - OpenCV always encodes a uint8 image
        raise RuntimeError("JPEG encoding failed")
    T_cam_head = Transform(f.T_cam_cap.rotation * scene.R_cap_head, f.T_cam_cap.translation_m)
    R_frontal_cam = Transform(scene.R_cam_frontal.inv(), np.zeros(3))
    in_camera = header(ROSBAGS, stamp, CAMERA_FRAME)
    bag.write(CAMERA_INFO_TOPIC, stamp, camera_info(ROSBAGS, in_camera, scene.camera))
    bag.write(IMAGE_TOPIC, stamp, compressed_image(ROSBAGS, in_camera, jpg.tobytes()))
    bag.write(TRUTH_CAP_TOPIC, stamp, pose_stamped(ROSBAGS, in_camera, f.T_cam_cap))
    bag.write(TRUTH_HEAD_TOPIC, stamp,
              pose_stamped(ROSBAGS, header(ROSBAGS, stamp, FRONTAL_FRAME),
                           R_frontal_cam * T_cam_head))
    bag.write(TRUTH_HEAD_CAMERA_TOPIC, stamp, pose_stamped(ROSBAGS, in_camera, T_cam_head))
    bag.write(TRUTH_FRONTAL_TOPIC, stamp,
              jazzy_typestore().types["std_msgs/msg/Bool"](data=bool(f.frontal)))
    bag.write(TRUTH_TWIST_TOPIC, stamp,
              twist_stamped(ROSBAGS, in_camera, motion.cap_velocity_at(f.stamp_ns / 1e9)))
