"""Replay a recording through the pipeline: labels.mcap, labels.csv, detections.csv and
summary.json.

Every frame goes through ``FrameProcessor.process`` (the node's code path), with tracking: a frame
is looked at where the previous frames put the cap; it becomes the node's record
(``ficap_ros.io.labels.FrameRecord``), and the head calibration, known only once every frame is
in when it is calibrated from a frontal window, is applied to all of them at the end. So that the outputs do not depend on how the
frames are shared out, the recording is cut into segments of ``SEGMENT_FRAMES`` consecutive frames
and tracking starts afresh (a whole-image search) at each segment's first frame, whatever ``jobs``
is. With ``jobs > 1`` the main process reads the bag and worker processes decode and process whole
segments; results come back in recording order, identical to ``jobs = 1`` (summary.json's timing
fields aside).

With the camera's timing stated (an exposure or a readout), each frame is solved again once the
next frame has its pose (``vision.two_sided``: the motion model interpolates the cap's path
between the frames before and the next one instead of extrapolating it; ``two_sided=False``, the
command line's ``--causal-motion``, keeps the live node's causal model). A segment then carries
the next segment's first frame as its look-ahead, tracked on from the segment's own frames and
not output, so that the segment's last frame has its next one whatever ``jobs`` is.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from itertools import islice
from pathlib import Path
from typing import IO, Any, Callable, Iterable, Iterator, Mapping

import numpy as np

from ficap_ros.errors import BagError, ImageError
from ficap_ros.files import write_atomic
from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.calibration_file import q_wxyz
from ficap_ros.io.detections import detections_csv_text, tag_fits
from ficap_ros.io.frames import OutputFrames
from ficap_ros.io.labels import (
    UNCALIBRATED,
    FrameRecord,
    labels_csv_text,
    write_labels_bag,
)
from ficap_ros.io.sources import FrameSource, Loss, RawFrame, decode_raw
from ficap_ros.process import freeze_start_up, keep_freed_memory
from ficap_ros.tools.worker_pool import parallel_frames
from ficap_ros.vision.calibration import HeadCalibration, frontal_from_camera_mount
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import FrameProcessor, FrameResult
from ficap_ros.vision.pose import PoseConfig
from ficap_ros.vision.shutter import TimingEvidence, combine_evidence
from ficap_ros.vision.two_sided import TwoSidedFrames

__all__ = ["Progress", "ReplayedFrame", "process_frames", "frontal_calibration",
           "ReplayOutput", "replay", "recording_timing", "check_window", "available_cores",
           "capped_jobs", "segments", "two_sided_applies", "SEGMENT_FRAMES", "MAX_WINDOW_S"]


class _SilentProgress:
    """``Progress`` turned off: what a disabled ``tqdm`` bar does (nothing; ``n`` stays 0),
    without importing tqdm (``--quiet`` runs start sooner)."""

    n = 0

    def update(self, n: int = 1) -> None:
        """Count nothing."""

    def close(self) -> None:
        """Nothing to close."""


def Progress(total: int, label: str = "frames", stream: IO[str] | None = None,  # noqa: N802
             enabled: bool = True) -> Any:
    """A ``tqdm`` bar on stderr: per-frame updates, rate and ETA (tqdm's moving average), and
    nothing at all when the stream is not a terminal (logs, CI) or ``enabled`` is False."""
    if not enabled:
        return _SilentProgress()
    from tqdm import tqdm

    return tqdm(total=max(int(total), 0) or None, desc=label, unit="frame",
                file=stream if stream is not None else sys.stderr, dynamic_ncols=True,
                smoothing=0.1, disable=None if enabled else True)


@dataclass(frozen=True)
class ReplayedFrame:
    """A frame after the pipeline: its record (compact: no image, no corners; the head pose is
    composed once its calibration is known) and the pipeline's timings.

    Attributes:
        record: the frame's record, uncalibrated (``labels.UNCALIBRATED``) until ``replay`` applies
            the run's calibration.
        detect_ms, pose_ms: pipeline timings (NaN for an undecodable image).
        timing_evidence: what the frame says of the camera's readout (``FrameResult``'s).
    """

    record: FrameRecord
    detect_ms: float = math.nan
    pose_ms: float = math.nan
    timing_evidence: TimingEvidence | None = None


# -- worker side ---------------------------------------------------------------------------------
_PROCESSOR: FrameProcessor | None = None
_DONE: Any = None  # frames finished in this pool (a shared counter), for the progress bar
_TWO_SIDED = True  # frames solved again with the next frame's pose (``vision.two_sided``)


def _init_worker(model: CapModel, pose: PoseConfig, single_thread: bool, done: Any = None,
                 detector: DetectorConfig | None = None, two_sided: bool = True) -> None:
    global _PROCESSOR, _DONE, _TWO_SIDED
    _DONE = done
    _TWO_SIDED = two_sided
    if single_thread:  # a worker process of ours (a pool's, Ray's): see keep_freed_memory
        keep_freed_memory()
        import signal

        # Ctrl-C reaches the whole process group: only the main process handles it (and stops
        # the pool), so workers print no KeyboardInterrupt tracebacks of their own.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        import cv2

        cv2.setNumThreads(1)  # N processes already use the cores; avoid oversubscription
    _PROCESSOR = FrameProcessor(model=model, detector=detector, pose=pose,
                                readout_evidence=True)
    if single_thread:
        freeze_start_up()


def _replayed(raw: RawFrame, result: FrameResult) -> ReplayedFrame:
    """A processed frame's record."""
    assert _PROCESSOR is not None and raw.camera is not None
    tags = tag_fits(result.detections, result.pose, _PROCESSOR.model, raw.camera)
    return ReplayedFrame(FrameRecord.of(result, raw.index, raw.stamp_ns, raw.frame_id,
                                        method=_PROCESSOR.pose_config.method, tags=tags),
                         result.detect_ms, result.pose_ms, result.timing_evidence)


#: Frames per tracking segment (see the module docstring): 128 frames are about 4 s at 30 fps, so
#: the segment's whole-image search costs about a 128th of a search per frame.
SEGMENT_FRAMES = 128


def _segment_frames(raws: list[RawFrame], lookahead: RawFrame | None = None) -> Iterator[ReplayedFrame]:
    """One segment's frames through the pipeline, tracking afresh from its first frame, in order
    as each is finished (``TwoSidedFrames``: a frame waits for the next one's pose); the
    ``lookahead`` frame (the next segment's first) only gives the last frame its next one."""
    assert _PROCESSOR is not None
    _PROCESSOR.reset_tracking()
    frames: TwoSidedFrames[int] = TwoSidedFrames(_PROCESSOR, enabled=_TWO_SIDED)
    done: list[ReplayedFrame | None] = [None] * len(raws)
    given = 0
    for i, raw in enumerate(raws + ([lookahead] if lookahead is not None else [])):
        try:
            image = decode_raw(raw)
            if raw.camera is None:
                raise ImageError("no camera intrinsics for this image")
            finished = frames.process(i, image, raw.camera, raw.stamp_ns)
        except ImageError as err:
            finished = []
            if i < len(raws):
                done[i] = ReplayedFrame(FrameRecord.unprocessed(
                    raw.index, raw.stamp_ns, raw.frame_id, str(err),
                    method=_PROCESSOR.pose_config.method))
        for k, result in finished:
            if k < len(raws):
                done[k] = _replayed(raws[k], result)
        while given < len(raws) and done[given] is not None:
            yield done[given]  # type: ignore[misc]
            given += 1
    for k, result in frames.finish():
        if k < len(raws):
            done[k] = _replayed(raws[k], result)
    for item in done[given:]:
        assert item is not None
        yield item


def _process_segment(raws: list[RawFrame], timing: CameraTiming | None = None,
                     lookahead: RawFrame | None = None) -> list[ReplayedFrame]:
    """One segment of a recording whose camera has ``timing`` (None: not known), tracking
    afresh from its first frame; ``lookahead``: the next segment's first frame, where frames
    are solved with their next one (``segments``)."""
    assert _PROCESSOR is not None
    _PROCESSOR.timing = timing or CameraTiming()
    out = []
    for frame in _segment_frames(raws, lookahead):
        out.append(frame)
        if _DONE is not None:
            with _DONE.get_lock():
                _DONE.value += 1
    return out


def two_sided_applies(timing: CameraTiming | None, two_sided: bool = True) -> bool:
    """Whether frames are solved with their next frame's pose: asked for, and the camera's
    timing states an exposure or a readout (only then has a frame a motion model)."""
    return two_sided and timing is not None and timing.stated


def segments(raws: Iterable[RawFrame],
             lookahead: bool) -> Iterator[tuple[list[RawFrame], RawFrame | None]]:
    """A recording's frames in tracking segments of ``SEGMENT_FRAMES``, each with its look-ahead
    (the next segment's first frame; None for the last segment, or without ``lookahead``)."""
    it = iter(raws)
    head = next(it, None)
    while head is not None:
        segment = [head, *islice(it, SEGMENT_FRAMES - 1)]
        head = next(it, None)
        yield segment, (head if lookahead else None)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which containers and taskset narrow)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


def capped_jobs(requested: int) -> tuple[int, str]:
    """``requested`` worker processes capped at the cores available, and a note when capped.

    More processes than cores only add memory (each holds a pipeline) and contention.
    """
    cores = available_cores()
    if requested > cores:
        return cores, f"--jobs {requested} capped at {cores}, the cores available"
    return max(requested, 1), ""


def process_frames(
    raws: Iterable[RawFrame], model: CapModel, pose: PoseConfig, jobs: int = 1,
    on_progress: Callable[[int], None] | None = None, detector: DetectorConfig | None = None,
    timing: CameraTiming | None = None, two_sided: bool = True,
) -> Iterator[ReplayedFrame]:
    """Run the pipeline over raw frames, in order, in ``jobs`` processes (at most one per core),
    with the camera's ``timing`` (``recording_timing``; None: not known); ``two_sided``: each
    frame solved again with the next frame's pose where its timing gives it a motion model
    (``vision.two_sided``; False: the causal model, as live).

    Undecodable frames come back with an ``UNDECODABLE`` record saying why.
    ``on_progress`` is called with the number of frames processed so far, frame by frame (with
    ``jobs > 1`` the workers count into a shared counter, read about 10 times a second while
    waiting for the next segment, so a bar moves smoothly although results come in segments).

    Raises:
        WorkerError: a worker process died twice on the same segment (``worker_pool.SegmentPool``).
    """
    jobs = capped_jobs(jobs)[0]
    it = segments(raws, two_sided_applies(timing, two_sided))
    if jobs <= 1:
        _init_worker(model, pose, single_thread=False, detector=detector, two_sided=two_sided)
        done = 0
        for segment, lookahead in it:
            assert _PROCESSOR is not None
            _PROCESSOR.timing = timing or CameraTiming()
            for frame in _segment_frames(segment, lookahead):
                yield frame
                done += 1
                if on_progress is not None:
                    on_progress(done)
        return
    import multiprocessing

    counter = multiprocessing.get_context("spawn").Value("q", 0)
    yield from parallel_frames(it, jobs, _init_worker, (model, pose, True, counter, detector, two_sided),
                               _process_segment, counter, on_progress, timing)


# -- calibration ---------------------------------------------------------------------------------
#: Latest time a window may name, s from a recording's start: decades, and in nanoseconds still
#: far inside an int64 stamp.
MAX_WINDOW_S = 1e9


def parse_window(text: str) -> tuple[float, float]:
    """``START:END`` in seconds -> (start_s, end_s); an empty START is 0, an empty END the end of
    the recording (``math.inf``). Raises ``ValueError`` with a one-line message."""
    start, sep, end = text.partition(":")
    usage = f"expected START:END in seconds (e.g. 0:3, or 2: to the end), got {text!r}"
    if not sep or not (start.strip() or end.strip()):
        raise ValueError(usage)
    try:
        s, e = float(start or 0.0), float(end) if end.strip() else math.inf
    except ValueError:
        raise ValueError(usage) from None
    if not math.isfinite(s) or (end.strip() and not math.isfinite(e)):
        raise ValueError(f"window {text!r}: START and END must be finite numbers of seconds")
    if max(s, e if end.strip() else 0.0) > MAX_WINDOW_S:
        raise ValueError(f"window {text!r}: START and END must be at most {MAX_WINDOW_S:g} s "
                         "(longer than any recording)")
    if not (s >= 0 and e > s):
        raise ValueError(f"window {text!r} must have 0 <= START < END")
    return s, e


def frontal_calibration(
    frames: list[FrameRecord], start_ns: int, window_s: tuple[float, float],
    base: HeadCalibration,
) -> tuple[HeadCalibration, dict[str, Any]]:
    """R_cap_head from the records of a frontal window (``ficap_ros.vision.calibration``'s solver).

    Raises:
        CalibrationError: too few frames with a pose in the window, or too much spread.
    """
    from scipy.spatial.transform import Rotation

    from ficap_ros.errors import CalibrationError
    from ficap_ros.stamps import window_from_start_ns
    from ficap_ros.vision.calibration import calibrate_frontal, frontal_frames

    posed = [f.pose for f in frames if f.pose is not None]
    sel = frontal_frames(np.array([f.stamp_ns for f in frames if f.pose is not None], dtype=np.int64),
                         np.array([p.reliability for p in posed], dtype=np.float64),
                         window_from_start_ns(start_ns, window_s))
    rots = [posed[i].T_cam_cap.rotation for i in sel]
    if not rots:
        raise CalibrationError(
            f"no frame with a cap pose between {window_s[0]:g} s and {window_s[1]:g} s")
    if len(rots) < 5:
        # replay asks for min(30, frames in the window), never fewer than 5; it has no --min-frames.
        raise CalibrationError(
            f"frontal calibration needs 5 frames with a cap pose, the window {window_s[0]:g}-"
            f"{window_s[1]:g} s has {len(rots)}: widen --calibrate-frontal "
            f"(or run `ficap calibrate --frontal ... --min-frames N` on the labels)")
    result = calibrate_frontal(Rotation.concatenate(rots), base.R_cam_frontal,
                               min_frames=min(30, max(len(rots), 5)))
    cal = HeadCalibration(R_cap_head=result.R_cap_head, R_cam_frontal=base.R_cam_frontal,
                          calibrated=True)
    info = {"mode": "frontal", "window_s": [window_s[0], window_s[1]],
            "frames_used": result.frames_used, "spread_deg": result.spread_deg}
    return cal, info


# -- outputs -------------------------------------------------------------------------------------
@dataclass
class ReplayOutput:
    """What ``replay`` produced."""

    records: list[FrameRecord]
    summary: dict[str, Any]
    files: list[Path] = field(default_factory=list)
    loss: Loss | None = None


def _summary(frames: list[ReplayedFrame], elapsed_s: float) -> dict:
    records = [f.record for f in frames]
    n = len(records)
    skipped = [r for r in records if r.skipped]
    decoded = n - len(skipped)
    with_pose = sum(r.T_cam_cap is not None for r in records)
    ge1 = sum(r.tags_detected >= 1 for r in records if not r.skipped)
    ge4 = sum(r.tags_detected >= 4 for r in records if not r.skipped)
    reasons = Counter(r.reason for r in skipped)
    no_pose = Counter(r.reason for r in records if r.T_cam_cap is None and not r.skipped)
    detect_ms = [f.detect_ms for f in frames if not f.record.skipped]
    pose_ms = [f.pose_ms for f in frames if not f.record.skipped]

    def pct(k: int) -> float:
        # Shares of every frame read, undecodable ones included (not of the decoded frames).
        return round(100.0 * k / n, 3) if n else 0.0

    return {
        "frames": n,
        "frames_decoded": decoded,
        "pct_decoded": pct(decoded),
        "frames_with_pose": with_pose,
        "pct_with_pose": pct(with_pose),
        "frames_no_tag": decoded - ge1,
        "frames_ge1_tag": ge1,
        "frames_ge4_tags": ge4,
        "pct_ge1_tag": pct(ge1),
        "pct_ge4_tags": pct(ge4),
        "frames_skipped": len(skipped),
        "skipped_reasons": dict(sorted(reasons.items())),
        "no_pose_reasons": dict(sorted(no_pose.items())),
        "elapsed_s": round(elapsed_s, 3),
        "throughput_fps": round(n / elapsed_s, 2) if elapsed_s > 0 else None,
        "mean_detect_ms": round(float(np.mean(detect_ms)), 3) if detect_ms else None,
        "mean_pose_ms": round(float(np.mean(pose_ms)), 3) if pose_ms else None,
        # The camera's readout read from the moving frames (signed: negative bottom to top).
        "timing_estimate": combine_evidence([f.timing_evidence for f in frames]).as_dict(),
    }


def replay(
    source: FrameSource,
    out_dir: str | Path,
    model: CapModel,
    pose: PoseConfig,
    calibration: HeadCalibration | None = None,
    calibrate_window_s: tuple[float, float] | None = None,
    jobs: int = 1,
    namespace: str = "",
    progress: bool = True,
    progress_stream: IO[str] | None = None,
    engine: Callable[[Iterable[RawFrame]], Iterable[ReplayedFrame]] | None = None,
    summary_extra: dict[str, Any] | None = None,
    detector: DetectorConfig | None = None,
    frames: OutputFrames | None = None,
    inputs: Iterable[str | Path | None] = (),
    timing: Mapping[str, Any] | None = None,
    two_sided: bool = True,
) -> ReplayOutput:
    """Process every frame of ``source`` and write labels.mcap, labels.csv, detections.csv and
    summary.json.

    The outputs are built in a temporary folder beside ``out_dir`` and replace it as a unit
    (``ficap_ros.files.OutputFolder``, checked and locked before the first frame): an error or
    Ctrl-C leaves ``out_dir`` as it was, and so does a recording that gives no usable frame. A
    damaged input yields labels for every frame before the damage; ``ReplayOutput.loss`` and
    summary.json's ``lost`` say what was lost.

    Args:
        source: the opened recording.
        out_dir: output folder (created).
        model: cap model.
        pose: pose estimator settings.
        calibration: head calibration (default: uncalibrated, camera looking forward).
        calibrate_window_s: (start, end) seconds from the first frame in which the wearer looks
            straight ahead: R_cap_head is computed from them and applied to every frame.
        jobs: worker processes (capped at the cores available).
        namespace: topic namespace of labels.mcap.
        progress: show progress on ``progress_stream`` (stderr).
        engine: what turns the raw frames into processed ones, in order (default:
            ``process_frames`` with ``jobs`` processes; ``ficap_ros.tools.fleet`` passes a Ray one).
        summary_extra: more fields for summary.json (the fleet's fingerprint).
        detector: detector settings (default ``DetectorConfig()``): ``process_frames``'s; an
            ``engine`` carries its own, and this only records them (summary.json's
            ``photometric``).
        frames: the output frames (``ficap_ros.io.frames.OutputFrames``: ``camera_mount`` and
            ``output_frame`` as the node's; default none). A mount also sets the frontal frame of
            the head angles, as the node's does.
        inputs: the run's other input files (model, calibration, intrinsics): never written.
        timing: ``CameraTiming`` fields given for the camera (the command line's), over the
            recording's own timing (``recording_timing``); summary.json's ``camera_timing``
            records the timing used and its source. An ``engine`` must process with the same
            (``recording_timing`` of the source and these fields).
        two_sided: with a timing that states an exposure or a readout, solve each frame again
            with the next frame's pose (``process_frames``; summary.json's ``motion_model``).

    Raises:
        BagError: unreadable input, or no frame of it usable. OutputError: an output that is or
        holds an input, lies in a recording, a folder ficap did not write, not writable, or
        written by another ficap process now. CalibrationError: bad frontal window.
        IntrinsicsError: a timing field out of range. WorkerError: a worker process died twice
        on one segment.
    """
    from ficap_ros.files import OutputFolder

    out = Path(out_dir)
    camera_timing = recording_timing(source, timing)  # a bad field fails before any output
    folder = OutputFolder(out, inputs=[source.path, *inputs])  # every check, and the lock
    try:
        check_window(source, calibrate_window_s)
        output = _replay_into(folder.tmp, out, source, model, pose, calibration,
                              calibrate_window_s, jobs, namespace, progress, progress_stream,
                              engine, summary_extra, detector, frames or OutputFrames(),
                              camera_timing, two_sided)
        _check_usable(source, output.summary)
    except BaseException:
        folder.discard()
        raise
    folder.commit()
    return output


def check_window(source: FrameSource, window_s: tuple[float, float] | None) -> None:
    """Refuse, before any frame is processed, a frontal window that starts after the recording
    ends (its length from the container, when it says; one second of slack for stamps).

    Raises:
        CalibrationError: naming the window and the recording's length.
    """
    from ficap_ros.errors import CalibrationError

    if window_s is None or not source.end_ns:
        return
    length_s = (source.end_ns - source.start_ns) / 1e9
    if window_s[0] > length_s + 1.0:
        raise CalibrationError(f"the frontal window {window_s[0]:g}-{window_s[1]:g} s starts after "
                               f"the recording ends ({length_s:.3f} s)")


def _check_usable(source: FrameSource, summary: dict[str, Any]) -> None:
    """Refuse to commit outputs of a recording that gave no usable frame (one line naming why)."""
    loss = source.loss
    lost = f"; {loss.describe(source.start_ns)}" if loss is not None else ""
    if summary["frames"] == 0:
        raise BagError(f"{source.path} holds no image on "
                       f"{source.image_topic or 'its video track'}{lost}")
    if not summary["frames_decoded"]:
        reasons = summary["skipped_reasons"]
        top = max(reasons, key=reasons.get) if reasons else "no image decoded"
        raise BagError(f"none of the {summary['frames']} frames of {source.path} could be used "
                       f"({top}){lost}")


def _replay_into(
    tmp: Path, out: Path, source: FrameSource, model: CapModel, pose: PoseConfig,
    calibration: HeadCalibration | None, calibrate_window_s: tuple[float, float] | None,
    jobs: int, namespace: str, progress: bool, progress_stream: IO[str] | None,
    engine: Callable[[Iterable[RawFrame]], Iterable[ReplayedFrame]] | None,
    summary_extra: dict[str, Any] | None, detector: DetectorConfig | None = None,
    frames: OutputFrames = OutputFrames(),
    camera_timing: tuple[CameraTiming, str] = (CameraTiming(), "not known"),
    two_sided: bool = True,
) -> ReplayOutput:
    jobs = capped_jobs(jobs)[0]
    timing, timing_source = camera_timing
    bar = Progress(source.count, "frames", progress_stream, enabled=progress)
    t0 = time.perf_counter()
    replayed: list[ReplayedFrame] = []
    try:
        raws = source.raw_frames()
        if engine is not None:
            for item in engine(raws):
                replayed.append(item)
                bar.update()
        else:
            replayed.extend(process_frames(raws, model, pose, jobs, detector=detector, timing=timing,
                                           on_progress=lambda n: bar.update(n - bar.n),
                                           two_sided=two_sided))
    finally:
        bar.close()
    elapsed = time.perf_counter() - t0
    cal, cal_info = _calibration(replayed, source.start_ns, calibration, calibrate_window_s,
                                 frames.mount)
    records = [f.record if f.record.calibration is cal else replace(f.record, calibration=cal)
               for f in replayed]
    loss = source.loss
    summary = {
        "writer": "ficap replay",
        "input": str(source.path),
        "image_topic": source.image_topic,
        "camera_info_topic": source.camera_info_topic,
        "method": pose.method,
        # Only when on (the default runs' summaries name no detector setting).
        **({"photometric": True} if detector is not None and detector.edge_photometric else {}),
        "jobs": jobs,
        "camera_timing": {**timing.to_dict(), "source": timing_source},
        # Only with a motion model (a timing stated): how each frame's motion was modelled.
        **({"motion_model": "two-sided" if two_sided else "causal"}
           if two_sided_applies(timing) else {}),
        **_summary(replayed, elapsed),
        # A damaged input: frames_lost is None when the container cannot say how many.
        "damaged": loss is not None,
        "frames_lost": (loss.frames_lost if loss is not None else 0),
        "lost": loss.to_dict(source.start_ns) if loss is not None else None,
        "calibration": {
            **cal_info,
            "calibrated": cal.calibrated,
            "R_cap_head_q_wxyz": [round(v, 9) for v in q_wxyz(cal.R_cap_head)],
            "R_cam_frontal_q_wxyz": [round(v, 9) for v in q_wxyz(cal.R_cam_frontal)],
        },
        # Only when set (the default runs' summaries name no frame).
        **({"output_frame": frames.output_frame} if frames.output_frame else {}),
        **({"camera_mount": [round(float(v), 9) for v in (*frames.mount.translation_m,
                                                          *frames.mount.q_xyzw)]}
           if frames.mount is not None else {}),
        **(summary_extra or {}),
    }
    write_labels_bag(tmp / "labels.mcap", records, namespace, frames)
    _write(tmp / "labels.csv", labels_csv_text(records))
    _write(tmp / "detections.csv", detections_csv_text(records))
    _write(tmp / "summary.json", json.dumps(summary, indent=2) + "\n")
    files = [out / "labels.mcap", out / "metadata.yaml", out / "labels.csv",
             out / "detections.csv", out / "summary.json"]
    return ReplayOutput(records, summary, files, loss)


def _write(path: Path, text: str) -> None:
    """One file of the (checked, temporary) output folder, atomically."""
    from ficap_ros.errors import OutputError

    try:
        write_atomic(path, text)
    except OSError as err:
        raise OutputError(f"cannot write {path.name}: {err.strerror or err}") from err


def recording_timing(source: FrameSource, given: Mapping[str, Any] | None = None,
                     ) -> tuple[CameraTiming, str]:
    """The camera timing a recording is processed with, and where it comes from (summary.json's
    ``camera_timing.source``): the ``given`` fields (``CameraTiming``'s names: the command
    line's) over the recording's own (``FrameSource.timing``: its intrinsics file's, else its
    bag's metadata), else ``CameraTiming()``, "not known".

    Raises:
        IntrinsicsError: a given field out of range.
    """
    base = source.timing or CameraTiming()
    if not given:
        return base, source.timing_source or "not known"
    origin = "command line" + (f" over {source.timing_source}" if source.timing_source else "")
    return replace(base, **dict(given)), origin


def _calibration(frames: list[ReplayedFrame], start_ns: int, given: HeadCalibration | None,
                 window_s: tuple[float, float] | None,
                 mount: Transform | None = None) -> tuple[HeadCalibration, dict[str, Any]]:
    """The run's head calibration and summary.json's account of it: the one given (or none),
    or a frontal calibration from ``window_s`` (``frontal_calibration``) over it. A camera
    ``mount`` sets the frontal frame (its parent's axes), as the node's does."""
    base = given or UNCALIBRATED
    if mount is not None:
        base = HeadCalibration(base.R_cap_head, frontal_from_camera_mount(mount), base.calibrated)
    if window_s is None:
        return base, {"mode": "file" if base.calibrated else "none"}
    return frontal_calibration([f.record for f in frames], start_ns, window_s, base)
