"""Label a fleet of recordings: many inputs, one command, resumable, optionally on Ray.

``ficap replay`` hands this module every recording it finds (several inputs, folder trees searched
for recordings, a manifest). Each recording is replayed by ``ficap_ros.tools.replay.replay`` (one code
path: the same labels.mcap / labels.csv / summary.json as a single replay) into a folder under
``--out`` that mirrors where the input sits, and a fleet summary (CSV, JSON, PNG) is written at the
top of ``--out``.

Resuming: summary.json carries a *fingerprint* of everything that decides the labels (the input's
identity, the ficap version, every label-changing setting, the segment length). A recording whose
three outputs exist with the fingerprint of this run is skipped, so an interrupted fleet resumes
where it stopped and a second run does nothing; ``--force`` redoes them. summary.json is written
last, so a recording cut off mid-write has no matching summary and is redone.

Engines: without Ray, recordings are replayed one after the other, each with ``--jobs`` processes.
With Ray (``--ray``: an embedded single-machine Ray kept on loopback; ``--ray-address``: an existing
cluster), every recording is cut into the replay's fixed segments (``replay.SEGMENT_FRAMES``, at
whose first frames tracking restarts whatever the engine), the segments of all recordings are
spread over the cluster's CPUs, and each recording's results come back in order: the labels are
byte-identical to ``--jobs 1``. The driver reads the recordings and ships the undecoded frames
through Ray's object store, so workers need ficap_ros installed but no access to the inputs or
outputs; only the driver reads and writes files. A segment whose worker dies is retried
(``retries``); a recording that still fails is reported and the others complete.

Nothing here imports ray unless a Ray engine is asked for.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

from ficap_ros import __version__
from ficap_ros.errors import BagError, ConfigError, FicapError
from ficap_ros.files import write_output_file
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io.sources import VIDEO_SUFFIXES, FrameSource, RawFrame
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import pose_config_for
from ficap_ros.vision.pose import PoseConfig

__all__ = ["Recording", "RecordingResult", "FleetResult", "find_recordings", "read_manifest",
           "label_settings", "input_identity", "fingerprint", "current_outputs", "run_fleet",
           "RayEngine", "write_fleet_summary", "FLEET_FILES"]

#: Files of a bag container (a rosbag2 folder holds metadata.yaml and these).
BAG_SUFFIXES = (".mcap", ".db3", ".bag")
#: The fleet summary, at the top of --out.
FLEET_FILES = ("fleet_summary.csv", "fleet_summary.json", "fleet_summary.png")
#: The outputs of one recording; summary.json is written last (see the module docstring).
_OUTPUTS = ("labels.mcap", "labels.csv", "summary.json")
#: Bytes hashed at each end of every input file for its identity (with its size): cheap on
#: hours of video, and a recording that changed (re-recorded, cut, appended) changes there.
_IDENTITY_BYTES = 1 << 20


# -- finding recordings --------------------------------------------------------------------------
@dataclass(frozen=True)
class Recording:
    """One recording of the fleet.

    Attributes:
        path: the input (rosbag2 folder, .mcap/.db3 file, or video).
        rel: its output folder under ``--out`` (``.``: ``--out`` itself, for a single input).
    """

    path: Path
    rel: Path


def _is_bag_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _is_replay_output(path: Path) -> bool:
    """A folder ficap replay wrote (it is a rosbag2 too, of labels only)."""
    return (path / "labels.csv").is_file() and (path / "summary.json").is_file()


def is_recording(path: Path, videos: bool = False) -> bool:
    """A rosbag2 folder, a bag file, or (with ``videos``) a video file."""
    if path.is_dir():
        return _is_bag_folder(path) and not _is_replay_output(path)
    suffix = path.suffix.lower()
    return path.is_file() and (suffix in BAG_SUFFIXES or (videos and suffix in VIDEO_SUFFIXES))


def _stem(path: Path) -> str:
    return path.name if path.is_dir() else path.stem


def _search_tree(root: Path, videos: bool, exclude: Path | None) -> Iterator[Path]:
    """Recordings under ``root``, in sorted order; a bag folder is not searched inside."""
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if exclude is not None and _inside(here, exclude):
            dirnames[:] = []
            continue
        if here != root and _is_bag_folder(here):
            dirnames[:] = []
            if not _is_replay_output(here):
                yield here
            continue
        dirnames.sort()
        for name in sorted(filenames):
            p = here / name
            if is_recording(p, videos):
                yield p


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def read_manifest(path: str | Path) -> list[tuple[Path, Path | None]]:
    """A manifest: one input per line (``#`` starts a comment), relative to the manifest's folder.

    Returns (input path, output folder or None) per entry: a relative entry's output mirrors its
    path (``drivers/d01/drive.mcap`` -> ``drivers/d01/drive``), an absolute one uses its name.

    Raises:
        BagError: unreadable manifest.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise BagError(f"cannot read manifest {p}: {getattr(err, 'strerror', None) or err}") from err
    entries: list[tuple[Path, Path | None]] = []
    for line in text.splitlines():
        entry = line.split("#", 1)[0].strip()
        if not entry:
            continue
        e = Path(entry)
        if e.is_absolute():
            entries.append((e, None))
        else:
            entries.append((p.parent / e, e.parent / _stem(p.parent / e)))
    return entries


def find_recordings(
    inputs: Sequence[str | Path], manifest: str | Path | None = None, out: str | Path | None = None,
    videos: bool = False,
) -> list[Recording]:
    """Every recording named by ``inputs`` and ``manifest``, with its output folder.

    A recording given alone (one input, no manifest) writes into ``--out`` itself, as a single
    replay does. Otherwise: a folder tree given as the only input mirrors into ``--out``
    (``ROOT/a/b/drive`` -> ``OUT/a/b/drive``); with several inputs each goes under its own name
    (``OUT/NAME/...``); a manifest's relative entries mirror their paths. ``out`` is never
    searched, so outputs inside the input tree are not taken for recordings.

    Raises:
        BagError: a missing input, an input that is no recording and holds none, no recording at
            all, or two recordings that would write to one folder.
    """
    out_path = Path(out) if out is not None else None
    entries: list[tuple[Path, Path | None]] = [(Path(i), None) for i in inputs]
    if manifest is not None:
        entries += read_manifest(manifest)
    single = len(entries) == 1
    found: list[Recording] = []
    for path, rel in entries:
        if not path.exists():
            raise BagError(f"{path} does not exist")
        if is_recording(path, videos=True):
            if out_path is not None and _inside(out_path, path):
                raise BagError(f"output folder {out_path} is inside the input {path}")
            found.append(Recording(path, Path(".") if single and rel is None else
                                   rel if rel is not None else Path(_stem(path))))
            continue
        if not path.is_dir():
            raise BagError(f"{path} is neither a recording (rosbag2 folder, .mcap, .db3, video) "
                           "nor a folder")
        base = rel if rel is not None else (Path(".") if single else Path(path.name))
        before = len(found)
        for rec in _search_tree(path, videos, out_path):
            sub = rec.relative_to(path)
            found.append(Recording(rec, base / sub.parent / _stem(rec)))
        if len(found) == before:
            raise BagError(f"no recording (rosbag2 folder, .mcap, .db3"
                           f"{', video' if videos else ''}) found under {path}")
    seen: dict[Path, Path] = {}
    for r in found:
        if r.rel in seen:
            raise BagError(f"{seen[r.rel]} and {r.path} would both write to {r.rel}; "
                           "rename one or list them in a manifest with distinct paths")
        seen[r.rel] = r.path
    return found


# -- fingerprints --------------------------------------------------------------------------------
def _file_identity(path: Path) -> dict[str, Any]:
    size = path.stat().st_size
    h = hashlib.sha256()
    with path.open("rb") as f:
        h.update(f.read(_IDENTITY_BYTES))
        if size > 2 * _IDENTITY_BYTES:
            f.seek(size - _IDENTITY_BYTES)
        h.update(f.read(_IDENTITY_BYTES))
    return {"size": size, "sha256_ends": h.hexdigest()}


def input_identity(path: str | Path) -> dict[str, Any]:
    """Identity of an input: name, and per file its size and a hash of its first and last MiB.

    Not its modification time or absolute path, so a fleet copied elsewhere still resumes.

    Raises:
        BagError: unreadable input.
    """
    p = Path(path)
    try:
        if p.is_dir():
            files = sorted(f for f in p.rglob("*") if f.is_file() and not f.name.startswith("."))
            return {"name": p.name, "files": {str(f.relative_to(p)): _file_identity(f) for f in files}}
        return {"name": p.name, "files": {p.name: _file_identity(p)}}
    except OSError as err:
        raise BagError(f"cannot read {p}: {err.strerror or err}") from err


def _text_sha256(path: str | Path | None) -> str | None:
    if not path:
        return None
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError as err:
        raise BagError(f"cannot read {path}: {err.strerror or err}") from err


def label_settings(
    model: CapModel, pose: PoseConfig, calibration: HeadCalibration | None = None,
    calibrate_window_s: tuple[float, float] | None = None, namespace: str = "",
    image_topic: str | None = None, camera_info_topic: str | None = None,
    intrinsics: str | Path | None = None, fps: float | None = None, rectified: bool = False,
    detector: DetectorConfig | None = None,
) -> dict[str, Any]:
    """Every setting that changes the labels, as plain JSON values (files by content hash).

    Left out on purpose: ``--jobs`` and the engine (labels are identical whatever they are),
    progress and output paths.
    """
    from ficap_ros.tools import replay

    cal = calibration or HeadCalibration()
    return {
        "model_sha256": hashlib.sha256(
            repr(model.ids).encode() + model.corners_mm.astype("<f8").tobytes()).hexdigest(),
        # As the pipeline applies it: with photometric corners the default uncertainty is their
        # profile (``pipeline.pose_config_for``), so runs made before that profile existed are not
        # taken as current; with the default corners this is ``repr(pose)`` as it always was.
        "pose": repr(pose_config_for(pose, detector or DetectorConfig())),
        "calibration": None if calibration is None else {
            "R_cap_head_q_xyzw": [round(float(v), 12) for v in cal.R_cap_head.as_quat(canonical=True)],
            "R_cam_frontal_q_xyzw": [round(float(v), 12) for v in cal.R_cam_frontal.as_quat(canonical=True)],
            "calibrated": bool(cal.calibrated)},
        "calibrate_frontal_s": None if calibrate_window_s is None else [
            calibrate_window_s[0], calibrate_window_s[1] if math.isfinite(calibrate_window_s[1]) else None],
        "namespace": namespace,
        "image_topic": image_topic or None,
        "camera_info_topic": camera_info_topic or None,
        "intrinsics_sha256": _text_sha256(intrinsics),
        "fps": fps,
        "segment_frames": replay.SEGMENT_FRAMES,
        # Only when set, so fingerprints of earlier runs (raw images) stay current.
        **({"rectified": True} if rectified else {}),
        # Likewise only when not the default (``--photometric``).
        **({"detector": repr(detector)} if detector is not None and detector != DetectorConfig() else {}),
    }


def fingerprint(path: str | Path, settings: dict[str, Any]) -> dict[str, Any]:
    """The fingerprint summary.json carries: identity, version, settings and their sha256."""
    body = {"ficap_version": __version__, "input": input_identity(path), "settings": settings}
    digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    return {"sha256": digest, **body}


def current_outputs(out_dir: Path, digest: str) -> dict[str, Any] | None:
    """The summary of outputs in ``out_dir`` made with fingerprint ``digest``, or None."""
    if not all((out_dir / name).is_file() for name in _OUTPUTS):
        return None
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    fp = summary.get("fingerprint") if isinstance(summary, dict) else None
    return summary if isinstance(fp, dict) and fp.get("sha256") == digest else None


# -- Ray -----------------------------------------------------------------------------------------
_WORKER_KEY: Any = None


def _settings_key(model: CapModel, pose: PoseConfig, detector: DetectorConfig | None) -> tuple[int, str, str]:
    """What a task labels with: a worker re-initialises when it changes, and ``run_fleet``
    refuses a given engine started with another."""
    return hash(model), repr(pose), repr(detector or DetectorConfig())


def _ray_segment(config: tuple[CapModel, PoseConfig, DetectorConfig | None],
                 raws: list[RawFrame]) -> list[Any]:
    """A Ray task: one segment through the pipeline (the worker keeps its FrameProcessor)."""
    global _WORKER_KEY
    from ficap_ros.tools import replay

    model, pose, detector = config
    key = _settings_key(model, pose, detector)
    if key != _WORKER_KEY:
        replay._init_worker(model, pose, single_thread=True, detector=detector)
        _WORKER_KEY = key
    return replay._process_segment(raws)


class RayEngine:
    """Segments of any number of recordings on one Ray cluster, each recording's in order.

    Args:
        address: an existing cluster (``ray.init(address=...)``: ``auto``, ``HOST:6379``,
            ``ray://HOST:10001``), or None for an embedded single-machine Ray on loopback.
        num_cpus: CPUs of the embedded Ray (default: the machine's).
        retries: times a segment is re-run when its worker or node dies.
        model, pose: what every task processes with (shipped once through the object store).
        segment_fn: the task, ``fn((model, pose, detector), raws) -> processed frames``
            (default: the pipeline; tests pass one that fails).
        detector: detector settings of every task (default ``DetectorConfig()``).
    """

    def __init__(self, model: CapModel, pose: PoseConfig, address: str | None = None,
                 num_cpus: int | None = None, retries: int = 2,
                 segment_fn: Callable[..., list[Any]] | None = None,
                 detector: DetectorConfig | None = None) -> None:
        # Never phone home (usage statistics), and keep an embedded Ray on loopback: Ray replaces
        # 127.0.0.1 by the machine's outward address unless it believes clusters are off.
        # The variable is read when ray is imported (here, and by the worker processes, which
        # inherit it); a ray imported earlier gets the constant set as well.
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        loopback = address is None or _is_loopback_address(address)
        if loopback:
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
        if address is not None:
            _check_reachable(address)
        try:
            import ray
        except ModuleNotFoundError as err:
            raise ConfigError("--ray needs ray: pip install ray==2.60.0 (pinned in requirements.txt; "
                              "the extra ficap_ros[ray])") from err

        self._ray = ray
        self._owned = not ray.is_initialized()
        if self._owned:
            if loopback:
                from ray._private import ray_constants

                ray_constants.ENABLE_RAY_CLUSTER = False
            try:
                if address is None:
                    ray.init(_node_ip_address="127.0.0.1", include_dashboard=False,
                             num_cpus=num_cpus or os.cpu_count() or 1, log_to_driver=False,
                             logging_level="ERROR")
                else:
                    ray.init(address=address, log_to_driver=False, logging_level="ERROR")
            except Exception as err:  # ray raises ConnectionError, RuntimeError, ValueError ...
                raise ConfigError(f"cannot start Ray{'' if address is None else f' at {address}'}: "
                               f"{str(err).splitlines()[0] if str(err) else type(err).__name__}") from err
            node_ip = ray.util.get_node_ip_address()
            if address is None and not node_ip.startswith("127."):
                ray.shutdown()
                raise ConfigError(f"the embedded Ray came up on {node_ip}, not loopback; refusing to run")
        self.cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        # Two segments per CPU in flight: workers never wait for the driver, and the driver holds
        # at most 2 x CPUs x 128 undecoded frames.
        self._slots = threading.BoundedSemaphore(2 * self.cpus)
        # Retries cover a worker or node that dies (max_retries); an exception raised by the
        # pipeline would only repeat, so it fails its recording at once.
        self._task = ray.remote(num_cpus=1, max_retries=int(retries), retry_exceptions=False)(
            segment_fn or _ray_segment)
        self._config = ray.put((model, pose, detector))
        #: What its tasks label with (``_settings_key``).
        self.settings_key = _settings_key(model, pose, detector)

    def process(self, raws: Iterable[RawFrame]) -> Iterator[Any]:
        """``replay``'s engine: processed frames of ``raws``, in order (thread-safe)."""
        from ficap_ros.tools import replay

        ray = self._ray
        it = iter(raws)
        pending: deque[Any] = deque()
        done_reading = False
        try:
            while True:
                while not done_reading:
                    # Block for a slot only with nothing of ours in flight: a recording that
                    # holds finished segments must be free to collect them (no deadlock).
                    if not self._slots.acquire(blocking=not pending):
                        break
                    segment = list(islice(it, replay.SEGMENT_FRAMES))
                    if not segment:
                        self._slots.release()
                        done_reading = True
                        break
                    pending.append(self._task.remote(self._config, segment))
                if not pending:
                    return
                ref = pending.popleft()
                try:
                    frames = ray.get(ref)
                finally:
                    self._slots.release()
                yield from frames
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
                self._slots.release()

    def close(self) -> None:
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of ``HOST:PORT`` or ``ray://HOST:PORT``; None for ``auto`` and the like."""
    text = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    return host.strip("[]"), int(port)


def _is_loopback_address(address: str) -> bool:
    hp = _host_port(address)
    return hp is not None and (hp[0] in ("localhost", "::1") or hp[0].startswith("127."))


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in one line when a cluster's port does not answer (ray.init retries for minutes)."""
    import socket

    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=timeout_s):
            pass
    except OSError as err:
        raise ConfigError(f"no Ray cluster answers at {address}: {err.strerror or err}") from err


# -- the fleet -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RecordingResult:
    """One recording's line in the fleet summary.

    Attributes:
        recording, rel: input and output folder (relative to --out).
        status: ``done``, ``skipped`` (outputs current), ``damaged`` (labelled what could be
            read; frames were lost) or ``failed`` (no labels; ``error`` says why).
        frames: images labelled; frames_with_pose, pct_with_pose: coverage; pct_ge4_tags: share
            of decoded frames with at least 4 tags; reliability_mean/median: over frames with a
            pose; frames_lost: frames that gave no label input (undecodable images plus what a
            damaged container lost); wall_s: this run's time on it (0 when skipped).
    """

    recording: str
    rel: str
    status: str
    frames: int = 0
    frames_with_pose: int = 0
    pct_with_pose: float = 0.0
    pct_ge4_tags: float = 0.0
    reliability_mean: float = math.nan
    reliability_median: float = math.nan
    frames_lost: int = 0
    wall_s: float = 0.0
    error: str = ""


@dataclass
class FleetResult:
    results: list[RecordingResult] = field(default_factory=list)
    wall_s: float = 0.0
    engine: str = "processes"
    workers: int = 1

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)


def _lost(summary: dict[str, Any]) -> int:
    """Frames a recording lost: undecodable images, plus what a damaged container cut off."""
    lost = int(summary.get("frames_skipped", 0) or 0)
    for key in ("frames_lost", "messages_lost"):
        value = summary.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return lost + int(value)
        if isinstance(value, dict) and isinstance(value.get("count"), (int, float)):
            return lost + int(value["count"])
    recovery = summary.get("recovery") or summary.get("damage")
    if isinstance(recovery, dict):
        for key in ("frames_lost", "messages_lost", "lost", "count"):
            if isinstance(recovery.get(key), (int, float)):
                return lost + int(recovery[key])
    return lost


def _damaged(summary: dict[str, Any]) -> bool:
    return _lost(summary) > int(summary.get("frames_skipped", 0) or 0) or bool(
        summary.get("truncated") or summary.get("damaged"))


def _result(rec: Recording, status: str, summary: dict[str, Any], reliability: Sequence[float],
            wall_s: float) -> RecordingResult:
    import numpy as np

    rel = np.asarray([r for r in reliability if math.isfinite(r)], dtype=float)
    if status == "done" and _damaged(summary):
        status = "damaged"
    return RecordingResult(
        str(rec.path), str(rec.rel), status, int(summary.get("frames", 0)),
        int(summary.get("frames_with_pose", 0)), float(summary.get("pct_with_pose", 0.0)),
        float(summary.get("pct_ge4_tags", 0.0)),
        round(float(rel.mean()), 4) if rel.size else math.nan,
        round(float(np.median(rel)), 4) if rel.size else math.nan,
        _lost(summary), round(wall_s, 3))


def run_fleet(
    recordings: Sequence[Recording],
    out: str | Path,
    open_source: Callable[[Path], FrameSource],
    model: CapModel,
    pose: PoseConfig,
    settings: dict[str, Any],
    calibration: HeadCalibration | None = None,
    calibrate_window_s: tuple[float, float] | None = None,
    namespace: str = "",
    jobs: int = 1,
    ray_address: str | None = None,
    use_ray: bool = False,
    retries: int = 2,
    force: bool = False,
    progress: bool = True,
    summary_files: bool = True,
    ray_engine: RayEngine | None = None,
    detector: DetectorConfig | None = None,
) -> FleetResult:
    """Replay every recording into ``out / rec.rel`` (see the module docstring).

    Args:
        open_source: opens one recording (the CLI's topic/intrinsics options).
        settings: ``label_settings`` of this run (goes into each fingerprint).
        jobs: processes per recording without Ray; CPUs of an embedded Ray.
        use_ray, ray_address: Ray engine: embedded (``use_ray``) or the cluster at ``ray_address``.
        retries: Ray task retries when a worker dies.
        force: redo recordings whose outputs are current.
        summary_files: write fleet_summary.csv/.json/.png at the top of ``out``.
        ray_engine: a Ray engine to use (not closed here) instead of starting one; it carries
            its own ``detector``.
        detector: detector settings (default ``DetectorConfig()``); give the same to
            ``label_settings`` so the fingerprint holds them.

    Returns:
        One result per recording, in the given order. A failing recording does not stop the others.

    Raises:
        BagError: ``out`` not writable. ConfigError: Ray missing or not startable.
    """
    from ficap_ros.tools import replay as replay_mod

    out = Path(out)
    replay_mod.check_output_dir(out)
    t0 = time.perf_counter()
    results: dict[int, RecordingResult] = {}
    todo: list[tuple[int, Recording, FrameSource, dict[str, Any]]] = []
    for i, rec in enumerate(recordings):
        try:
            fp = fingerprint(rec.path, settings)
            summary = None if force else current_outputs(out / rec.rel, fp["sha256"])
            if summary is not None:
                results[i] = _result(rec, "skipped", summary, _reliability(out / rec.rel), 0.0)
                continue
            todo.append((i, rec, open_source(rec.path), fp))
        except FicapError as err:
            results[i] = RecordingResult(str(rec.path), str(rec.rel), "failed", error=str(err))

    engine: RayEngine | None = None
    bar = _FleetProgress(sum(src.count for _, _, src, _ in todo), len(recordings),
                         len(results), sum(r.status == "failed" for r in results.values()), progress)
    fleet = FleetResult(engine="processes", workers=jobs)
    try:
        if todo and ray_engine is not None:
            if ray_engine.settings_key != _settings_key(model, pose, detector):
                raise ConfigError("the Ray engine given was started with another model, pose or "
                                  "detector setting than this fleet's (its labels would not match "
                                  "the fingerprints)")
            engine = ray_engine
            fleet.engine, fleet.workers = "ray", engine.cpus
        elif todo and (use_ray or ray_address):
            engine = RayEngine(model, pose, ray_address, jobs if ray_address is None else None, retries,
                               detector=detector)
            fleet.engine, fleet.workers = ("ray" if ray_address is None else f"ray {ray_address}",
                                           engine.cpus)

        def one(item: tuple[int, Recording, FrameSource, dict[str, Any]]) -> None:
            i, rec, source, fp = item
            t = time.perf_counter()
            process = engine.process if engine is not None else (
                lambda raws: replay_mod.process_frames(raws, model, pose, jobs, detector=detector))
            try:
                output = replay_mod.replay(
                    source, out / rec.rel, model, pose, calibration, calibrate_window_s, jobs,
                    namespace, progress=False, engine=lambda raws: bar.counted(process(raws)),
                    summary_extra={"fingerprint": fp}, detector=detector)
                results[i] = _result(rec, "done", output.summary,
                                     [r.reliability for r in output.records if r.T_cam_cap is not None],
                                     time.perf_counter() - t)
            except Exception as err:  # noqa: BLE001 - one recording's failure must not stop the fleet
                results[i] = RecordingResult(str(rec.path), str(rec.rel), "failed",
                                             wall_s=round(time.perf_counter() - t, 3),
                                             error=_one_line(err))
            bar.recording_done(results[i].status)

        if engine is None:
            for item in todo:
                one(item)
        else:
            # Several recordings at once, so short ones do not leave the cluster idle; the
            # engine's slots bound what is in flight overall.
            with ThreadPoolExecutor(max_workers=max(1, min(len(todo), engine.cpus))) as pool:
                for future in [pool.submit(one, item) for item in todo]:
                    future.result()
    finally:
        bar.close()
        if engine is not None and engine is not ray_engine:
            engine.close()
        fleet.results = [results[i] for i in sorted(results)]
        fleet.wall_s = time.perf_counter() - t0
        if summary_files and len(fleet.results) == len(recordings):
            write_fleet_summary(out, fleet)
    return fleet


def _reliability(out_dir: Path) -> list[float]:
    from ficap_ros.io.labels import read_labels

    try:
        lab = read_labels(out_dir)
    except FicapError:
        return []
    return lab.reliability[lab.has_pose].tolist()


def _one_line(err: BaseException) -> str:
    if isinstance(err, FicapError):
        return str(err)
    text = str(err).strip().splitlines()
    # A Ray task error's first line names the task; its cause is the last line.
    return f"{type(err).__name__}: {text[-1] if text else ''}".strip()


class _LogLines:
    """A stream for tqdm off a terminal: each redraw (``\\r`` + the bar) becomes a line of its own,
    so a log holds one line per update instead of one endless line of carriage returns."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> None:
        for piece in text.replace("\r", "\n").split("\n"):
            if piece.strip():
                self._stream.write(piece.rstrip() + "\n")

    def flush(self) -> None:
        self._stream.flush()


class _FleetProgress:
    """tqdm over the fleet's frames (frames/s, ETA), recordings done in the postfix."""

    def __init__(self, total_frames: int, recordings: int, done: int, failed: int,
                 enabled: bool, stream: Any = None) -> None:
        self._lock = threading.Lock()
        self._recordings, self._done, self._failed = recordings, done, failed
        self._bar = None
        if enabled:
            import sys

            from tqdm import tqdm

            # A fleet runs for hours, often into a log: there a plain line every 30 s (and one
            # at the end), not silence and not a line redrawn with carriage returns.
            stream = sys.stderr if stream is None else stream
            self._tty = stream.isatty()
            self._bar = tqdm(total=total_frames, unit="frame", desc="fleet", dynamic_ncols=True,
                             file=stream if self._tty else _LogLines(stream),
                             ascii=not self._tty, mininterval=0.5 if self._tty else 30.0,
                             smoothing=0.05)
            self._postfix()

    def _postfix(self) -> None:
        if self._bar is not None:
            text = f"{self._done}/{self._recordings} recordings"
            # Off a terminal a recording done waits for the next 30 s line.
            self._bar.set_postfix_str(text + (f", {self._failed} failed" if self._failed else ""),
                                      refresh=self._tty)

    def counted(self, frames: Iterable[Any]) -> Iterator[Any]:
        for item in frames:
            if self._bar is not None:
                with self._lock:
                    self._bar.update(1)
            yield item

    def recording_done(self, status: str) -> None:
        with self._lock:
            self._done += 1
            self._failed += status == "failed"
            self._postfix()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


# -- fleet summary -------------------------------------------------------------------------------
_COLUMNS = ("recording", "rel", "status", "frames", "frames_with_pose", "pct_with_pose",
            "pct_ge4_tags", "reliability_mean", "reliability_median", "frames_lost", "wall_s",
            "error")


def write_fleet_summary(out: Path, fleet: FleetResult) -> list[Path]:
    """fleet_summary.csv (a row per recording), .json (the rows and totals) and .png."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(_COLUMNS)
    for r in fleet.results:
        row = asdict(r)
        writer.writerow(["" if isinstance(row[c], float) and math.isnan(row[c]) else row[c]
                         for c in _COLUMNS])
    totals = {
        "recordings": len(fleet.results),
        **{s: fleet.count(s) for s in ("done", "skipped", "damaged", "failed")},
        "frames": sum(r.frames for r in fleet.results),
        "frames_processed": sum(r.frames for r in fleet.results if r.status in ("done", "damaged")),
        "frames_with_pose": sum(r.frames_with_pose for r in fleet.results),
        "frames_lost": sum(r.frames_lost for r in fleet.results),
        "wall_s": round(fleet.wall_s, 3),
        "engine": fleet.engine,
        "workers": fleet.workers,
        "ficap_version": __version__,
    }
    processed = totals["frames_processed"]
    totals["throughput_fps"] = round(processed / fleet.wall_s, 2) if fleet.wall_s > 0 else None
    doc = {"fleet": totals,
           "recordings": [{k: (None if isinstance(v, float) and math.isnan(v) else v)
                           for k, v in asdict(r).items()} for r in fleet.results]}
    paths = [out / name for name in FLEET_FILES]
    write_output_file(paths[0], buf.getvalue())
    write_output_file(paths[1], json.dumps(doc, indent=2) + "\n")
    write_output_file(paths[2], _plot(fleet))
    return paths


_STATUS_COLOURS = {"done": "#2b7bba", "skipped": "#8fb9dc", "damaged": "#e39b2d", "failed": "#c8312b"}


def _plot(fleet: FleetResult) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rs = fleet.results
    names = [r.rel if r.rel != "." else Path(r.recording).name for r in rs]
    colours = [_STATUS_COLOURS.get(r.status, "grey") for r in rs]
    panels = (("frames", "frames labelled", lambda r: r.frames),
              ("coverage %", "frames with a pose, %", lambda r: r.pct_with_pose),
              (">= 4 tags %", "decoded frames with >= 4 tags, %", lambda r: r.pct_ge4_tags),
              ("reliability", "mean reliability (frames with a pose)",
               lambda r: 0.0 if math.isnan(r.reliability_mean) else r.reliability_mean),
              ("frames lost", "undecodable or cut off", lambda r: r.frames_lost),
              ("wall s", "this run's time, s (0: skipped)", lambda r: r.wall_s))
    height = max(3.0, 0.28 * len(rs) + 1.6)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), height), sharey=True)
    ys = range(len(rs))
    for ax, (label, title, value) in zip(axes, panels):
        values = [value(r) for r in rs]
        ax.barh(list(ys), values, color=colours)
        ax.set_xlim(0, max(max(values, default=0) * 1.05, 1e-9) if any(values) else 1)
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(label, fontsize=8)
        ax.tick_params(labelsize=7)
    for y, r in zip(ys, rs):  # a failed recording has no bars: say so where they would be
        if r.status == "failed":
            axes[0].text(0, y, " failed", va="center", fontsize=7, color=_STATUS_COLOURS["failed"])
    axes[0].invert_yaxis()
    axes[0].set_yticks(list(ys), names)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in _STATUS_COLOURS.values()]
    fig.legend(handles, list(_STATUS_COLOURS), loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"ficap fleet: {len(rs)} recordings, {fleet.count('done')} done, "
                 f"{fleet.count('skipped')} skipped, {fleet.count('damaged')} damaged, "
                 f"{fleet.count('failed')} failed", fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()
