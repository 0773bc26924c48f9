"""The cap's motion over a frame: the velocity prior's finite differences and their covariance, and
the rolling-shutter pose (``estimate_cap_pose`` with a ``CameraTiming``) on corners projected from a
moving cap row by row (test/helpers/rolling_shutter.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rolling_shutter import (
    accelerating,
    bag_truths,
    constant_velocity,
    detections,
    facing_ids,
    rolling_corners,
)
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.motion import (
    MotionConfig,
    MotionPrior,
    MovingFit,
    PastPose,
    VelocityPrior,
    acceleration,
    corner_times_s,
    static_velocity,
)
from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose
from ficap_ros.vision.uncertainty import UncertaintyConfig

MODEL = nominal_model()
CAMERA = CameraModel.pinhole(960, 540, hfov_deg=67.4)
ROLLING = CameraTiming(exposure_ms=0.0, readout_ms=22.0)
T0 = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", [20.0, 5.0, 0.0], degrees=True),
               [0.01, -0.02, 0.7])
#: A fast glance: 200 deg/s about the camera's vertical axis, and the cap origin moving with it.
GLANCE = np.array([0.05, 0.01, 0.12, 0.1, np.radians(200.0), 0.05])
#: A glance's acceleration at its quarter: 2 m/s^2 and 50 rad/s^2 about the camera's vertical axis.
GLANCE_ACCEL = np.array([1.0, 0.2, -2.0, 2.0, 50.0, -1.0])
SMALL_COV = np.diag([1e-10] * 3 + [1e-10] * 3)


def _past(pose_at, ages_s, cov=SMALL_COV) -> tuple[PastPose, ...]:
    return tuple(PastPose(a, pose_at(-a), cov) for a in ages_s)


def _errors(pose, truth: Transform) -> tuple[float, float]:
    """(rotation deg, translation mm) of a CapPose against the truth."""
    return (angle_deg(pose.T_cam_cap.rotation, truth.rotation),
            1e3 * float(np.linalg.norm(pose.T_cam_cap.translation_m - truth.translation_m)))


@settings(max_examples=40, deadline=None)
@given(h1=st.floats(0.01, 0.05), h2=st.floats(0.01, 0.05),
       w=st.lists(st.floats(-4.0, 4.0), min_size=3, max_size=3),
       v=st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3))
def test_prior_is_exact_for_constant_velocity(h1: float, h2: float, w: list, v: list) -> None:
    """A cap turning at a constant rate about a fixed axis and moving along a line: the finite
    difference through two past poses (any spacing) and through one gives its twist exactly."""
    twist = np.array(v + w)
    pose_at = constant_velocity(T0, twist)
    for ages in ((h1, h1 + h2), (h1,)):
        prior = MotionPrior(_past(pose_at, ages))
        np.testing.assert_allclose(prior.at(T0).mean, twist, atol=1e-9)


def _assert_derivatives_by_pose(prior: MotionPrior) -> VelocityPrior:
    """``prior.at(T0)``, after checking its ``d_mean`` and ``d_accel`` against finite differences
    by a left perturbation (d_theta, d_t) of the pose being solved."""
    vp = prior.at(T0)
    eps = 1e-6
    for k in range(6):
        dx = np.zeros(6)
        dx[k] = eps
        moved = prior.at(T0.turned(dx[:3], T0.translation_m + dx[3:]))
        np.testing.assert_allclose((moved.mean - vp.mean) / eps, vp.d_mean[:, k], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose((moved.accel - vp.accel) / eps, vp.d_accel[:, k], rtol=1e-4,
                                   atol=1e-4 * np.abs(vp.d_accel).max())
    return vp


@pytest.mark.parametrize("ages", [(1 / 30, 2 / 30), (1 / 30, 2 / 30, 3 / 30)])
def test_prior_mean_moves_with_the_pose_as_its_derivative_says(ages: tuple[float, ...]) -> None:
    """``d_mean`` and ``d_accel`` are the prior mean's and acceleration's derivatives by a left
    perturbation (d_theta, d_t) of the pose being solved (numerically)."""
    prior = MotionPrior(_past(accelerating(T0, GLANCE, GLANCE_ACCEL), ages))
    _assert_derivatives_by_pose(prior)


@pytest.mark.parametrize("ages", [(1 / 30, 2 / 30), (0.03, 0.07, 0.1)])
def test_prior_acceleration_is_the_polynomials(ages: tuple[float, ...]) -> None:
    """A cap speeding up at a constant rate about a fixed axis and along a line: the second
    derivative through two past poses and through three gives its acceleration (to the
    rotation vectors' composition, exact for a fixed axis); one past pose gives none."""
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    twist = np.concatenate([GLANCE[:3], np.radians(150.0) * axis])
    accel = np.concatenate([[1.5, -0.5, 0.8], 40.0 * axis])
    pose_at = accelerating(T0, twist, accel)
    prior = MotionPrior(_past(pose_at, ages))
    vp = prior.at(T0)
    np.testing.assert_allclose(vp.accel, accel, rtol=1e-6, atol=1e-6)
    got, weight = acceleration(T0, prior.usable)
    np.testing.assert_array_equal(got, vp.accel)
    if len(ages) == 2:
        assert weight == pytest.approx(2.0 / (ages[0] * ages[1]))
    assert not MotionPrior(_past(pose_at, ages[:1])).at(T0).accel.any()


def test_prior_covariance_holds_the_past_poses_and_the_model_error() -> None:
    """Two past poses: c1^2 S1 + c2^2 S2 plus the jerk truncation; one: 1/h^2 S1 plus the
    acceleration's; none: the weak prior around rest."""
    h = 1 / 30
    cfg = MotionConfig()
    S = np.diag([1e-8, 2e-8, 3e-8, 1e-6, 2e-6, 3e-6])
    pose_at = constant_velocity(T0, GLANCE)
    two = MotionPrior(_past(pose_at, (h, 2 * h), S)).at(T0).covariance
    jerk = np.array([cfg.linear_jerk_m_s3] * 3 + [cfg.angular_jerk_rad_s3] * 3) * h * h / 3
    np.testing.assert_allclose(two, np.diag(jerk**2) + (4 / h**2 + 1 / (4 * h**2)) * S, rtol=1e-12)
    one = MotionPrior(_past(pose_at, (h,), S)).at(T0).covariance
    acc = np.array([cfg.linear_accel_m_s2] * 3 + [cfg.angular_accel_rad_s2] * 3) * h / 2
    np.testing.assert_allclose(one, np.diag(acc**2) + S / h**2, rtol=1e-12)
    none = MotionPrior().at(T0)
    assert not MotionPrior().from_past and np.all(none.mean == 0) and np.all(none.d_mean == 0)
    np.testing.assert_allclose(np.sqrt(np.diag(none.covariance)),
                               [cfg.linear_speed_m_s] * 3 + [cfg.angular_speed_rad_s] * 3)


def test_prior_uses_consecutive_recent_poses_only() -> None:
    """Poses beyond ``max_age_s``, out of order or without a finite covariance are not used."""
    pose_at = constant_velocity(T0, GLANCE)
    p1, p2 = _past(pose_at, (0.03, 0.06))
    assert MotionPrior((p1, p2, p1)).usable == (p1, p2)
    assert MotionPrior((p2, p1)).usable == (p2,)
    assert MotionPrior((PastPose(0.5, p1.T_cam_cap, SMALL_COV),)).usable == ()
    assert MotionPrior((p1, PastPose(0.06, p2.T_cam_cap, np.full((6, 6), np.nan)))).usable == (p1,)


def test_motion_config_rejects_non_positive_sizes() -> None:
    with pytest.raises(ConfigError):
        MotionConfig(angular_jerk_rad_s3=0.0)
    with pytest.raises(ConfigError):
        MotionConfig(max_age_s=float("nan"))


def _glance_frame(rng: np.random.Generator | None = None, noise_px: float = 0.0):
    pose_at = constant_velocity(T0, GLANCE)
    corners = rolling_corners(MODEL, CAMERA, pose_at, ROLLING, facing_ids(MODEL, T0))
    return pose_at, detections(corners, rng, noise_px)


def test_rolling_shutter_pose_is_the_pose_at_the_stamp() -> None:
    """Corners of a 200 deg/s glance read over 22 ms: with the timing and the past poses the
    pose at the stamp comes back exactly and the velocity with it; a static fit of the same
    corners is off by the shear between the rows."""
    pose_at, dets = _glance_frame()
    prior = MotionPrior(_past(pose_at, (1 / 30, 2 / 30)))
    moving = estimate_cap_pose(dets, MODEL, CAMERA, timing=ROLLING, prior=prior).pose
    rot, trans = _errors(moving, T0)
    assert rot < 1e-4 and trans < 1e-4
    np.testing.assert_allclose(moving.velocity, GLANCE, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(moving.velocity_covariance) > 0)
    assert np.isfinite(moving.rot_err95_deg) and np.isfinite(moving.trans_err95_mm)
    static = estimate_cap_pose(dets, MODEL, CAMERA).pose
    assert _errors(static, T0)[0] > 50 * max(rot, 1e-4) and static.velocity is None


def test_rolling_shutter_pose_follows_the_glance_speeding_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """A glance speeding up at 50 rad/s^2 over a 22 ms readout, three past poses of the same
    motion: projected with the acceleration of the polynomial through them, the corners give
    back the pose at the stamp to a few ten-thousandths of a degree and micrometres; at constant
    velocity (the acceleration taken as zero) the top and bottom rows' lag of half the
    acceleration times their time squared tilts it by ten times that and more."""
    import ficap_ros.vision.motion as motion

    pose_at = accelerating(T0, GLANCE, GLANCE_ACCEL)
    dets = detections(rolling_corners(MODEL, CAMERA, pose_at, ROLLING, facing_ids(MODEL, T0)))
    prior = MotionPrior(_past(pose_at, (1 / 30, 2 / 30, 3 / 30)))
    pose = estimate_cap_pose(dets, MODEL, CAMERA, timing=ROLLING, prior=prior).pose
    rot, trans = _errors(pose, T0)
    assert rot < 5e-4 and trans < 3e-3
    np.testing.assert_allclose(pose.velocity[3:], GLANCE[3:], atol=0.01)
    monkeypatch.setattr(motion, "_second_derivative", lambda values, vander_inv: (np.zeros(6), 0.0))
    constant = estimate_cap_pose(dets, MODEL, CAMERA, timing=ROLLING, prior=prior).pose
    assert _errors(constant, T0)[0] > 10.0 * max(rot, 1e-4)


def _glance_errors(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """(rotation error deg, true angular speed deg/s) per frame of a synth rolling-shutter bag,
    its frames in order through the pipeline with the bag's timing."""
    from ficap_ros.io.sources import decode_raw, open_frames
    from ficap_ros.vision.pipeline import FrameProcessor

    truths = bag_truths(bag)
    source = open_frames(bag)
    proc = FrameProcessor(MODEL, timing=source.timing)
    rot, speed = [], []
    for raw in source.raw_frames():
        pose = proc.process(decode_raw(raw), raw.camera, raw.stamp_ns).pose
        T, s = truths[raw.stamp_ns]
        rot.append(angle_deg(pose.T_cam_cap.rotation, T.rotation) if pose is not None else np.inf)
        speed.append(s)
    return np.array(rot), np.array(speed)


def test_rendered_rolling_glance_follows_its_acceleration(glance_rs_drive: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Rendered frames of a glance through a 20 ms rolling readout (the ``glance_rs_drive``
    fixture, six frames at 90 deg/s and over): a pose in every frame; in the fast frames the mean
    rotation error with the acceleration in the readout's model is under 0.04 deg and a tenth
    below that at constant velocity (the acceleration taken as zero); slow frames stay near
    0.005 deg either way."""
    import ficap_ros.vision.motion as motion

    rot, speed = _glance_errors(glance_rs_drive)
    monkeypatch.setattr(motion, "_second_derivative", lambda values, vander_inv: (np.zeros(6), 0.0))
    constant, _ = _glance_errors(glance_rs_drive)
    fast, slow = speed >= 90.0, speed < 30.0
    assert np.all(np.isfinite(rot)) and fast.sum() >= 5 and slow.sum() >= 10
    assert np.mean(rot[fast]) < 0.04 and np.mean(rot[fast]) < 0.9 * np.mean(constant[fast])
    assert np.median(rot[slow]) < 0.008 and np.median(constant[slow]) < 0.008


def test_rolling_shutter_without_a_past_fits_the_velocity() -> None:
    """No past pose: the velocity is fitted with the pose under a weak prior around rest; the
    corners' shear then carries it (noise-free corners: near the truth, far better than static)."""
    _, dets = _glance_frame()
    pose = estimate_cap_pose(dets, MODEL, CAMERA, timing=ROLLING).pose
    static = estimate_cap_pose(dets, MODEL, CAMERA).pose
    assert _errors(pose, T0)[0] < 0.2 * _errors(static, T0)[0]
    assert abs(np.degrees(pose.velocity[4] - GLANCE[4])) < 20.0


def test_rolling_shutter_bound_covers_noisy_corners() -> None:
    """Seeded 0.1 px corner noise: the rolling-shutter pose stays near the truth and its 95 %
    bounds hold in most draws."""
    rng = np.random.default_rng(3)
    hits = []
    for _ in range(20):
        pose_at, dets = _glance_frame(rng, 0.1)
        prior = MotionPrior(_past(pose_at, (1 / 30, 2 / 30), np.diag([1e-8] * 3 + [3e-7] * 3)))
        pose = estimate_cap_pose(dets, MODEL, CAMERA, timing=ROLLING, prior=prior).pose
        rot, trans = _errors(pose, T0)
        assert rot < 0.2
        hits.append(rot <= pose.rot_err95_deg and trans <= pose.trans_err95_mm)
    assert np.mean(hits) >= 0.8


def test_global_shutter_velocity_is_the_prior_and_leaves_the_pose_alone() -> None:
    """A global shutter: the pose is the static fit's whatever the prior, and its velocity the
    prior's finite difference at it, with the pose's covariance propagated in. A known exposure
    adds the motion blur's terms to the covariance (the defaults' gains are small: motion-aware
    corners fit the smear); none known, nothing."""
    rng = np.random.default_rng(5)
    pose_at = constant_velocity(T0, GLANCE)
    dets = detections({i: CAMERA.project(T0.apply(MODEL.corners_of(i) / 1000.0))
                       for i in facing_ids(MODEL, T0)}, rng, 0.05)
    prior = MotionPrior(_past(pose_at, (1 / 30, 2 / 30)))
    gains = PoseConfig(uncertainty=UncertaintyConfig(motion_blur_gain=0.35, motion_blur_shift_gain=0.1))
    for config in (None, gains):
        plain = estimate_cap_pose(dets, MODEL, CAMERA, config).pose
        for timing in (None, CameraTiming(exposure_ms=16.0)):
            pose = estimate_cap_pose(dets, MODEL, CAMERA, config, timing=timing, prior=prior).pose
            assert pose.T_cam_cap.matrix.tobytes() == plain.T_cam_cap.matrix.tobytes()
            grown = np.linalg.eigvalsh(pose.covariance - plain.covariance)
            if timing is None:
                assert pose.covariance.tobytes() == plain.covariance.tobytes()
            else:
                assert grown.min() > -1e-15 and pose.rot_err95_deg >= plain.rot_err95_deg
            if timing is not None and config is gains:  # a glance smears each tag by px: wider bounds
                assert grown.max() > 0.1 * np.linalg.eigvalsh(plain.covariance).max()
                assert pose.rot_err95_deg > plain.rot_err95_deg
            expected = static_velocity(prior, pose.T_cam_cap, pose.covariance)
            np.testing.assert_array_equal(pose.velocity, expected[0])
        assert np.all(np.linalg.eigvalsh(pose.velocity_covariance - prior.at(pose.T_cam_cap).covariance)
                      > -1e-12)
    assert static_velocity(MotionPrior(), T0, plain.covariance) is None


def test_rolling_shutter_needs_the_joint_method() -> None:
    """The other estimators fit every corner at once, timing or not."""
    _, dets = _glance_frame()
    config = PoseConfig(method="paper")
    a = estimate_cap_pose(dets, MODEL, CAMERA, config, timing=ROLLING).pose
    b = estimate_cap_pose(dets, MODEL, CAMERA, config).pose
    assert a.T_cam_cap.matrix.tobytes() == b.T_cam_cap.matrix.tobytes() and a.velocity is None


def test_corner_times_are_the_distorted_rows_times() -> None:
    """Undistorted corners are timed by the row they were seen in, in the distorted image."""
    camera = CameraModel(960, 540, CAMERA.K, np.array([-0.3, 0.1, 0.0, 0.0, 0.0]), "plumb_bob")
    seen = {7: np.array([[100.0, 30.0], [900.0, 40.0], [880.0, 500.0], [90.0, 520.0]])}
    undistorted = {7: camera.undistort_px(seen[7])}
    times = corner_times_s(undistorted, camera, ROLLING)[7]
    np.testing.assert_allclose(times, ROLLING.row_time_s(seen[7][:, 1], 540), atol=1e-8)


def test_three_past_poses_measure_the_jerk() -> None:
    """A cap whose position is a cubic in time and whose turn rate grows linearly: with three
    past poses the prior's model error is the measured jerk's truncation (exact for a cubic),
    not the glance's sizes; at rest it falls to the floor."""
    cfg = MotionConfig()
    jerk = np.array([2.0, -3.0, 1.0])  # m/s^3
    h = 1 / 30

    def cubic(s: float) -> Transform:
        return Transform(T0.rotation, T0.translation_m + jerk * s**3 / 6.0)

    prior = MotionPrior(tuple(PastPose(k * h, cubic(-k * h), SMALL_COV * 1e-8) for k in (1, 2, 3)),
                        cfg)
    sd = np.sqrt(np.diag(prior.at(T0).covariance))
    floor = cfg.jerk_floor * np.array([cfg.linear_jerk_m_s3] * 3 + [cfg.angular_jerk_rad_s3] * 3)
    expected = np.hypot(np.concatenate([np.abs(jerk), np.zeros(3)]), floor) * h * 2 * h / 6
    np.testing.assert_allclose(sd, expected, rtol=1e-4)
    assert sd[3] < 0.5 * MotionPrior(prior.past[:2], cfg).at(T0).covariance[3, 3] ** 0.5


def _readout_problem(rng: np.random.Generator, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A fit's Jacobian (n, 12: pose then velocity columns) and weights (n,)."""
    return rng.normal(size=(n, 12)), rng.uniform(0.5, 2.0, n)


def test_prior_error_without_readout_evidence_is_the_prior() -> None:
    """Corners that say nothing of the velocity (zero velocity columns): the held velocity's
    error is the prior's covariance, whatever the residuals."""
    rng = np.random.default_rng(0)
    J12, w = _readout_problem(rng)
    J12[:, 6:] = 0.0
    P = np.diag([1e-4, 2e-4, 3e-4, 1e-2, 2e-2, 3e-2])
    np.testing.assert_allclose(MovingFit.prior_error(rng.normal(size=40), J12, w, P, 0.1), P, rtol=1e-12)


def test_prior_error_follows_what_the_readout_shows() -> None:
    """Strong evidence of the velocity: the second moment of the prior's error is the velocity
    misfit the residuals show (its outer product), not the prior's covariance; and, the prior
    stating its error right, the moment averaged over draws of that error and of the corner
    noise is the prior's covariance (the evidence shares the error out, it does not remove it)."""
    rng = np.random.default_rng(1)
    J12, w = _readout_problem(rng)
    P = np.diag([1e-2, 2e-2, 3e-2, 1.0, 2.0, 3.0])
    e = np.array([0.05, -0.1, 0.02, 0.3, -0.2, 0.1])  # true velocity less the held one
    pose_part = J12[:, :6] @ rng.normal(size=6)  # absorbed by the pose's columns
    moment = MovingFit.prior_error(-J12[:, 6:] @ e + pose_part, J12, w, P, 1e-4)
    np.testing.assert_allclose(moment, np.outer(e, e), atol=1e-6)
    noise_px = 0.5
    draws = []
    for _ in range(4000):
        e = rng.multivariate_normal(np.zeros(6), P)
        noise = noise_px * rng.normal(size=len(w)) / np.sqrt(w)
        draws.append(MovingFit.prior_error(-J12[:, 6:] @ e + noise, J12, w, P, noise_px))
    scale = np.sqrt(np.outer(np.diag(P), np.diag(P)))
    assert np.max(np.abs(np.mean(draws, axis=0) - P) / scale) < 0.1


def _glance_at(t0_s: float):  # noqa: ANN202
    """A minimum-jerk mirror glance (60 deg in 0.4 s about an axis near the camera's vertical,
    peak 281 deg/s) seen from ``t0_s`` into it: the pose at ``s`` seconds from there."""
    axis = np.array([0.1, 1.0, 0.15]) / np.linalg.norm([0.1, 1.0, 0.15])

    def at(s: float) -> Transform:
        u = np.clip((t0_s + s) / 0.4, 0.0, 1.0)
        angle = np.radians(60.0) * (10 * u**3 - 15 * u**4 + 6 * u**5)
        R = Rotation.from_rotvec(angle * axis) * T0.rotation
        return Transform(R, T0.translation_m + 0.03 * (10 * u**3 - 15 * u**4 + 6 * u**5) * np.array([1.0, 0.0, 0.2]))

    return at


def _true_twist(pose_at, s: float = 0.0, h: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """(velocity, acceleration) (6,) ROS order of ``pose_at`` at ``s`` by fine central differences."""
    def tw(t: float) -> np.ndarray:
        a, b = pose_at(t - h), pose_at(t + h)
        return np.concatenate([(b.translation_m - a.translation_m), (b * a.inv()).rvec]) / (2 * h)
    return tw(s), (tw(s + h) - tw(s - h)) / (2 * h)


def test_two_sided_prior_interpolates_the_glance() -> None:
    """Through a whole glance (speeding up and slowing down, 30 fps, every 20 ms of it), the
    velocity and acceleration from two past poses and the next one are several times closer to
    the truth, in root mean square, than those from the three past poses alone (the backward
    prior's, as live)."""
    h = 1 / 30
    err: dict[str, list[np.ndarray]] = {"causal": [], "two": []}
    for t0_s in np.arange(0.02, 0.4, 0.02):
        pose_at = _glance_at(float(t0_s))
        past = _past(pose_at, (h, 2 * h, 3 * h))
        following = (PastPose(-h, pose_at(h), SMALL_COV),)
        causal, two = MotionPrior(past), MotionPrior(past, following=following)
        assert two.two_sided and not causal.two_sided
        assert two.neighbours == past[:2] + following
        v, a = _true_twist(pose_at)
        for name, prior in (("causal", causal), ("two", two)):
            vp = prior.at(pose_at(0.0))
            err[name].append(np.concatenate([vp.mean - v, vp.accel - a]))
    rms = {k: np.sqrt(np.mean(np.square(e), axis=0)) for k, e in err.items()}
    w, acc = slice(3, 6), slice(9, 12)
    print({k: (f"{np.degrees(np.linalg.norm(r[w])):.2f} deg/s",
               f"{np.degrees(np.linalg.norm(r[acc])):.0f} deg/s^2") for k, r in rms.items()})
    assert np.linalg.norm(rms["two"][w]) < 0.25 * np.linalg.norm(rms["causal"][w])
    assert np.linalg.norm(rms["two"][acc]) < 0.15 * np.linalg.norm(rms["causal"][acc])
    assert np.linalg.norm(rms["two"][:3]) < 0.25 * np.linalg.norm(rms["causal"][:3])


def test_two_sided_prior_derivatives_and_covariance() -> None:
    """The two-sided prior's derivatives by the pose are its finite differences, and its
    covariance holds each neighbour's weighted by its coefficient squared plus the snap's
    truncation (``MotionConfig.angular_snap_rad_s4``)."""
    pose_at = accelerating(T0, GLANCE, GLANCE_ACCEL)
    h = 1 / 30
    S = np.diag([1e-8, 2e-8, 3e-8, 1e-6, 2e-6, 3e-6])
    prior = MotionPrior(_past(pose_at, (h, 2 * h), S), following=(PastPose(-h, pose_at(h), S),))
    vp = _assert_derivatives_by_pose(prior)
    # Nodes -2h, -h, 0, h: the velocity's weights at -2h, -h, h are 1/6, -1, 1/3 (over h).
    cfg = MotionConfig()
    snap = np.array([cfg.linear_snap_m_s4] * 3 + [cfg.angular_snap_rad_s4] * 3) * 2 * h**3 / 24
    want = np.diag(snap**2) + (1 / 36 + 1 + 1 / 9) / h**2 * S
    np.testing.assert_allclose(vp.covariance, want, rtol=1e-9)
    # Speeding up about a fixed axis and along a line: the two-sided polynomial is exact.
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    accel = np.concatenate([[1.5, -0.5, 0.8], 40.0 * axis])
    fixed = accelerating(T0, np.concatenate([GLANCE[:3], np.radians(150.0) * axis]), accel)
    exact = MotionPrior(_past(fixed, (h, 2 * h)), following=(PastPose(-h, fixed(h), S),)).at(T0)
    np.testing.assert_allclose(exact.accel, accel, rtol=1e-6, atol=1e-6)


def test_two_sided_needs_a_past_pose_and_a_near_next_one() -> None:
    pose_at = constant_velocity(T0, GLANCE)
    p1, p2 = _past(pose_at, (0.03, 0.06))
    nxt = PastPose(-0.03, pose_at(0.03), SMALL_COV)
    assert MotionPrior((p1, p2), following=(nxt,)).two_sided
    assert not MotionPrior((), following=(nxt,)).two_sided
    assert not MotionPrior((p1,), following=(PastPose(-0.5, pose_at(0.5), SMALL_COV),)).two_sided
    assert not MotionPrior((p1,), following=(PastPose(-0.03, nxt.T_cam_cap, np.full((6, 6), np.nan)),)).two_sided
    # Not two-sided: the backward prior itself.
    one = MotionPrior((p1, p2), following=(PastPose(0.03, nxt.T_cam_cap, SMALL_COV),))
    np.testing.assert_array_equal(one.at(T0).mean, MotionPrior((p1, p2)).at(T0).mean)
