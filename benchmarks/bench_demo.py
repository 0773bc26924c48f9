"""``make demo``: what the README's first command does and how long it takes.

Each run is the real command, ``python -m ficap_ros.cli demo`` in a fresh process: the cached
540p sample drive (240 frames) played lock-step into an in-process ``ficap_node`` over ROS 2
topics (DDS on loopback), then calibrated and compared with the truth. Per run: the demo's own
report (frames with a head pose, play time, head-pose error after calibration, node latency) and
the whole process's wall and CPU time (``os.wait4``: start-up, rclpy, the node's worker, the
player). The sample drive is rendered once before the runs (``sample_recording``), so no run pays
for it. Writes docs/benchmarks/demo.md.
"""

from __future__ import annotations

import re
import sys

import numpy as np

from _lib import cli, report
from _lib.timing import ficap_command, run_child

PATTERNS = {
    "frames": r"frames: (\d+), with head pose",
    "with_pose": r"with head pose: (\d+)",
    "play_s": r"played in ([0-9.]+) s",
    "err_mean": r"after calibration, geodesic: mean ([0-9.]+)",
    "err_p95": r"after calibration, geodesic: .*p95 ([0-9.]+)",
    "lat_p50": r"node latency .*p50 ([0-9.]+) ms",
    "lat_p99": r"node latency .*p99 ([0-9.]+) ms",
}


def one_run(env: dict[str, str]) -> dict[str, float]:
    r = run_child(ficap_command("demo"), env=env)
    out = {"wall_s": r.wall_s, "cpu_s": r.cpu_s}
    for key, pattern in PATTERNS.items():
        m = re.search(pattern, r.stdout)
        out[key] = float(m.group(1)) if m else float("nan")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="1 run (full: 3)")
    ap.add_argument("--runs", type=int, default=None, help="runs (default 3)")
    args = ap.parse_args(argv)
    env = cli.ros_environment()
    from ficap_ros.cli.demo import sample_recording

    sample_recording(progress=False)  # rendered once and cached, outside the timed runs
    run = report.Run()
    runs = []
    for k in range(args.runs or (1 if args.quick else 3)):
        runs.append(one_run(env))
        print(f"  run {k + 1}: {runs[-1]}", file=sys.stderr, flush=True)

    def cell(key: str, spec: str = ".1f") -> str:
        v = [r[key] for r in runs]
        return f"{np.median(v):{spec}} ({min(v):{spec}}-{max(v):{spec}})" if len(v) > 1 else f"{v[0]:{spec}}"

    table = report.md_table(
        ["runs", "frames with a head pose", "play s", "process wall s", "process CPU s",
         "head error after calibration, mean / p95 deg", "node latency p50 / p99 ms"],
        [[len(runs), f"{min(r['with_pose'] for r in runs):.0f}-{max(r['with_pose'] for r in runs):.0f} of "
          f"{runs[0]['frames']:.0f}", cell("play_s"), cell("wall_s"), cell("cpu_s"),
          f"{np.median([r['err_mean'] for r in runs]):.3f} / {np.median([r['err_p95'] for r in runs]):.3f}",
          f"{np.median([r['lat_p50'] for r in runs]):.1f} / {np.median([r['lat_p99'] for r in runs]):.1f}"]])
    body = (f"{table}\n\nMedian (range) over the runs. The play is lock-step (the next frame goes out "
            "when the node has answered the last), so its time is the node's processing plus the "
            "round trip; the process's time adds the start-up (Python, rclpy, the node).")
    what = ("What it measures: `make demo`'s command (`ficap demo`): the sample drive through a live "
            "`ficap_node` in a fresh process per run; frames with a head pose, the head-pose error "
            "after the frontal calibration, node latency, and the process's wall and CPU time.")
    report.write_section("demo", what, report.how("bench_demo.py", "1 run"), body, run, report.command(),
                         args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
