"""End-to-end accuracy on rendered frames with exact ground truth (issue: foundation).

Seeded naturalistic-drive frames go through the one pipeline (detection + `joint` pose); the error
is the geodesic angle between the estimated and the true cap rotation. The naive peer (OpenCV
sub-pixel corners + one SQPnP/LM) runs on the same frames: our median and p95 must be at most half
of its.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import pytest

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import FrameProcessor
from ficap_ros.vision.pose import PoseConfig

MODEL = nominal_model()
OURS = FrameProcessor(MODEL)
# The peer is the afternoon pipeline: every frame searched, OpenCV sub-pixel corners, one PnP.
PEER = FrameProcessor(MODEL, DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive"), tracking=False)


@lru_cache(maxsize=None)
def _frames(resolution: str, n: int, seed: int):
    """Frames spread over a drive (every 7th of 7n), so glances and frontal poses both appear."""
    scene = default_scene(resolution)
    drive = naturalistic_drive(7 * n, fps=30.0, seed=seed, scene=scene)
    out = []
    for k, truth in enumerate(drive[::7]):
        frame = render(MODEL, scene.camera, truth.T_cam_cap, RenderConfig(lighting="neutral"), seed=seed * 1000 + k)
        out.append((frame, truth))
    return scene, out


def _errors(processor: FrameProcessor, scene, frames, edit=None) -> np.ndarray:
    errs = []
    for frame, truth in frames:
        image = frame.image if edit is None else edit(frame)
        result = processor.process(image, scene.camera)
        errs.append(
            angle_deg(result.pose.T_cam_cap.rotation, truth.T_cam_cap.rotation) if result.pose else np.inf
        )
    return np.array(errs)


@pytest.mark.parametrize("resolution, n, median_limit_deg", [("540p", 36, 0.25), ("1080p", 16, 0.12)])
def test_accuracy_and_peer(resolution: str, n: int, median_limit_deg: float) -> None:
    scene, frames = _frames(resolution, n, seed=7)
    ours = _errors(OURS, scene, frames)
    peer = _errors(PEER, scene, frames)
    assert np.all(np.isfinite(ours)), "a frame gave no pose"
    print(f"{resolution}: ours median {np.median(ours):.3f} p95 {np.percentile(ours, 95):.3f}; "
          f"peer median {np.median(peer):.3f} p95 {np.percentile(peer, 95):.3f} deg")
    assert np.median(ours) < median_limit_deg
    assert np.median(ours) <= 0.5 * np.median(peer[np.isfinite(peer)])
    assert np.percentile(ours, 95) <= 0.5 * np.percentile(peer[np.isfinite(peer)], 95)


def _paste_spurious(frame) -> np.ndarray:
    """Copy the image patch of one visible tag to another place: a second, wrong copy of a real id."""
    image = frame.image.copy()
    tag_id, corners = max(frame.corners_px.items(), key=lambda kv: cv2.contourArea(kv[1].astype(np.float32)))
    x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 4
    x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 4
    patch = image[y0:y1, x0:x1].copy()
    h, w = patch.shape[:2]
    # Paste into the top-left corner region (background, away from the cap).
    image[10:10 + h, 10:10 + w] = patch
    return image


def test_spurious_detection_moves_median_little() -> None:
    scene, frames = _frames("540p", 36, seed=7)
    clean = _errors(OURS, scene, frames)
    spurious = _errors(OURS, scene, frames, edit=_paste_spurious)
    assert np.all(np.isfinite(spurious))
    assert abs(np.median(spurious) - np.median(clean)) < 0.1


def _occlude_half(frame) -> np.ndarray:
    """Cover the left half of the visible tags with a dark hand-like blob."""
    image = frame.image.copy()
    pts = np.concatenate(list(frame.corners_px.values()))
    xs = np.sort(np.array([c[:, 0].mean() for c in frame.corners_px.values()]))
    x_split = 0.5 * (xs[len(xs) // 2 - 1] + xs[len(xs) // 2]) if len(xs) > 1 else xs[0]
    y0, y1 = int(pts[:, 1].min()) - 20, int(pts[:, 1].max()) + 20
    x0 = int(pts[:, 0].min()) - 20
    cv2.rectangle(image, (x0, y0), (int(x_split), y1), 35, thickness=-1)
    return image


def test_half_occluded() -> None:
    scene, frames = _frames("540p", 36, seed=7)
    clean = _errors(OURS, scene, frames)
    occluded = _errors(OURS, scene, frames, edit=_occlude_half)
    assert np.all(np.isfinite(occluded)), "no pose with half the tags occluded"
    assert np.median(occluded) < 2.0 * np.median(clean)


def test_a_frame_result_and_pose_settings_replaced_between_frames() -> None:
    """What a frame shows: its tags (ids sorted, each once), the cap pose, how they were found and
    the time spent; ``pose_config`` replaced as a whole applies from the next frame (the node's
    parameters), and an unset uncertainty is the default corners' profile."""
    from ficap_ros.vision.uncertainty import UncertaintyConfig

    scene, frames = _frames("540p", 2, seed=3)
    proc = FrameProcessor(MODEL)
    assert proc.effective_pose_config.uncertainty == UncertaintyConfig()
    r = proc.process(frames[0][0].image, scene.camera, 1_000)
    assert r.pose is not None and r.reason == "" and r.search == "image"
    assert r.detected_ids == tuple(sorted({d.tag_id for d in r.detections}))
    assert r.tags_detected == len(r.detected_ids) >= r.pose.tags_used
    assert r.detect_ms > 0 and r.pose_ms > 0
    proc.pose_config = PoseConfig(method="paper")
    r = proc.process(frames[1][0].image, scene.camera, 2_000)
    assert r.pose is not None and r.pose.method == "paper"
    assert proc.effective_pose_config.method == "paper"
    assert FrameProcessor(MODEL, tracking=False).process(np.full((540, 960), 90, np.uint8),
                                                         scene.camera).reason


def test_tracked_frames_give_the_cap_velocity() -> None:
    """Consecutive 30 fps frames through a glance: the first frame (searched, nothing before it)
    has no velocity; the tracked ones have the velocity of their poses' finite difference, near
    the true one and within what its covariance says. Without a stated timing the same poses come
    without a velocity, while the frames still give their readout evidence."""
    from ficap_ros.geometry.camera import CameraTiming
    from ficap_ros.tools.synth import naturalistic_motion

    scene = default_scene("540p")
    motion = naturalistic_motion(12.0, seed=2, scene=scene)
    times = np.arange(3.0, 12.0, 1 / 30)
    speeds = [angle_deg(motion.T_cam_cap_at(t - 0.005).rotation, motion.T_cam_cap_at(t + 0.005).rotation)
              / 0.01 for t in times]
    t_fast = float(times[int(np.argmax(speeds))])
    # Frames rendered without motion blur: the motion-aware corners (which would model the
    # stated exposure's blur) are off, so the poses are the same corners' with or without timing.
    proc = FrameProcessor(MODEL, DetectorConfig(motion_corners=False), timing=CameraTiming(exposure_ms=8.0),
                          readout_evidence=True)
    bare = FrameProcessor(MODEL, readout_evidence=True)
    assert proc.timing.exposure_ms == 8.0 and not proc.timing.rolling
    for k in range(-3, 2):
        t = t_fast + k / 30
        frame = render(MODEL, scene.camera, motion.T_cam_cap_at(t), RenderConfig(lighting="neutral"), seed=k + 10)
        r = proc.process(frame.image, scene.camera, int(round(t * 1e9)))
        b = bare.process(frame.image, scene.camera, int(round(t * 1e9)))
        assert b.pose.velocity is None and b.pose.velocity_covariance is None
        np.testing.assert_array_equal(b.pose.T_cam_cap.matrix, r.pose.T_cam_cap.matrix)
        assert (b.timing_evidence is None) == (k == -3)
        if k == -3:
            assert r.pose.velocity is None and r.pose.velocity_covariance is None
            assert r.timing_evidence is None  # no velocity: nothing said of the readout
            continue
        # A global shutter: the frame's readout evidence is none within its error.
        ev = r.timing_evidence
        assert ev is not None and abs(ev.readout_s) < 4.0 * np.sqrt(ev.readout_var_s2)
        a, b = motion.T_cam_cap_at(t - 1e-4), motion.T_cam_cap_at(t + 1e-4)
        w_true = (b * a.inv()).rvec / 2e-4
        w_err = r.pose.velocity[3:] - w_true
        sigma = np.sqrt(np.diag(r.pose.velocity_covariance)[3:])
        assert np.degrees(np.linalg.norm(w_true)) > 50.0
        assert np.degrees(np.abs(w_err)).max() < 25.0 and np.all(np.abs(w_err) < 4.0 * sigma)


def test_the_camera_timing_is_a_setting_of_the_processor() -> None:
    """``timing`` is held as given (``CameraTiming()``, not known, by default) and, like
    ``pose_config``, replaced as a whole between frames."""
    from ficap_ros.geometry.camera import CameraTiming

    assert FrameProcessor(MODEL).timing == CameraTiming()
    rs = CameraTiming(exposure_ms=16.7, readout_ms=22.0, stamp_offset_ms=-5.0)
    proc = FrameProcessor(MODEL, tracking=False, timing=rs)
    assert proc.timing is rs
    proc.timing = CameraTiming(exposure_ms=4.0)
    scene, frames = _frames("540p", 2, seed=3)
    assert proc.process(frames[0][0].image, scene.camera).pose is not None
    assert proc.timing == CameraTiming(exposure_ms=4.0)


def test_corner_estimator_names_the_uncertainty_profile() -> None:
    """The cell-edge corners, the photometric ones and every refinement that keeps the tone
    curve's bias each get their own profile when the pose's uncertainty is not set."""
    from ficap_ros.vision.pipeline import corner_estimator, pose_config_for
    from ficap_ros.vision.uncertainty import UncertaintyConfig

    assert corner_estimator(DetectorConfig()) == "edge"
    assert corner_estimator(DetectorConfig(edge_photometric=True)) == "photometric"
    for refine in ("subpix", "apriltag", "none"):
        assert corner_estimator(DetectorConfig(corner_refine=refine)) == "uncorrected"
    peer = pose_config_for(PoseConfig(method="naive"), DetectorConfig(corner_refine="subpix"))
    assert peer.uncertainty == UncertaintyConfig.for_corners("uncorrected")
