"""The live node's head calibration: the one in use (swapped whole under a lock), the recorder it
is computed from, what ``~/calibrate`` computes under the node's settings, and its file
(``calibration.file``: loaded at start, written by the services). ROS-free: the node only calls it.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Callable

from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError, FicapError
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.calibration_file import load_calibration, save_calibration
from ficap_ros.vision.calibration import (
    CalibrationRecorder,
    CalibrationResult,
    HeadCalibration,
    calibrated_frontal,
    frontal_from_camera_mount,
)

__all__ = ["LiveCalibration", "compute_calibration"]


def compute_calibration(config: Any, recorder: CalibrationRecorder,
                        R_cam_frontal: Rotation) -> CalibrationResult:
    """What ``~/calibrate`` computes under the node's settings (``ros.params.NodeConfig``: its
    ``effective_calibration_mode`` and ``calibration_*`` values) from ``recorder``'s buffers;
    ``R_cam_frontal`` is the frontal frame a frontal calibration keeps.

    Raises:
        CalibrationError: too few frames or pairs, too much spread, or reference mode without a
            reference topic.
    """
    if config.effective_calibration_mode == "frontal":
        return recorder.frontal(config.calibration_window_s, R_cam_frontal,
                                min_frames=config.calibration_min_frames,
                                max_spread_deg=config.calibration_max_spread_deg,
                                min_reliability=config.calibration_min_reliability)
    if not config.calibration_reference_topic:
        raise CalibrationError("reference mode needs calibration.reference_topic")
    return recorder.reference(int(config.calibration_pair_tolerance_ms * 1e6),
                              min_pairs=config.calibration_min_pairs,
                              max_pairs=config.calibration_max_pairs)


class LiveCalibration:
    """The calibration a live node uses, swapped whole (``HeadCalibration`` is immutable) under a
    lock, and the recorder it is computed from. Readers take ``current`` once per frame.

    Args:
        mount: the ``camera_mount`` transform (T_parent_cam), or None.
    """

    def __init__(self, mount: Transform | None = None) -> None:
        self._lock = threading.Lock()
        self._mount = mount
        self._current = HeadCalibration(R_cam_frontal=frontal_from_camera_mount(mount))
        self.last_result: CalibrationResult | None = None
        self.recorder = CalibrationRecorder()

    @property
    def current(self) -> HeadCalibration:
        return self._current

    def load(self, path: str | Path) -> str:
        """Use a calibration file; returns a warning ('' when none). The file's frontal frame is
        kept (as ``replay --calibration`` does) unless a mount sets one.

        Raises:
            CalibrationError: unreadable file.
        """
        loaded = load_calibration(path)
        with self._lock:
            R_cam_frontal = loaded.R_cam_frontal if self._mount is None else \
                frontal_from_camera_mount(self._mount)
            self._current = HeadCalibration(loaded.R_cap_head, R_cam_frontal, loaded.calibrated)
        off = angle_deg(loaded.R_cam_frontal, R_cam_frontal)
        if loaded.calibrated and off > 0.01:
            return (f"calibration {path} was made with a frontal frame {off:.2f} deg from the "
                    "current camera_mount parameter; head angles keep the current frontal frame")
        return ""

    def apply(self, result: CalibrationResult) -> HeadCalibration:
        """Use a computed calibration (frontal frame: ``calibrated_frontal``)."""
        with self._lock:
            self._current = HeadCalibration(result.R_cap_head,
                                            calibrated_frontal(result, self._mount), True)
            self.last_result = result
            return self._current

    def clear(self) -> HeadCalibration:
        with self._lock:
            self._current = HeadCalibration(R_cam_frontal=frontal_from_camera_mount(self._mount))
            self.last_result = None
            return self._current

    def set_mount(self, mount: Transform | None) -> None:
        """A new ``camera_mount``: the frontal frame follows it (R_cap_head stays)."""
        with self._lock:
            self._mount = mount
            old = self._current
            R = calibrated_frontal(self.last_result if old.calibrated else None, mount)
            if angle_deg(old.R_cam_frontal, R) > 1e-9:
                self._current = HeadCalibration(old.R_cap_head, R, old.calibrated)

    def frontal_frame(self) -> Rotation:
        """The frontal frame a new calibration is computed in (the mount's)."""
        return calibrated_frontal(None, self._mount)

    @property
    def mode(self) -> str:
        """How the current calibration came: the last computed one's mode (frontal, reference),
        ``loaded`` (from a file) or ``none`` (/diagnostics says it)."""
        last = self.last_result
        return last.mode if last else ("loaded" if self._current.calibrated else "none")

    def persist(self, path: str | Path, result: CalibrationResult | None,
                message: str) -> tuple[bool, str]:
        """Save the current calibration to ``path`` ('' = not persisted): (success, message). A
        calibration in use but not saved is a failure (lost at the next start: the caller must
        know); ``save_calibration`` never replaces a file that is not a calibration, and no
        folder is made for it."""
        if not path:
            return True, message
        what = "; in use but NOT saved" if result else f" in memory; {path} NOT updated"
        if not Path(path).parent.is_dir():  # never a new folder tree from a typo in the path
            return False, f"{message}{what}: folder {Path(path).parent} does not exist"
        try:
            save_calibration(path, self._current, result)
        except (OSError, FicapError) as err:
            return False, f"{message}{what}: {err}"
        return True, message + (f", saved to {path}" if result else "")

    def start(self, path: str | Path) -> list[tuple[str, str]]:
        """Load ``path`` at start when it exists ('' = none): what to log, (severity, text)."""
        if not path or not Path(path).exists():
            return []
        try:
            warning = self.load(path)
        except CalibrationError as err:
            return [("error", f"{err}; starting uncalibrated")]
        return ([("warning", warning)] if warning else []) + [
            ("info", f"loaded calibration {path} (calibrated: {self._current.calibrated})")]

    def calibrate(self, compute: Callable[[], CalibrationResult],
                  path: str | Path) -> tuple[str, str]:
        """``~/calibrate``: compute, use, save to ``path``. Returns (outcome, message), outcome
        ``refused`` (nothing changed), ``unsaved`` (in use, not saved) or ``ok``."""
        try:
            result = compute()
        except CalibrationError as err:
            return "refused", f"calibration refused: {err}"
        self.apply(result)
        ok, message = self.persist(path, result, (
            f"calibrated ({result.mode}) from {result.frames_used} frames, spread "
            f"{result.spread_deg:.2f} deg, uncertainty {result.uncertainty_deg:.2f} deg"))
        return ("ok" if ok else "unsaved"), message

    def clear_and_save(self, path: str | Path) -> tuple[str, str]:
        """``~/clear_calibration``: (outcome, message) as ``calibrate``'s. Without a calibration in
        use and without a file at ``path`` there is nothing to clear and no file is written."""
        if not self._current.calibrated and not (path and Path(path).exists()):
            return "ok", "not calibrated: nothing to clear" + (f", {path} not written" if path else "")
        self.clear()
        ok, message = self.persist(path, None, "calibration cleared")
        return ("ok" if ok else "unsaved"), message
