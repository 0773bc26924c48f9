"""``ficap replay``: a recorded drive (bag, .mcap or video) into head-pose labels."""

from __future__ import annotations

import argparse
from typing import Any

from ficap_ros.cli.args import (
    POSE_METHOD_CHOICES,
    ROW_ORDERS,
    duration_ms,
    finite_float,
    frame_rate,
    int_in,
    offset_ms,
    positive_int,
    time_window,
)

HELP = ("replay rosbag2 bags, .mcap files or videos (or folder trees of them, or a manifest) "
        "through the pipeline; write labels.mcap, labels.csv and summary.json per recording, "
        "optionally on Ray")


def add_input_arguments(parser: argparse.ArgumentParser, many: bool = False) -> None:
    """The options that say how to read a recording (shared with ``ficap stats``); ``many``:
    several inputs (recordings or folder trees holding them)."""
    if many:
        parser.add_argument("input", metavar="INPUT", nargs="*",
                            help="rosbag2 folders (sqlite3 or MCAP), .mcap/.db3 files or videos, or "
                                 "folders searched for them (outputs mirror the inputs under --out)")
    else:
        parser.add_argument("input", metavar="INPUT",
                            help="labels.csv or a replay output folder (counted as they are), or a "
                                 "rosbag2 folder (sqlite3 or MCAP), single .mcap/.db3 file or video "
                                 "(the pipeline runs)")
    parser.add_argument("--image-topic", help="Image or CompressedImage topic (auto when only one)")
    parser.add_argument("--camera-info-topic", help="CameraInfo topic (auto)")
    parser.add_argument("--rectified", action="store_true",
                        help="the images are rectified: use CameraInfo P, no distortion (the "
                             "node's image_is_rectified; default: raw images, K and D)")
    parser.add_argument("--intrinsics", metavar="CAMERA_YAML",
                        help="camera_calibration YAML; required for a video, overrides CameraInfo")
    parser.add_argument("--fps", type=frame_rate,
                        help="video frame rate, 0.01 to 1000 Hz (default: the container's)")
    parser.add_argument("--model", help="as-built cap model YAML (default: nominal)")
    parser.add_argument("--method", choices=POSE_METHOD_CHOICES, default="joint",
                        help="cap pose estimator, the node's pose.method: joint (PnP over all "
                             "corners, tag-level outlier rejection), paper (per-tag + Kabsch + "
                             "outlier trimming) or naive (the baseline; default: joint)")
    parser.add_argument("--jobs", type=positive_int, default=1,
                        help="worker processes, capped at the cores available (default 1; "
                             "output identical to --jobs 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser, many=True)
    parser.add_argument("--photometric", action=argparse.BooleanOptionalAction, default=None,
                        help="corners' last step: fit each tag's pattern, blurred in linear light and "
                             "through a tone curve, to its pixels (more accurate on noisy frames, "
                             "at a CPU cost per tag: docs/detection.md; every recording of a fleet, "
                             "any engine): --photometric every tag's; --no-photometric none (the "
                             "cell-edge fit's corners); neither (the default): the tags whose "
                             "corners noise limits")
    parser.add_argument("--motion-corners", action=argparse.BooleanOptionalAction, default=True,
                        help="with a stated exposure (--exposure-ms, a camera YAML's camera_timing): "
                             "refit each tag that moves over the exposure with its pattern moving "
                             "along its corners' paths, for the mid-exposure corners (the default; "
                             "more CPU in fast frames); --no-motion-corners: the still fit only")
    parser.add_argument("--two-sided-motion", action=argparse.BooleanOptionalAction, default=True,
                        help="with a stated exposure or readout: solve each frame again once the "
                             "next frame has its pose, so the cap's path over the exposure and "
                             "readout is interpolated between the frames before and the next one "
                             "(the default; about one more pose solve a frame); "
                             "--no-two-sided-motion: the frames before only, as the live node "
                             "(one recording only)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--calibration", metavar="FILE",
                        help="head calibration YAML (ficap calibrate / the node's service)")
    parser.add_argument("--calibrate-frontal", type=time_window, metavar="START:END",
                        help="seconds from the start in which the wearer looks straight ahead: "
                             "calibrate R_cap_head from them and apply it to every frame")
    parser.add_argument("--namespace", default="",
                        help="topic namespace in labels.mcap (default: none, as the node: /head_pose ...)")
    parser.add_argument("--camera-mount", type=finite_float, nargs=7,
                        metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                        help="the camera's optical frame in --output-frame (or in the frontal frame "
                             "without one): metres and a unit quaternion, static_transform_publisher's "
                             "order, as the node's camera_mount; on /tf_static in labels.mcap, and "
                             "the frontal frame of the head angles takes its parent's axes")
    parser.add_argument("--output-frame", default="", metavar="FRAME",
                        help="frame of labels.mcap's poses (e.g. base_link), reached through "
                             "--camera-mount, as the node's output_frame (default: the image's)")
    timing = parser.add_argument_group(
        "camera timing", "when the camera's rows see the scene (the node's camera.* parameters); "
        "each one given replaces that field of the recording's own timing (a camera_timing "
        "mapping in --intrinsics, a ficap synth bag's metadata); summary.json records the timing "
        "used and where it came from")
    timing.add_argument("--exposure-ms", type=duration_ms, metavar="MS",
                        help="each row's exposure time, ms (0 = not known)")
    timing.add_argument("--readout-ms", type=duration_ms, metavar="MS",
                        help="rolling shutter: time between the first and the last row's "
                             "exposure centres, ms (0 = a global shutter)")
    timing.add_argument("--row-order", choices=ROW_ORDERS,
                        help="order in which a rolling shutter reads its rows")
    timing.add_argument("--stamp-offset-ms", type=offset_ms, metavar="MS",
                        help="added to each stamp to reach the middle row's mid-exposure, ms "
                             "(the poses are reported at the stamp plus it)")
    fleet = parser.add_argument_group(
        "fleet", "several recordings: one output folder each under --out (mirroring the inputs) "
                 "and fleet_summary.csv/.json/.png; recordings whose outputs match this run's "
                 "fingerprint are skipped")
    fleet.add_argument("--manifest", metavar="FILE",
                       help="text file listing inputs, one per line (relative to the file; "
                            "# comments); relative entries mirror their paths under --out")
    fleet.add_argument("--ray", action="store_true",
                       help="run on an embedded local Ray (loopback only; --jobs CPUs)")
    fleet.add_argument("--ray-address", metavar="ADDR",
                       help="run on an existing Ray cluster (e.g. auto, HEAD:6379)")
    fleet.add_argument("--retries", type=int_in(0, 10), default=2, metavar="N",
                       help="Ray: re-runs of a segment whose worker died, 0 to 10 (default 2)")
    fleet.add_argument("--force", action="store_true",
                       help="redo recordings whose outputs are already current")
    fleet.add_argument("--videos", action="store_true",
                       help="also take video files found in searched folders (needs --intrinsics)")


def timing_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The camera timing fields given on the command line (``CameraTiming``'s names)."""
    names = ("exposure_ms", "readout_ms", "row_order", "stamp_offset_ms")
    return {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}


def open_source(args: argparse.Namespace, path: object = None):  # noqa: ANN201 - FrameSource
    from ficap_ros.io.sources import open_frames

    return open_frames(args.input if path is None else path, args.image_topic,
                       args.camera_info_topic, args.intrinsics, args.fps, args.rectified)


def output_frames(args: argparse.Namespace):  # noqa: ANN201 - io.frames.OutputFrames
    """``--output-frame`` and ``--camera-mount`` (``ficap_ros.io.frames``' rule, the node's).

    Raises:
        ConfigError: an output frame without a mount, or a mount that is not a unit quaternion.
    """
    from ficap_ros.io.frames import OutputFrames, camera_mount_transform

    mount = camera_mount_transform(args.camera_mount) if args.camera_mount else None
    return OutputFrames(args.output_frame, mount)


def _is_fleet(args: argparse.Namespace) -> bool:
    """Several recordings, a folder tree, a manifest or Ray: the fleet runner (ficap_ros.tools.fleet)."""
    from pathlib import Path

    from ficap_ros.tools.fleet.manifest import is_recording

    return bool(len(args.input) != 1 or args.manifest or args.ray or args.ray_address
                or not is_recording(Path(args.input[0]), videos=True))


def cap_jobs(args: argparse.Namespace) -> int:
    """``--jobs`` capped at the cores available; says so on stderr when it is."""
    import sys

    from ficap_ros.tools.replay import capped_jobs

    jobs, note = capped_jobs(args.jobs)
    if note:
        print(f"ficap: {note}", file=sys.stderr)
    return jobs


def side_files(args: argparse.Namespace) -> list[str | None]:
    """The configuration files a run reads besides its recordings (never outputs)."""
    return [args.model, args.intrinsics, getattr(args, "calibration", None),
            getattr(args, "manifest", None)]


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ficap_ros.cli.args import EXIT_FRAMES_LOST
    from ficap_ros.files import check_output_folder
    from ficap_ros.geometry.cap_model import load_model, nominal_model
    from ficap_ros.process import freeze_start_up, keep_freed_memory
    from ficap_ros.tools.replay import replay
    from ficap_ros.vision.detector import DetectorConfig
    from ficap_ros.vision.pose import PoseConfig

    keep_freed_memory()  # this process decodes and processes the frames (--jobs 1)
    frames = output_frames(args)
    model = load_model(args.model) if args.model else nominal_model()
    detector = DetectorConfig(edge_photometric=args.photometric is True,
                              edge_photometric_auto=args.photometric is None, motion_corners=args.motion_corners)
    calibration = None
    if args.calibration:
        from ficap_ros.io.calibration_file import load_calibration

        calibration = load_calibration(args.calibration)
    if not args.input and not args.manifest:
        from ficap_ros.errors import ConfigError

        raise ConfigError("give at least one INPUT or --manifest FILE")
    if _is_fleet(args):
        if not args.two_sided_motion:
            from ficap_ros.errors import ConfigError

            raise ConfigError("--no-two-sided-motion is for one recording; a fleet's frames are "
                              "solved with their next frame's pose")
        freeze_start_up()  # this process reads the recordings (and processes them with --jobs 1)
        return _run_fleet(args, model, calibration, detector, frames)
    args.input = args.input[0]
    # Before any processing: never an input, a recording or a folder ficap did not write.
    check_output_folder(Path(args.out), [args.input, *side_files(args)])
    jobs = cap_jobs(args)
    source = open_source(args)
    freeze_start_up()  # this process processes the frames (--jobs 1) or reads them (more)
    out = replay(source, args.out, model, PoseConfig(method=args.method), calibration,
                 args.calibrate_frontal, jobs, args.namespace, progress=not args.quiet,
                 detector=detector, frames=frames, inputs=side_files(args), timing=timing_fields(args),
                 two_sided=args.two_sided_motion)
    s = out.summary
    line = (f"{s['frames']} frames, {s['frames_with_pose']} with a pose "
            f"({s['pct_with_pose']:.1f} %), >=1 tag {s['pct_ge1_tag']:.1f} %, >=4 tags "
            f"{s['pct_ge4_tags']:.1f} %, {s['frames_skipped']} skipped, "
            f"{s['throughput_fps']} fps -> {args.out}")
    if out.loss is not None:
        line += f"; {out.loss.describe(source.start_ns)}"
    print(line)
    return EXIT_FRAMES_LOST if out.loss is not None else 0


def _run_fleet(args: argparse.Namespace, model, calibration, detector, frames) -> int:  # noqa: ANN001
    from ficap_ros.files import check_output_folder
    from ficap_ros.tools.fleet.manifest import find_recordings

    # The fleet's --out holds a folder per recording: every file in it must be ficap's, none an
    # input (run_fleet checks again and holds its lock for the whole run).
    check_output_folder(args.out, side_files(args), subfolders=True)
    recordings = find_recordings(args.input, args.manifest, args.out, videos=args.videos)
    return _fleet(args, recordings, model, calibration, detector, frames)


def _fleet(args: argparse.Namespace, recordings, model, calibration, detector, frames) -> int:  # noqa: ANN001
    from pathlib import Path

    from ficap_ros.tools.fleet.fingerprints import label_settings
    from ficap_ros.tools.fleet.run import run_fleet
    from ficap_ros.vision.pose import PoseConfig

    pose = PoseConfig(method=args.method)
    settings = label_settings(model, pose, calibration, args.calibrate_frontal, args.namespace,
                              args.image_topic, args.camera_info_topic, args.intrinsics, args.fps,
                              args.rectified, detector, frames, timing_fields(args))
    single = len(recordings) == 1 and str(recordings[0].rel) == "."
    fleet = run_fleet(
        recordings, args.out, lambda path: open_source(args, path), model, pose, settings,
        calibration, args.calibrate_frontal, args.namespace, args.jobs, args.ray_address,
        args.ray, args.retries, args.force, progress=not args.quiet, summary_files=not single,
        detector=detector, frames=frames, inputs=side_files(args), timing=timing_fields(args))
    for r in fleet.results:
        if r.status == "failed":
            print(f"{r.rel}: failed: {r.error}")
        elif r.status == "damaged":
            lost = "an unknown number" if r.frames_lost is None else r.frames_lost
            print(f"{r.rel}: damaged: {r.frames} frames recovered, {lost} lost")
    n_frames = sum(r.frames for r in fleet.results if r.status in ("done", "damaged"))
    print(f"{len(fleet.results)} recordings: {fleet.count('done')} done, "
          f"{fleet.count('skipped')} skipped (current), {fleet.count('damaged')} damaged, "
          f"{fleet.count('failed')} failed; {n_frames} frames in {fleet.wall_s:.1f} s "
          f"({fleet.engine}, {fleet.workers} workers) -> {Path(args.out) / ('' if single else 'fleet_summary.csv')}")
    # 1: a recording has no labels; 3 (as a single replay of a damaged input): frames were lost.
    return 1 if fleet.count("failed") else 3 if fleet.count("damaged") else 0
