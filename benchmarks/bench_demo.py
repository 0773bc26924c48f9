"""``ficap demo`` (the README's first command): how long the live demo takes to play its sample drive.

Each run is a fresh process that plays the cached 540p sample drive (240 frames, lock-step: the
next frame goes out when the node has answered the last) into an in-process ``ficap_node`` exactly
as ``ficap demo`` does, and reports the play time, the whole process's CPU time during the play
(all threads: the node's worker, the executor, the player), the frames with a head pose and the
head error after calibration. With ``--ref REV`` the runs alternate between this tree and REV's
``ficap_ros/node.py`` and ``ficap_ros/ros_demo.py`` (loaded in their place; the rest of the package
is this tree's), so both see the same load.

Usage: .venv/bin/python benchmarks/bench_demo.py [--runs 5] [--ref fd372e8] [--record]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", "16")

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, load_avg, machine_line, md_table, record_section  # noqa: E402

SECTION = "Node in the demo: play time (`make demo`)"


def _load_from(rev: str, module: str) -> None:
    """Import ``ficap_ros.<module>`` from revision ``rev``'s source in place of this tree's."""
    source = subprocess.run(["git", "show", f"{rev}:ficap_ros/{module}.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="bench_demo_")) / f"{module}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"ficap_ros.{module}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[f"ficap_ros.{module}"] = mod
    spec.loader.exec_module(mod)


def child(ref: str | None) -> int:
    """One demo play in this process; the last stdout line is a JSON of the measurements."""
    if ref:
        for module in ("node", "ros_demo"):
            _load_from(ref, module)
    from ficap_ros.cli.demo import SAMPLE, sample_recording
    from ficap_ros.ros import demo as ros_demo

    measured: dict[str, float] = {}
    play = ros_demo._play

    def timed_play(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        cpu0, wall0, load0 = time.process_time(), time.monotonic(), os.getloadavg()[0]
        code = play(*args, **kwargs)
        measured.update(play_s=time.monotonic() - wall0, cpu_s=time.process_time() - cpu0,
                        load=load0)
        return code

    ros_demo._play = timed_play
    code = ros_demo.run_demo(sample_recording(), frontal_s=float(SAMPLE["frontal_s"]), every=1000)
    print(json.dumps(measured), flush=True)
    return code


def one_run(ref: str | None) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", *(["--ref", ref] if ref else [])]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600).stdout
    run = json.loads(out.strip().splitlines()[-1])
    pose = re.search(r"with head pose: (\d+)", out)
    err = re.search(r"after calibration, geodesic: mean ([0-9.]+)", out)
    run["with_pose"] = int(pose.group(1)) if pose else 0
    run["err_deg"] = float(err.group(1)) if err else float("nan")
    return run


def row(label: str, runs: list[dict[str, float]]) -> list[object]:
    play = [r["play_s"] for r in runs]
    cpu = [r["cpu_s"] for r in runs]
    return [label, len(runs), f"{np.median(play):.1f} ({min(play):.1f}-{max(play):.1f})",
            f"{np.median(cpu):.1f} ({min(cpu):.1f}-{max(cpu):.1f})",
            f"{min(r['with_pose'] for r in runs)}-{max(r['with_pose'] for r in runs)} / 240",
            f"{np.nanmedian([r['err_deg'] for r in runs]):.3f}",
            f"{min(r['load'] for r in runs):.1f}-{max(r['load'] for r in runs):.1f}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ref", default=None, help="also run this revision's node.py + ros_demo.py")
    ap.add_argument("--record", action="store_true")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.ref)
    results: dict[str, list[dict[str, float]]] = {"this tree": []}
    if args.ref:
        results[f"{args.ref} (ref)"] = []
    for k in range(args.runs):
        for label in results:
            run = one_run(args.ref if label != "this tree" else None)
            results[label].append(run)
            print(f"{label} run {k + 1}: played in {run['play_s']:.1f} s, CPU {run['cpu_s']:.1f} s, "
                  f"{run['with_pose']} with pose, load {run['load']:.1f}", file=sys.stderr, flush=True)
    table = md_table(["tree", "runs", "play s: median (range)", "process CPU during play s",
                      "frames with pose", "head err deg (mean)", "load (1 min)"],
                     [row(label, runs) for label, runs in reversed(results.items())])
    text = "\n".join([
        f"Machine: {machine_line()}; {load_avg()} at the end. `benchmarks/bench_demo.py --runs "
        f"{args.runs}{' --ref ' + args.ref if args.ref else ''}`: each run a fresh process playing "
        "the cached 540p sample drive (240 frames, lock-step) into an in-process ficap_node as "
        "`make demo` does; runs alternate between the trees. Process CPU = every thread of the "
        "demo process during the play.",
        "",
        table,
        "",
        "Why a tree before b1df6bd (its demo spun a 4-thread MultiThreadedExecutor) costs more and "
        "varies with the load: rclpy 7.1's MultiThreadedExecutor yields a callback still queued in "
        "its thread pool again, without waiting, and re-submits it (ros2/rclpy#1452, fixed upstream "
        "by #1547), so its spin thread loops on the GIL the pool thread and the node's worker need, "
        "longer the busier the machine (25-60 submissions per callback measured). ficap_node and "
        "the demo spin one SingleThreadedExecutor (`spin.make_executor`).",
    ])
    print(text)
    if args.record:
        record_section(SECTION, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
