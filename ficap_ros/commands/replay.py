"""``ficap replay``: a recorded drive (bag, .mcap or video) into head-pose labels."""

from __future__ import annotations

import argparse

from ficap_ros.cli import positive_int

HELP = ("replay a rosbag2 bag, .mcap file or video through the pipeline; write labels.mcap, "
        "labels.csv and summary.json")


def _window(text: str) -> tuple[float, float]:
    from ficap_ros.replay import parse_window

    try:
        return parse_window(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that say how to read a recording (shared with ``ficap stats``)."""
    parser.add_argument("input", metavar="INPUT",
                        help="rosbag2 folder (sqlite3 or MCAP), single .mcap/.db3 file, or video")
    parser.add_argument("--image-topic", help="Image or CompressedImage topic (auto when only one)")
    parser.add_argument("--camera-info-topic", help="CameraInfo topic (auto)")
    parser.add_argument("--intrinsics", metavar="CAMERA_YAML",
                        help="camera_calibration YAML; required for a video, overrides CameraInfo")
    parser.add_argument("--fps", type=_positive_float,
                        help="video frame rate (default: the container's)")
    parser.add_argument("--model", help="as-built cap model YAML (default: nominal)")
    parser.add_argument("--method", choices=("joint", "paper"), default="joint",
                        help="cap pose estimator (default: joint)")
    parser.add_argument("--jobs", type=positive_int, default=1,
                        help="worker processes (output identical to --jobs 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--calibration", metavar="FILE",
                        help="head calibration YAML (ficap calibrate / the node's service)")
    parser.add_argument("--calibrate-frontal", type=_window, metavar="START:END",
                        help="seconds from the start in which the wearer looks straight ahead: "
                             "calibrate R_cap_head from them and apply it to every frame")
    parser.add_argument("--namespace", default="",
                        help="topic namespace in labels.mcap (default: none, as the node: /head_pose ...)")


def open_source(args: argparse.Namespace):  # noqa: ANN201 - FrameSource, imported lazily
    from ficap_ros.bag_io import open_frames

    return open_frames(args.input, args.image_topic, args.camera_info_topic, args.intrinsics,
                       args.fps)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ficap_ros.cap_model import load_model, nominal_model
    from ficap_ros.pose import PoseConfig
    from ficap_ros.replay import check_output_dir, replay

    model = load_model(args.model) if args.model else nominal_model()
    calibration = None
    if args.calibration:
        from ficap_ros.calibration import load_calibration

        calibration = load_calibration(args.calibration)
    check_output_dir(Path(args.out))
    source = open_source(args)
    out = replay(source, args.out, model, PoseConfig(method=args.method), calibration,
                 args.calibrate_frontal, args.jobs, args.namespace, progress=not args.quiet)
    s = out.summary
    print(f"{s['frames']} frames, {s['frames_with_pose']} with a pose ({s['pct_with_pose']:.1f} %), "
          f">=1 tag {s['pct_ge1_tag']:.1f} %, >=4 tags {s['pct_ge4_tags']:.1f} %, "
          f"{s['frames_skipped']} skipped, {s['throughput_fps']} fps -> {args.out}")
    return 0
