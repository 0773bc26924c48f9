"""Motion-aware corners (``ficap_ros.vision.motion_corners`` and the moving photometric model).

Tags rendered moving over the exposure (``tag_images.moving_tag_image``: their light averaged over
32 instants in linear light, a lens blur, the sRGB curve, noise) with exact mid-exposure corners:
the fit with the motion in its model lands on them; the still model, fitted to the same pixels
from the same start (its Gaussian blur fitted per tag), is off by a tenth of the smear and more.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tag_images import moving_tag_image

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision import motion_corners
from ficap_ros.vision.corners import fit_tags_photometric
from ficap_ros.vision.detector import DetectorConfig, TagDetection
from ficap_ros.vision.motion import MotionPrior, PastPose
from ficap_ros.vision.motion_corners import (
    applies,
    corner_paths_px,
    motion_aware_corners,
)


def _tag(rng: np.random.Generator, side_px: float = 40.0) -> np.ndarray:
    """A square tag of ``side_px`` turned at random near (100, 90): corners (4, 2)."""
    a = rng.uniform(0.0, 2.0 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side_px / 2 @ rot.T + [100, 90] + rng.uniform(-1, 1, 2)


@pytest.mark.parametrize("length_px, spin_deg", [(3.0, 0.0), (6.0, 0.0), (6.0, 3.0)])
def test_the_motion_model_finds_the_mid_exposure_corners(length_px: float, spin_deg: float) -> None:
    """Blur of 3-6 px (a 40 px tag, 5 px cells), a pure slide or a slide with a spin (each corner
    its own motion): the motion model's mean corner error under 0.04 px and under a quarter of the
    still model's, every tag fitted."""
    rng = np.random.default_rng(7)
    moving, still = [], []
    for _ in range(5):
        c = _tag(rng)
        d = rng.uniform(0.0, 2.0 * np.pi)
        spin = np.radians(spin_deg)
        lever = c - c.mean(axis=0)
        motion = np.array([np.cos(d), np.sin(d)]) * length_px + spin * lever @ np.array([[0, 1], [-1, 0]])
        img = moving_tag_image(7, c, motion, (200, 180), rng)
        start = c + rng.normal(0.0, 0.2, (4, 2))
        got, ok = fit_tags_photometric(img, start[None], np.array([7]), motion_px=motion[None])
        base, ok_still = fit_tags_photometric(img, start[None], np.array([7]))
        assert ok[0] and ok_still[0]
        moving.append(np.linalg.norm(got[0] - c, axis=1).mean())
        still.append(np.linalg.norm(base[0] - c, axis=1).mean())
    print(f"blur {length_px} px spin {spin_deg} deg: moving {np.mean(moving):.3f} still {np.mean(still):.3f} px")
    assert np.mean(moving) <= 0.04
    assert np.mean(moving) <= 0.25 * np.mean(still)


@pytest.mark.parametrize("length_px", [3.0, 6.0])
def test_the_refits_settings_find_the_mid_exposure_corners(length_px: float) -> None:
    """The refit's own settings (its damping, instants three blur sds apart, stopping at a small
    step), from starts a quarter pixel off: the mean corner error under 0.04 px, within 0.01 px of
    the fit at the still fit's damping with two-sd instants and every step taken (a 3 px smear,
    two instants instead of three, is the case furthest from it)."""
    rng = np.random.default_rng(11)
    refit, dense = [], []
    settings = dict(iterations=motion_corners.MAX_STEPS, converged_px=motion_corners.CONVERGED_PX,
                    damping=motion_corners.DAMPING, instant_spacing_sds=motion_corners.INSTANT_SPACING_SDS)
    for _ in range(5):
        c = _tag(rng)
        d = rng.uniform(0.0, 2.0 * np.pi)
        motion = np.tile(np.array([np.cos(d), np.sin(d)]) * length_px, (4, 1))
        img = moving_tag_image(7, c, motion, (200, 180), rng)
        start = c + rng.normal(0.0, 0.25, (4, 2))
        got, ok = fit_tags_photometric(img, start[None], np.array([7]), motion_px=motion[None], **settings)
        ref, ok_ref = fit_tags_photometric(img, start[None], np.array([7]), motion_px=motion[None],
                                           iterations=motion_corners.MAX_STEPS)
        assert ok[0] and ok_ref[0]
        refit.append(np.linalg.norm(got[0] - c, axis=1).mean())
        dense.append(np.linalg.norm(ref[0] - c, axis=1).mean())
    print(f"blur {length_px} px: refit settings {np.mean(refit):.4f} px, dense {np.mean(dense):.4f} px")
    assert np.mean(refit) <= 0.04
    assert np.mean(refit) <= np.mean(dense) + 0.01


def _six_tags_turning() -> tuple[CameraModel, np.ndarray, np.ndarray, Rotation]:
    """The corner-path cases' scene: a 960 x 540 pinhole camera, six model tags' corners (m),
    the turn's unit axis and the cap's rotation at the start of the turn."""
    model = nominal_model()
    corners_m = 1e-3 * np.stack([model.corners_of(i) for i in list(model.ids)[:6]])
    axis = np.array([0.1, 1.0, 0.2]) / np.linalg.norm([0.1, 1.0, 0.2])
    return CameraModel.pinhole(960, 540, f_px=700.0), corners_m, axis, Rotation.from_rotvec([0.1, 2.9, 0.2])


def test_corner_paths_follow_a_turn_that_speeds_up() -> None:
    """A cap turning at 150 deg/s and speeding up at 3000 deg/s^2, seen through a rolling
    shutter: the paths through the pose and three past ones (30 fps) give each corner's motion
    over the exposure at its row's time and its bend close to the true path's."""
    cam, corners_m, axis, base = _six_tags_turning()

    def pose(t: float) -> Transform:
        angle = np.radians(150.0 * t + 0.5 * 3000.0 * t * t)
        R = Rotation.from_rotvec(angle * axis) * base
        return Transform.from_rvec_tvec(R.as_rotvec(), np.array([0.01, -0.02, 0.6]) + t * np.array([0.05, 0.0, 0.0]))

    past = tuple(PastPose(k / 30.0, pose(-k / 30.0), np.eye(6) * 1e-8) for k in (1, 2, 3))
    rows = cam.project(pose(0.0).apply(corners_m.reshape(-1, 3)))[:, 1].reshape(-1, 4)
    timing = CameraTiming(exposure_ms=16.7, readout_ms=22.0)
    motion, bend = corner_paths_px(corners_m, rows, pose(0.0), past, cam, timing)
    t_row = timing.row_time_s(rows, cam.height_px).reshape(-1)
    at = {s: np.array([cam.project(pose(t + s).apply(p[None]))[0] for t, p in zip(t_row, corners_m.reshape(-1, 3))])
          for s in (-0.00835, 0.0, 0.00835)}
    want_motion = (at[0.00835] - at[-0.00835]).reshape(motion.shape)
    want_bend = (0.5 * (at[0.00835] + at[-0.00835]) - at[0.0]).reshape(bend.shape)
    assert np.abs(want_motion).max() > 3.0 and np.abs(want_bend).max() > 0.03  # the case moves and bends
    print(f"motion off by {np.abs(motion - want_motion).max():.3f} of {np.abs(want_motion).max():.3f} px, "
          f"bend by {np.abs(bend - want_bend).max():.4f} of {np.abs(want_bend).max():.4f} px")
    # The cubic through poses a frame apart, a few milliseconds past the newest: within 6 % of the
    # motion, and the bend within a quarter of itself (none at all would be off by all of it).
    np.testing.assert_allclose(motion, want_motion, rtol=0.0, atol=0.06 * np.abs(want_motion).max())
    np.testing.assert_allclose(bend, want_bend, rtol=0.0, atol=0.25 * np.abs(want_bend).max())


def test_two_sided_corner_paths_follow_a_glance_the_past_lags() -> None:
    """A minimum-jerk glance (70 deg in 0.4 s, peak 330 deg/s) through a rolling shutter, at
    every 20 ms of it: the paths through the pose, two past poses and the next one (30 fps;
    ``MotionPrior.neighbours`` two-sided) give each corner's motion and bend several times closer
    to the true path's than the paths through the pose and three past poses (the causal model),
    whose cubic extrapolates the glance's changing acceleration."""
    cam, corners_m, axis, base = _six_tags_turning()
    timing = CameraTiming(exposure_ms=16.7, readout_ms=22.0)
    h, half = 1 / 30, 0.5e-3 * 16.7
    errors: dict[str, list[float]] = {"causal motion": [], "two motion": [], "causal bend": [],
                                      "two bend": []}
    for t0 in np.arange(0.04, 0.37, 0.02):
        def pose(t: float, t0: float = float(t0)) -> Transform:
            u = np.clip((t0 + t) / 0.4, 0.0, 1.0)
            angle = np.radians(70.0) * (10 * u**3 - 15 * u**4 + 6 * u**5)
            R = Rotation.from_rotvec(angle * axis) * base
            return Transform.from_rvec_tvec(R.as_rotvec(), np.array([0.01, -0.02, 0.6]))

        rows = cam.project(pose(0.0).apply(corners_m.reshape(-1, 3)))[:, 1].reshape(-1, 4)
        t_row = timing.row_time_s(rows, cam.height_px).reshape(-1)
        at = {s: np.array([cam.project(pose(t + s).apply(c[None]))[0]
                           for t, c in zip(t_row, corners_m.reshape(-1, 3))]) for s in (-half, 0.0, half)}
        want_motion = (at[half] - at[-half]).reshape(-1, 4, 2)
        want_bend = (0.5 * (at[half] + at[-half]) - at[0.0]).reshape(-1, 4, 2)
        past = tuple(PastPose(k * h, pose(-k * h), np.eye(6) * 1e-8) for k in (1, 2, 3))
        prior = MotionPrior(past, following=(PastPose(-h, pose(h), np.eye(6) * 1e-8),))
        for name, nodes in (("causal", MotionPrior(past).neighbours), ("two", prior.neighbours)):
            motion, bend = corner_paths_px(corners_m, rows, pose(0.0), nodes, cam, timing)
            errors[f"{name} motion"].append(float(np.abs(motion - want_motion).max()))
            errors[f"{name} bend"].append(float(np.abs(bend - want_bend).max()))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    print({k: f"{v:.4f} px" for k, v in rms.items()})
    assert rms["causal motion"] > 0.1 and rms["causal bend"] > 0.01  # the causal paths lag
    assert rms["two motion"] < 0.35 * rms["causal motion"]
    assert rms["two bend"] < 0.25 * rms["causal bend"]


def test_refit_runs_only_with_an_exposure_a_past_pose_and_enough_motion() -> None:
    past = MotionPrior((PastPose(1 / 30, Transform.identity(), np.eye(6) * 1e-6),))
    on = DetectorConfig()
    assert applies(on, CameraTiming(exposure_ms=10.0), past)
    assert not applies(on, CameraTiming(), past)  # no exposure stated
    assert not applies(on, CameraTiming(exposure_ms=10.0), MotionPrior())  # no past pose
    assert not applies(on, CameraTiming(exposure_ms=10.0), None)
    assert not applies(replace(on, motion_corners=False), CameraTiming(exposure_ms=10.0), past)
    assert not applies(DetectorConfig(corner_refine="subpix"), CameraTiming(exposure_ms=10.0), past)
    with pytest.raises(Exception, match="motion_corners_min_px"):
        DetectorConfig(motion_corners_min_px=-1.0)
    # A cap at rest: every tag keeps its detection (the same objects).
    model = nominal_model()
    cam = CameraModel.pinhole(960, 540, f_px=700.0)
    T = Transform.from_rvec_tvec(np.array([0.0, np.pi, 0.0]), np.array([0.0, 0.0, 0.6]))
    tags = tuple(TagDetection(i, cam.project(T.apply(1e-3 * model.corners_of(i)))) for i in list(model.ids)[:4])
    gray = np.full((540, 960), 128, np.uint8)
    still = (PastPose(1 / 30, T, np.eye(6) * 1e-8),)
    out = motion_aware_corners(gray, tags, model, cam, CameraTiming(exposure_ms=16.0), T, still, on)
    assert all(a is b for a, b in zip(out, tags))
