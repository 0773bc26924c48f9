"""Run every benchmark with modest sizes (about 20-25 min on 2 idle cores, plus the 10 min soak) and
record the tables.

Each script writes its section of docs/benchmarks.md (replacing the section of the same name) with
machine, date, commit and load. Full-size runs: call the scripts directly, e.g.
``benchmarks/bench_accuracy.py --frames 1800 --stride 1 --record``.

Usage: .venv/bin/python benchmarks/run_all.py [--only accuracy,speed,...]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = {
    "calibration": ["bench_calibration.py", "--sessions", "10"],
    "visibility": ["bench_visibility.py"],
    "speed": ["bench_speed.py", "--frames", "150", "--replay-frames", "300"],
    "accuracy": ["bench_accuracy.py", "--frames", "1800", "--stride", "18"],
    "node": ["bench_node.py", "--rates", "10,15,30,60", "--seconds", "4"],
    "demo": ["bench_demo.py", "--runs", "5"],
    "pipeline": ["bench_pipeline.py", "--frames", "20"],
    "replay_command": ["bench_replay_command.py", "--seconds", "20"],
    # Issue 13's soak is long by definition (10 min at 30 Hz): skip it with --only when in a hurry.
    "soak": ["bench_soak.py", "--minutes", "10"],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--only", default=",".join(RUNS), help=f"comma-separated subset of {', '.join(RUNS)}")
    args = ap.parse_args()
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", "16")
    failed = []
    for name in args.only.split(","):
        if name not in RUNS:
            print(f"unknown benchmark {name!r}; choose from {', '.join(RUNS)}", file=sys.stderr)
            return 2
        cmd = [sys.executable, str(HERE / RUNS[name][0]), *RUNS[name][1:], "--record"]
        print(f"== {name}: {' '.join(cmd[1:])}", file=sys.stderr, flush=True)
        t0 = time.time()
        rc = subprocess.run(cmd, env=env).returncode
        print(f"== {name}: exit {rc} after {(time.time() - t0) / 60:.1f} min", file=sys.stderr, flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
