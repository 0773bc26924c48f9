"""The fault probe's cases as inputs built at test time, and a verb run as a user runs it.

``run_cli`` runs ``ficap`` in a child process (the real file descriptor 2, where C libraries and
tracebacks print) and measures what the issue's rules bound: wall time and peak memory (the
child's own high-water mark ``VmHWM``, not its ``ru_maxrss``, which Linux carries across exec from
the test process that started it; its workers' ``ru_maxrss``; reported through a file so stderr
stays the verb's).
The builders make the damaged and hostile inputs small, or sparse where a case needs a large file
(holes cost neither disk nor time). ``Probe`` builds the probe's inputs in one folder; the case
tables (``QUICK_REFUSALS``, ``BAD_NUMBERS``, ``walk_cases``) are what test_bad_inputs.py runs.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np
import yaml

from ficap_ros.cli.main import main
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE

ROOT = Path(__file__).resolve().parents[2]
#: The issue's bounds on every case.
TIME_LIMIT_S = 30.0
MEMORY_LIMIT_MB = 500.0
T0_NS = 1_700_000_000_000_000_000
DT_NS = 33_333_333

_CHILD = (
    "import os, resource, sys\n"
    "from ficap_ros.cli.main import main\n"
    "code = 2\n"
    "try:\n"
    "    code = main(sys.argv[1:])\n"
    "except SystemExit as stop:\n"
    "    code = stop.code if isinstance(stop.code, int) else 2\n"
    "finally:\n"
    "    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
    "    if os.path.exists('/proc/self/status'):\n"
    "        with open('/proc/self/status') as status:\n"
    "            own = next((int(line.split()[1]) for line in status\n"
    "                        if line.startswith('VmHWM:')), own)\n"
    "    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
    "    with open(os.environ['FICAP_PROBE_RSS'], 'w') as f:\n"
    "        f.write(f'{own} {kids}')\n"
    "sys.exit(code)\n")


@dataclass(frozen=True)
class Run:
    """A finished ``ficap`` run: exit code, output, wall time and peak memory (the largest
    process's resident set, MB)."""

    code: int
    out: str
    err: str
    wall_s: float
    max_rss_mb: float

    @property
    def err_lines(self) -> list[str]:
        return self.err.strip().splitlines()


def run_cli(argv: Sequence[str], tmp: Path, timeout_s: float = TIME_LIMIT_S,
            env: dict[str, str] | None = None) -> Run:
    """``ficap ARGV`` in a child process with the worktree first on the path; fails the test if
    it does not end within ``timeout_s``."""
    rss = tmp / f".rss-{time.monotonic_ns()}"
    full_env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]), "FICAP_PROBE_RSS": str(rss),
        **(env or {})}
    t0 = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, "-c", _CHILD, *map(str, argv)], capture_output=True,
                              text=True, timeout=timeout_s, env=full_env, cwd=tmp)
    except subprocess.TimeoutExpired as err:
        raise AssertionError(f"ficap {' '.join(map(str, argv))} ran past {timeout_s:g} s "
                             f"(stderr: {err.stderr!r})") from None
    wall = time.monotonic() - t0
    own, kids = (int(v) for v in rss.read_text().split()) if rss.exists() else (0, 0)
    rss.unlink(missing_ok=True)
    return Run(proc.returncode, proc.stdout, proc.stderr, wall, max(own, kids) / 1024.0)


def check_run(run: Run, code: int, says: str = "", max_rss_mb: float = MEMORY_LIMIT_MB) -> str:
    """The issue's rule for a case: the exit code, no traceback, within the time and memory
    bounds; an error (1) is exactly one ``ficap: error:`` line, a bad argument (2) argparse's
    usage and one error line, both naming the problem (``says``); a run that labelled (0, or 3
    for frames lost to damage) prints no error. Returns the line that names the outcome."""
    assert "Traceback" not in run.err, run.err
    assert run.code == code, (run.code, run.err, run.out)
    assert run.wall_s <= TIME_LIMIT_S, run.wall_s
    assert run.max_rss_mb <= max_rss_mb, run.max_rss_mb
    errors = [line for line in run.err_lines if "error:" in line]
    if code == 1:
        assert len(run.err_lines) == 1 and errors == run.err_lines, run.err_lines
    elif code == 2:
        assert len(errors) == 1, run.err_lines
    else:
        assert not errors, run.err_lines
        errors = run.out.strip().splitlines()[-1:]
    assert errors and says in errors[0], (says, errors)
    return errors[0]


def sha256s(paths: Iterable[Path]) -> dict[str, str]:
    """SHA-256 of every file under ``paths`` (files and folders, symlinks not followed)."""
    out = {}
    for p in paths:
        files = sorted(q for q in p.rglob("*") if q.is_file() and not q.is_symlink()) \
            if p.is_dir() else [p]
        for f in files:
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


# -- inputs ---------------------------------------------------------------------------------------
def jpeg_bag(path: Path, jpegs: Sequence[bytes], camera: CameraModel | object,
             layout: str = "folder") -> Path:
    """A bag of CompressedImage JPEGs at 30 fps, each with its CameraInfo (``camera`` a
    ``CameraModel``, or a function of the stamp giving the message)."""
    with BagWriter(path, storage="mcap", layout=layout) as w:
        w.add_topic("/cam/image_raw/compressed", COMPRESSED_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i, data in enumerate(jpegs):
            stamp = T0_NS + i * DT_NS
            head = messages.header(ROSBAGS, stamp, "cam")
            info = (messages.camera_info(ROSBAGS, head, camera) if isinstance(camera, CameraModel)
                    else camera(stamp))  # type: ignore[operator]
            w.write("/cam/camera_info", stamp, info)
            w.write("/cam/image_raw/compressed", stamp, messages.compressed_image(ROSBAGS, head,
                                                                                   data))
    return path


def camera_info_with(camera: CameraModel, **fields: object):  # noqa: ANN201
    """A CameraInfo builder (for ``jpeg_bag``) with fields replaced: ``d``, ``k``,
    ``distortion_model``."""
    def make(stamp: int):  # noqa: ANN202
        msg = messages.camera_info(ROSBAGS, messages.header(ROSBAGS, stamp, "cam"), camera)
        for name, value in fields.items():
            setattr(msg, name, np.asarray(value, dtype=np.float64) if name in ("d", "k", "p")
                    else value)
        return msg
    return make


def flip_bytes(jpeg: bytes, count: int, seed: int) -> bytes:
    """``jpeg`` with ``count`` bytes of its entropy-coded data (after the scan header, before
    the end marker) replaced by other random values."""
    data = bytearray(jpeg)
    sos = jpeg.index(b"\xff\xda")
    start = sos + 2 + int.from_bytes(jpeg[sos + 2: sos + 4], "big")
    rng = np.random.default_rng(seed)
    for pos in rng.choice(np.arange(start, len(data) - 2), count, replace=False):
        data[pos] = (data[pos] + int(rng.integers(1, 256))) % 256
    return bytes(data)


def huge_jpeg_header(width: int = 30000, height: int = 30000) -> bytes:
    """A small JPEG whose frame header claims ``width`` x ``height`` pixels."""
    jpeg = bytearray(cv2.imencode(".jpg", np.zeros((64, 64), np.uint8))[1].tobytes())
    for marker in (b"\xff\xc0", b"\xff\xc2"):
        pos = jpeg.find(marker)
        if pos >= 0:
            jpeg[pos + 5: pos + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
            return bytes(jpeg)
    raise AssertionError("no frame header")


def extend_sparse(path: Path, size: int) -> None:
    """Grow ``path`` to ``size`` bytes with a hole (no data written, no disk used)."""
    with open(path, "r+b") as handle:
        handle.truncate(size)


def kill_pool_workers(stop: threading.Event, times: int, killed: list[int]) -> None:
    """Kill this process's pool workers (spawned children, not the resource tracker) as they
    appear, ``times`` kills in all."""
    me = os.getpid()
    while not stop.is_set() and len(killed) < times:
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
                cmd = (stat.parent / "cmdline").read_bytes()
            except (OSError, IndexError, ValueError):
                continue
            pid = int(stat.parent.name)
            if ppid == me and b"spawn_main" in cmd and pid not in killed:
                time.sleep(0.3)  # let it take a segment
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue
                killed.append(pid)
                break
        time.sleep(0.05)


# -- the probe's inputs and cases -------------------------------------------------------------------
class Probe:
    """The probe's inputs in one folder (built once per test process)."""

    def __init__(self, root: Path, rendered_frames) -> None:  # noqa: ANN001
        images, scene = rendered_frames
        self.root, self.camera = root, scene.camera
        self.jpegs = [cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
                      for img in images]
        self.bag = jpeg_bag(root / "in" / "bag", self.jpegs, self.camera)
        self.single = jpeg_bag(root / "in" / "single" / "drive.mcap", self.jpegs, self.camera,
                               layout="file")
        self.model = root / "in" / "model.yaml"
        nominal_model().save(self.model)
        self.labels = root / "in" / "labels"
        assert main(["replay", str(self.bag), "--out", str(self.labels), "--quiet"]) == 0
        self.files = root / "cfg"
        self.files.mkdir()
        self._configs()
        self.fifo = root / "cfg" / "calibration.fifo"
        os.mkfifo(self.fifo)

    def _configs(self) -> None:
        texts = {
            "cal_bigint.yaml": "R_cap_head_q_wxyz: [1, 0, 0, " + "9" * 5000 + "]\n",
            "cal_deep.yaml": "R_cap_head_q_wxyz: " + "[" * 100_000 + "]" * 100_000 + "\n",
            "cal_laughs.yaml": "a: &a [1, 0, 0, 0]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a]\n"
                               "c: &c [*b, *b, *b, *b, *b, *b, *b, *b]\nR_cap_head_q_wxyz: *a\n",
            "cal_q1e308.yaml": "R_cap_head_q_wxyz: [1.0e+308, 1.0e+308, 0, 0]\n",
            "cal_qbool.yaml": "R_cap_head_q_wxyz: [true, false, 0, 0]\n",
            "model_id587.yaml": "tags: [{id: 587, corners_mm: [[0, 0, 80], [32, 0, 80], "
                                "[32, 32, 80], [0, 32, 80]]}]\n",
            "model_far.yaml": "tags: [{id: 3, corners_mm: [[0, 0, 80], [1.0e+308, 0, 80], "
                              "[32, 32, 80], [0, 32, 80]]}]\n",
        }
        for name, text in texts.items():
            (self.files / name).write_text(text)
        data = self.camera.to_camera_yaml()
        for name, fx, d in (("intr_fx1e308.yaml", 1e308, [0.0] * 5),
                            ("intr_fx_tiny.yaml", 1e-300, [0.0] * 5),
                            ("intr_d1e10.yaml", None, [1e10, 0.0, 0.0, 0.0, 0.0]),
                            ("intr_d6.yaml", None, [0.1, 0.0, 0.0, 0.0, 0.0, 0.2])):
            k = list(data["camera_matrix"]["data"])
            if fx is not None:
                k[0] = k[4] = fx
            (self.files / name).write_text(yaml.safe_dump(
                {**data, "camera_matrix": {**data["camera_matrix"], "data": k},
                 "distortion_coefficients": {"rows": 1, "cols": len(d), "data": d}}))

    def inputs(self) -> list[Path]:
        return [self.root / "in", self.files]


#: (id, argv with {bag} {single} {model} {cfg} {fifo} {out} in it, exit code, what the line says)
QUICK_REFUSALS = [
    ("model-build-over-its-input", ["model", "build", "{single}/drive.mcap", "--allow-partial",
                                    "--out", "{single}/drive.mcap"], 1, "input"),
    ("model-over-a-bags-metadata", ["model", "--out", "{bag}/metadata.yaml"], 1,
     "lies inside the recording"),
    ("model-build-report-into-a-bag", ["model", "build", "{bag}", "--out", "{out}.yaml",
                                       "--report", "{single}/metadata.yaml"], 1, "recording"),
    ("model-build-plot-over-a-recording", ["model", "build", "{bag}", "--out", "{out}.yaml",
                                           "--plot", "{single}/drive.mcap"], 1, "recording"),
    ("model-build-out-equals-report", ["model", "build", "{bag}", "--out", "{out}.yaml",
                                       "--report", "{out}.yaml"], 1, "name one file"),
    ("calibration-fifo", ["replay", "{bag}", "--out", "{out}", "--calibration", "{fifo}"], 1,
     "not a regular file"),
    ("calibration-dev-zero", ["replay", "{bag}", "--out", "{out}", "--calibration", "/dev/zero"],
     1, "/dev/zero is not a regular file"),
    ("model-dev-zero", ["replay", "{bag}", "--out", "{out}", "--model", "/dev/zero"], 1,
     "not a regular file"),
    ("intrinsics-dev-zero", ["replay", "{bag}", "--out", "{out}", "--intrinsics", "/dev/zero"], 1,
     "not a regular file"),
    ("calibration-5000-digits", ["replay", "{bag}", "--out", "{out}", "--calibration",
                                 "{cfg}/cal_bigint.yaml"], 1, "an integer of 5000 digits"),
    ("calibration-100k-deep", ["replay", "{bag}", "--out", "{out}", "--calibration",
                               "{cfg}/cal_deep.yaml"], 1, "nested deeper than"),
    ("calibration-billion-laughs", ["replay", "{bag}", "--out", "{out}", "--calibration",
                                    "{cfg}/cal_laughs.yaml"], 1, "aliases"),
    ("calibration-quaternion-1e308", ["replay", "{bag}", "--out", "{out}", "--calibration",
                                      "{cfg}/cal_q1e308.yaml"], 1, "must be of unit length"),
    ("calibration-quaternion-booleans", ["replay", "{bag}", "--out", "{out}", "--calibration",
                                         "{cfg}/cal_qbool.yaml"], 1, "must be 4 numbers"),
    ("model-tag-id-587", ["replay", "{bag}", "--out", "{out}", "--model",
                          "{cfg}/model_id587.yaml"], 1, "not a tag36h11 id"),
    ("model-corner-1e308", ["replay", "{bag}", "--out", "{out}", "--model",
                            "{cfg}/model_far.yaml"], 1, "from the cap origin"),
    ("intrinsics-6-plumb-bob-coefficients", ["replay", "{bag}", "--out", "{out}",
                                             "--intrinsics", "{cfg}/intr_d6.yaml"], 1,
     "plumb_bob takes 5 coefficients"),
    ("intrinsics-fx-1e308", ["replay", "{bag}", "--out", "{out}", "--intrinsics",
                             "{cfg}/intr_fx1e308.yaml"], 1, "are not sane"),
    ("intrinsics-fx-1e-300", ["replay", "{bag}", "--out", "{out}", "--intrinsics",
                              "{cfg}/intr_fx_tiny.yaml"], 1, "are not sane"),
    ("intrinsics-d-1e10", ["replay", "{bag}", "--out", "{out}", "--intrinsics",
                           "{cfg}/intr_d1e10.yaml"], 1, "exceed 1000"),
    ("frontal-window-after-the-end", ["replay", "{bag}", "--out", "{out}",
                                      "--calibrate-frontal", "100:110"], 1,
     "starts after the recording ends"),
    ("detect-a-folder", ["detect", "{bag}"], 1, "is a folder"),
    ("detect-dev-zero", ["detect", "/dev/zero"], 1, "not a regular file"),
]


#: Numbers whose range bounds the memory or time they imply (argparse: exit 2, one error line).
BAD_NUMBERS = [
    ["synth", "--out", "{out}", "--frames", "99999999999999999999"],
    ["synth", "--out", "{out}", "--seed", "-1"],
    ["synth", "--out", "{out}", "--psf-sigma-px", "1e20"],
    ["synth", "--out", "{out}", "--defocus-px", "1e4"],
    ["synth", "--out", "{out}", "--fps", "1e308"],
    ["demo", "--offline", "--frames", "99999999999999999999"],
    ["demo", "--offline", "--seed", "-1"],
    ["replay", "{bag}", "--out", "{out}", "--calibrate-frontal", "0:1e308"],
    ["calibrate", "labels.csv", "--frontal", "0:1e308", "--out", "{out}.yaml"],
    ["calibrate", "labels.csv", "--reference", "b:/t", "--max-dt-ms", "1e308", "--out", "c.yaml"],
    ["calibrate", "labels.csv", "--reference", "b:/t", "--random", "3", "--seed", "-1",
     "--out", "c.yaml"],
    ["evaluate", "--truth", "a.csv", "--estimate", "b.csv", "--max-dt-ms", "1e308"],
    ["kit", "--out", "{out}", "--shell-thickness-mm", "1000"],
    ["replay", "{bag}", "--out", "{out}", "--retries", "1000000"],
    ["model", "build", "{bag}", "--out", "{out}.yaml", "--max-frames", "99999999999"],
]


def walk_cases(probe: Probe) -> list[tuple[str, list[str], Path]]:
    """(name, argv with OUT where the output goes, an input the output is pointed at) for every
    output flag of every verb that writes (``detect`` writes nothing; ``demo`` writes only its
    own cache of rendered samples)."""
    bag, mcap, labels, model = probe.bag, probe.single, probe.labels / "labels.csv", probe.model
    truth, estimate = f"{probe.labels}/labels.csv", str(labels)
    return [
        ("replay", ["replay", str(bag), "--out", "OUT", "--model", str(model)], bag),
        ("replay-file", ["replay", str(mcap), "--out", "OUT"], mcap),
        ("stats", ["stats", str(bag), "--out", "OUT"], bag),
        ("stats-labels", ["stats", str(probe.labels), "--out", "OUT"], probe.labels),
        ("calibrate", ["calibrate", str(labels), "--frontal", "0:1", "--out", "OUT"], labels),
        ("evaluate", ["evaluate", "--truth", truth, "--estimate", estimate, "--out", "OUT"],
         labels),
        ("model", ["model", "--model", str(model), "--out", "OUT"], model),
        ("model-build", ["model", "build", str(mcap), "--out", "OUT"], mcap),
        ("model-build-report", ["model", "build", str(bag), "--out", "m.yaml", "--report", "OUT"],
         bag),
        ("model-build-plot", ["model", "build", str(bag), "--out", "m.yaml", "--plot", "OUT"],
         bag),
        ("synth", ["synth", "--model", str(model), "--out", "OUT", "--frames", "2"], model),
        ("kit", ["kit", "--model", str(model), "--out", "OUT"], model),
    ]


def no_setup(*_args: object) -> None:
    """A worker pool's initializer that does nothing (``worker_pool`` tests)."""


def echo_segment(raws: list, timing: object, lookahead: object) -> list:
    """A segment function for worker-pool tests: each frame with the segment's look-ahead and
    the worker's process id."""
    return [(raw, lookahead, os.getpid()) for raw in raws]
