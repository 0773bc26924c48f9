"""ficap_ros.io.calibration_file: calibrations written as YAML and read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError, OutputError
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.calibration_file import (
    CALIBRATION_FORMAT,
    load_calibration,
    q_wxyz,
    save_calibration,
)
from ficap_ros.vision.calibration import (
    CalibrationResult,
    HeadCalibration,
    frontal_from_camera_mount,
)


def _mount(pitch_down_deg: float = 0.0, yaw_left_deg: float = 0.0) -> Transform:
    """camera_mount of a camera behind the wearer looking forward, pitched down and yawed left:
    built from its axes in base_link (x forward, y left, z up), not from Euler angles."""
    p, y = np.radians(pitch_down_deg), np.radians(yaw_left_deg)
    z_cam = np.array([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), -np.sin(p)])  # optical axis
    x_cam = np.array([np.sin(y), -np.cos(y), 0.0])  # image right
    y_cam = np.cross(z_cam, x_cam)  # image down
    R = np.column_stack([x_cam, y_cam, z_cam])
    assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) > 0
    return Transform(Rotation.from_matrix(R), [-0.6, 0.0, 1.2])


def test_save_load_round_trip(tmp_path) -> None:
    R_cap_head = Rotation.random(random_state=7)
    R_cam_frontal = frontal_from_camera_mount(_mount(pitch_down_deg=5.0))
    res = CalibrationResult(R_cap_head, 42, 1.25, "reference", Rotation.random(random_state=8))
    path = tmp_path / "sub" / "calib.yaml"
    save_calibration(path, res, R_cam_frontal=R_cam_frontal)
    text = path.read_text()
    assert "quaternion_order: wxyz" in text and "R_cam_reference_q_wxyz" in text
    loaded = load_calibration(path)
    assert loaded.calibrated
    assert angle_deg(loaded.R_cap_head, R_cap_head) < 1e-6
    assert angle_deg(loaded.R_cam_frontal, R_cam_frontal) < 1e-6
    save_calibration(path, HeadCalibration())
    assert not load_calibration(path).calibrated
    assert list(path.parent.iterdir()) == [path]  # no temporary files left behind


def test_load_refuses_bad_files(tmp_path) -> None:
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("R_cap_head_q_wxyz: [0, 0, 0, 0]\n")
    with pytest.raises(CalibrationError, match=r"R_cap_head_q_wxyz \(w, x, y, z\) must be of unit"):
        load_calibration(bad)
    bad.write_text("just: text\n")
    with pytest.raises(CalibrationError, match="R_cap_head_q_wxyz"):
        load_calibration(bad)


_unit_quaternions = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1)


@settings(max_examples=60, deadline=None)
@given(q_head=_unit_quaternions, q_frontal=_unit_quaternions, calibrated=st.booleans())
def test_save_then_load_is_the_calibration(tmp_path_factory, q_head, q_frontal, calibrated) -> None:
    """Any calibration saved and loaded back is the same rotations (to the file's float text,
    exact to 1e-12 rad) and the same flag; its quaternions are written w >= 0."""
    cal = HeadCalibration(Rotation.from_quat(q_head), Rotation.from_quat(q_frontal), calibrated)
    path = tmp_path_factory.mktemp("cal") / "calibration.yaml"
    save_calibration(path, cal)
    loaded = load_calibration(path)
    assert loaded.calibrated is calibrated
    assert angle_deg(loaded.R_cap_head, cal.R_cap_head) < 1e-9
    assert angle_deg(loaded.R_cam_frontal, cal.R_cam_frontal) < 1e-9
    text = path.read_text()
    assert f"format: {CALIBRATION_FORMAT}" in text
    for rot in (cal.R_cap_head, cal.R_cam_frontal):
        w, x, y, z = q_wxyz(rot)
        assert w >= 0 and abs(np.hypot(np.hypot(w, x), np.hypot(y, z)) - 1.0) < 1e-12


def test_a_file_that_is_not_a_calibration_is_never_replaced(tmp_path) -> None:
    foreign = tmp_path / "notes.yaml"
    foreign.write_text("shopping: [milk]\n")
    with pytest.raises(OutputError, match="not overwritten"):
        save_calibration(foreign, HeadCalibration())
    assert foreign.read_text() == "shopping: [milk]\n"


def test_calibrated_no_loads_as_uncalibrated(tmp_path: Path) -> None:
    path = tmp_path / "cal.yaml"
    for text, expected in (('"no"', False), ("false", False), ('"yes"', True), ("true", True)):
        path.write_text(f"R_cap_head_q_wxyz: [1, 0, 0, 0]\ncalibrated: {text}\n")
        assert load_calibration(path).calibrated is expected
    path.write_text("R_cap_head_q_wxyz: [1, 0, 0, 0]\ncalibrated: maybe\n")
    with pytest.raises(CalibrationError, match="true or false"):
        load_calibration(path)


def test_save_calibration_never_replaces_a_foreign_file(binary_files: dict[str, Path],
                                                        tmp_path: Path) -> None:
    before = binary_files["bin"].read_bytes()
    with pytest.raises(OutputError, match="not overwritten"):
        save_calibration(binary_files["bin"], HeadCalibration())
    assert binary_files["bin"].read_bytes() == before
    with pytest.raises(OutputError):
        save_calibration(tmp_path, HeadCalibration())  # a folder
    good = tmp_path / "cal.yaml"
    save_calibration(good, HeadCalibration())
    save_calibration(good, HeadCalibration())  # a calibration replaces a calibration
