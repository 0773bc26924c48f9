"""The node's own messages (ficap_ros.ros.msgs: diagnostics, markers, debug image) and the
parameter table, without DDS traffic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from std_msgs.msg import Header

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.params import PARAMETERS, validate_parameter

CONFIG = Path(__file__).resolve().parents[2] / "config" / "ficap.yaml"


def _grey(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


def test_status_values_are_strings() -> None:
    st = ros_msgs.diagnostic_status("ficap", ros_msgs.LEVEL_WARN, "m",
                                    {"a": 1, "b": 0.123456, "c": True})
    assert [(kv.key, kv.value) for kv in st.values] == [("a", "1"), ("b", "0.1235"), ("c", "true")]
    arr = ros_msgs.diagnostic_array(Header(frame_id="x"), st)
    assert arr.status[0].level == ros_msgs.LEVEL_WARN



# -- parameters ----------------------------------------------------------------------------------
def test_config_file_lists_every_parameter_with_its_default() -> None:
    # Keyed '/**' so it applies under any node name and namespace.
    data = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert set(data) == {p.name for p in PARAMETERS}
    for p in PARAMETERS:
        assert data[p.name] == p.default and type(data[p.name]) is type(p.default), p.name
        assert validate_parameter(p.name, p.default) == ""


def test_validation_rejects_out_of_range_and_unknown_choices() -> None:
    assert "within" in validate_parameter("pose.min_tags", 0)
    assert "within" in validate_parameter("calibration.max_spread_deg", 100.0)
    assert "finite" in validate_parameter("calibration.window_s", float("nan"))
    assert "one of" in validate_parameter("pose.method", "magic")
    assert "one of" in validate_parameter("image_transport", "theora")
    assert "must be a" in validate_parameter("pose.min_tags", "3")
    assert validate_parameter("warn_throttle_s", 2) == ""  # int accepted for a float
    assert validate_parameter("camera_mount", [0.0] * 7) == ""  # all zeros: not set
    assert validate_parameter("camera_mount", [0.1, 0.0, 1.2, 0.5, -0.5, 0.5, -0.5]) == ""
    assert "unit length" in validate_parameter("camera_mount", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])
    assert "7 finite" in validate_parameter("camera_mount", [0.0, 0.0, 1.0])
    assert "7 finite" in validate_parameter("camera_mount", [float("nan")] * 3 + [0.0, 0.0, 0.0, 1.0])
    assert validate_parameter("use_sim_time", True) == ""


def test_markers_and_debug_image_without_pose() -> None:
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.labels import FrameRecord

    rec = FrameRecord.processed(0, 0, "cam", None, (), "no tags")
    arr = ros_msgs.markers_msg(Header(frame_id="cam"), nominal_model(), rec)
    assert len(arr.markers) == 1  # only DELETEALL
    img = ros_msgs.debug_image_msg(_grey(), (), None, CameraModel.pinhole(64, 48, hfov_deg=60),
                                   Header(frame_id="cam"))
    assert img.encoding == "bgr8" and img.width == 64 and len(img.data) == 64 * 48 * 3


def test_pose_outputs_are_the_records_head_pose() -> None:
    """The node's pose messages are the frame record's poses (labels.mcap's): in the camera's
    frame and the frontal frame without a mount; through the mount into output_frame with one."""
    from ficap_ros.geometry.metrics import yaw_pitch_roll_deg
    from ficap_ros.io.labels import FrameRecord
    from ficap_ros.vision.calibration import HeadCalibration, frontal_from_camera_mount
    from ficap_ros.vision.pose import CapPose

    T_cam_cap = Transform(Rotation.from_euler("xyz", [160.0, 15.0, -5.0], degrees=True), [0.02, 0.05, 0.6])
    pose = CapPose(T_cam_cap, 5, 5, (1, 2, 3, 4, 5), 0.1, np.diag([1e-6] * 3 + [1e-5] * 3), 0.9, "joint")
    rec = FrameRecord.processed(0, 10, "cam", pose, (1, 2, 3, 4, 5), calibration=HeadCalibration(
        Rotation.from_euler("y", 10.0, degrees=True), calibrated=True))
    header = Header(frame_id="cam")

    def q(msg) -> np.ndarray:
        o = msg.pose.orientation
        return np.array([o.x, o.y, o.z, o.w])

    out = ros_msgs.pose_outputs(header, rec, "", "ficap_frontal", None)
    assert out["head"].header.frame_id == "cam" and out["head_frontal"].header.frame_id == "ficap_frontal"
    assert np.allclose(q(out["head"]), rec.T_cam_head.q_xyzw, rtol=0, atol=1e-15)
    assert np.allclose(q(out["cap"]), T_cam_cap.q_xyzw, rtol=0, atol=1e-15)
    assert np.array_equal(q(out["head_frontal"]), rec.T_frontal_head.q_xyzw)
    ypr = yaw_pitch_roll_deg(rec.T_frontal_head.rotation)
    assert (out["rpy"].vector.z, out["rpy"].vector.y, out["rpy"].vector.x) == pytest.approx(tuple(ypr))
    assert np.allclose(np.reshape(out["head_cov"].pose.covariance, (6, 6)), pose.covariance)

    mount = Transform(Rotation.from_euler("y", 10.0, degrees=True) * frontal_from_camera_mount(None).inv(),
                      [0.2, 0.0, 1.1])
    out = ros_msgs.pose_outputs(header, rec, "base_link", "ficap_frontal", mount)
    assert out["head"].header.frame_id == out["head_frontal"].header.frame_id == "base_link"
    p = out["head"].pose.position
    assert np.allclose([p.x, p.y, p.z], (mount * rec.T_cam_head).translation_m, atol=1e-12)
    cov = np.reshape(out["head_cov"].pose.covariance, (6, 6))
    assert np.trace(cov) == pytest.approx(np.trace(pose.covariance))  # rotated, not rescaled


def test_pose_outputs_carry_the_twist_only_when_measured() -> None:
    """``pose_outputs`` adds ``twist`` (``ros.twist.head_twist``) for a pose with a velocity and
    nothing for one without; the poses are the same either way."""
    from dataclasses import replace

    from ficap_ros.io.labels import FrameRecord
    from ficap_ros.vision.pose import CapPose

    T_cam_cap = Transform(Rotation.from_euler("xyz", [160.0, 15.0, -5.0], degrees=True), [0.02, 0.05, 0.6])
    pose = CapPose(T_cam_cap, 5, 5, (1, 2, 3, 4, 5), 0.1, np.eye(6) * 1e-6, 0.9, "joint")
    header = Header(frame_id="cam")
    without = ros_msgs.pose_outputs(header, FrameRecord.processed(0, 10, "cam", pose, (1,)), "",
                                    "ficap_frontal", None)
    moving = replace(pose, velocity=np.array([0.1, 0.0, -0.02, 0.3, -3.5, 0.1]))
    with_twist = ros_msgs.pose_outputs(header, FrameRecord.processed(0, 10, "cam", moving, (1,)),
                                       "", "ficap_frontal", None)
    assert "twist" not in without and set(with_twist) == set(without) | {"twist"}
    assert all(with_twist[k] == without[k] for k in without)
    assert with_twist["twist"].header.frame_id == "cam"
    assert with_twist["twist"].twist.angular.y == -3.5
