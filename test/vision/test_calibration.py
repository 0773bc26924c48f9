"""Cap-to-head calibration on synthetic rotations with known truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError
from ficap_ros.geometry.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.calibration import (
    CalibrationRecorder,
    calibrate_frontal,
    calibrate_reference,
    frontal_from_camera_mount,
    reference_pairs,
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


def _noise(rng: np.random.Generator, n: int, sigma_deg: float) -> Rotation:
    """Per-axis Gaussian rotation noise, sigma in degrees."""
    return Rotation.from_rotvec(rng.normal(0.0, np.radians(sigma_deg), size=(n, 3)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frontal_recovers_cap_to_head(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R_cap_head = Rotation.random(random_state=seed)
    R_cam_frontal = frontal_from_camera_mount(_mount(pitch_down_deg=10.0))
    n = 90
    # The wearer looks "straight ahead" with ~1 deg of natural wobble per axis, and the cap
    # estimate adds 0.5 deg more; 10 % of the frames are gross glances elsewhere.
    R_frontal_head = _noise(rng, n, 1.0)
    glances = rng.random(n) < 0.1
    R_frontal_head = Rotation.from_rotvec(
        np.where(glances[:, None], rng.normal(0, np.radians(25), (n, 3)), R_frontal_head.as_rotvec())
    )
    R_cam_cap = R_cam_frontal * R_frontal_head * R_cap_head.inv() * _noise(rng, n, 0.5)
    res = calibrate_frontal(R_cam_cap, R_cam_frontal)
    assert res.mode == "frontal" and res.R_cam_reference is None
    assert angle_deg(res.R_cap_head, R_cap_head) < 0.5
    assert res.frames_used >= int(0.8 * n)
    assert 0.5 < res.spread_deg < 3.0


def test_frontal_refuses_too_few_frames() -> None:
    r = Rotation.random(5, random_state=3)
    with pytest.raises(CalibrationError, match="needs 30 frames"):
        calibrate_frontal(r, CAM_FROM_FORWARD)


def test_frontal_refuses_large_spread() -> None:
    rng = np.random.default_rng(4)
    R_cam_cap = CAM_FROM_FORWARD * _noise(rng, 60, 8.0)  # the head roams: not a frontal segment
    with pytest.raises(CalibrationError, match="spread"):
        calibrate_frontal(R_cam_cap, CAM_FROM_FORWARD, max_spread_deg=3.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_reference_recovers_both_rotations(seed: int) -> None:
    rng = np.random.default_rng(10 + seed)
    R_cap_head = Rotation.random(random_state=20 + seed)
    R_cam_ref = Rotation.random(random_state=30 + seed)
    n = 300
    # Naturalistic head motion: yaw +-40, pitch +-15, roll +-8 deg.
    ypr = rng.uniform([-40, -15, -8], [40, 15, 8], size=(n, 3))
    # (Pitch drawn with the opposite sign: the calibration does not depend on it.)
    R_ref_head_true = Rotation.concatenate([rotation_from_ypr_deg(a[0], -a[1], a[2]) for a in ypr])
    R_cam_cap = R_cam_ref * R_ref_head_true * R_cap_head.inv() * _noise(rng, n, 0.3)
    R_ref_head = R_ref_head_true * _noise(rng, n, 2.0)  # 2 deg per axis reference noise
    res = calibrate_reference(R_cam_cap, R_ref_head)
    assert res.mode == "reference"
    assert angle_deg(res.R_cap_head, R_cap_head) < 1.0
    assert angle_deg(res.R_cam_reference, R_cam_ref) < 1.0
    # 2 deg per axis gives a ~3.5 deg RMS geodesic residual.
    assert 2.0 < res.spread_deg < 5.0
    # The predicted 1-sigma error is of the size of the actual error (not 10x off either way).
    assert 0.05 < res.uncertainty_deg < 1.0


def test_reference_refuses_too_few_pairs_and_no_motion() -> None:
    r = Rotation.random(5, random_state=1)
    with pytest.raises(CalibrationError, match="needs 10 pairs"):
        calibrate_reference(r, r)
    with pytest.raises(CalibrationError, match="paired"):
        calibrate_reference(Rotation.random(20, random_state=1), Rotation.random(12, random_state=2))
    rng = np.random.default_rng(5)
    still = _noise(rng, 50, 0.2)
    with pytest.raises(CalibrationError, match="two axes"):
        calibrate_reference(still, still)


def test_frontal_frame_from_camera_mount_axes() -> None:
    assert angle_deg(frontal_from_camera_mount(None), CAM_FROM_FORWARD) < 1e-9
    assert angle_deg(frontal_from_camera_mount(_mount()), CAM_FROM_FORWARD) < 1e-9
    # Camera pitched down 10 deg: the horizontal forward direction appears above the optical axis
    # (negative optical y), 10 deg off it.
    fwd_cam = frontal_from_camera_mount(_mount(pitch_down_deg=10.0)).apply([1.0, 0.0, 0.0])
    assert fwd_cam[1] < 0
    assert np.degrees(np.arccos(fwd_cam[2])) == pytest.approx(10.0, abs=1e-9)
    # Camera yawed to the left: vehicle forward appears to the right of the image centre (+x).
    fwd_cam = frontal_from_camera_mount(_mount(yaw_left_deg=15.0)).apply([1.0, 0.0, 0.0])
    assert fwd_cam[0] > 0 and np.degrees(np.arctan2(fwd_cam[0], fwd_cam[2])) == pytest.approx(15.0)


T0 = 10**9
DT = 33_333_333


def test_recorder_pairs_one_to_one_as_the_cli() -> None:
    """References at twice the camera rate: each cap pose pairs with one reference (the nearest),
    in the recorder (live) exactly as in ``reference_pairs`` (``ficap calibrate``)."""
    rng = np.random.default_rng(3)
    cap_ns = T0 + np.arange(40) * DT
    ref_ns = T0 + np.arange(80) * 16_666_667 + 1_000_000
    R_cap = Rotation.from_rotvec(rng.normal(0, 0.3, (40, 3)))
    R_ref = Rotation.from_rotvec(rng.normal(0, 0.3, (80, 3)))
    rec = CalibrationRecorder()
    for s, r in zip(cap_ns, R_cap):
        rec.add_cap(int(s), r, 1.0)
    for s, r in zip(ref_ns, R_ref):
        rec.add_reference(int(s), r.as_quat())
    i_cap, i_ref = reference_pairs(cap_ns, ref_ns, 20_000_000)
    assert i_cap.size == 40 and len(set(i_ref.tolist())) == 40  # one-to-one
    assert np.abs(ref_ns[i_ref] - cap_ns[i_cap]).max() < 1_000_100  # the nearest, 1 ms late
    q_cap, q_ref = rec.pairs(20_000_000)
    assert np.array_equal(q_cap, R_cap[i_cap].as_quat())
    assert np.array_equal(q_ref, R_ref[i_ref].as_quat())
    q_cap, _ = rec.pairs(20_000_000, max_pairs=7)
    assert len(q_cap) == 7
