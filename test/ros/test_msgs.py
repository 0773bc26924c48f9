"""Message conversions (ficap_ros.ros.msgs) and the parameter table, without DDS traffic."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from ficap_ros.errors import ImageError, IntrinsicsError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.params import PARAMETERS, validate_parameter

CONFIG = Path(__file__).resolve().parents[2] / "config" / "ficap.yaml"


def _grey(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


def _msg(arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> Image:
    """An Image with ``pad`` bytes of row padding (so step != width * bytes per pixel)."""
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
    np.testing.assert_array_equal(ros_msgs.image_to_array(_msg(want, "mono8", pad)), want)
    np.testing.assert_array_equal(ros_msgs.image_to_array(_msg(bgr, "bgr8", pad)), want)
    np.testing.assert_array_equal(ros_msgs.image_to_array(_msg(bgr[:, :, ::-1].copy(), "rgb8", pad)), want)
    bgra = np.dstack([bgr, np.full(bgr.shape[:2], 255, np.uint8)])
    np.testing.assert_array_equal(ros_msgs.image_to_array(_msg(bgra, "bgra8", pad)), want)
    rgba = np.dstack([bgr[:, :, ::-1], np.full(bgr.shape[:2], 9, np.uint8)])
    np.testing.assert_array_equal(ros_msgs.image_to_array(_msg(rgba, "rgba8", pad)), want)


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_respects_endianness(bigendian: bool) -> None:
    arr = np.random.default_rng(2).integers(0, 65536, (20, 30), dtype=np.uint16)
    out = ros_msgs.image_to_array(_msg(arr, "mono16", pad=6, bigendian=bigendian))
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
    out = ros_msgs.image_to_array(_msg(mosaic, encoding))
    want = cv2.cvtColor(np.array([[[b, g, r]]], np.uint8), cv2.COLOR_BGR2GRAY)[0, 0]
    assert np.all(np.abs(out[4:-4, 4:-4].astype(int) - int(want)) <= 2)


def test_bad_images_raise_image_error() -> None:
    good = _msg(_grey(), "mono8")
    bad = _msg(_grey(), "mono8")
    bad.encoding = "32FC1"  # float depth images are not a camera we read
    with pytest.raises(ImageError, match="unsupported image encoding"):
        ros_msgs.image_to_array(bad)
    short = Image(height=good.height, width=good.width, encoding="mono8", step=good.step,
                  data=bytes(good.data)[:-1])
    with pytest.raises(ImageError, match="image data holds"):
        ros_msgs.image_to_array(short)
    narrow = Image(height=4, width=10, encoding="bgr8", step=20, data=bytes(80))
    with pytest.raises(ImageError, match="smaller than a bgr8 row"):
        ros_msgs.image_to_array(narrow)
    with pytest.raises(ImageError, match="no pixels"):
        ros_msgs.image_to_array(Image(encoding="mono8"))


def test_compressed_images() -> None:
    gray = cv2.GaussianBlur(_grey(60, 80), (5, 5), 0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    assert ok
    out = ros_msgs.compressed_to_array(CompressedImage(format="png", data=png.tobytes()))
    np.testing.assert_array_equal(out, gray)
    ok, jpg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = ros_msgs.compressed_to_array(CompressedImage(format="jpeg", data=jpg.tobytes()))
    assert out.shape == gray.shape and np.mean(np.abs(out.astype(int) - gray)) < 4
    with pytest.raises(ImageError, match="cannot decode"):
        ros_msgs.compressed_to_array(CompressedImage(format="jpeg", data=jpg.tobytes()[:40]))
    with pytest.raises(ImageError, match="empty"):
        ros_msgs.compressed_to_array(CompressedImage(format="jpeg"))


def info_at(**kw: object) -> CameraInfo:
    msg = CameraInfo(width=640, height=480, distortion_model="plumb_bob",
                     d=[-0.1, 0.01, 0.0, 0.0, 0.0],
                     k=[500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0],
                     p=[480.0, 0.0, 315.0, 0.0, 0.0, 490.0, 238.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    for k, v in kw.items():
        setattr(msg, k, v)
    return msg


def test_camera_info_to_model() -> None:
    cam = ros_msgs.camera_info_to_model(info_at())
    assert cam.distortion_model == "plumb_bob" and cam.K[0, 0] == 500.0 and cam.D[0] == -0.1
    rect = ros_msgs.camera_info_to_model(info_at(), rectified=True)
    assert rect.distortion_model == "none" and rect.K[0, 0] == 480.0 and rect.K[1, 2] == 238.0
    back = ros_msgs.camera_model_to_info(cam)
    assert ros_msgs.camera_info_to_model(back).K.tolist() == cam.K.tolist()
    with pytest.raises(IntrinsicsError, match="all zero"):
        ros_msgs.camera_info_to_model(info_at(k=[0.0] * 9, p=[0.0] * 12))
    # K all zero with a valid P (some drivers): P, as the bag tools do (one rule).
    assert ros_msgs.camera_info_to_model(info_at(k=[0.0] * 9)).K.tolist() == rect.K.tolist()
    with pytest.raises(IntrinsicsError, match="NaN"):
        ros_msgs.camera_info_to_model(info_at(k=[float("nan")] + [0.0] * 8))
    with pytest.raises(IntrinsicsError, match="P is all zero"):
        ros_msgs.camera_info_to_model(info_at(p=[0.0] * 12), rectified=True)
    with pytest.raises(IntrinsicsError):
        ros_msgs.camera_info_to_model(info_at(width=0, height=0))
    with pytest.raises(IntrinsicsError, match="distortion model"):
        ros_msgs.camera_info_to_model(info_at(distortion_model="weird_lens"))


def test_pose_messages_and_stamps() -> None:
    T = Transform(Rotation.from_euler("xyz", [10, -20, 30], degrees=True), [0.1, -0.2, 0.7])
    header = Header(stamp=ros_msgs.ns_to_stamp(1_234_567_890_123), frame_id="cam")
    assert ros_msgs.stamp_to_ns(header.stamp) == 1_234_567_890_123
    msg = ros_msgs.pose_stamped(header, T)
    q = msg.pose.orientation
    assert Rotation.from_quat([q.x, q.y, q.z, q.w]).approx_equal(T.rotation, atol=1e-12)
    assert (msg.pose.position.x, msg.pose.position.z) == (0.1, 0.7)
    cov = np.diag(np.arange(1.0, 7.0))
    with_cov = ros_msgs.pose_with_covariance_stamped(header, T, cov)
    assert list(with_cov.pose.covariance)[0] == 1.0 and list(with_cov.pose.covariance)[35] == 6.0
    assert with_cov.header.frame_id == "cam"


def test_status_values_are_strings() -> None:
    st = ros_msgs.diagnostic_status("ficap", ros_msgs.LEVEL_WARN, "m",
                                    {"a": 1, "b": 0.123456, "c": True})
    assert [(kv.key, kv.value) for kv in st.values] == [("a", "1"), ("b", "0.1235"), ("c", "true")]
    arr = ros_msgs.diagnostic_array(Header(frame_id="x"), st)
    assert arr.status[0].level == ros_msgs.LEVEL_WARN


def test_array_to_image_round_trip() -> None:
    g = _grey()
    np.testing.assert_array_equal(ros_msgs.image_to_array(ros_msgs.array_to_image(g, "mono8")), g)
    with pytest.raises(ImageError):
        ros_msgs.array_to_image(g, "bgr8")


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
