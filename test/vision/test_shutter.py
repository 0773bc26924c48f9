"""A camera's readout read from its frames: the shear a rolling shutter leaves in a static fit's
residuals, per frame and combined (corners of a moving cap projected row by row,
test/helpers/rolling_shutter.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rolling_shutter import constant_velocity, detections, facing_ids, rolling_corners
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.motion import MotionPrior, PastPose
from ficap_ros.vision.pose import estimate_cap_pose
from ficap_ros.vision.reprojection import TagObservations, undistorted_corners
from ficap_ros.vision.shutter import (
    TimingEvidence,
    _corner_velocity_px_s,
    combine_evidence,
    frame_evidence,
    speed_bound_px_s,
)

MODEL = nominal_model()
CAMERA = CameraModel.pinhole(960, 540, hfov_deg=67.4)
T0 = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", [-15.0, 4.0, 0.0], degrees=True),
               [0.0, -0.01, 0.75])
GLANCE = np.array([0.04, 0.0, 0.1, 0.05, np.radians(180.0), 0.05])


def _evidence(timing: CameraTiming, twist: np.ndarray, noise_px: float = 0.0, seed: int = 0):
    """The readout evidence of one frame of a cap moving at ``twist`` seen through ``timing``,
    fitted as a global shutter with the velocity from exact past poses."""
    pose_at = constant_velocity(T0, twist)
    corners = rolling_corners(MODEL, CAMERA, pose_at, timing, facing_ids(MODEL, T0))
    dets = detections(corners, np.random.default_rng(seed), noise_px)
    past = tuple(PastPose(a, pose_at(-a), np.eye(6) * 1e-12) for a in (1 / 30, 2 / 30))
    pose = estimate_cap_pose(dets, MODEL, CAMERA, prior=MotionPrior(past)).pose
    used = [d for d in dets if d.tag_id in pose.used_ids]
    obs = TagObservations.of({i: c[0] for i, c in undistorted_corners(used, CAMERA).items()},
                             MODEL, CAMERA.K)
    rows = np.concatenate([next(d for d in used if d.tag_id == i).corners_px[:, 1] for i in obs.ids])
    return frame_evidence(obs, pose.T_cam_cap, pose.velocity, CAMERA, rows)


@pytest.mark.parametrize("order, sign", [("top_to_bottom", 1.0), ("bottom_to_top", -1.0)])
def test_a_moving_frame_gives_the_readout_and_its_row_order(order: str, sign: float) -> None:
    """Noise-free corners of a 180 deg/s turn read over 25 ms: the readout comes back within a
    few per cent, signed by the row order."""
    e = _evidence(CameraTiming(readout_ms=25.0, row_order=order), GLANCE)
    assert e is not None and e.exposure2_s2 is None
    assert abs(e.readout_s - sign * 0.025) < 0.002


def test_a_global_shutter_gives_no_readout_within_its_error() -> None:
    """Noisy corners of a global shutter: the readout is zero within three standard errors, and
    those errors are a few milliseconds at most."""
    for seed in range(4):
        e = _evidence(CameraTiming(), GLANCE, noise_px=0.1, seed=seed)
        se = math.sqrt(e.readout_var_s2)
        assert se < 0.01 and abs(e.readout_s) < 3.0 * se


def test_a_still_cap_says_nothing() -> None:
    assert _evidence(CameraTiming(readout_ms=25.0), np.zeros(6)) is None


@pytest.mark.parametrize("seed", range(20))
def test_the_speed_bound_holds_and_is_near_the_speed(seed: int) -> None:
    """``speed_bound_px_s`` is at least every corner's central-difference speed (what lets a
    slow frame skip it), and within an order of magnitude of the fastest, for random turns and
    shifts of the cap from still to fast (up to 0.5 m/s, 400 deg/s)."""
    rng = np.random.default_rng(seed)
    T = Transform(CAM_FROM_FORWARD * Rotation.from_rotvec(rng.normal(0.0, 0.3, 3)),
                  [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.4, 1.0)])
    ids = facing_ids(MODEL, T)
    obs = TagObservations.of({i: np.zeros((4, 2)) for i in ids}, MODEL, CAMERA.K)
    velocity = np.concatenate([rng.normal(0.0, 0.5, 3), rng.normal(0.0, 7.0, 3)]) * rng.uniform(0.0, 1.0)
    speed = float(np.linalg.norm(_corner_velocity_px_s(obs, T, velocity), axis=1).max())
    bound = speed_bound_px_s(obs, T, velocity)
    assert speed <= bound <= 10.0 * speed + 1e-9


def test_frames_combine_by_their_information() -> None:
    """Inverse-variance mean; frames without evidence count for nothing; the standard error grows
    with the frames' scatter beyond their variances; none at all: no estimate."""
    est = combine_evidence([TimingEvidence(0.020, 1e-6), None, TimingEvidence(0.030, 4e-6)])
    assert est.readout_ms == pytest.approx(1e3 * (0.020 / 1e-6 + 0.030 / 4e-6) / (1 / 1e-6 + 1 / 4e-6))
    assert est.readout_frames == 2 and est.exposure_ms is None and est.exposure_frames == 0
    assert est.readout_se_ms > 1e3 * math.sqrt(1 / (1 / 1e-6 + 1 / 4e-6))  # scattered: widened
    empty = combine_evidence([None, None])
    assert empty.readout_ms is None and empty.as_dict()["readout_frames"] == 0
    squares = combine_evidence([TimingEvidence(exposure2_s2=1e-4, exposure2_var_s4=1e-12)] * 3)
    assert squares.exposure_ms == pytest.approx(10.0) and squares.exposure_frames == 3
