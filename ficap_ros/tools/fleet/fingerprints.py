"""What decides a recording's labels, as a fingerprint summary.json carries: the input's
identity (every byte of it, hashed), the ficap version and every label-changing setting (configs
as ``dataclasses.asdict`` JSON, files by content hash, the segment length). Outputs whose
fingerprint matches a run's are current, and that run skips them.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping

from ficap_ros import __version__
from ficap_ros.errors import BagError
from ficap_ros.files import read_bytes
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io.frames import OutputFrames
from ficap_ros.tools import replay
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import pose_config_for
from ficap_ros.vision.pose import PoseConfig

__all__ = ["OUTPUTS", "input_identity", "config_json", "label_settings", "settings_key",
           "fingerprint", "current_outputs"]

#: The outputs of one recording; summary.json is written last (a recording cut off mid-write has
#: no matching summary and is redone).
OUTPUTS = ("labels.mcap", "labels.csv", "detections.csv", "summary.json")


def _file_identity(path: Path) -> dict[str, Any]:
    """Size and SHA-256 of every byte of the file, read in a stream (a change anywhere in a
    recording, even one that keeps its size, is a new identity; docs/fleet.md: the cost)."""
    with path.open("rb") as f:
        size = os.fstat(f.fileno()).st_size
        digest = hashlib.file_digest(f, "sha256").hexdigest()
    return {"size": size, "sha256": digest}


def input_identity(path: str | Path) -> dict[str, Any]:
    """Identity of an input: name, and per file its size and the SHA-256 of its content.

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
    return hashlib.sha256(read_bytes(path, "intrinsics", BagError)).hexdigest()


def config_json(config: Any) -> Any:
    """A settings dataclass as plain JSON values (``dataclasses.asdict``; nested configs nested)."""
    return json.loads(json.dumps(asdict(config), sort_keys=True))


def label_settings(
    model: CapModel, pose: PoseConfig, calibration: HeadCalibration | None = None,
    calibrate_window_s: tuple[float, float] | None = None, namespace: str = "",
    image_topic: str | None = None, camera_info_topic: str | None = None,
    intrinsics: str | Path | None = None, fps: float | None = None, rectified: bool = False,
    detector: DetectorConfig | None = None, frames: OutputFrames | None = None,
    timing: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Every setting that changes the labels, as plain JSON values (files by content hash;
    ``timing``: camera timing fields given over the recordings' own, recorded when given).

    The pose settings are those the pipeline applies (``pipeline.pose_config_for``: an unset
    uncertainty is the corner estimator's profile), so runs whose labels agree agree here. Left
    out on purpose: ``--jobs`` and the engine (labels are identical whatever they are), progress
    and output paths.
    """
    detector = detector or DetectorConfig()
    cal = calibration or HeadCalibration()
    return {
        "model_sha256": hashlib.sha256(
            repr(model.ids).encode() + model.corners_mm.astype("<f8").tobytes()).hexdigest(),
        "pose": config_json(pose_config_for(pose, detector)),
        "detector": config_json(detector),
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
        "rectified": bool(rectified),
        "segment_frames": replay.SEGMENT_FRAMES,
        **_frames_json(frames),
        **({"camera_timing": dict(sorted(timing.items()))} if timing else {}),
    }


def _frames_json(frames: OutputFrames | None) -> dict[str, Any]:
    """The output frames' settings, only when set (a run without them keeps its fingerprint)."""
    if frames is None or (not frames.output_frame and frames.mount is None):
        return {}
    mount = frames.mount
    return {"frames": {"output_frame": frames.output_frame, "camera_mount": None if mount is None
                       else [round(float(v), 12) for v in (*mount.translation_m, *mount.q_xyzw)]}}


def settings_key(model: CapModel, pose: PoseConfig, detector: DetectorConfig | None) -> tuple[int, str, str]:
    """What a pipeline labels with (the pose as applied to the detector's corners): a Ray worker
    re-initialises when it changes, and ``run_fleet`` refuses a given engine started with another."""
    detector = detector or DetectorConfig()
    return (hash(model), json.dumps(config_json(pose_config_for(pose, detector)), sort_keys=True),
            json.dumps(config_json(detector), sort_keys=True))


def fingerprint(path: str | Path, settings: dict[str, Any]) -> dict[str, Any]:
    """The fingerprint summary.json carries: identity, version, settings and their sha256."""
    body = {"ficap_version": __version__, "input": input_identity(path), "settings": settings}
    digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    return {"sha256": digest, **body}


def current_outputs(out_dir: Path, digest: str) -> dict[str, Any] | None:
    """The summary of outputs in ``out_dir`` made with fingerprint ``digest``, or None."""
    if not all((out_dir / name).is_file() for name in OUTPUTS):
        return None
    try:
        summary = json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    fp = summary.get("fingerprint") if isinstance(summary, dict) else None
    return summary if isinstance(fp, dict) and fp.get("sha256") == digest else None
