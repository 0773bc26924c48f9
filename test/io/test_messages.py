"""ficap_ros.io.messages: one set of conversions over the message fields, fed by rclpy's classes
(``ros_msgs.RCLPY``, the node) and by the rosbags typestore's (``messages.ROSBAGS``, the bag
tools): the same input gives the same fields and the same core types."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import bag_writer, messages
from ficap_ros.io.camera_info import camera_from_info
from ficap_ros.io.messages import ROSBAGS, jazzy_typestore
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.msgs import RCLPY

T = Transform(Rotation.from_euler("xyz", [10.0, -20.0, 33.0], degrees=True),
              np.array([0.05, -0.02, 0.61]))
STAMP_NS = 1_700_000_123_456_789
CAMERA = CameraModel(960, 540, np.array([[700.0, 0.0, 481.5], [0.0, 705.0, 270.25], [0, 0, 1]]),
                     np.array([0.1, -0.05, 0.001, 0.002, 0.0]), "plumb_bob")
COV = np.diag([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4]) + 1e-8


def _both(build) -> tuple[object, object]:
    """One builder through both classes, each with its own header."""
    return (build(RCLPY, messages.header(RCLPY, STAMP_NS, "cam")),
            build(ROSBAGS, messages.header(ROSBAGS, STAMP_NS, "cam")))


def _same_cdr(live: object, offline: object, msgtype: str) -> None:
    """rclpy reads the rosbags message's CDR back as the live message, field for field (bytes
    are not compared: rclpy leaves padding unset and writes trailing bytes after empty arrays)."""
    offline_cdr = bytes(jazzy_typestore().serialize_cdr(offline, msgtype))
    assert deserialize_message(offline_cdr, type(live)) == live
    assert len(bytes(serialize_message(live))) >= len(offline_cdr)


@pytest.mark.parametrize("builder,msgtype", [
    (lambda c, h: messages.pose_stamped(c, h, T), "geometry_msgs/msg/PoseStamped"),
    (lambda c, h: messages.pose_with_covariance_stamped(c, h, T, COV),
     "geometry_msgs/msg/PoseWithCovarianceStamped"),
    (lambda c, h: messages.camera_info(c, h, CAMERA), "sensor_msgs/msg/CameraInfo"),
    (lambda c, h: messages.rpy_deg(c, h, T.rotation), "geometry_msgs/msg/Vector3Stamped"),
    (lambda c, h: messages.named_values(c, h, {"tags_used": 7, "rms_px": 0.12}),
     "sensor_msgs/msg/JointState"),
    (lambda c, h: messages.image(c, h, np.arange(12 * 7, dtype=np.uint8).reshape(7, 12), "mono8"),
     "sensor_msgs/msg/Image"),
    (lambda c, h: messages.image(c, h, np.arange(6 * 5, dtype=np.uint16).reshape(5, 6) * 999,
                                 "mono16"), "sensor_msgs/msg/Image"),
    (lambda c, h: messages.compressed_image(c, h, b"\x89PNG-not-really", "png"),
     "sensor_msgs/msg/CompressedImage"),
])
def test_one_builder_gives_the_same_message_live_and_offline(builder, msgtype: str) -> None:
    live, offline = _both(builder)
    _same_cdr(live, offline, msgtype)


def test_poses_read_back_the_same_through_both_classes() -> None:
    live, offline = _both(lambda c, h: messages.pose_with_covariance_stamped(c, h, T, COV))
    for msg in (live, offline):
        back = messages.pose_to_transform(msg)
        assert np.abs(back.translation_m - T.translation_m).max() < 1e-15
        assert np.abs(back.rotation.as_quat() - T.rotation.as_quat()).max() < 1e-15
        o = messages.orientation(msg)
        assert (o.x, o.y, o.z, o.w) == tuple(float(v) for v in T.q_xyzw)
        np.testing.assert_array_equal(np.asarray(msg.pose.covariance).reshape(6, 6), COV)
    # The node's wrappers and the bag tools' are the same builders.
    _same_cdr(ros_msgs.pose_stamped(live.header, T), bag_writer.pose_stamped_msg(STAMP_NS, "cam", T),
              "geometry_msgs/msg/PoseStamped")
    _same_cdr(ros_msgs.camera_model_to_info(CAMERA, live.header),
              bag_writer.camera_info_msg(STAMP_NS, "cam", CAMERA), "sensor_msgs/msg/CameraInfo")


def test_named_values_keep_nan_on_both_sides() -> None:
    live, offline = _both(lambda c, h: messages.named_values(c, h, {"a": 1.5, "b": float("nan")}))
    for msg in (live, offline):
        assert list(msg.name) == ["a", "b"] and len(msg.velocity) == len(msg.effort) == 0
        assert msg.position[0] == 1.5 and np.isnan(msg.position[1])


def test_unknown_covariance_goes_out_huge_on_both_sides() -> None:
    bad = np.full((6, 6), np.nan)
    live, offline = _both(lambda c, h: messages.pose_with_covariance_stamped(c, h, T, bad))
    for msg in (live, offline):
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        np.testing.assert_array_equal(cov, messages.UNKNOWN_COVARIANCE)


def test_camera_info_and_images_read_back_the_same_through_both_classes() -> None:
    k_zero = {"k": np.zeros(9)}  # some drivers fill only P: the CameraInfo rule takes P's 3x3
    for fields in ({}, k_zero):
        live, offline = _both(lambda c, h: messages.camera_info(c, h, CAMERA))
        for name, value in fields.items():
            setattr(live, name, [float(v) for v in value])
            setattr(offline, name, np.asarray(value, dtype=np.float64))
        for rectified in (False, True):
            a = camera_from_info(live, rectified)
            b = camera_from_info(offline, rectified)
            assert a == b and hash(a) == hash(b)
            assert np.abs(a.K - CAMERA.K).max() < 1e-12
            assert a.distortion_model == ("none" if rectified or fields else "plumb_bob")
    grey = np.random.default_rng(5).integers(0, 256, (9, 13), dtype=np.uint8)
    live, offline = _both(lambda c, h: messages.image(c, h, grey, "mono8"))
    np.testing.assert_array_equal(messages.image_to_array(live), grey)
    np.testing.assert_array_equal(messages.image_to_array(offline), grey)
    big = np.random.default_rng(6).integers(0, 65536, (4, 7), dtype=np.uint16).astype(">u2")
    live, offline = _both(lambda c, h: messages.image(c, h, big, "mono16"))
    assert live.is_bigendian == offline.is_bigendian == 1
    np.testing.assert_array_equal(messages.image_to_array(live), big.astype(np.uint16))
    np.testing.assert_array_equal(messages.image_to_array(offline), big.astype(np.uint16))
    for msg in (live, offline):
        assert messages.header(RCLPY, 0, "").stamp.sec == 0
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(STAMP_NS, 10**9)


def test_messages_module_is_ros_free() -> None:
    text = (Path(messages.__file__)).read_text()
    assert not re.search(r"^\s*(import|from) (rclpy|\w+_msgs|builtin_interfaces)\b", text, re.M)
