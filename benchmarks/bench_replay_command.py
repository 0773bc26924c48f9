"""The whole ``ficap replay`` command on a continuous 1080p drive against AprilTag 3 decimate 1,
one core, and where the command's time goes.

1. ``ficap synth`` renders a continuous 1080p 30 fps drive (``--seconds``, default 20 s, the
   issue's reference length; JPEG q95 CompressedImage in an MCAP bag).
2. Ours: the real command, ``python -m ficap_ros.cli replay BAG --out DIR --jobs 1 --quiet``, in
   a child process pinned to one core (this process's affinity, inherited), ``--rounds`` times;
   its CPU time (user + sys, from ``os.wait4``'s rusage of that child: start-up, imports, bag
   reading, decode, pipeline, label writing, everything) and wall time. Per frame = CPU / frames;
   the median round counts.
3. AprilTag 3 decimate 1 (pupil-apriltags, 1 thread, with our joint pose, as bench_fleet) on the
   same JPEG payloads, decode included (``cv2.imdecode`` grey), in this process on the same core,
   ``--at3-rounds`` rounds, CPU time (``time.process_time``), per frame the median of its rounds;
   with the allocator setting the command makes for itself (``replay.keep_freed_memory``).
   The command's runs and AprilTag 3's rounds alternate, so a change of load falls on both.
   Its start-up (imports, reading the bag) is not counted: the ratio favours AprilTag 3.
4. Where the time goes: the command again in a child pinned to the same core, instrumented: the
   interpreter's start, the imports of every module the command loads (the list from an earlier
   child's ``sys.modules``, imported first so no stage pays for a lazy import), then each stage's
   own CPU time (without the stages it calls; bench_fleet's pipeline stages plus the command's).

The machine is shared: CPU times (what waiting adds is left out), medians, load average stated.

5. With ``--long-seconds S`` (or ``--long-bag``): the command (``--rounds`` runs) and AprilTag 3
   (``--long-at3-rounds``) on a longer continuous drive too, reported beside the first: a real
   drive lasts 20-68 minutes, and start-up weighs less per frame than on a 20 s clip.

Usage: .venv/bin/python benchmarks/bench_replay_command.py [--seconds 20] [--rounds 3]
       [--at3-rounds 3] [--core 0] [--bag EXISTING_SYNTH_BAG] [--long-seconds 60]
       [--long-bag EXISTING_LONGER_BAG] [--long-at3-rounds 1] [--record]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
FPS = 30


def _replay_args(bag: Path, out: Path) -> list[str]:
    return ["replay", str(bag), "--out", str(out), "--jobs", "1", "--quiet"]


# -- child: the instrumented command ------------------------------------------------------------
#: (module, attribute, stage) of the command around the pipeline; a generator function's time is
#: that of its steps. Attributes a refactor removed are skipped.
COMMAND_STAGES = (
    ("ficap_ros.cli.main", "build_parser", "arguments (every verb's parser)"),
    ("ficap_ros.geometry.cap_model", "nominal_model", "cap model (nominal)"),
    ("ficap_ros.files", "check_output_folder", "output folder (checks, temporary folder, commit)"),
    ("ficap_ros.files", "OutputFolder.__init__", "output folder (checks, temporary folder, commit)"),
    ("ficap_ros.files", "OutputFolder.commit", "output folder (checks, temporary folder, commit)"),
    ("ficap_ros.io.sources", "open_frames", "open the bag (topics, CameraInfo, first stamp)"),
    ("ficap_ros.io.sources", "BagSource._bag_frames", "bag reading (MCAP chunks, CDR, RawFrame)"),
    ("ficap_ros.tools.replay", "process_frames", "replay loop (segments, ReplayedFrame)"),
    ("ficap_ros.tools.replay", "_process_one", "replay loop (segments, ReplayedFrame)"),
    ("ficap_ros.tools.replay", "decode_raw", "JPEG decode (cv2.imdecode, grey)"),
    ("ficap_ros.vision.pipeline", "FrameProcessor.process", "pipeline: bookkeeping (FrameProcessor.process)"),
    # Under "bookkeeping" until 2026-11-24: the hidden-tag check (the pose's input) and the
    # tracker's extrapolation, measured on their own.
    ("ficap_ros.vision.pipeline", "hidden_tag_ids", "pipeline: hidden-tag check (partly_hidden)"),
    ("ficap_ros.vision.tracking", "Tracker._predict_pose", "pipeline: tracker's pose extrapolation"),
    ("ficap_ros.io.labels", "head_pose", "labels: records (head pose, angles)"),
    ("ficap_ros.tools.replay", "_summary", "labels: summary statistics"),
    ("ficap_ros.tools.replay", "write_labels_bag", "labels.mcap (messages, CDR, MCAP)"),
    ("ficap_ros.tools.replay", "labels_csv_text", "labels.csv and summary.json (text, write)"),
    ("ficap_ros.tools.replay", "write_output_file", "labels.csv and summary.json (text, write)"),
)


def _child(mode: str, bag: Path, out: Path, modules_file: Path) -> None:
    """``modules``: run the command, write the modules it loaded (in load order) to
    ``modules_file``. ``breakdown``: import those, then run the command instrumented; JSON on
    stdout."""
    import resource

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    interp = cpu()
    before = set(sys.modules)
    if mode == "modules":
        from ficap_ros.cli import main

        main(_replay_args(bag, out))
        modules_file.write_text("\n".join(m for m in sys.modules if m not in before) + "\n")
        return
    import importlib

    t0 = cpu()
    for name in modules_file.read_text().split():
        if name.startswith(("bench_", "_common")):
            continue
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a module only its parent can import: the parent did
            pass
    imports = cpu() - t0
    sys.path.insert(0, str(HERE))
    from _common import patch_own_time  # noqa: PLC0415 - after the timed imports
    from bench_fleet import STAGES  # noqa: PLC0415

    from ficap_ros.cli import main

    own: dict[str, float] = {}
    patched = patch_own_time(COMMAND_STAGES + STAGES, own)
    t0 = time.process_time()
    try:
        main(_replay_args(bag, out))
    finally:
        for owner, name, fn in reversed(patched):
            setattr(owner, name, fn)
    run = time.process_time() - t0
    print(json.dumps({"interp": interp, "imports": imports, "run": run, "own": own}))


# -- parent -------------------------------------------------------------------------------------
def run_command(bag: Path, out: Path, extra: list[str] | None = None) -> tuple[float, float, str]:
    """(CPU s of the child, wall s, stdout) of ``ficap replay`` (or ``extra``) in a child."""
    import shutil

    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, *(extra or ["-m", "ficap_ros.cli", *_replay_args(bag, out)])]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    stdout = proc.stdout.read() if proc.stdout else ""
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}")
    return usage.ru_utime + usage.ru_stime, wall, stdout


class AprilTag3:
    """AprilTag 3 decimate 1 + joint pose on the bag's JPEGs, decode included, one round at a time."""

    def __init__(self, bag: Path) -> None:
        import numpy as np

        from ficap_ros.geometry.cap_model import nominal_model
        from ficap_ros.io.sources import open_frames
        from ficap_ros.vision.detector import DetectorConfig

        self.raws = list(open_frames(bag).raw_frames())
        self.bufs = [np.frombuffer(r.payload, np.uint8) for r in self.raws]
        self.model = nominal_model()
        self.config = DetectorConfig(backend="apriltag", corner_refine="apriltag", quad_decimate=1.0)
        self.ms: list = []  # per round, per frame
        self.tags: list[int] = []

    def round(self) -> float:
        """One pass over the frames (a fresh processor); its mean ms per frame."""
        import cv2
        import numpy as np

        from ficap_ros.vision.pipeline import FrameProcessor

        proc = FrameProcessor(self.model, self.config, tracking=False)
        ms = np.zeros(len(self.raws))
        for k, (raw, buf) in enumerate(zip(self.raws, self.bufs)):
            t0 = time.process_time()
            gray = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
            r = proc.process(gray, raw.camera, raw.stamp_ns)
            ms[k] = (time.process_time() - t0) * 1e3
            if not self.ms:
                self.tags.append(len({d.tag_id for d in r.detections}))
        self.ms.append(ms)
        return float(ms.mean())

    def per_frame_ms(self) -> float:
        """Mean over the frames of each frame's median round."""
        import numpy as np

        return float(np.mean(np.median(np.array(self.ms), axis=0)))


def alternate(bag: Path, out: Path, at3: AprilTag3, rounds: int, at3_rounds: int,
              label: str = "") -> list[tuple[float, float]]:
    """(CPU s, wall s) of each of ``rounds`` runs of the command; AprilTag 3's ``at3_rounds``
    rounds alternate with them, so a change of the shared machine's load falls on both."""
    runs = []
    for rnd in range(max(rounds, at3_rounds)):
        if rnd < rounds:
            cpu, wall, stdout = run_command(bag, out)
            runs.append((cpu, wall))
            print(f"  {label}ficap replay round {rnd + 1}: CPU {cpu:.2f} s, wall {wall:.2f} s; "
                  f"{stdout.strip()}", file=sys.stderr)
        if rnd < at3_rounds:
            print(f"  {label}AprilTag 3 round {rnd + 1}: {at3.round():.1f} ms/frame", file=sys.stderr)
    return runs


def breakdown(bag: Path, tmp: Path) -> dict:
    modules = tmp / "modules.txt"
    script = [str(Path(__file__).resolve())]
    run_command(bag, tmp / "out_modules",
                [*script, "--child", "modules", "--bag", str(bag), "--out", str(tmp / "out_modules"),
                 "--modules-file", str(modules)])
    cpu, _wall, stdout = run_command(
        bag, tmp / "out_breakdown",
        [*script, "--child", "breakdown", "--bag", str(bag), "--out", str(tmp / "out_breakdown"),
         "--modules-file", str(modules)])
    data = json.loads(stdout.strip().splitlines()[-1])
    data["child_cpu"] = cpu
    return data


def breakdown_table(data: dict, frames: int) -> str:
    from _common import md_table
    from bench_fleet import STAGES

    own = dict(data["own"])
    rows = [("start-up: interpreter", data["interp"]), ("start-up: imports (every module the command loads)",
                                                        data["imports"])]
    command = [label for *_m, label in COMMAND_STAGES]
    for label in dict.fromkeys(command + [label for *_m, label in STAGES]):
        if label in own:
            rows.append((label if label in command else f"pipeline: {label}", own.pop(label)))
    rows += [(f"other: {k}", v) for k, v in own.items()]
    rows.append(("the rest (main's own code, tqdm, argparse run, ...)",
                 data["run"] - sum(data["own"].values())))
    total = data["interp"] + data["imports"] + data["run"]
    out = [[name, f"{s:.3f}", f"{1e3 * s / frames:.2f}", f"{100 * s / total:.1f} %"] for name, s in rows]
    out.append(["total (instrumented run)", f"{total:.3f}", f"{1e3 * total / frames:.2f}", "100 %"])
    return md_table(["stage", "CPU s", "ms/frame", "share"], out)


def long_drive(args: argparse.Namespace, tmp: Path, short_bag: Path) -> dict:
    """The command and AprilTag 3 on a longer continuous drive (``--long-seconds`` rendered with
    the same settings, or ``--long-bag``): a real drive lasts 20-68 minutes, so the command's
    start-up weighs less per frame than on a 20 s clip. Runs and rounds alternate as above."""
    import numpy as np

    bag = args.long_bag
    if bag is None:
        bag = tmp / "long_drive"
        subprocess.run([sys.executable, "-m", "ficap_ros.cli", "synth", "--out", str(bag),
                        "--resolution", "1080p", "--frames", str(int(round(args.long_seconds * FPS))),
                        "--fps", str(FPS), "--seed", "0", "--quiet"], check=True)
    at3 = AprilTag3(bag)
    from ficap_ros.io.sources import open_frames

    # Does the longer drive continue the shorter one (same seed: the same first frames)?
    short = [r.payload for r in open_frames(short_bag).raw_frames()]
    prefix = sum(a == r.payload for a, r in zip(short, at3.raws))
    runs = alternate(bag, tmp / "out_long", at3, args.rounds, args.long_at3_rounds, "longer drive: ")
    summary = json.loads((tmp / "out_long" / "summary.json").read_text())
    frames = int(summary["frames"])
    assert len(at3.raws) == frames, (len(at3.raws), frames)
    return {"frames": frames, "rounds": args.rounds, "at3_rounds": args.long_at3_rounds,
            "cpu_s": float(np.median([c for c, _ in runs])), "wall_s": float(np.median([w for _, w in runs])),
            "at3_ms": at3.per_frame_ms(), "at3_tags": float(np.mean(at3.tags)),
            "pct_with_pose": summary["pct_with_pose"], "ge4": summary["frames_ge4_tags"],
            "prefix_same": prefix, "short_frames": len(short)}


def ratio_table(frames: int, rounds: int, cpu_s: float, wall_s: float, at3_rounds: int,
                at3_ms: float) -> tuple[str, float, float]:
    """(the command-against-AprilTag 3 table, ours ms a frame, ratio) of one drive."""
    from _common import md_table

    ours_ms = 1e3 * cpu_s / frames
    ratio = at3_ms / ours_ms
    table = md_table(
        ["", "CPU s (median)", "wall s (median)", "CPU ms/frame", "x AprilTag 3"],
        [[f"`ficap replay --jobs 1`, whole command ({rounds} run{'s' if rounds > 1 else ''})",
          f"{cpu_s:.2f}", f"{wall_s:.2f}", f"{ours_ms:.2f}", f"**{ratio:.1f}**"],
         [f"AprilTag 3 decimate 1 + joint pose, decode included ({at3_rounds} round"
          f"{'s' if at3_rounds > 1 else ''})", f"{at3_ms * frames / 1e3:.1f}", "", f"{at3_ms:.1f}", "1.0"]])
    return table, ours_ms, ratio


def long_table(long: dict, start_s: float) -> str:
    frames = long["frames"]
    n_short = long["short_frames"]
    same_path = (f"the drive above continued: its first {n_short} JPEGs are that drive's, byte for byte"
                 if long["prefix_same"] == n_short else
                 f"another path of the head: {long['prefix_same']} of its first {n_short} JPEGs are "
                 "the drive above's")
    table, ours_ms, ratio = ratio_table(frames, long["rounds"], long["cpu_s"], long["wall_s"],
                                        long["at3_rounds"], long["at3_ms"])
    return (
        f"### A longer continuous drive (--long-seconds)\n\n{frames} frames ({frames / FPS:.0f} s), "
        f"the same settings (1080p, 30 fps, seed 0, q95; {same_path}), "
        f"{long['pct_with_pose']:.1f} % of frames with a pose, "
        f"{long['ge4']} with >= 4 tags, AprilTag 3 {long['at3_tags']:.2f} tags per frame. Real "
        f"drives last 20-68 minutes: the start-up (interpreter and imports, {start_s:.2f} s in the "
        f"instrumented run above) weighs {1e3 * start_s / frames:.2f} ms a frame here. Whole "
        f"`ficap replay` {ours_ms:.2f} ms per frame vs AprilTag 3 {long['at3_ms']:.1f} ms = "
        f"**{ratio:.1f}x**.\n\n{table}\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the rendered drive, s")
    ap.add_argument("--rounds", type=int, default=3, help="runs of the command")
    ap.add_argument("--at3-rounds", type=int, default=3, help="runs of AprilTag 3 over the frames")
    ap.add_argument("--core", type=int, default=0, help="the one core everything runs on")
    ap.add_argument("--bag", type=Path, help="an existing ficap synth bag (skips rendering)")
    ap.add_argument("--long-seconds", type=float, default=0.0,
                    help="also a longer continuous drive of this many s (0: none): the command "
                         "and AprilTag 3 on it, reported beside the --seconds drive's figure")
    ap.add_argument("--long-bag", type=Path, help="an existing longer ficap synth bag (skips rendering)")
    ap.add_argument("--long-at3-rounds", type=int, default=1, help="AprilTag 3 runs over the longer drive")
    ap.add_argument("--record", action="store_true", help="write the section into docs/benchmarks.md")
    ap.add_argument("--child", choices=("modules", "breakdown"), help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--modules-file", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args.child, args.bag, args.out, args.modules_file)
        return 0
    sys.path.insert(0, str(HERE))
    import cv2
    import numpy as np
    from _common import load_avg, machine_line, record_section

    os.sched_setaffinity(0, {args.core})  # children inherit it: everything on one core
    cv2.setNumThreads(1)
    # The allocator setting the replay command makes for itself, here too: AprilTag 3's rounds
    # (decode included) run in this process and must not pay page faults the command does not.
    from ficap_ros.tools.replay import keep_freed_memory

    keep_freed_memory()
    load_before = load_avg()
    with tempfile.TemporaryDirectory(prefix="bench_replay_command.") as tmp_name:
        tmp = Path(tmp_name)
        frames = int(round(args.seconds * FPS))
        bag = args.bag
        if bag is None:
            bag = tmp / "drive"
            subprocess.run([sys.executable, "-m", "ficap_ros.cli", "synth", "--out", str(bag),
                            "--resolution", "1080p", "--frames", str(frames), "--fps", str(FPS),
                            "--seed", "0", "--quiet"], check=True)
        at3 = AprilTag3(bag)
        runs = alternate(bag, tmp / "out", at3, args.rounds, args.at3_rounds)
        summary = json.loads((tmp / "out" / "summary.json").read_text())
        frames = int(summary["frames"])
        assert len(at3.raws) == frames, (len(at3.raws), frames)
        at3_ms, at3_tags = at3.per_frame_ms(), float(np.mean(at3.tags))
        del at3  # its decoded frames' payloads
        data = breakdown(bag, tmp)
        long = None
        if args.long_seconds > 0 or args.long_bag is not None:
            long = long_drive(args, tmp, bag)
    cpu_s = float(np.median([c for c, _ in runs]))
    wall_s = float(np.median([w for _, w in runs]))
    table, ours_ms, ratio = ratio_table(frames, args.rounds, cpu_s, wall_s, args.at3_rounds, at3_ms)
    start_ms = 1e3 * (data["interp"] + data["imports"]) / frames
    load_after = load_avg()
    body = (
        f"Machine: {machine_line()}; {load_before} at the start, {load_after} at the end. One core "
        f"(affinity {{{args.core}}} for this process and its children). A continuous 1080p 30 fps "
        f"`ficap synth` drive of {frames} frames ({frames / FPS:.0f} s, seed 0, JPEG q95), "
        f"{summary['pct_with_pose']:.1f} % of frames with a pose, {summary['frames_ge4_tags']} with "
        f">= 4 tags; AprilTag 3 found {at3_tags:.2f} tags per frame. Ours: the whole command's CPU "
        "time (user + sys of the child: start-up, imports, bag reading, decode, pipeline, label "
        "writing), median of the runs; AprilTag 3: decode + detect + pose per frame in CPU time "
        "(its start-up and bag reading not counted).\n\n"
        f"Headline: whole `ficap replay` {ours_ms:.2f} ms per frame vs AprilTag 3 decimate 1 "
        f"{at3_ms:.1f} ms = **{ratio:.1f}x** (start-up {start_ms:.2f} ms of it per frame at this "
        f"length).\n\n{table}\n\n"
        "### Where the whole command's time goes (one instrumented run, own CPU time per stage)\n\n"
        f"{breakdown_table(data, frames)}\n\n"
        f"The instrumented child took {data['child_cpu']:.2f} s CPU in all (the wrappers, ~1 us a "
        "call, and importing the benchmark's own modules add to the command's).\n")
    if long is not None:
        body += "\n" + long_table(long, start_ms * frames / 1e3)
    print(body)
    if args.record:
        record_section("Whole replay command vs AprilTag 3 (bench_replay_command.py)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
