"""``ficap evaluate``: benchmark a head-pose estimator against Fi-Cap labels."""

from __future__ import annotations

import argparse

from ficap_ros.cli.args import max_dt_ms

HELP = ("compare a head-pose estimate (BAG:TOPIC or CSV) with Fi-Cap labels: geodesic and Phi3 "
        "errors, per-axis errors, report.md/json and plots")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--truth", required=True, metavar="LABELS",
                        help="labels.csv or a replay output folder (or BAG:TOPIC)")
    parser.add_argument("--estimate", required=True, metavar="BAG:TOPIC|CSV",
                        help="estimator output: a pose topic of a bag, or a CSV with stamp_ns and "
                             "qw,qx,qy,qz or yaw_deg,pitch_deg,roll_deg (head in the frontal frame)")
    parser.add_argument("--max-dt-ms", type=max_dt_ms, default=20.0,
                        help="largest stamp difference of a pair, ms (default 20; at most 60000)")
    parser.add_argument("--out", default="evaluation", metavar="DIR",
                        help="report folder (default: ./evaluation)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def series_path(spec: str) -> str:
    """The file or folder a ``BAG:TOPIC`` or CSV argument reads."""
    from pathlib import Path

    path, sep, topic = spec.rpartition(":")
    return path if sep and topic.startswith("/") and Path(path).exists() else spec


def run(args: argparse.Namespace) -> int:
    from ficap_ros.files import OutputFolder
    from ficap_ros.tools.evaluation import evaluate, load_series, write_report

    # Before anything is read: never an input, a recording or a folder of the user's files;
    # the report is built beside the folder and swapped in (files it does not write are kept).
    with OutputFolder(args.out, [series_path(args.truth), series_path(args.estimate)],
                      merge=True) as tmp:
        truth = load_series(args.truth)
        estimate = load_series(args.estimate)
        result = evaluate(truth, estimate, args.max_dt_ms)
        write_report(result, tmp, plots=not args.no_plots)
    s = result.summary()
    g, p = s["geodesic_deg"], s["phi3_deg"]
    ax = s["axis_error_deg"]
    print(f"{s['n_paired']} pairs: geodesic mean {g['mean']:.2f} median {g['median']:.2f} "
          f"p95 {g['p95']:.2f} deg; Phi3 mean {p['mean']:.2f} median {p['median']:.2f} "
          f"p95 {p['p95']:.2f} deg; bias yaw {ax['yaw']['mean']:+.2f} pitch "
          f"{ax['pitch']['mean']:+.2f} roll {ax['roll']['mean']:+.2f} deg -> {args.out}")
    return 0
