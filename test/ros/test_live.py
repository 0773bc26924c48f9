"""ficap_ros.ros.live: the node's frame without ROS, driven here by rosbags messages (the node feeds
rclpy's; test_live_offline compares the node with replay)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.camera_info import CameraInfoCache
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.status import ERROR, OK, WARN, FrameStatus
from ficap_ros.ros.live import (
    failed_frame,
    frame_processor,
    process_image,
    reference_q_xyzw,
)
from ficap_ros.tools.synth import RenderConfig, default_scene, render
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pipeline import FrameProcessor

CONFIG = SimpleNamespace(camera_info_max_stamp_diff_ms=1.0, image_is_rectified=False,
                         publish_min_reliability=0.0, warn_reliability=0.5)
S = 5_000_000_000


def test_a_rendered_image_gives_its_pose_and_an_ok_status() -> None:
    scene = default_scene("540p")
    truth = scene.cap_pose(Transform.identity().rotation)
    image = render(nominal_model(), scene.camera, truth, RenderConfig(), seed=11).image
    cameras = CameraInfoCache()
    cameras.add(S, messages.camera_info(ROSBAGS, messages.header(ROSBAGS, S, "cam"), scene.camera))
    msg = messages.image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), image, "mono8")
    frame = process_image(msg, FrameProcessor(model=nominal_model()), cameras, HeadCalibration(),
                          CONFIG)
    assert (frame.level, frame.message) == (OK, "pose") and frame.publish_pose
    rec = frame.record
    assert rec.status is FrameStatus.POSE and rec.T_cam_cap is not None and not frame.failed
    assert angle_deg(rec.T_cam_cap.rotation, truth.rotation) < 0.2
    assert np.abs(rec.T_cam_cap.translation_m - truth.translation_m).max() < 0.005
    assert rec.stamp_ns == S and rec.frame_id == "cam" and frame.image is not None
    assert rec.detected_ids == tuple(sorted({d.tag_id for d in frame.detections}))
    assert rec.T_cam_head is not None and not rec.calibrated
    values = frame.status_values(12.5, 3)
    assert values["search"] == frame.search == "image" and values["dropped_frames"] == 3
    assert frame.quality_values(12.5)["latency_ms"] == 12.5
    # Not reliable enough to publish: the status says so, the pose is kept back.
    strict = SimpleNamespace(**{**vars(CONFIG), "publish_min_reliability": 1.01,
                                "warn_reliability": 1.01})
    frame = process_image(msg, FrameProcessor(model=nominal_model()), cameras, HeadCalibration(),
                          strict)
    assert frame.level == WARN and frame.message.startswith("low reliability")
    assert not frame.publish_pose


def test_errors_become_failed_frames() -> None:
    grey = np.zeros((540, 960), np.uint8)
    msg = messages.image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), grey, "mono8")
    frame = process_image(msg, FrameProcessor(model=nominal_model()), CameraInfoCache(),
                          HeadCalibration(), CONFIG)
    assert frame.level == ERROR and "no CameraInfo" in frame.message and frame.failed
    assert frame.record.reason == frame.message and frame.image is None
    bad = messages.compressed_image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), b"not a jpeg", "jpeg")
    frame = process_image(bad, FrameProcessor(model=nominal_model()), CameraInfoCache(),
                          HeadCalibration(), CONFIG)
    assert frame.level == ERROR and frame.failed and frame.record.stamp_ns == S
    frame = failed_frame(S, "cam", "internal error: boom", HeadCalibration())
    assert (frame.level, frame.message, frame.record.reason) == (
        ERROR, "internal error: boom", "internal error: boom")
    assert frame.record.status is FrameStatus.FAILED and not frame.record.skipped


def test_the_node_settings_build_its_pipeline() -> None:
    """``frame_processor``: the cap model, detector, pose and tracking of the node's settings."""
    from ficap_ros.vision.detector import DetectorConfig
    from ficap_ros.vision.pose import PoseConfig

    cfg = SimpleNamespace(model_file="", detector_config=DetectorConfig(edge_photometric=True),
                          pose_config=PoseConfig(method="paper"), tracking=False)
    proc = frame_processor(cfg)
    assert proc.tracker is None and proc.detector.config.edge_photometric
    assert proc.pose_config.method == "paper" and proc.model.ids == nominal_model().ids
    # The pose settings resolved for photometric corners: that profile's uncertainty.
    assert proc.effective_pose_config.uncertainty.light_gradient_tilt_gain == 0.1


def test_reference_quaternions_are_checked_and_normalised() -> None:
    T = Transform.identity()
    msg = messages.pose_stamped(ROSBAGS, messages.header(ROSBAGS, S, "ref"), T)
    msg.pose.orientation.w = 2.0
    assert reference_q_xyzw(msg) == pytest.approx([0.0, 0.0, 0.0, 1.0])
    msg.pose.orientation.w = 0.0
    assert reference_q_xyzw(msg) is None
    msg.pose.orientation.x = float("nan")
    assert reference_q_xyzw(msg) is None
