"""ficap_ros.io.messages: the one set of message builders and readers, fed by rclpy's classes
(``ros.msgs.RCLPY``, the node) and by the rosbags typestore's (``messages.ROSBAGS``, the bag
tools): the same input gives the same fields and the same core types."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from ficap_ros.errors import ImageError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.camera_info import camera_from_info
from ficap_ros.io.messages import ROSBAGS, jazzy_typestore
from ficap_ros.ros.msgs import RCLPY
from ficap_ros.stamps import stamp_to_ns

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
    (lambda c, h: messages.twist_stamped(c, h, [0.1, -0.2, 0.03, 2.5, -0.4, 0.01]),
     "geometry_msgs/msg/TwistStamped"),
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


@st.composite
def transforms(draw: st.DrawFn) -> Transform:
    """Any rigid transform: a rotation from a non-degenerate quaternion, a translation within
    a kilometre (metres)."""
    q = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(4)])
    if np.linalg.norm(q) < 1e-3:
        q = np.array([0.0, 0.0, 0.0, 1.0])
    t = np.array([draw(st.floats(-1000.0, 1000.0)) for _ in range(3)])
    return Transform(Rotation.from_quat(q), t)


def _serialized_and_back(c: messages.MessageClasses, msg: object, msgtype: str) -> object:
    """The message through its CDR bytes, as each side stores or sends it."""
    if c is ROSBAGS:
        store = jazzy_typestore()
        return store.deserialize_cdr(bytes(store.serialize_cdr(msg, msgtype)), msgtype)
    return deserialize_message(serialize_message(msg), type(msg))


@given(T=transforms(), stamp_ns=st.integers(0, 2**31 * 10**9 - 1),
       frame=st.text(st.characters(codec="ascii", categories=("L", "N")), max_size=20),
       live=st.booleans())
def test_pose_message_pose_round_trip(T: Transform, stamp_ns: int, frame: str,
                                      live: bool) -> None:
    """pose -> PoseStamped / PoseWithCovarianceStamped -> CDR -> pose, with rclpy's classes and
    with rosbags': the translation comes back exactly, the rotation to rounding, the stamp and
    frame exactly."""
    c = RCLPY if live else ROSBAGS
    head = messages.header(c, stamp_ns, frame)
    for msg, msgtype in ((messages.pose_stamped(c, head, T), "geometry_msgs/msg/PoseStamped"),
                         (messages.pose_with_covariance_stamped(c, head, T, COV),
                          "geometry_msgs/msg/PoseWithCovarianceStamped")):
        back_msg = _serialized_and_back(c, msg, msgtype)
        back = messages.pose_to_transform(back_msg)
        np.testing.assert_array_equal(back.translation_m, T.translation_m)
        assert (back.rotation.inv() * T.rotation).magnitude() < 1e-12
        o = messages.orientation(back_msg)
        assert (o.x, o.y, o.z, o.w) == tuple(float(v) for v in T.q_xyzw)
        assert stamp_to_ns(back_msg.header.stamp) == stamp_ns
        assert back_msg.header.frame_id == frame


@given(twist=st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=6, max_size=6),
       live=st.booleans())
def test_twist_message_round_trip(twist: list[float], live: bool) -> None:
    """(6,) twist -> TwistStamped -> CDR -> (6,): linear then angular, exactly, both classes."""
    c = RCLPY if live else ROSBAGS
    msg = messages.twist_stamped(c, messages.header(c, STAMP_NS, "cam"), np.array(twist))
    back = _serialized_and_back(c, msg, "geometry_msgs/msg/TwistStamped")
    np.testing.assert_array_equal(messages.twist_to_array(back), twist)
    np.testing.assert_array_equal(messages.twist_to_array(back.twist), twist)


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


# -- rclpy messages read and built (the node's side) ------------------------------------------
def _grey(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


def _msg(arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> Image:
    """An rclpy Image with ``pad`` bytes of row padding (so step != width * bytes per pixel)."""
    h, w = arr.shape[:2]
    rows = arr.reshape(h, -1)
    if arr.dtype == np.uint16:
        rows = arr.astype(">u2" if bigendian else "<u2").view(np.uint8).reshape(h, -1)
    padded = np.zeros((h, rows.shape[1] + pad), dtype=np.uint8)
    padded[:, : rows.shape[1]] = rows
    padded[:, rows.shape[1]:] = 77  # garbage that must be ignored
    return Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
                 step=padded.shape[1], data=padded.tobytes())



@pytest.mark.parametrize("pad", [0, 13])
def test_mono8_and_colour_encodings(pad: int) -> None:
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(messages.image_to_array(_msg(want, "mono8", pad)), want)
    np.testing.assert_array_equal(messages.image_to_array(_msg(bgr, "bgr8", pad)), want)
    np.testing.assert_array_equal(messages.image_to_array(
        _msg(bgr[:, :, ::-1].copy(), "rgb8", pad)), want)
    bgra = np.dstack([bgr, np.full(bgr.shape[:2], 255, np.uint8)])
    np.testing.assert_array_equal(messages.image_to_array(_msg(bgra, "bgra8", pad)), want)
    rgba = np.dstack([bgr[:, :, ::-1], np.full(bgr.shape[:2], 9, np.uint8)])
    np.testing.assert_array_equal(messages.image_to_array(_msg(rgba, "rgba8", pad)), want)


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_respects_endianness(bigendian: bool) -> None:
    arr = np.random.default_rng(2).integers(0, 65536, (20, 30), dtype=np.uint16)
    out = messages.image_to_array(_msg(arr, "mono16", pad=6, bigendian=bigendian))
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, arr)


# Where the red pixel of each 2x2 cell sits, per ROS encoding (row, col).
_BAYER_RED = {"bayer_rggb8": (0, 0), "bayer_bggr8": (1, 1), "bayer_gbrg8": (1, 0),
              "bayer_grbg8": (0, 1)}


@pytest.mark.parametrize("encoding", sorted(_BAYER_RED))
def test_bayer_patterns_demosaic_to_the_right_grey(encoding: str) -> None:
    # A flat colour mosaicked with the encoding's pattern: the interior must come back as the
    # colour's grey; a swapped R/B pattern would be off by tens of levels.
    b, g, r = 20, 120, 230
    h, w = 16, 20
    mosaic = np.full((h, w), g, np.uint8)
    ry, rx = _BAYER_RED[encoding]
    mosaic[ry::2, rx::2] = r
    mosaic[1 - ry::2, 1 - rx::2] = b
    out = messages.image_to_array(_msg(mosaic, encoding))
    want = cv2.cvtColor(np.array([[[b, g, r]]], np.uint8), cv2.COLOR_BGR2GRAY)[0, 0]
    assert np.all(np.abs(out[4:-4, 4:-4].astype(int) - int(want)) <= 2)


def test_bad_images_raise_image_error() -> None:
    good = _msg(_grey(), "mono8")
    bad = _msg(_grey(), "mono8")
    bad.encoding = "32FC1"  # float depth images are not a camera we read
    with pytest.raises(ImageError, match="unsupported image encoding"):
        messages.image_to_array(bad)
    short = Image(height=good.height, width=good.width, encoding="mono8", step=good.step,
                  data=bytes(good.data)[:-1])
    with pytest.raises(ImageError, match="image data holds"):
        messages.image_to_array(short)
    narrow = Image(height=4, width=10, encoding="bgr8", step=20, data=bytes(80))
    with pytest.raises(ImageError, match="smaller than a bgr8 row"):
        messages.image_to_array(narrow)
    with pytest.raises(ImageError, match="no pixels"):
        messages.image_to_array(Image(encoding="mono8"))


def test_compressed_images() -> None:
    gray = cv2.GaussianBlur(_grey(60, 80), (5, 5), 0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    assert ok
    out = messages.compressed_to_array(CompressedImage(format="png", data=png.tobytes()))
    np.testing.assert_array_equal(out, gray)
    ok, jpg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = messages.compressed_to_array(CompressedImage(format="jpeg", data=jpg.tobytes()))
    assert out.shape == gray.shape and np.mean(np.abs(out.astype(int) - gray)) < 4
    with pytest.raises(ImageError, match="cannot decode"):
        messages.compressed_to_array(CompressedImage(format="jpeg", data=jpg.tobytes()[:40]))
    with pytest.raises(ImageError, match="empty"):
        messages.compressed_to_array(CompressedImage(format="jpeg"))



def test_pose_messages_and_stamps() -> None:
    T = Transform(Rotation.from_euler("xyz", [10, -20, 30], degrees=True), [0.1, -0.2, 0.7])
    header = Header(stamp=messages.time(RCLPY, 1_234_567_890_123), frame_id="cam")
    assert stamp_to_ns(header.stamp) == 1_234_567_890_123
    msg = messages.pose_stamped(RCLPY, header, T)
    q = msg.pose.orientation
    assert Rotation.from_quat([q.x, q.y, q.z, q.w]).approx_equal(T.rotation, atol=1e-12)
    assert (msg.pose.position.x, msg.pose.position.z) == (0.1, 0.7)
    cov = np.diag(np.arange(1.0, 7.0))
    with_cov = messages.pose_with_covariance_stamped(RCLPY, header, T, cov)
    assert list(with_cov.pose.covariance)[0] == 1.0 and list(with_cov.pose.covariance)[35] == 6.0
    assert with_cov.header.frame_id == "cam"



def test_image_builder_checks_the_array_against_the_encoding() -> None:
    g = _grey()
    for c in (RCLPY, ROSBAGS):
        head = messages.header(c, 0, "")
        np.testing.assert_array_equal(messages.image_to_array(messages.image(c, head, g, "mono8")),
                                      g)
        with pytest.raises(ImageError, match="does not match"):
            messages.image(c, head, g, "bgr8")
        with pytest.raises(ImageError, match="unsupported"):
            messages.image(c, head, g.astype(np.float32), "32FC1")


def test_transform_stamped_and_rpy_rad_live_and_offline() -> None:
    for builder, msgtype in (
            (lambda c, h: messages.transform_stamped(c, h, "ficap_cap", T),
             "geometry_msgs/msg/TransformStamped"),
            (lambda c, h: messages.rpy_rad(c, h, T.rotation), "geometry_msgs/msg/Vector3Stamped")):
        live, offline = _both(builder)
        _same_cdr(live, offline, msgtype)
    live, _ = _both(lambda c, h: messages.transform_stamped(c, h, "ficap_cap", T))
    r, t = live.transform.rotation, live.transform.translation
    assert (r.x, r.y, r.z, r.w) == tuple(float(v) for v in T.q_xyzw)
    assert (t.x, t.y, t.z) == tuple(float(v) for v in T.translation_m)
    assert live.child_frame_id == "ficap_cap" and live.header.frame_id == "cam"
    deg, rad = (_both(lambda c, h, f=f: f(c, h, T.rotation))[0].vector
                for f in (messages.rpy_deg, messages.rpy_rad))
    np.testing.assert_allclose(np.radians([deg.x, deg.y, deg.z]), [rad.x, rad.y, rad.z], rtol=1e-13)


def test_the_vendored_apriltag_definitions_are_in_the_typestore() -> None:
    defs = messages.vendored_msg_definitions()
    assert list(defs) == ["apriltag_msgs/msg/Point", "apriltag_msgs/msg/AprilTagDetection",
                          "apriltag_msgs/msg/AprilTagDetectionArray"]
    assert "Point[4] corners" in defs["apriltag_msgs/msg/AprilTagDetection"]
    assert set(defs) <= set(jazzy_typestore().types)
