"""Speed: the whole ``ficap replay`` command against AprilTag 3 decimate 1, on 1080p drives.

Two continuous 30 fps 1080p drives, JPEG (q95) CompressedImage in MCAP bags:

* synth: a ``ficap synth`` drive (seed 0, a mirror glance included), rendered once into the cache;
* blender_dev: ``dev_1080p_drive30`` (60 path-traced frames through a left-mirror glance) played
  ``--loops`` times over (each loop starts with a jump of the head, as after a cut).

And two of 1080p frames that must all be searched (2 s apart, or 0.67 s for synth, beyond
tracking's reach): every 20th frame of the synth drive, and blender_dev's three still 1080p sets
(``dev_1080p_high``, ``_neutral``, ``_neutral_asbuilt``), each played over until it is
``--searched-frames`` long (600 by default, as long as the continuous drives, so the command's
fixed start-up weighs the same on every input). AprilTag 3 and the decode alone, which keep no
state from frame to frame, are timed on one play of the searched frames. The command is also run on
a bag of one frame: its CPU time is the fixed cost of a run (start-up, imports, loading the
compiled kernels, opening the bag, one frame, writing the labels).

Ours: the real command, ``python -m ficap_ros.cli replay BAG --out DIR --jobs 1 --quiet``, in a
child process, with its defaults and with ``--photometric`` (the photometric corner fit on every tag); its
CPU time (user + sys from ``os.wait4``: start-up, imports, bag reading, JPEG
decode, pipeline, label writing, everything) per frame. AprilTag 3: pupil-apriltags decimate 1,
one thread, with our joint pose, on the same JPEG payloads in this process, decode included
(``cv2.imdecode`` grey); its start-up and bag reading are not counted (the ratio favours it).
Beside them the JPEG decode alone: ``cv2.imdecode`` grey (the reference the ratios are taken
against) and the command's own (``image_codec.decode_compressed``: simplejpeg where it is
installed, else OpenCV; the same pixels either way). Everything runs on one core (this process's affinity, which
the child inherits); the command's runs and the other rounds alternate (``--rounds``), so a change
of the shared machine's load falls on all; each figure is the median of its rounds. The package's
modules are compiled to bytecode first (``__pycache__`` beside them), as a pip or colcon install has
them: ``make`` runs with ``PYTHONDONTWRITEBYTECODE``, which would otherwise make each run compile
them again. Then one
instrumented pass of ours in this process: each stage's own CPU time (the package's public
functions, timed wherever they are called). Writes docs/benchmarks/speed.md and speed.png.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from _lib import cli, devsets, report
from _lib.methods import AT3, OURS
from _lib.synthdata import cached_synth_bag, looped_bag, searched_bag
from _lib.timing import OwnTime, ficap_command, run_child

#: Stages of the instrumented pass: (module, public function, label); a stage's own time leaves
#: out the listed stages it calls.
STAGES = (
    ("ficap_ros.vision.detector", "TagDetector.detect", "search (ArUco, rejected quads read again)"),
    ("ficap_ros.vision.corners", "refine_tag_corners", "corner stage (unbias, cell-edge fit)"),
    ("ficap_ros.vision.edges", "refine_corners_edge_ok", "tracked tags: line refinement"),
    ("ficap_ros.vision.tracking", "predict_tags", "tracked tags: prediction and verification"),
    ("ficap_ros.vision.tracking", "verify_tags", "tracked tags: prediction and verification"),
    ("ficap_ros.vision.occlusion", "partly_hidden", "partly-hidden check"),
    ("ficap_ros.vision.pose", "estimate_cap_pose", "pose and its uncertainty"),
    ("ficap_ros.vision.pipeline", "FrameProcessor.process", "tracker and pipeline bookkeeping"),
)


@dataclass
class Drive:
    """One bag's frames in memory and the rounds measured on it (ms per frame, per round)."""

    label: str
    bag: Path
    #: Frames in one play: AprilTag 3 and the decode alone are timed on these (they keep no state).
    period: int | None = None
    raws: list = field(default_factory=list)
    command_cpu_s: list[float] = field(default_factory=list)
    command_wall_s: list[float] = field(default_factory=list)
    photometric_cpu_s: list[float] = field(default_factory=list)
    at3_ms: list[float] = field(default_factory=list)
    decode_ms: list[float] = field(default_factory=list)
    own_decode_ms: list[float] = field(default_factory=list)
    at3_tags: float = float("nan")
    ours_tags: float = float("nan")
    summary: dict = field(default_factory=dict)

    def load(self) -> None:
        from ficap_ros.io.sources import open_frames

        self.raws = [(np.frombuffer(r.payload, np.uint8), r.camera, r.stamp_ns)
                     for r in open_frames(self.bag).raw_frames()]

    @property
    def frames(self) -> int:
        return len(self.raws)

    @property
    def one_play(self) -> list:
        return self.raws[: self.period or len(self.raws)]

    def ours_ms(self) -> float:
        return 1e3 * float(np.median(self.command_cpu_s)) / self.frames

    def photometric_ms(self) -> float:
        return 1e3 * float(np.median(self.photometric_cpu_s)) / self.frames


def count_frames(bag: Path) -> int:
    """The compressed images in ``bag``."""
    from ficap_ros.io.sources import open_frames

    return sum(1 for r in open_frames(bag).raw_frames() if r.kind == "compressed" and not r.error)


def command_round(d: Drive, out: Path) -> None:
    shutil.rmtree(out, ignore_errors=True)
    r = run_child(ficap_command("replay", str(d.bag), "--out", str(out), "--jobs", "1", "--quiet",
                                "--photometric"), ok=(0, 3))
    d.photometric_cpu_s.append(r.cpu_s)
    shutil.rmtree(out, ignore_errors=True)
    r = run_child(ficap_command("replay", str(d.bag), "--out", str(out), "--jobs", "1", "--quiet"), ok=(0, 3))
    d.command_cpu_s.append(r.cpu_s)
    d.command_wall_s.append(r.wall_s)
    d.summary = json.loads((out / "summary.json").read_text())
    with open(out / "labels.csv", newline="") as f:
        d.ours_tags = float(np.mean([int(row["tags_detected"]) for row in csv.DictReader(f)]))
    print(f"  {d.label}: ficap replay CPU {r.cpu_s:.2f} s = {1e3 * r.cpu_s / d.frames:.2f} ms/frame",
          file=sys.stderr, flush=True)


def at3_round(d: Drive) -> None:
    import cv2

    proc = AT3.processor()
    tags = []
    t0 = time.process_time()
    for buf, camera, stamp in d.one_play:
        r = proc.process(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), camera, stamp)
        tags.append(len(r.detections))
    d.at3_ms.append(1e3 * (time.process_time() - t0) / len(tags))
    d.at3_tags = float(np.mean(tags))
    print(f"  {d.label}: AprilTag 3 {d.at3_ms[-1]:.1f} ms/frame", file=sys.stderr, flush=True)


def decode_round(d: Drive) -> None:
    """The decode alone, ms per frame: ``cv2.imdecode`` grey, then the command's own."""
    import cv2

    from ficap_ros.io.image_codec import decode_compressed

    plays = d.one_play
    t0 = time.process_time()
    for buf, _camera, _stamp in plays:
        cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    d.decode_ms.append(1e3 * (time.process_time() - t0) / len(plays))
    t0 = time.process_time()
    for buf, _camera, _stamp in plays:
        decode_compressed(buf)
    d.own_decode_ms.append(1e3 * (time.process_time() - t0) / len(plays))


def own_decoder(d: Drive) -> str:
    """Which decoder ``image_codec.decode_compressed`` uses for the drive's JPEGs."""
    from ficap_ros.io.image_codec import jpeg_decoder

    return jpeg_decoder(d.raws[0][0])


def instrumented(d: Drive) -> tuple[dict[str, float], float, float]:
    """Own ms per frame of each stage, the decode's (the command's own) and the pass's total, ours
    in this process."""
    from ficap_ros.io.image_codec import decode_compressed

    present = []
    for mod, attr, label in STAGES:
        import importlib

        owner = importlib.import_module(mod)
        for part in attr.split(".")[:-1]:
            owner = getattr(owner, part, None)
        if owner is not None and attr.split(".")[-1] in getattr(owner, "__dict__", {}):
            present.append((mod, attr, label))
        else:
            print(f"  (stage {mod}.{attr} not found: not timed)", file=sys.stderr)
    proc = OURS.processor()
    decode = 0.0
    with OwnTime(present) as timer:
        t_start = time.process_time()
        for buf, camera, stamp in d.raws:
            t0 = time.process_time()
            gray = decode_compressed(buf)
            decode += time.process_time() - t0
            proc.process(gray, camera, stamp)
        total = time.process_time() - t_start
    return timer.ms_per(d.frames), 1e3 * decode / d.frames, 1e3 * total / d.frames


def plot(drives: list[Drive], stages: dict[str, tuple[dict[str, float], float, float]]) -> str:
    plt = report.pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.2))
    labels, x = [], 0
    for d in drives:
        own, dec, total = stages[d.label]
        ours = d.ours_ms()
        parts = [("JPEG decode", dec, "tab:gray"), ("pipeline", total - dec, "tab:blue"),
                 ("start-up, bag, labels", max(ours - total, 0.0), "tab:cyan")]
        bottom = 0.0
        for name, v, c in parts:
            ax.barh(x, v, left=bottom, color=c, label=name if x == 0 else None)
            bottom += v
        labels.append(f"{d.label}: ficap replay")
        x += 1
        at3 = float(np.median(d.at3_ms))
        dec_alone = float(np.median(d.decode_ms))
        ax.barh(x, dec_alone, color="tab:gray")
        ax.barh(x, at3 - dec_alone, left=dec_alone, color="tab:orange",
                label="AprilTag 3 detect + pose" if x == 1 else None)
        labels.append(f"{d.label}: AprilTag 3 ({at3 / ours:.1f}x ours)")
        x += 1
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("CPU ms per frame (one core, median of rounds)")
    ax.legend(fontsize=8)
    ax.grid(True, axis="x", alpha=0.3)
    fig.suptitle("Whole replay command vs AprilTag 3 decimate 1, 1080p")
    fig.tight_layout()
    return report.save_figure(fig, "speed")


def compile_package() -> None:
    """Compile the package's modules to bytecode beside them (``__pycache__``, ignored by git), so
    the command starts as an installed one does. Not ``PYTHONPYCACHEPREFIX``: a prefix applies to
    every module, and the installed libraries' own bytecode would then go unread."""
    import compileall

    import ficap_ros

    compileall.compile_dir(Path(ficap_ros.__file__).parent, quiet=1)


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="a 5 s synth drive, blender_dev's drive played 3 times, 2 rounds "
                                   "(full: 20 s, 10 times, 3 rounds)")
    ap.add_argument("--rounds", type=int, default=None, help="alternated rounds (default 3)")
    ap.add_argument("--seconds", type=float, default=None, help="synth drive length, s (default 20)")
    ap.add_argument("--loops", type=int, default=None, help="times blender_dev's drive is played (default 10)")
    ap.add_argument("--searched-frames", type=int, default=None, help="length of each searched input, frames "
                                                                      "(default 600)")
    ap.add_argument("--core", type=int, default=None, help="the one core everything runs on (default: the "
                                                           "last this process may use)")
    args = ap.parse_args(argv)
    rounds = args.rounds or (2 if args.quick else 3)
    seconds = args.seconds or (5.0 if args.quick else 20.0)
    loops = args.loops or (3 if args.quick else 10)
    searched_frames = args.searched_frames or (60 if args.quick else 600)
    import cv2

    from ficap_ros.process import keep_freed_memory

    core = args.core if args.core is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})  # the command's children inherit it
    cv2.setNumThreads(1)
    keep_freed_memory()  # the allocator setting the command makes for itself, for AprilTag 3's rounds too
    compile_package()
    run = report.Run()
    synth = cached_synth_bag(args.cache, "1080p", int(round(seconds * 30)))
    drives = [Drive("synth", synth)]
    if devsets.present(args.data, ("dev_1080p_drive30",)):
        src = devsets.root_of(args.data) / "dev_1080p_drive30"
        drives.append(Drive(f"blender_dev drive30 x{loops}", looped_bag(args.cache, src, loops)))
    else:
        print("blender_dev's dev_1080p_drive30 not found (--data): synth only", file=sys.stderr)
    every = 20
    synth_play = count_frames(searched_bag(args.cache, f"{synth.name}_every{every}", [synth], 1, every=every))
    loops_s = -(-searched_frames // synth_play)
    drives.append(Drive(f"synth searched x{loops_s}",
                        searched_bag(args.cache, f"{synth.name}_every{every}", [synth], loops_s, every=every,
                                     gap_ns=667_000_000), period=synth_play))
    still = ("dev_1080p_high", "dev_1080p_neutral", "dev_1080p_neutral_asbuilt")
    if devsets.present(args.data, still) == list(still):
        dirs = [devsets.root_of(args.data) / s for s in still]
        still_play = count_frames(searched_bag(args.cache, "blender_dev_1080p_still", dirs, 1))
        loops_b = -(-searched_frames // still_play)
        drives.append(Drive(f"blender_dev 1080p searched x{loops_b}",
                            searched_bag(args.cache, "blender_dev_1080p_still", dirs, loops_b), period=still_play))
    for d in drives:
        d.load()
    one_frame = searched_bag(args.cache, f"{synth.name}_one_frame", [synth], 1, every=1 << 30)
    fixed_cpu_s = []
    stages = {}
    with tempfile.TemporaryDirectory(prefix="bench_speed.") as tmp:
        for rnd in range(rounds):
            for d in drives:
                command_round(d, Path(tmp) / "out")
                at3_round(d)
                decode_round(d)
            shutil.rmtree(Path(tmp) / "one", ignore_errors=True)
            fixed_cpu_s.append(run_child(ficap_command("replay", str(one_frame), "--out", str(Path(tmp) / "one"),
                                                       "--jobs", "1", "--quiet"), ok=(0, 3)).cpu_s)
        for d in drives:
            stages[d.label] = instrumented(d)
    rows = []
    for d in drives:
        ours, at3, dec = d.ours_ms(), float(np.median(d.at3_ms)), float(np.median(d.decode_ms))
        own_dec = float(np.median(d.own_decode_ms))
        photo = d.photometric_ms()
        rows.append([d.label, d.frames, f"{ours:.1f}", f"{at3:.1f}", f"**{at3 / ours:.1f}x**", f"{dec:.2f}",
                     f"**{ours / dec:.2f}x**", f"{own_dec:.2f} ({own_dec / dec:.2f}x)", f"{photo:.1f} ({at3 / photo:.1f}x, {photo / dec:.2f}x)",
                     f"{at3 - dec:.1f} / {ours - dec:.1f} = {(at3 - dec) / (ours - dec):.1f}x",
                     f"{d.summary.get('frames_with_pose', 0)}/{d.frames}", f"{d.ours_tags:.1f} / {d.at3_tags:.1f}",
                     f"{d.frames / np.median(d.command_wall_s):.0f}"])
    decoder = own_decoder(drives[0])
    table = report.md_table(["drive", "frames", "ficap replay ms/frame (whole command)",
                             "AprilTag 3 ms/frame (decode + detect + pose)", "AprilTag 3 / ficap",
                             "JPEG decode alone ms/frame (cv2.imdecode grey)", "ficap / decode alone",
                             f"the command's decode alone ms/frame ({decoder}; / cv2's)",
                             "--photometric ms/frame (AprilTag 3 / it, it / decode)",
                             "without the decode: AprilTag 3 / ficap",
                             "frames with a pose (ficap)", "tags/frame: ficap / AprilTag 3",
                             "ficap replay frames/s (wall)"], rows)
    labels = list(dict.fromkeys(label for *_m, label in STAGES))
    srows = []
    own_label = f"JPEG decode (the command's: {decoder})"
    for label in [own_label] + labels + ["pass total (decode + pipeline)",
                                                                    "the command's rest (start-up, bag, labels)"]:
        row = [label]
        for d in drives:
            own, dec, total = stages[d.label]
            v = {own_label: dec, "pass total (decode + pipeline)": total,
                 "the command's rest (start-up, bag, labels)": d.ours_ms() - total}.get(label, own.get(label, 0.0))
            row += [f"{v:.2f}", f"{100 * v / d.ours_ms():.0f} %"]
        srows.append(row)
    stage_table = report.md_table(["stage (own CPU time)"] + [c for d in drives for c in (f"{d.label} ms/frame",
                                                                                          "of the command")], srows)
    body = (f"{table}\n\n{plot(drives, stages)}\n\n"
            f"Rounds: {rounds}, alternated (the command with `--photometric` and with its defaults, "
            f"AprilTag 3, decode alone) drive by drive; one core (affinity {{{core}}}). Where our time goes, from one instrumented pass in this process "
            "(each stage's own CPU time, without the listed stages it calls; the command's rest is "
            "its median CPU time less this pass's total):\n\n" + stage_table +
            f"\n\nThe command on a bag of one synth frame: {float(np.median(fixed_cpu_s)):.2f} s CPU (median "
            "of the rounds): the fixed cost of a run (start-up, imports, loading the compiled kernels, "
            "opening the bag, writing the labels), in every figure above once per run.")
    what = ("What it measures: CPU time per frame of the whole `ficap replay --jobs 1` command "
            "(start-up, bag reading, JPEG decode, pipeline, label writing; its defaults, and with "
            "`--photometric`) against AprilTag 3 "
            "decimate 1 with our pose on the same JPEGs (decode included, start-up not), with the "
            "JPEG decode alone beside them, on a continuous 1080p `ficap synth` drive, on "
            "blender_dev's continuous 1080p drive played several times over, and on 1080p frames "
            "that must all be searched (synth and blender_dev); one core, interleaved rounds, medians.")
    report.write_section("speed", what, report.how("bench_speed.py", "shorter drives, 2 rounds"), body, run,
                         report.command(), args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
