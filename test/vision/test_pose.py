"""Pose estimators on exactly projected corners with seeded noise (rendered frames: test_accuracy.py),
and the joint pose's least-squares refinement (``pose._refine``, MINPACK's Levenberg-Marquardt): it
reaches the reprojection minimum from near and far starts, as ``least_squares(method="lm")`` does."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pose import (
    PoseConfig,
    _refine,
    _rodrigues,
    _turned_residuals_and_jacobian,
    estimate_cap_pose,
)
from ficap_ros.vision.reprojection import TagObservations, residuals_and_jacobian

MODEL = nominal_model()
CAMERA = CameraModel.pinhole(960, 540, hfov_deg=60.0)


def _pose(rng: np.random.Generator) -> Transform:
    ypr = rng.uniform(-1, 1, 3) * [45.0, 20.0, 10.0]
    R = CAM_FROM_FORWARD * Rotation.from_euler("ZYX", ypr, degrees=True)
    return Transform(R, [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.5])


def _detections(T: Transform, rng: np.random.Generator, noise_px: float,
                camera: CameraModel = CAMERA) -> list[TagDetection]:
    n = T.rotation.apply(MODEL.normals)
    c = T.apply(MODEL.centres_mm / 1000.0)
    facing = np.sum(n * c, axis=1) < -0.2 * np.linalg.norm(c, axis=1)
    return [
        TagDetection(tag_id, camera.project(T.apply(MODEL.corners_of(tag_id) / 1000.0))
                     + rng.normal(0.0, noise_px, (4, 2)))
        for tag_id in np.asarray(MODEL.ids)[facing]
    ]


def _errors(method: str, noise_px: float, n: int = 40, seed: int = 1, **kw) -> np.ndarray:
    rng = np.random.default_rng(seed)
    errs = []
    for _ in range(n):
        T = _pose(rng)
        result = estimate_cap_pose(_detections(T, rng, noise_px), MODEL, CAMERA, PoseConfig(method=method, **kw))
        errs.append(angle_deg(result.pose.T_cam_cap.rotation, T.rotation) if result.ok else np.inf)
    return np.array(errs)


@pytest.mark.parametrize("method", ["joint", "paper", "naive"])
def test_exact_corners_give_exact_pose(method: str) -> None:
    rng = np.random.default_rng(3)
    T = _pose(rng)
    result = estimate_cap_pose(_detections(T, rng, 0.0), MODEL, CAMERA, PoseConfig(method=method))
    assert result.ok, result.reason
    assert angle_deg(result.pose.T_cam_cap.rotation, T.rotation) < 1e-5
    np.testing.assert_allclose(result.pose.T_cam_cap.translation_m, T.translation_m, atol=1e-7)
    assert result.pose.rms_px < 1e-4


def test_joint_beats_paper_under_noise() -> None:
    joint = _errors("joint", 0.3)
    paper = _errors("paper", 0.3)
    assert np.all(np.isfinite(joint)) and np.all(np.isfinite(paper))
    assert np.median(joint) < 0.5 * np.median(paper)


def test_spurious_tag_is_rejected() -> None:
    """A real id's corners pasted elsewhere, as a duplicate and as the only copy of that id."""
    rng = np.random.default_rng(5)
    moved = []
    for _ in range(20):
        T = _pose(rng)
        dets = _detections(T, rng, 0.2)
        clean = estimate_cap_pose(dets, MODEL, CAMERA)
        # Duplicate: a second copy of one id 60 px away.
        dup = dets + [TagDetection(dets[0].tag_id, dets[0].corners_px + [60.0, 25.0])]
        r_dup = estimate_cap_pose(dup, MODEL, CAMERA)
        assert dets[0].tag_id in r_dup.pose.used_ids
        # Misplaced: the only copy of one id moved 40 px.
        bad = [TagDetection(dets[1].tag_id, dets[1].corners_px + [40.0, -30.0])] + dets[:1] + dets[2:]
        r_bad = estimate_cap_pose(bad, MODEL, CAMERA)
        assert dets[1].tag_id not in r_bad.pose.used_ids
        for r in (r_dup, r_bad):
            moved.append(angle_deg(r.pose.T_cam_cap.rotation, clean.pose.T_cam_cap.rotation))
    assert np.median(moved) < 0.1


def test_duplicate_that_disagrees_with_pose_drops_both() -> None:
    rng = np.random.default_rng(8)
    T = _pose(rng)
    dets = _detections(T, rng, 0.1)
    wrong = [TagDetection(dets[0].tag_id, dets[0].corners_px + 80.0),
             TagDetection(dets[0].tag_id, dets[0].corners_px - 80.0)]
    result = estimate_cap_pose(wrong + dets[1:], MODEL, CAMERA)
    assert result.ok and dets[0].tag_id not in result.pose.used_ids
    assert result.pose.tags_detected == len(dets)


def test_single_tag_gives_a_low_reliability_pose() -> None:
    rng = np.random.default_rng(9)
    T = _pose(rng)
    dets = _detections(T, rng, 0.2)
    one = estimate_cap_pose(dets[:1], MODEL, CAMERA)
    many = estimate_cap_pose(dets, MODEL, CAMERA)
    assert one.ok and one.pose.tags_used == 1
    assert one.pose.reliability < 0.3 < many.pose.reliability
    assert many.pose.reliability > 0.8


def test_no_pose_with_reason() -> None:
    empty = estimate_cap_pose([], MODEL, CAMERA)
    assert not empty.ok and "no tag" in empty.reason
    foreign = estimate_cap_pose([TagDetection(400, np.array([[0, 0], [10, 0], [10, 10], [0, 10]]))], MODEL, CAMERA)
    assert not foreign.ok and foreign.tags_detected == 0
    rng = np.random.default_rng(2)
    T = _pose(rng)
    two = estimate_cap_pose(_detections(T, rng, 0.1)[:2], MODEL, CAMERA, PoseConfig(min_tags=3))
    assert not two.ok and "need 3" in two.reason


def test_covariance_matches_scatter() -> None:
    """The reported rotation sigma is the right size: within a factor 2 of the observed scatter."""
    rng = np.random.default_rng(11)
    T = _pose(rng)
    base = _detections(T, rng, 0.0)
    rotvecs, sigmas = [], []
    for _ in range(60):
        dets = [TagDetection(d.tag_id, d.corners_px + rng.normal(0, 0.5, (4, 2))) for d in base]
        pose = estimate_cap_pose(dets, MODEL, CAMERA).pose
        rotvecs.append((pose.T_cam_cap.rotation * T.rotation.inv()).as_rotvec())
        sigmas.append(np.sqrt(np.diag(pose.covariance)[3:]))
    observed = np.std(np.array(rotvecs), axis=0)
    predicted = np.median(np.array(sigmas), axis=0)
    assert np.all(predicted < 2.0 * observed) and np.all(predicted > 0.5 * observed)
    assert np.allclose(pose.covariance, pose.covariance.T)


def test_distorted_camera() -> None:
    """Corners seen through a plumb_bob lens are undistorted before the solve."""
    cam = CameraModel(960, 540, CAMERA.K, [-0.25, 0.08, 0.001, -0.0005, -0.01], "plumb_bob")
    rng = np.random.default_rng(4)
    T = _pose(rng)
    result = estimate_cap_pose(_detections(T, rng, 0.0, cam), MODEL, cam)
    assert angle_deg(result.pose.T_cam_cap.rotation, T.rotation) < 1e-4


def test_fisheye_camera() -> None:
    cam = CameraModel(960, 540, CAMERA.K, [0.05, -0.01, 0.002, -0.001], "equidistant")
    rng = np.random.default_rng(6)
    T = _pose(rng)
    result = estimate_cap_pose(_detections(T, rng, 0.0, cam), MODEL, cam)
    assert angle_deg(result.pose.T_cam_cap.rotation, T.rotation) < 1e-4


def test_square_tags_take_out_what_no_pose_explains() -> None:
    """Squared tags (``PoseConfig.square_tags``) under isotropic corner noise: the pose is at least
    as accurate as from the raw corners (to first order the same: the part removed is orthogonal
    to every pose change), and ``rms_px`` falls (the residual keeps 6 T - 6 of the 8 T - 6 degrees of
    freedom of T tags' corners, to first order)."""
    rng = np.random.default_rng(21)
    rot, rms = {True: [], False: []}, {True: [], False: []}
    for _ in range(30):
        T = _pose(rng)
        dets = _detections(T, rng, 0.3)
        for square in (True, False):
            pose = estimate_cap_pose(dets, MODEL, CAMERA, PoseConfig(square_tags=square)).pose
            rot[square].append(angle_deg(pose.T_cam_cap.rotation, T.rotation))
            rms[square].append(pose.rms_px)
    assert np.median(rot[True]) < 1.1 * np.median(rot[False])
    assert np.median(rms[True]) < 0.9 * np.median(rms[False])


def test_unknown_method() -> None:
    with pytest.raises(ConfigError, match="unknown pose method"):
        PoseConfig(method="magic")


@pytest.mark.parametrize("method", ["joint", "naive"])
def test_without_uncertainty_same_pose(method: str) -> None:
    """``with_uncertainty=False`` (the tracker's intermediate poses) returns the same pose, tags and
    rms bit for bit, and no covariance or bounds (NaN, reliability 0)."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        T = _pose(rng)
        dets = _detections(T, rng, 0.3)
        config = PoseConfig(method=method)
        full = estimate_cap_pose(dets, MODEL, CAMERA, config).pose
        lean = estimate_cap_pose(dets, MODEL, CAMERA, config, with_uncertainty=False).pose
        assert full is not None and lean is not None
        np.testing.assert_array_equal(lean.T_cam_cap.rotation.as_quat(), full.T_cam_cap.rotation.as_quat())
        np.testing.assert_array_equal(lean.T_cam_cap.translation_m, full.T_cam_cap.translation_m)
        assert (lean.used_ids, lean.tags_used, lean.rms_px) == (full.used_ids, full.tags_used, full.rms_px)
        assert np.isfinite(full.rot_err95_deg) and np.all(np.isfinite(full.covariance))
        assert np.isnan(lean.rot_err95_deg) and np.isnan(lean.trans_err95_mm)
        assert np.all(np.isnan(lean.covariance)) and lean.reliability == 0.0


# -- the least-squares refinement --------------------------------------------------------------------

SOLVER_CAMERA = CameraModel.pinhole(1920, 1080, hfov_deg=60.0)


def _gauss_newton_step(obs: TagObservations, T: Transform) -> Transform:
    """One undamped Gauss-Newton step from ``T``: at the minimum it moves nothing."""
    res, J = residuals_and_jacobian(T, obs)
    dx = -np.linalg.solve(J.T @ J, J.T @ res)
    return Transform(Rotation.from_rotvec(dx[:3]) * T.rotation, T.translation_m + dx[3:])


def test_refine_reaches_the_least_squares_minimum() -> None:
    rng = np.random.default_rng(7)
    worst_deg = worst_mm = 0.0
    for k in range(30):
        ypr = rng.uniform(-1, 1, 3) * [50.0, 25.0, 10.0]
        T = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", ypr, degrees=True),
                      [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.4, 0.7)])
        n = T.rotation.apply(MODEL.normals)
        c = T.apply(MODEL.centres_mm / 1000.0)
        facing = np.asarray(MODEL.ids)[np.sum(n * c, axis=1) < -0.2 * np.linalg.norm(c, axis=1)]
        corners = {int(i): SOLVER_CAMERA.project(T.apply(MODEL.corners_of(int(i)) / 1000.0))
                   + rng.normal(0.0, 0.3, (4, 2)) for i in facing}
        obs = TagObservations.of(corners, MODEL, SOLVER_CAMERA.K)
        # Starts as tracking gives them (a fraction of a degree off) and as a poor consensus might.
        off_deg, off_m = (0.2, 0.002) if k % 2 else (5.0, 0.03)
        start = Transform(Rotation.from_rotvec(rng.normal(0, 1, 3) * np.radians(off_deg) / np.sqrt(3)) * T.rotation,
                          T.translation_m + rng.normal(0, off_m, 3))
        ours, rms = _refine(obs, start)
        # At the minimum the gradient vanishes: a further Gauss-Newton step stays put.
        ref = _gauss_newton_step(obs, ours)
        worst_deg = max(worst_deg, float(angle_deg(ours.rotation, ref.rotation)))
        worst_mm = max(worst_mm, 1000.0 * float(np.abs(ours.translation_m - ref.translation_m).max()))
        assert 0.3 < rms < 0.55  # 0.3 px per coordinate: 0.42 px per corner
        assert float(angle_deg(ours.rotation, T.rotation)) < 0.2  # the minimum near the truth, not the start
    assert worst_deg < 1e-6 and worst_mm < 1e-6, (worst_deg, worst_mm)


def test_refine_is_least_squares_lm_bit_for_bit() -> None:
    """``_refine`` runs MINPACK's lmder as ``least_squares(method="lm", x_scale="jac")`` does (through
    ``leastsq``, without that wrapper's per-call cost): the same pose and rms to the last bit, from
    near and far starts, so labels do not move; a scipy upgrade that makes the two differ shows here."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(11)
    for k in range(12):
        T = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", rng.uniform(-1, 1, 3) * [40.0, 20.0, 10.0],
                                                             degrees=True),
                      [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.4, 0.7)])
        corners = {int(i): SOLVER_CAMERA.project(T.apply(MODEL.corners_of(int(i)) / 1000.0))
                   + rng.normal(0.0, 0.3, (4, 2)) for i in MODEL.ids[:6 + k]}
        obs = TagObservations.of(corners, MODEL, SOLVER_CAMERA.K)
        # Near starts (tracking) and far ones, where LM's step bound and damping shape the path.
        off_deg, off_m = (0.5, 0.003) if k % 2 else (10.0, 0.05)
        start = Transform(Rotation.from_rotvec(rng.normal(0, 1, 3) * np.radians(off_deg)) * T.rotation,
                          T.translation_m + rng.normal(0, off_m, 3))
        ours, rms = _refine(obs, start)
        R0, x0 = start.rotation_matrix, np.concatenate([np.zeros(3), start.translation_m])
        sol = least_squares(lambda x: _turned_residuals_and_jacobian(x, R0, obs)[0], x0,
                            jac=lambda x: _turned_residuals_and_jacobian(x, R0, obs)[1],
                            method="lm", x_scale="jac", xtol=1e-10, ftol=1e-10, max_nfev=50)
        ref = Rotation.from_rotvec(sol.x[:3]) * start.rotation
        assert np.array_equal(ours.rotation.as_quat(), ref.as_quat())
        assert np.array_equal(ours.q_xyzw, ref.as_quat(canonical=True))
        assert np.array_equal(ours.translation_m, sol.x[3:])
        assert rms == float(np.sqrt(np.mean(sol.fun**2) * 2.0))


def test_refine_refuses_a_start_least_squares_refuses() -> None:
    """The same errors as ``least_squares`` for a start with non-finite residuals (a model point on
    the camera plane) and for fewer residuals than unknowns (one corner)."""
    T = Transform(CAM_FROM_FORWARD, [0.0, 0.0, 0.5])
    corners_m = MODEL.corners_of(int(MODEL.ids[0])) / 1000.0
    obs = TagObservations.of({int(MODEL.ids[0]): SOLVER_CAMERA.project(T.apply(corners_m))}, MODEL, SOLVER_CAMERA.K)
    on_the_lens = Transform(CAM_FROM_FORWARD, -CAM_FROM_FORWARD.apply(corners_m[0]))  # corner 0 at z = 0
    with np.errstate(divide="ignore", invalid="ignore"), pytest.raises(ValueError, match="not finite"):
        _refine(obs, on_the_lens)
    one_corner = TagObservations(obs.ids, obs.image_px[:, :1], obs.model_m[:, :1], obs.K)
    with pytest.raises(ValueError, match="number of residuals"):
        _refine(one_corner, T)


@given(st.tuples(*[st.floats(-1.0, 1.0)] * 3), st.floats(-18.0, 0.7), st.sampled_from([(), (0,), (0, 1), (1, 2)]))
def test_rodrigues_is_opencvs_bit_for_bit(direction: tuple[float, float, float], log_angle: float,
                                         zeros: tuple[int, ...]) -> None:
    """The LM's rotation matrix is ``cv2.Rodrigues``' to the last bit (zeros' signs included), from
    below machine epsilon to beyond a half turn, with some components exactly zero."""
    v = np.array(direction) * 10.0**log_angle
    v[list(zeros)] = 0.0
    ref = cv2.Rodrigues(np.ascontiguousarray(v))[0]
    ours = _rodrigues(v.tolist())
    assert np.array_equal(ours, ref) and np.array_equal(np.signbit(ours), np.signbit(ref))
