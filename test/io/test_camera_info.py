"""ficap_ros.io.camera_info: which CameraInfo an image uses, and CameraInfo (rosbags' or rclpy's)
-> CameraModel."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from sensor_msgs.msg import CameraInfo

from ficap_ros.errors import FicapError, IntrinsicsError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.io.camera_info import (
    CameraInfoCache,
    camera_from_info,
    camera_info_key,
    pick_camera_info,
)
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.ros.msgs import RCLPY

MS = 1_000_000


def test_pick_camera_info_nearest_within_tolerance_else_last_before() -> None:
    stamps = [100 * MS, 105 * MS, 105 * MS, 120 * MS]
    assert pick_camera_info(stamps, 100 * MS, MS) == 0  # equal stamp
    assert pick_camera_info(stamps, 119 * MS + 500_000, MS) == 3  # 0.5 ms after the image
    assert pick_camera_info(stamps, 110 * MS, MS) == 2  # none close: the last at or before
    assert pick_camera_info(stamps, 105 * MS, MS) == 2  # equal stamps: the last received
    assert pick_camera_info(stamps, 99 * MS, MS) == 0  # 1 ms before the first: within
    assert pick_camera_info(stamps, 50 * MS, MS) == 0  # before every one: the first
    assert pick_camera_info(stamps, 500 * MS, MS) == 3
    assert pick_camera_info([0, 10], 5, 5) == 0  # a tie: the earlier
    assert pick_camera_info([0, 10], 6, 5) == 1  # the nearer
    assert pick_camera_info([0, 10], 6, 0) == 0  # zero tolerance: the last before


@given(stamps=st.lists(st.integers(0, 10**6), min_size=1, max_size=20),
       stamp=st.integers(-10, 10**6 + 10), tolerance=st.integers(0, 10**5))
def test_pick_camera_info_takes_a_nearest_close_one_else_the_last_before(
        stamps: list[int], stamp: int, tolerance: int) -> None:
    stamps = sorted(stamps)
    i = pick_camera_info(stamps, stamp, tolerance)
    assert 0 <= i < len(stamps)
    nearest = min(abs(s - stamp) for s in stamps)
    before = [k for k, s in enumerate(stamps) if s <= stamp]
    if stamps[i] > stamp:  # after the image: only when close and strictly nearer than any before
        assert stamps[i] - stamp <= tolerance or not before
        assert stamps[i] - stamp == nearest or not before
        assert not before or stamp - stamps[before[-1]] > stamps[i] - stamp
    else:  # at or before: the last such
        assert i == before[-1]


@given(fx=st.floats(50.0, 3000.0), k1=st.floats(-0.3, 0.3), rectified=st.booleans())
def test_camera_from_info_inverts_the_camera_info_builder(fx: float, k1: float,
                                                          rectified: bool) -> None:
    camera = CameraModel(640, 480, np.array([[fx, 0.0, 320.5], [0.0, fx * 1.01, 239.0],
                                             [0.0, 0.0, 1.0]]),
                         np.array([k1, 0.01, 0.0, 0.001, 0.0]), "plumb_bob")
    msg = messages.camera_info(ROSBAGS, messages.header(ROSBAGS, 5, "cam"), camera)
    back = camera_from_info(msg, rectified=rectified)
    if rectified:  # P's 3x3 (= K here) and no distortion
        assert back.distortion_model == "none"
        np.testing.assert_array_equal(back.K, camera.K)
    else:
        assert back == camera
    assert camera_info_key(msg) == camera_info_key(
        messages.camera_info(ROSBAGS, messages.header(ROSBAGS, 9, "other"), camera))


def test_camera_info_cache_picks_by_stamp_and_falls_back_to_static() -> None:
    static = CameraModel.pinhole(640, 480, f_px=500.0)
    cache = CameraInfoCache(static)
    assert cache.camera_for(0, MS, False) is static
    a, b = CameraModel.pinhole(640, 480, f_px=600.0), CameraModel.pinhole(640, 480, f_px=700.0)
    for stamp, cam in ((100 * MS, a), (200 * MS, b)):
        cache.add(stamp, messages.camera_info(ROSBAGS, messages.header(ROSBAGS, stamp, "c"), cam))
    assert cache.has(100 * MS) and not cache.has(150 * MS)
    # CameraInfo carries an ideal lens as plumb_bob with five zeros: the same K, no distortion.
    for stamp, cam in ((150 * MS, a), (int(199.5 * MS), b)):
        got = cache.camera_for(stamp, MS, False)
        np.testing.assert_array_equal(got.K, cam.K)
        assert not got.is_distorted
    assert CameraInfoCache(None, "no file").static_error == "no file"


def info_at(**kw: object) -> CameraInfo:
    """An rclpy CameraInfo with K, D and a different P, fields overridden by ``kw``."""
    msg = CameraInfo(width=640, height=480, distortion_model="plumb_bob",
                     d=[-0.1, 0.01, 0.0, 0.0, 0.0],
                     k=[500.0, 0.0, 320.0, 0.0, 510.0, 240.0, 0.0, 0.0, 1.0],
                     p=[480.0, 0.0, 315.0, 0.0, 0.0, 490.0, 238.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    for k, v in kw.items():
        setattr(msg, k, v)
    return msg


def test_camera_from_info_of_rclpy_messages() -> None:
    cam = camera_from_info(info_at())
    assert cam.distortion_model == "plumb_bob" and cam.K[0, 0] == 500.0 and cam.D[0] == -0.1
    rect = camera_from_info(info_at(), rectified=True)
    assert rect.distortion_model == "none" and rect.K[0, 0] == 480.0 and rect.K[1, 2] == 238.0
    back = messages.camera_info(RCLPY, messages.header(RCLPY, 0, ""), cam)
    assert camera_from_info(back).K.tolist() == cam.K.tolist()
    with pytest.raises(IntrinsicsError, match="all zero"):
        camera_from_info(info_at(k=[0.0] * 9, p=[0.0] * 12))
    # K all zero with a valid P (some drivers): P, as the bag tools do (one rule).
    assert camera_from_info(info_at(k=[0.0] * 9)).K.tolist() == rect.K.tolist()
    with pytest.raises(IntrinsicsError, match="NaN"):
        camera_from_info(info_at(k=[float("nan")] + [0.0] * 8))
    with pytest.raises(IntrinsicsError, match="P is all zero"):
        camera_from_info(info_at(p=[0.0] * 12), rectified=True)
    with pytest.raises(IntrinsicsError):
        camera_from_info(info_at(width=0, height=0))
    with pytest.raises(IntrinsicsError, match="distortion model"):
        camera_from_info(info_at(distortion_model="weird_lens"))


def test_camera_info_with_only_p_one_rule_for_node_and_bags() -> None:
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import CameraInfo

    p = [400.0, 0.0, 320.0, 0.0, 0.0, 410.0, 240.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    ros = CameraInfo(width=640, height=480, distortion_model="plumb_bob", d=[0.1] * 5,
                     k=[0.0] * 9, p=p)
    t = get_typestore(Stores.ROS2_JAZZY).types
    stamp = t["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    bag = t["sensor_msgs/msg/CameraInfo"](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="c"), height=480, width=640,
        distortion_model="plumb_bob", d=np.full(5, 0.1), k=np.zeros(9), r=np.eye(3).ravel(),
        p=np.array(p), binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False))

    node_cam = camera_from_info(ros)
    bag_cam = camera_from_info(bag)
    for cam in (node_cam, bag_cam):
        np.testing.assert_allclose(cam.K, [[400, 0, 320], [0, 410, 240], [0, 0, 1]])
        assert cam.distortion_model == "none"
    ros.p = [0.0] * 12
    with pytest.raises(IntrinsicsError, match="all zero"):
        camera_from_info(ros)
    ros.k = [float("nan")] * 9
    with pytest.raises(FicapError):
        camera_from_info(ros)


def test_camera_info_beside_the_image_topic() -> None:
    """image_transport's getCameraInfoTopic: camera_info in the image topic's namespace."""
    from ficap_ros.io.camera_info import camera_info_beside

    assert camera_info_beside("/rear_cam/image_raw") == "/rear_cam/camera_info"
    assert camera_info_beside("/image") == "/camera_info"
    assert camera_info_beside("/a/b/image_rect/") == "/a/b/camera_info"
    assert camera_info_beside("image") == "camera_info"
    assert camera_info_beside("cam/image") == "cam/camera_info"
