"""ficap_ros.tools.synth.drive: the drive's frames are its continuous motion sampled, the motion is
naturalistic (glances, smooth, about the neck) and reproducible, the default scene's geometry."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from synth_frames import MODEL

from ficap_ros.geometry.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    naturalistic_motion,
    render,
)


def test_drive_motion_matches_frames() -> None:
    scene = default_scene("540p")
    drive = naturalistic_drive(400, fps=30.0, seed=5, scene=scene)
    motion = naturalistic_motion(400 / 30.0, seed=5, scene=scene)
    for f in drive[::37]:
        T = motion.around(f.stamp_ns / 1e9)(0.0)
        assert angle_deg(T.rotation, f.T_cam_cap.rotation) < 1e-9
        assert np.allclose(T.translation_m, f.T_cam_cap.translation_m, atol=1e-12)
    # Between frames the motion is continuous: half a frame later lies between the two frames.
    a, b = drive[200], drive[201]
    mid = motion.T_cam_cap_at((a.stamp_ns + b.stamp_ns) / 2e9)
    gap = angle_deg(a.T_cam_cap.rotation, b.T_cam_cap.rotation)
    assert angle_deg(mid.rotation, a.T_cam_cap.rotation) <= gap + 1e-9
    assert angle_deg(mid.rotation, b.T_cam_cap.rotation) <= gap + 1e-9


def test_drive_motion_is_naturalistic_and_consistent() -> None:
    scene = default_scene("540p")
    fps = 30.0
    drive = naturalistic_drive(int(60 * fps), fps=fps, seed=3, scene=scene, frontal_s=3.0)
    ypr = np.array([f.ypr_deg for f in drive])
    assert np.all(np.abs(ypr[:, 0]) <= 62.0)
    assert ypr[:, 0].max() > 40.0 and ypr[:, 0].min() < -40.0
    assert np.any(ypr[:, 1] > 15.0)  # instrument cluster: below, pitch positive nose down (REP-103)
    start = [f for f in drive if f.frontal]
    assert len(start) == int(3.0 * fps)
    assert max(angle_deg(Rotation.identity(), f.R_frontal_head) for f in start) < 1.0
    assert [f.index for f in drive] == list(range(len(drive)))
    assert drive[31].stamp_ns == round(31 * 1e9 / fps)
    # Smooth: no frame-to-frame jump above what 400 deg/s allows.
    steps = [angle_deg(a.R_frontal_head, b.R_frontal_head) for a, b in zip(drive, drive[1:])]
    assert max(steps) < 400.0 / fps
    for f in drive[::97]:
        expected = scene.R_cam_frontal * f.R_frontal_head * scene.R_cap_head.inv()
        assert angle_deg(expected, f.T_cam_cap.rotation) < 1e-9
        back = scene.R_cam_frontal.inv() * f.T_cam_cap.rotation * scene.R_cap_head
        assert angle_deg(back, f.R_frontal_head) < 1e-9
        assert np.allclose(rotation_from_ypr_deg(*f.ypr_deg).as_matrix(), f.R_frontal_head.as_matrix())
        # The head turns about the neck pivot (plus a lean of at most a few cm).
        pivot_to_cap = f.T_cam_cap.translation_m - scene.p_cam_neck_m
        turned = scene.R_cam_frontal.apply(f.R_frontal_head.apply(np.array(scene.neck_to_cap_m)))
        assert np.linalg.norm(pivot_to_cap - turned) < 0.03
    again = naturalistic_drive(100, fps=fps, seed=3, scene=scene)
    assert all(np.array_equal(a.ypr_deg, b.ypr_deg) for a, b in zip(again, drive))


def test_default_scene_tag_size() -> None:
    scene = default_scene("540p")
    frame = render(MODEL, scene.camera, scene.cap_pose(Rotation.identity()), RenderConfig())
    c = frame.corners_px[11]
    side = np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1))
    assert 55.0 <= side <= 65.0


def test_default_scene_resolutions_and_cap_pose() -> None:
    import pytest

    from ficap_ros.errors import ConfigError
    from ficap_ros.geometry.transform import CAM_FROM_FORWARD
    from ficap_ros.tools.synth import RESOLUTIONS

    for name, (w, h) in RESOLUTIONS.items():
        camera = default_scene(name).camera
        assert (camera.width_px, camera.height_px) == (w, h)
        # A 60 deg horizontal field of view: f = (w / 2) / tan(30 deg).
        assert camera.K[0, 0] == pytest.approx(w / 2 / np.tan(np.radians(30.0)), rel=1e-9)
    assert (default_scene((480, 270)).camera.width_px, default_scene((480, 270)).camera.height_px) \
        == (480, 270)
    with pytest.raises(ConfigError, match="unknown resolution"):
        default_scene("4k")
    scene = default_scene("540p")
    # Looking straight ahead the cap origin is 0.542 m ahead of the camera and 6 cm below it.
    T = scene.cap_pose(Rotation.identity())
    np.testing.assert_allclose(CAM_FROM_FORWARD.inv().apply(np.array(T.translation_m)), [0.542, 0.0, -0.06],
                               atol=1e-12)
    assert angle_deg(T.rotation, scene.R_cam_frontal * scene.R_cap_head.inv()) < 1e-9
    # A head translation in F moves the cap by the same vector, in the camera frame.
    shifted = scene.cap_pose(Rotation.identity(), np.array([0.0, 0.01, 0.0]))
    np.testing.assert_allclose(shifted.translation_m - T.translation_m,
                               scene.R_cam_frontal.apply([0.0, 0.01, 0.0]), atol=1e-12)


def test_drive_arguments_are_checked() -> None:
    import pytest

    from ficap_ros.errors import ConfigError

    for bad in (dict(n_frames=-1), dict(n_frames=3, fps=0.0), dict(n_frames=3, frontal_s=-1.0)):
        with pytest.raises(ConfigError):
            naturalistic_drive(**bad)
    assert naturalistic_drive(0) == []
    frames = naturalistic_drive(4, fps=2.0, frontal_s=1.0)
    assert [f.frontal for f in frames] == [True, True, False, False]
    assert [f.stamp_ns for f in frames] == [0, 500_000_000, 1_000_000_000, 1_500_000_000]


def _turns(motion):
    """(start, end, label) of every turn of a motion after its frontal segment."""
    return [(a, b, label) for a, b, p0, p1, label in motion.segments[1:] if not np.allclose(p0, p1)]


def test_glance_drives_turn_at_150_to_250_deg_s() -> None:
    """``glance_motion``: glances back to back, every turn (to a target and back) peaking at
    150-250 deg/s, the targets of a naturalistic drive visited in blocks of four; reproducible by
    seed; ``drive_motion`` names it; the frontal segment stays still for calibration."""
    from ficap_ros.tools.synth import (
        GLANCE_PEAK_DEG_S,
        MOTIONS,
        drive_motion,
        glance_motion,
    )

    scene = default_scene("540p")
    motion = glance_motion(12.0, seed=7, scene=scene, frontal_s=1.0)
    turns = _turns(motion)
    assert len(turns) >= 12
    assert {label for *_, label in turns} == {"frontal", "left_mirror", "right_mirror",
                                              "rear_mirror", "cluster"}
    peaks = np.array([max(motion.angular_speed_deg_s(t) for t in np.linspace(a, b, 41))
                      for a, b, _ in turns])
    lo, hi = GLANCE_PEAK_DEG_S
    print(f"\nglance turns: {len(peaks)}, peak speeds {peaks.min():.0f}-{peaks.max():.0f} deg/s")
    assert lo - 2.0 <= peaks.min() and peaks.max() <= hi + 2.0  # the sway adds under 2 deg/s
    assert peaks.max() - peaks.min() > 0.5 * (hi - lo)  # drawn over the range
    assert max(motion.angular_speed_deg_s(t) for t in np.linspace(0.0, 1.0, 21)) < 3.0
    frames = [motion.frame(i, 30.0) for i in range(0, 360, 9)]
    again = drive_motion("glances", 12.0, seed=7, scene=scene, frontal_s=1.0)
    assert all(angle_deg(f.T_cam_cap.rotation, again.frame(f.index, 30.0).T_cam_cap.rotation) == 0
               for f in frames)
    assert MOTIONS == ("naturalistic", "glances")
    named, plain = drive_motion("naturalistic", 9.0, 3, scene), naturalistic_motion(9.0, 3, scene)
    assert all(np.array_equal(named.frame(i, 30.0).ypr_deg, plain.frame(i, 30.0).ypr_deg)
               for i in range(0, 270, 13))
    import pytest

    from ficap_ros.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown head motion"):
        drive_motion("sneeze", 1.0)
    with pytest.raises(ConfigError):
        glance_motion(1.0, peak_deg_s=(300.0, 200.0))


def test_the_true_cap_velocity_is_the_motions_derivative() -> None:
    """``cap_velocity_at``: the cap origin's velocity and the angular velocity in the camera's
    axes (R(t + dt) = exp([w] dt) R(t)), CapPose.velocity's convention: stepping the pose by
    it over a millisecond lands on the motion."""
    from ficap_ros.tools.synth import glance_motion

    motion = glance_motion(6.0, seed=2, frontal_s=0.5)
    a, b, _ = _turns(motion)[0]
    t = 0.5 * (a + b)  # mid-turn: fastest
    twist = motion.cap_velocity_at(t)
    assert np.degrees(np.linalg.norm(twist[3:])) > 140.0
    dt = 1e-3
    T0, T1 = motion.T_cam_cap_at(t), motion.T_cam_cap_at(t + dt)
    predicted = Rotation.from_rotvec(twist[3:] * dt) * T0.rotation
    assert angle_deg(predicted, T1.rotation) < 0.01 * np.degrees(np.linalg.norm(twist[3:]) * dt)
    np.testing.assert_allclose(T0.translation_m + twist[:3] * dt, T1.translation_m, atol=2e-6)
    # The origin swings about the neck pivot, and the lean moves it too.
    h = 1e-5
    lean, _ = motion.pose_vector_at(t)
    lean_rate = (motion.pose_vector_at(t + h)[0] - motion.pose_vector_at(t - h)[0])[3:] / (2 * h)
    R_cf = motion.scene.R_cam_frontal
    lever = T0.translation_m - motion.scene.p_cam_neck_m - R_cf.apply(lean[3:])
    np.testing.assert_allclose(twist[:3], np.cross(twist[3:], lever) + R_cf.apply(lean_rate),
                               atol=1e-4)
