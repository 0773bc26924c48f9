"""Fleet replay: ``ficap replay`` over a folder of recordings with the process engine and with an
embedded Ray, and what Ray costs over ``--jobs``.

A fleet of ``ficap synth`` 540p recordings (``--recordings`` of ``--frames`` frames each, seeds
0..N-1, kept in the cache folder) replayed as one command with: ``--jobs 1``, ``--jobs 2``,
``--ray --jobs 1`` and ``--ray --jobs 2`` (an embedded Ray on loopback; its start is counted).
Per engine: wall time of the whole command (start-up included), frames per second, and the CPU
time of the command and everything it waited for (``os.wait4``). The engines' runs alternate over
``--rounds`` rounds; medians. Writes docs/benchmarks/fleet.md.
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from _lib import cli, report
from _lib.timing import ficap_command, run_child
from ficap_ros.tools.replay import SEGMENT_FRAMES
from ficap_ros.tools.synth import RENDER_VERSION

ENGINES = {
    "processes, --jobs 1": ["--jobs", "1"],
    "processes, --jobs 2": ["--jobs", "2"],
    "Ray embedded, --jobs 1": ["--ray", "--jobs", "1"],
    "Ray embedded, --jobs 2": ["--ray", "--jobs", "2"],
}


def fleet(cache: Path, recordings: int, frames: int) -> Path:
    """A folder of ``recordings`` synth drives (rendered once, kept in ``cache``)."""
    root = cache / f"fleet_540p_{recordings}x{frames}f_r{RENDER_VERSION}"
    for i in range(recordings):
        bag = root / f"d{i}"
        if not (bag / "metadata.yaml").is_file():
            shutil.rmtree(bag, ignore_errors=True)
            run_child(ficap_command("synth", "--out", str(bag), "--resolution", "540p", "--frames",
                                    str(frames), "--seed", str(i), "--quiet"))
    return root


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="2 recordings of 150 frames, 1 round (full: 4 of 300, 2 rounds)")
    ap.add_argument("--recordings", type=int, default=None, help="recordings in the fleet (default 4)")
    ap.add_argument("--frames", type=int, default=None, help="frames per recording (default 300)")
    ap.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 2)")
    args = ap.parse_args(argv)
    recordings = args.recordings or (2 if args.quick else 4)
    frames = args.frames or (150 if args.quick else 300)
    rounds = args.rounds or (1 if args.quick else 2)
    env = cli.ros_environment()
    run = report.Run()
    root = fleet(args.cache, recordings, frames)
    wall = {k: [] for k in ENGINES}
    cpu = {k: [] for k in ENGINES}
    status = {}
    with tempfile.TemporaryDirectory(prefix="bench_fleet.") as tmp:
        for rnd in range(rounds):
            for label, extra in (ENGINES.items() if rnd % 2 == 0 else list(ENGINES.items())[::-1]):
                out = Path(tmp) / "out"
                shutil.rmtree(out, ignore_errors=True)
                r = run_child(ficap_command("replay", str(root), "--out", str(out), "--quiet", *extra), env=env)
                wall[label].append(r.wall_s)
                cpu[label].append(r.cpu_s)
                totals = json.loads((out / "fleet_summary.json").read_text()).get("totals", {})
                status[label] = totals
                print(f"  {label}: wall {r.wall_s:.1f} s, CPU {r.cpu_s:.1f} s", file=sys.stderr, flush=True)
    total = recordings * frames
    base = float(np.median(wall["processes, --jobs 1"]))
    rows = [[label, recordings, total, f"{np.median(wall[label]):.1f}", f"{total / np.median(wall[label]):.1f}",
             f"{np.median(cpu[label]):.1f}", f"{np.median(wall[label]) / base:.2f}"] for label in ENGINES]
    table = report.md_table(["engine", "recordings", "frames", "wall s (median, start-up included)", "frames/s",
                             "CPU s (command and the processes it waited for)", "wall vs --jobs 1"], rows)
    ray1 = float(np.median(wall["Ray embedded, --jobs 1"])) - base
    jobs2 = base / float(np.median(wall["processes, --jobs 2"]))
    ray2 = base / float(np.median(wall["Ray embedded, --jobs 2"]))
    body = (f"{table}\n\nA recording is cut into segments of {SEGMENT_FRAMES} frames (tracking restarts at "
            "each), and the segments go to the workers, so a recording shorter than a segment gains "
            f"nothing from a second worker. Here two workers run {jobs2:.2f}x as fast as one with "
            f"processes and {ray2:.2f}x with Ray, on a 2-core machine shared with other jobs (a second "
            "worker buys what the other core has free). Ray's fixed cost is its start and its workers' "
            f"imports (Ray with one worker against `--jobs 1`: {ray1:+.1f} s wall; the CPU column leaves "
            "out Ray's daemons, which the command does not wait for). On a cluster (`--ray-address`) "
            "the segments of every recording spread over its nodes, with labels byte-identical to "
            "`--jobs 1` (docs/fleet.md).")
    what = ("What it measures: a fleet replay's wall time and throughput with the process engine "
            f"and an embedded Ray, 1 and 2 workers, over {recordings} synth 540p recordings of "
            f"{frames} frames (the whole command, start-up included; engines alternated, medians).")
    report.write_section("fleet", what, report.how("bench_fleet.py", "a smaller fleet, 1 round"), body, run,
                         report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
