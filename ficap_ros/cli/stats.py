"""``ficap stats``: how often the cap is seen (the paper's section 6 figures)."""

from __future__ import annotations

import argparse

HELP = ("frames with no tag, >= 1 and >= 4 tags, per-tag detection rate and reliability "
        "histogram, from a bag/video (runs the pipeline) or from labels.csv")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ficap_ros.cli.replay import add_input_arguments

    add_input_arguments(parser)
    parser.add_argument("--out", metavar="DIR",
                        help="also write stats.json, reliability_histogram.png and "
                             "tag_detection_rate.png here")


def _is_labels(path: str) -> bool:
    from pathlib import Path

    p = Path(path)
    return (p.is_file() and p.suffix.lower() == ".csv") or (p.is_dir() and (p / "labels.csv").exists())


def run(args: argparse.Namespace) -> int:
    from contextlib import nullcontext

    from ficap_ros.files import OutputFolder

    # Before any processing: never an input, a recording or a folder of the user's files; the
    # files are built beside the folder and swapped in (files this run does not write are kept).
    folder = (OutputFolder(args.out, [args.input, args.model, args.intrinsics], merge=True)
              if args.out else nullcontext(None))
    with folder:
        return _stats(args, folder if args.out else None)


def _stats(args: argparse.Namespace, out) -> int:  # noqa: ANN001 - files.OutputFolder or None
    import json

    from ficap_ros.geometry.cap_model import load_model, nominal_model
    from ficap_ros.tools.evaluation import plot_stats

    model = load_model(args.model) if args.model else nominal_model()
    stats, lost_line, lost_info = _detection_stats(args, model)
    d = stats.to_dict()
    if lost_line:
        d["lost"] = lost_info
    print(f"frames {d['frames']} (skipped {d['frames_skipped']}): no tag {d['frames_no_tag']} "
          f"({d['pct_no_tag']:.2f} %), >=1 tag {d['frames_ge1_tag']} ({d['pct_ge1_tag']:.2f} %), "
          f">=4 tags {d['frames_ge4_tags']} ({d['pct_ge4_tags']:.2f} %), with a pose "
          f"{d['frames_with_pose']} ({d['pct_with_pose']:.2f} %)")
    print("tag detection rate (%): " + " ".join(
        f"{k}:{100 * v:.0f}" for k, v in stats.tag_rate.items()))
    e, c = stats.reliability_edges, stats.reliability_counts
    print("reliability histogram: " + " ".join(
        f"[{e[i]:.2f},{e[i + 1]:.2f}{']' if i == c.size - 1 else ')'}:{int(c[i])}"
        for i in range(c.size)))
    if out is not None:
        plot_stats(stats, out.tmp)
        out.write("stats.json", json.dumps(d, indent=2) + "\n")
    if lost_line:
        from ficap_ros.cli.args import EXIT_FRAMES_LOST

        print(lost_line)
        return EXIT_FRAMES_LOST
    return 0


def _detection_stats(args: argparse.Namespace, model):  # noqa: ANN001, ANN202
    """(DetectionStats, the loss line or '', the loss as JSON or None) of the input: labels
    counted as they are, or a recording through the pipeline."""
    import numpy as np

    from ficap_ros.tools.evaluation import detection_stats

    if _is_labels(args.input):
        from ficap_ros.io.labels import read_labels

        lab = read_labels(args.input)
        return detection_stats(lab.tags_detected, lab.detected_ids, lab.reliability,
                               lab.has_pose, lab.skipped, tuple(model.ids)), "", None
    from ficap_ros.cli.replay import cap_jobs, open_source
    from ficap_ros.tools.replay import Progress, process_frames
    from ficap_ros.vision.pose import PoseConfig

    jobs = cap_jobs(args)
    source = open_source(args)
    bar = Progress(source.count, "frames", enabled=not args.quiet)
    try:
        records = [f.record for f in process_frames(
            source.raw_frames(), model, PoseConfig(method=args.method), jobs,
            on_progress=lambda n: bar.update(n - bar.n))]
    finally:
        bar.close()
    stats = detection_stats(
        np.array([r.tags_detected for r in records], dtype=int),
        tuple(r.detected_ids for r in records),
        np.array([r.reliability for r in records]),
        np.array([r.pose is not None for r in records], dtype=bool),
        np.array([r.skipped for r in records], dtype=bool),
        tuple(model.ids),
    )
    loss = source.loss
    if loss is None:
        return stats, "", None
    return stats, loss.describe(source.start_ns), loss.to_dict(source.start_ns)
