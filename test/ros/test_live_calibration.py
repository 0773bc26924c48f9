"""ficap_ros.ros.live_calibration: the node's calibration state, its file and ~/calibrate's
computation under the node's settings (ROS-free)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.ros.live_calibration import LiveCalibration, compute_calibration
from ficap_ros.vision.calibration import CalibrationRecorder, CalibrationResult


def test_live_calibration_frontal_frame_rule(tmp_path) -> None:
    """One rule live and offline (``calibrated_frontal``): a reference calibration's frame is the
    frontal frame without a camera mount; a mount fixes it; clearing returns to the mount's."""
    from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
    from ficap_ros.vision.calibration import frontal_from_camera_mount

    R_ref = Rotation.from_euler("ZYX", [170.0, 20.0, -5.0], degrees=True)
    result = CalibrationResult(Rotation.from_euler("x", 3.0, degrees=True), 50, 0.5, "reference",
                               R_ref)
    live = LiveCalibration()
    before = live.current
    after = live.apply(result)
    assert before is not after and not before.calibrated  # swapped whole, never mutated
    assert angle_deg(live.current.R_cam_frontal, R_ref) < 1e-9
    mount = Transform(Rotation.from_euler("y", 10.0, degrees=True) * CAM_FROM_FORWARD.inv(),
                      np.zeros(3))
    live.set_mount(mount)
    assert angle_deg(live.current.R_cam_frontal, frontal_from_camera_mount(mount)) < 1e-9
    assert angle_deg(live.current.R_cap_head, result.R_cap_head) < 1e-9
    ok, message = live.persist(tmp_path / "cal.yaml", result, "calibrated")
    assert ok and message.endswith("cal.yaml")
    cleared = live.clear()
    assert not cleared.calibrated and angle_deg(cleared.R_cam_frontal,
                                                frontal_from_camera_mount(mount)) < 1e-9
    assert LiveCalibration().load(tmp_path / "cal.yaml") == ""  # no mount: the file's frame kept


def test_live_calibration_service_outcomes(tmp_path) -> None:
    live = LiveCalibration()
    assert live.start("") == [] and live.start(tmp_path / "missing.yaml") == []

    def refuse() -> CalibrationResult:
        raise CalibrationError("no reliable frames buffered for frontal calibration")

    assert live.calibrate(refuse, "") == ("refused", "calibration refused: no reliable frames "
                                          "buffered for frontal calibration")
    R = Rotation.from_euler("xyz", [2.0, -5.0, 1.0], degrees=True)
    outcome, message = live.calibrate(lambda: CalibrationResult(R, 60, 0.3, "frontal"),
                                      tmp_path / "cal.yaml")
    assert outcome == "ok" and message.startswith("calibrated (frontal) from 60 frames")
    assert live.current.calibrated
    blocker = tmp_path / "file"
    blocker.write_text("x")
    outcome, message = live.clear_and_save(blocker / "cal.yaml")  # its folder is a file
    assert outcome == "unsaved" and "NOT updated" in message and not live.current.calibrated
    other = LiveCalibration()
    log = other.start(tmp_path / "cal.yaml")
    assert log[-1][0] == "info" and other.current.calibrated
    assert angle_deg(other.current.R_cap_head, R) < 1e-6
    (tmp_path / "bad.yaml").write_text("not: a calibration")
    assert LiveCalibration().start(tmp_path / "bad.yaml")[0][0] == "error"


def _settings(**over) -> SimpleNamespace:
    values = dict(effective_calibration_mode="frontal", calibration_window_s=3.0,
                  calibration_min_frames=5, calibration_max_spread_deg=3.0,
                  calibration_min_reliability=0.5, calibration_reference_topic="",
                  calibration_pair_tolerance_ms=5.0, calibration_min_pairs=10,
                  calibration_max_pairs=0)
    return SimpleNamespace(**{**values, **over})


def test_compute_calibration_follows_the_mode() -> None:
    """Frontal mode averages the last window's reliable frames; reference mode needs its topic."""
    rng = np.random.default_rng(4)
    R_cap_head = Rotation.from_euler("xyz", [4.0, -7.0, 2.0], degrees=True)
    R_cam_frontal = Rotation.from_euler("y", 90.0, degrees=True)
    recorder = CalibrationRecorder()
    for k in range(20):
        noise = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.2), 3))
        recorder.add_cap(k * 50_000_000, R_cam_frontal * R_cap_head.inv() * noise, 0.9)
    recorder.add_cap(20 * 50_000_000, Rotation.random(random_state=1), 0.1)  # unreliable: left out
    result = compute_calibration(_settings(), recorder, R_cam_frontal)
    assert result.mode == "frontal" and result.frames_used == 20
    assert angle_deg(result.R_cap_head, R_cap_head) < 0.2
    with pytest.raises(CalibrationError, match="needs 30 frames"):
        compute_calibration(_settings(calibration_min_frames=30), recorder, R_cam_frontal)
    with pytest.raises(CalibrationError, match="reference_topic"):
        compute_calibration(_settings(effective_calibration_mode="reference"), recorder,
                            R_cam_frontal)


def test_live_calibration_says_where_its_calibration_came_from() -> None:
    live = LiveCalibration()
    assert live.mode == "none"
