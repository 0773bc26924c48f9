"""The fleet's run: which recordings are current and skipped, which engine replays the rest, each
recording through ``ficap_ros.tools.replay.replay`` into its folder, and the fleet summary.

Without Ray, recordings are replayed one after the other, each with ``--jobs`` processes; with a
Ray engine (``ray_engine``) several at once, so short ones do not leave the cluster idle. A
recording that fails is reported and the others complete.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from ficap_ros.errors import ConfigError, FicapError, OutputError, one_line
from ficap_ros.files import OutputLock, check_output_folder
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io.frames import OutputFrames
from ficap_ros.io.labels import read_labels
from ficap_ros.io.sources import FrameSource
from ficap_ros.tools import replay as replay_mod
from ficap_ros.tools.fleet.fingerprints import (
    current_outputs,
    fingerprint,
    settings_key,
)
from ficap_ros.tools.fleet.manifest import Recording
from ficap_ros.tools.fleet.progress import FleetProgress
from ficap_ros.tools.fleet.ray_engine import RayEngine
from ficap_ros.tools.fleet.summary import (
    FleetResult,
    RecordingResult,
    recording_result,
    write_fleet_summary,
)
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pose import PoseConfig

__all__ = ["run_fleet"]

#: A recording to replay: its place in the fleet, itself, its opened source and its fingerprint.
_Todo = tuple[int, Recording, FrameSource, dict[str, Any]]


@dataclass(frozen=True)
class _Labelling:
    """How every recording of a run is labelled (``replay.replay``'s settings) and where."""

    out: Path
    model: CapModel
    pose: PoseConfig
    calibration: HeadCalibration | None
    calibrate_window_s: tuple[float, float] | None
    namespace: str
    jobs: int
    detector: DetectorConfig | None
    frames: OutputFrames | None = None
    inputs: tuple[Any, ...] = ()
    timing: Mapping[str, Any] | None = None

    def replay_one(self, item: _Todo, engine: RayEngine | None,
                   bar: FleetProgress) -> RecordingResult:
        """One recording into ``out / rec.rel``: its result, ``failed`` on any error."""
        _, rec, source, fp = item
        t = time.perf_counter()
        try:
            timing = replay_mod.recording_timing(source, self.timing)[0]
            process = (lambda raws: engine.process(raws, timing)) if engine is not None else (
                lambda raws: replay_mod.process_frames(raws, self.model, self.pose, self.jobs,
                                                       detector=self.detector, timing=timing))
            output = replay_mod.replay(
                source, self.out / rec.rel, self.model, self.pose, self.calibration,
                self.calibrate_window_s, self.jobs, self.namespace, progress=False,
                engine=lambda raws: bar.counted(process(raws)),
                summary_extra={"fingerprint": fp}, detector=self.detector, frames=self.frames,
                inputs=self.inputs,
                timing=self.timing)
        except Exception as err:  # noqa: BLE001 - one recording's failure must not stop the fleet
            return RecordingResult(str(rec.path), str(rec.rel), "failed",
                                   wall_s=round(time.perf_counter() - t, 3),
                                   error=one_line(err, typed=True))
        return recording_result(rec, "done", output.summary,
                                [r.reliability for r in output.records if r.T_cam_cap is not None],
                                time.perf_counter() - t)


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
    frames: OutputFrames | None = None,
    inputs: Sequence[Any] = (),
    timing: Mapping[str, Any] | None = None,
) -> FleetResult:
    """Replay every recording into ``out / rec.rel`` (see the package docstring).

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
        frames: the output frames (``replay.replay``'s; give the same to ``label_settings``).
        inputs: the run's configuration files (model, calibration, intrinsics, manifest): no
            output may be one.
        timing: camera timing fields over each recording's own (``replay.recording_timing``);
            give the same to ``label_settings``.

    Returns:
        One result per recording, in the given order. A failing recording does not stop the others.

    Raises:
        OutputError: ``out`` breaks the output rule, or another ficap process writes it (its lock
        is held for the whole run). ConfigError: Ray missing or not startable, or a given engine
        started with other settings. WorkerError: Ray's workers did not start in time.
    """
    out = check_output_folder(out, inputs, subfolders=True)
    with OutputLock(out, "fleet output"):
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"cannot write output folder {out}: {err.strerror or err}") from err
        return _run(recordings, out, open_source, model, pose, settings, calibration,
                    calibrate_window_s, namespace, jobs, ray_address, use_ray, retries, force,
                    progress, summary_files, ray_engine, detector, frames, tuple(inputs), timing)


def _run(recordings: Sequence[Recording], out: Path, open_source: Callable[[Path], FrameSource],
         model: CapModel, pose: PoseConfig, settings: dict[str, Any],
         calibration: HeadCalibration | None, calibrate_window_s: tuple[float, float] | None,
         namespace: str, jobs: int, ray_address: str | None, use_ray: bool, retries: int,
         force: bool, progress: bool, summary_files: bool, ray_engine: RayEngine | None,
         detector: DetectorConfig | None, frames: OutputFrames | None, inputs: tuple[Any, ...],
         timing: Mapping[str, Any] | None) -> FleetResult:
    """``run_fleet`` once its output is checked and locked."""
    t0 = time.perf_counter()
    results, todo = _plan(recordings, out, settings, force, open_source)
    labelling = _Labelling(out, model, pose, calibration, calibrate_window_s, namespace, jobs,
                           detector, frames, inputs, timing)
    bar = FleetProgress(sum(src.count for _, _, src, _ in todo), len(recordings), len(results),
                        sum(r.status == "failed" for r in results.values()), progress)
    fleet = FleetResult(engine="processes", workers=jobs)
    engine: RayEngine | None = None
    try:
        if todo:
            engine = _engine(fleet, ray_engine, use_ray, ray_address, jobs, retries, model, pose,
                             detector)
        _replay_all(todo, labelling, engine, bar, results)
    finally:
        bar.close()
        if engine is not None and engine is not ray_engine:
            engine.close()
        fleet.results = [results[i] for i in sorted(results)]
        fleet.wall_s = time.perf_counter() - t0
        if summary_files and len(fleet.results) == len(recordings):
            write_fleet_summary(out, fleet)
    return fleet


def _plan(recordings: Sequence[Recording], out: Path, settings: dict[str, Any], force: bool,
          open_source: Callable[[Path], FrameSource],
          ) -> tuple[dict[int, RecordingResult], list[_Todo]]:
    """The results known before any replay (``skipped``: current outputs; ``failed``: an input
    that cannot be fingerprinted or opened) and the recordings to replay."""
    results: dict[int, RecordingResult] = {}
    todo: list[_Todo] = []
    for i, rec in enumerate(recordings):
        try:
            fp = fingerprint(rec.path, settings)
            summary = None if force else current_outputs(out / rec.rel, fp["sha256"])
            if summary is not None:
                results[i] = recording_result(rec, "skipped", summary,
                                              _reliability(out / rec.rel), 0.0)
                continue
            todo.append((i, rec, open_source(rec.path), fp))
        except FicapError as err:
            results[i] = RecordingResult(str(rec.path), str(rec.rel), "failed", error=str(err))
    return results, todo


def _engine(fleet: FleetResult, given: RayEngine | None, use_ray: bool, ray_address: str | None,
            jobs: int, retries: int, model: CapModel, pose: PoseConfig,
            detector: DetectorConfig | None) -> RayEngine | None:
    """The Ray engine of the run (the one given, checked against the run's settings; or one
    started), or None for processes; says which in ``fleet.engine`` and ``fleet.workers``."""
    if given is not None:
        if given.settings_key != settings_key(model, pose, detector):
            raise ConfigError("the Ray engine given was started with another model, pose or "
                              "detector setting than this fleet's (its labels would not match "
                              "the fingerprints)")
        fleet.engine, fleet.workers = "ray", given.cpus
        return given
    if not (use_ray or ray_address):
        return None
    engine = RayEngine(model, pose, ray_address, jobs if ray_address is None else None, retries,
                       detector=detector)
    fleet.engine = "ray" if ray_address is None else f"ray {ray_address}"
    fleet.workers = engine.cpus
    return engine


def _replay_all(todo: list[_Todo], labelling: _Labelling, engine: RayEngine | None,
                bar: FleetProgress, results: dict[int, RecordingResult]) -> None:
    """Every recording to do into ``results``: one after the other without Ray; with it, as many
    at once as the cluster has CPUs (the engine's slots bound what is in flight overall)."""
    def one(item: _Todo) -> None:
        results[item[0]] = labelling.replay_one(item, engine, bar)
        bar.recording_done(results[item[0]].status)

    if engine is None:
        for item in todo:
            one(item)
        return
    with ThreadPoolExecutor(max_workers=max(1, min(len(todo), engine.cpus))) as pool:
        for future in [pool.submit(one, item) for item in todo]:
            future.result()


def _reliability(out_dir: Path) -> list[float]:
    """The reliabilities of the frames with a pose in ``out_dir``'s labels.csv ([] unreadable)."""
    try:
        lab = read_labels(out_dir)
    except FicapError:
        return []
    return lab.reliability[lab.has_pose].tolist()
