"""``ficap calibrate``: cap-to-head calibration from labels (the paper's Table 2 protocols)."""

from __future__ import annotations

import argparse

from ficap_ros.cli.args import finite_float, max_dt_ms, positive_int, seed, time_window

HELP = ("compute R_cap_head from labels: a frontal window (--frontal START:END) or a reference "
        "head-pose topic (--reference BAG:TOPIC with --first N or --random N)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("labels", metavar="LABELS", help="labels.csv or a replay output folder")
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--frontal", type=time_window, metavar="START:END",
                      help="seconds from the first label in which the wearer looks straight ahead")
    mode.add_argument("--reference", metavar="BAG:TOPIC",
                      help="reference head pose (PoseStamped ...) paired with the labels by stamp")
    pick = parser.add_mutually_exclusive_group()
    pick.add_argument("--first", type=positive_int, metavar="N",
                      help="reference mode: use the first N pairs (the paper's First 10/100/500)")
    pick.add_argument("--random", type=positive_int, metavar="N",
                      help="reference mode: use N random pairs (the paper's Random 100)")
    parser.add_argument("--seed", type=seed, default=0, help="seed of --random (default 0)")
    parser.add_argument("--max-dt-ms", type=max_dt_ms, default=20.0,
                        help="reference mode: largest stamp difference of a pair, ms (default 20; "
                             "at most 60000)")
    parser.add_argument("--camera-mount", type=finite_float, nargs=7,
                        metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                        help="the camera's optical frame in the vehicle frame "
                             "(static_transform_publisher order, m and quaternion); the frontal "
                             "frame takes the vehicle's axes (default: frontal mode: camera looks "
                             "straight ahead; reference mode: the reference's frame), as the "
                             "node's camera_mount")
    parser.add_argument("--min-frames", type=positive_int, default=30,
                        help="frontal mode: least frames with a pose in the window (default 30)")
    parser.add_argument("--out", required=True, metavar="FILE", help="calibration YAML to write")


def run(args: argparse.Namespace) -> int:
    from ficap_ros.io.calibration_file import calibration_output

    reference_bag = args.reference.rpartition(":")[0] if args.reference else None
    # Before reading anything: checked (never an input or a recording) and locked.
    with calibration_output(args.out, (args.labels, reference_bag)) as out:
        return _calibrate(args, out)


def _calibrate(args: argparse.Namespace, out) -> int:  # noqa: ANN001 - files.OutputFile
    import numpy as np

    from ficap_ros.errors import BagError, CalibrationError, ConfigError
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io.calibration_file import save_calibration
    from ficap_ros.io.labels import read_labels
    from ficap_ros.stamps import window_from_start_ns
    from ficap_ros.vision.calibration import (
        calibrate_frontal,
        calibrate_reference,
        calibrated_frontal,
        frontal_frames,
        reference_pairs,
    )

    labels = read_labels(args.labels)
    pose_rows = np.nonzero(labels.has_pose)[0]
    if pose_rows.size == 0:
        raise CalibrationError(f"{args.labels} has no frame with a pose")
    R_cam_cap_all = labels.cap_rotations()
    stamps = labels.stamp_ns[pose_rows]
    mount = (Transform.from_xyz_q_xyzw(args.camera_mount, "--camera-mount")
             if args.camera_mount else None)
    if args.frontal is not None:
        if args.first or args.random:
            raise ConfigError("--first and --random apply to --reference only")
        window = window_from_start_ns(int(labels.stamp_ns.min()), args.frontal)
        sel = frontal_frames(stamps, labels.reliability[pose_rows], window)
        if sel.size == 0:
            raise CalibrationError(
                f"no frame with a pose between {args.frontal[0]:g} s and {args.frontal[1]:g} s")
        if sel.size < args.min_frames:
            raise CalibrationError(
                f"frontal calibration needs {args.min_frames} frames with a pose, the window "
                f"{args.frontal[0]:g}-{args.frontal[1]:g} s has {sel.size}: widen --frontal "
                f"or lower --min-frames")
        R_cam_frontal = calibrated_frontal(None, mount)
        result = calibrate_frontal(R_cam_cap_all[sel], R_cam_frontal, min_frames=args.min_frames)
        save_calibration(out, result, R_cam_frontal=R_cam_frontal)
        detail = f"frontal window {args.frontal[0]:g}-{args.frontal[1]:g} s"
    else:
        from ficap_ros.tools.evaluation import load_series

        path, sep, topic = args.reference.rpartition(":")
        if not sep or not topic.startswith("/"):
            raise BagError(f"--reference expects BAG:TOPIC, got {args.reference!r}")
        ref = load_series(args.reference)
        i_lab, i_ref = reference_pairs(stamps, ref.stamp_ns, int(round(args.max_dt_ms * 1e6)))
        if i_lab.size == 0:
            raise CalibrationError(f"no reference pose within {args.max_dt_ms:g} ms of a label")
        if args.first:
            keep = np.arange(min(args.first, i_lab.size))
        elif args.random:
            rng = np.random.default_rng(args.seed)
            keep = np.sort(rng.choice(i_lab.size, size=min(args.random, i_lab.size),
                                      replace=False))
        else:
            keep = np.arange(i_lab.size)
        result = calibrate_reference(R_cam_cap_all[i_lab[keep]], ref.rotations[i_ref[keep]])
        # Without --camera-mount the reference frame becomes the frontal frame (as in the node).
        save_calibration(out, result, R_cam_frontal=calibrated_frontal(result, mount))
        how = (f"first {args.first}" if args.first else
               f"random {args.random} (seed {args.seed})" if args.random else "all")
        detail = f"reference {args.reference}, {how} of {i_lab.size} pairs"
    rv = np.degrees(result.R_cap_head.as_rotvec())
    print(f"{result.mode} calibration from {detail}: {result.frames_used} frames used, spread "
          f"{result.spread_deg:.2f} deg, R_cap_head rotvec [{rv[0]:.2f} {rv[1]:.2f} {rv[2]:.2f}] "
          f"deg -> {args.out}")
    return 0
