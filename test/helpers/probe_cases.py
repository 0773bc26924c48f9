"""The fault probe's cases as inputs built at test time, and a verb run as a user runs it.

``run_cli`` runs ``ficap`` in a child process (the real file descriptor 2, where C libraries and
tracebacks print) and measures what the issue's rules bound: wall time and peak memory (the
child's own ``ru_maxrss`` and its workers', reported through a file so stderr stays the verb's).
The builders make the damaged and hostile inputs small, or sparse where a case needs a large file
(holes cost neither disk nor time).
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

from ficap_ros.geometry.camera import CameraModel
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
