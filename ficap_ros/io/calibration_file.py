"""Calibration files: a ``HeadCalibration`` (and how it was computed) as YAML, written under the
output rule (``ficap_ros.files.OutputFile``) and read back through the guarded loader
(``files.load_yaml``). Quaternions are ``q_wxyz`` (w, x, y, z), unit length
(``transform.unit_quaternion``); the format is named in the file (``CALIBRATION_FORMAT``). The
calibration itself (solvers, ``HeadCalibration``) is ``ficap_ros.vision.calibration``'s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError, OutputError
from ficap_ros.files import OutputFile, load_yaml
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, unit_quaternion
from ficap_ros.vision.calibration import CalibrationResult, HeadCalibration

__all__ = ["CALIBRATION_FORMAT", "calibration_output", "save_calibration", "load_calibration",
           "q_wxyz"]

#: Name and version written into calibration files.
CALIBRATION_FORMAT = "ficap_calibration/1"


def q_wxyz(rotation: Rotation) -> list[float]:
    """A rotation as the files write it: a unit quaternion (w, x, y, z), w >= 0, as floats."""
    x, y, z, w = rotation.as_quat(canonical=True)
    return [float(w), float(x), float(y), float(z)]


def _from_q_wxyz(values: Any, path: str | Path, name: str) -> Rotation:
    return unit_quaternion(values, f"calibration {path}: field {name} (w, x, y, z)", "wxyz",
                           CalibrationError)


def _not_a_calibration(path: Path) -> str:
    """Why the file at ``path`` must not be replaced by a calibration ('' when it is one)."""
    try:
        load_calibration(path)
    except CalibrationError as err:
        return f"a readable calibration ({err})"
    return ""


def calibration_output(path: str | Path, inputs: tuple[Any, ...] = ()) -> OutputFile:
    """The calibration file a verb will write, checked and locked before it computes anything
    (``files.OutputFile``; an existing file must be a calibration)."""
    return OutputFile(path, inputs, "calibration", replaceable=_not_a_calibration)


def save_calibration(
    path: str | Path | OutputFile,
    calibration: HeadCalibration | CalibrationResult,
    result: CalibrationResult | None = None,
    R_cam_frontal: Rotation | None = None,
    inputs: tuple[str | Path, ...] = (),
) -> None:
    """Write a calibration as YAML, atomically. Quaternions are ``q_wxyz`` (w, x, y, z).

    Args:
        path: output file, or the ``calibration_output`` taken when the verb started.
        calibration: the runtime calibration, or a result (then ``R_cam_frontal`` gives the frontal
            frame, default ``CAM_FROM_FORWARD``).
        result: how it was computed (mode, frames used, spread, R_cam_reference), when known.
        R_cam_frontal: frontal frame for a ``CalibrationResult`` argument.
        inputs: what it was computed from (never overwritten).

    Raises:
        OutputError: ``path`` breaks the output rule (``files.check_output_file``), is an existing
            file that is not a calibration, or cannot be written (one line).
    """
    if isinstance(calibration, CalibrationResult):
        result = calibration
        calibration = HeadCalibration(
            R_cap_head=calibration.R_cap_head,
            R_cam_frontal=R_cam_frontal if R_cam_frontal is not None else CAM_FROM_FORWARD,
            calibrated=True,
        )
    data: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "quaternion_order": "wxyz",
        "calibrated": bool(calibration.calibrated),
        "R_cap_head_q_wxyz": q_wxyz(calibration.R_cap_head),
        "R_cam_frontal_q_wxyz": q_wxyz(calibration.R_cam_frontal),
    }
    if result is not None:
        data["mode"] = result.mode
        data["frames_used"] = int(result.frames_used)
        data["spread_deg"] = float(result.spread_deg)
        if result.R_cam_reference is not None:
            data["R_cam_reference_q_wxyz"] = q_wxyz(result.R_cam_reference)
    text = yaml.safe_dump(data, sort_keys=False)
    if isinstance(path, OutputFile):
        path.write(text)
        return
    path = Path(path)
    if str(path.parent) and not path.parent.exists():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"cannot create folder {path.parent}: {err.strerror or err}") from err
    # Only a calibration replaces a calibration: an unreadable or foreign file at this path (a
    # typo in calibration.file, a binary) is the user's, not ours to overwrite.
    with calibration_output(path, inputs) as out:
        out.write(text)


def load_calibration(path: str | Path) -> HeadCalibration:
    """Read a calibration file written by ``save_calibration`` (the guarded loader: a regular
    file of at most ``files.MAX_CONFIG_BYTES``, YAML without aliases; unit quaternions).

    Raises:
        CalibrationError: missing, unreadable or malformed file, naming the file and the field.
    """
    data = load_yaml(path, "calibration", CalibrationError)
    if not isinstance(data, dict) or "R_cap_head_q_wxyz" not in data:
        raise CalibrationError(f"calibration {path} has no R_cap_head_q_wxyz")
    if str(data.get("quaternion_order", "wxyz")) != "wxyz":
        raise CalibrationError(f"calibration {path}: quaternion_order must be wxyz")
    R_cam_frontal = (
        _from_q_wxyz(data["R_cam_frontal_q_wxyz"], path, "R_cam_frontal_q_wxyz")
        if "R_cam_frontal_q_wxyz" in data else CAM_FROM_FORWARD
    )
    return HeadCalibration(
        R_cap_head=_from_q_wxyz(data["R_cap_head_q_wxyz"], path, "R_cap_head_q_wxyz"),
        R_cam_frontal=R_cam_frontal,
        calibrated=_flag(data.get("calibrated", True), f"calibration {path}: calibrated"),
    )


def _flag(value: Any, name: str) -> bool:
    """A YAML boolean; the strings a hand-edited file may hold ("no", "false", "0") too (where
    ``bool("no")`` would be True)."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    text = str(value).strip().lower()
    if text in ("true", "yes", "on", "1"):
        return True
    if text in ("false", "no", "off", "0"):
        return False
    raise CalibrationError(f"{name} must be true or false, got {value!r}")
