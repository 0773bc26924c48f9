"""``ficap model build``: the as-built cap model from recordings, by bundle adjustment.

Wired as a sub-verb of ``ficap model`` (``add_build_arguments`` / ``run_build``).

After the adjustment the recording is posed again with the nominal and with the built model
(``ficap_ros.tools.model_build.replay_check``) and both are printed. Exit status 1, nothing written:
the built model would place the cap worse than the nominal one (it changes the cap's distance by
more than hand assembly can), or, unless ``--allow-partial``, the solver did not converge, a tag is
poorly observed, or the built model fits the recording worse than the nominal one.
"""

from __future__ import annotations

import argparse
import sys

HELP = "build the as-built cap model from recordings (rosbag2/MCAP, or video with --intrinsics)"


def add_build_arguments(parser: argparse.ArgumentParser) -> None:
    # Bad numbers are argparse's (exit 2, naming the flag), as in every verb.
    from ficap_ros.cli.args import float_in, frame_rate, int_in, positive_int

    # The adjustment needs two frames and two tags; its memory grows with the frames it holds.
    max_frames, min_tags, counts = int_in(2, 100_000), int_in(2, 587), int_in(1, 100_000)

    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="rosbag2 folders, .mcap/.db3 files or videos (need --intrinsics)")
    parser.add_argument("--out", required=True, help="as-built model YAML to write")
    parser.add_argument("--model", dest="start_model",
                        help="model to start from and align to (default: the nominal cap)")
    parser.add_argument("--intrinsics", help="camera YAML (required for videos; overrides CameraInfo)")
    parser.add_argument("--image-topic", help="image topic (default: the bag's only image topic)")
    parser.add_argument("--camera-info-topic", help="CameraInfo topic (default: auto)")
    parser.add_argument("--fps", type=frame_rate,
                        help="video frame rate, Hz (default: the container's)")
    parser.add_argument("--every", type=positive_int, default=1, metavar="N",
                        help="use every N-th frame of each input (default 1)")
    parser.add_argument("--max-frames", type=max_frames, default=400,
                        help="at most this many frames in the adjustment, 2 to 100000 (default 400)")
    parser.add_argument("--min-tags", type=min_tags, default=4,
                        help="frames with fewer tags are not used (default 4)")
    parser.add_argument("--min-frames-per-tag", type=counts, default=3,
                        help="every tag must be seen in this many used frames (default 3)")
    parser.add_argument("--backend", choices=("opencv", "apriltag"), default="opencv",
                        help="detector backend (default opencv)")
    parser.add_argument("--refine", choices=("edge", "subpix", "apriltag", "none"), default="edge",
                        help="corner refinement (default edge)")
    parser.add_argument("--max-nfev", type=counts, default=100, metavar="N",
                        help="solver budget in function evaluations (default 100)")
    parser.add_argument("--assembly-sigma-mm", type=float_in(0.0, 100.0, low_open=True), default=1.0,
                        help="how far a plate may sit from its nominal place by hand, 1 sigma per "
                             "axis (default 1.0)")
    parser.add_argument("--size", choices=("auto", "nominal", "images", "tag-side"), default="auto",
                        help="where the cap's overall size comes from: the nominal layout with a "
                             "fitted edge offset absorbing the corner bias (hand assembly moves "
                             "plates, it does not grow the cap), the printed tag side (corners "
                             "unbiased), the images with the offset fitted; auto (default): the tag "
                             "side when the fitted offset changes the size less than hand assembly "
                             "does, else the nominal layout")
    parser.add_argument("--allow-partial", action="store_true",
                        help="write the model even when the solver did not converge, a tag is "
                             "poorly observed or the model fits the recording worse than nominal "
                             "(a model that moves the cap is never written)")
    parser.add_argument("--report", help="also write the per-tag report as JSON to this file")
    parser.add_argument("--plot", help="also write a PNG plot of the per-tag deviations")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _progress(quiet: bool):  # type: ignore[no-untyped-def]
    def say(message: str) -> None:
        if not quiet:
            print(f"model build: {message}", file=sys.stderr, flush=True)
    return say


def _outputs(args: argparse.Namespace) -> dict[str, object]:
    """The model, report and plot files, each checked and locked under the output rule before
    minutes of detection and adjustment (``files.OutputFile``): never an input, a recording or
    inside one, and never two of them one file."""
    from ficap_ros.errors import OutputError
    from ficap_ros.files import OutputFile

    inputs = [*args.inputs, args.start_model, args.intrinsics]
    named = {"model": args.out, "report": args.report, "plot": args.plot}
    taken: dict[str, object] = {}
    try:
        for what, path in named.items():
            if not path:
                continue
            out = OutputFile(path, inputs, what)
            for other, earlier in taken.items():
                if earlier.path == out.path:  # type: ignore[attr-defined]
                    out.close()
                    raise OutputError(f"--{'out' if what == 'model' else what} and "
                                      f"--{'out' if other == 'model' else other} name one file "
                                      f"{out.path}; give each its own")
            taken[what] = out
    except BaseException:
        for out in taken.values():
            out.close()  # type: ignore[attr-defined]
        raise
    return taken


def run_build(args: argparse.Namespace) -> int:
    outputs = _outputs(args)  # before anything is read
    try:
        return _build(args, outputs)
    finally:
        for out in outputs.values():
            out.close()  # type: ignore[attr-defined]


def _build(args: argparse.Namespace, outputs: dict) -> int:  # type: ignore[type-arg]
    import json

    from ficap_ros.geometry.cap_model import load_model, nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools.model_build import (
        BuildConfig,
        build_model,
        depth_change_limit,
        replay_check,
    )
    from ficap_ros.vision.detector import DetectorConfig, TagDetector

    size = {"auto": {}, "nominal": {"size": "fixed"},
            "images": {"size": "fixed", "anchor_size": False},
            "tag-side": {"size": "fixed", "anchor_size": False, "fit_edge_offset": False}}[args.size]
    say = _progress(args.quiet)
    config = BuildConfig(min_tags_per_frame=args.min_tags, min_frames_per_tag=args.min_frames_per_tag,
                         max_frames=args.max_frames, max_nfev=args.max_nfev,
                         assembly_sigma_mm=args.assembly_sigma_mm, **size)
    start = load_model(args.start_model) if args.start_model else nominal_model()
    detector = TagDetector(DetectorConfig(backend=args.backend, corner_refine=args.refine))
    frames, cameras = [], []
    for path in args.inputs:
        source = open_frames(path, image_topic=args.image_topic,
                             camera_info_topic=args.camera_info_topic,
                             intrinsics=args.intrinsics, fps=args.fps)
        read = kept = 0
        for frame in source.frames():
            if frame.index % args.every:
                continue
            read += 1
            if frame.image is None or frame.camera is None:
                continue
            dets = [d for d in detector.detect(frame.image) if d.tag_id in start]
            if len({d.tag_id for d in dets}) >= config.min_tags_per_frame:
                frames.append(dets)
                cameras.append(frame.camera)
                kept += 1
            if read % 100 == 0:
                say(f"{path}: {read} frames read, {kept} with >= {config.min_tags_per_frame} tags")
        say(f"{path}: {read} frames read, {kept} with >= {config.min_tags_per_frame} tags")
        if source.loss is not None:  # a damaged recording: its frames before the damage are used
            print(f"ficap: warning: {path}: {source.loss.describe(source.start_ns)}",
                  file=sys.stderr)
    result = build_model(frames, cameras, nominal=start, config=config, progress=say,
                         allow_partial=args.allow_partial)
    print(result.table())
    say("posing the recording with the nominal and with the built model")
    check = replay_check(frames, cameras, result.model, start, config, depth_change_limit(result, config))
    print(check.table())
    if args.report:
        outputs["report"].write(
            json.dumps({**result.to_dict(), "replay_check": check.to_dict()}, indent=1) + "\n")
    if args.plot:
        outputs["plot"].write(_plot(result))
    if check.problems:
        for p in check.problems:
            print(f"model build: {p}", file=sys.stderr)
        print(f"model build: refusing to write {args.out}: the built model would place the cap "
              "worse than the nominal one", file=sys.stderr)
        return 1
    doubts = list(result.problems) + list(check.warnings)
    for p in doubts:
        print(f"model build: {'warning: ' if args.allow_partial else ''}{p}", file=sys.stderr)
    if doubts and not args.allow_partial:
        print(f"model build: not writing {args.out}: the model is not to be trusted (see above); "
              "--allow-partial writes it anyway", file=sys.stderr)
        return 1
    result.model.save(outputs["model"])
    print(f"wrote {args.out}" + (" (partial: see the warnings)" if doubts else ""))
    return 0


def _plot(result) -> bytes:  # type: ignore[no-untyped-def]
    """Bar plot of per-tag centre offset (mm) and in-plane turn (deg), as PNG bytes."""
    import io

    import numpy as np
    from matplotlib.figure import Figure

    ids = [d.tag_id for d in result.deviations]
    x = np.arange(len(ids))
    fig = Figure(figsize=(10, 6))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.bar(x, [d.offset_norm_mm for d in result.deviations], color="#1f77b4")
    ax1.set_ylabel("centre offset, mm")
    ax1.set_title(f"as-built vs nominal: corner rms {result.corner_rms_mm:.2f} mm, "
                  f"reprojection rms {result.rms_px:.2f} px, {result.frames_used} frames")
    ax2.bar(x, [d.about_normal_deg for d in result.deviations], color="#d62728")
    ax2.axhline(0.0, color="k", linewidth=0.6)
    ax2.set_ylabel("turn about normal, deg")
    ax2.set_xticks(x, [str(i) for i in ids])
    ax2.set_xlabel("tag id")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    return buffer.getvalue()
