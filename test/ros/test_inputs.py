"""The node's subscriptions (ficap_ros.ros.inputs): the CameraInfo topic beside the image topic
(image_transport's rule) under remaps and namespaces, its parameter and remap, and the QoS from
``qos.*`` with rclpy's ``qos_overrides`` on top."""

from __future__ import annotations

import numpy as np
import pytest
import rclpy
from node_harness import header_at, info_at
from rclpy.context import Context
from rclpy.qos import ReliabilityPolicy

from ficap_ros.errors import ConfigError
from ficap_ros.io import messages
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.node import FicapNode


def _topics(cli_args: list[str] | None = None,
            overrides: dict | None = None) -> tuple[str, str, dict[str, object], list[str]]:
    """(image topic, CameraInfo topic, their reliabilities, unknown parameters) of a node started
    with these arguments."""
    from rclpy.parameter import Parameter

    context = Context()
    rclpy.init(context=context)
    try:
        node = FicapNode(context=context, cli_args=cli_args,
                         parameter_overrides=[Parameter(k, value=v) for k, v in (overrides or {}).items()])
        try:
            ins = node._inputs
            return (ins.image.topic_name, ins.camera_info.topic_name,
                    {"image": ins.image.qos_profile.reliability,
                     "camera_info": ins.camera_info.qos_profile.reliability,
                     "depth": ins.image.qos_profile.depth}, node.unknown_parameters)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_camera_info_is_beside_the_image_topic() -> None:
    assert _topics()[:2] == ("/image", "/camera_info")
    assert _topics(["--ros-args", "-r", "image:=/rear_cam/image_raw"])[:2] == (
        "/rear_cam/image_raw", "/rear_cam/camera_info")
    assert _topics(["--ros-args", "-r", "__ns:=/rear"])[:2] == ("/rear/image", "/rear/camera_info")
    # compressed: the base topic's namespace, not <image>/compressed's.
    assert _topics(["--ros-args", "-r", "image:=/cam/image_raw"],
                   {"image_transport": "compressed"})[:2] == ("/cam/image_raw/compressed",
                                                              "/cam/camera_info")
    # A remap of camera_info, and the parameter, win.
    assert _topics(["--ros-args", "-r", "image:=/a/image", "-r", "camera_info:=/b/info"])[1] == "/b/info"
    assert _topics(overrides={"camera_info_topic": "/calib/camera_info"})[1] == "/calib/camera_info"
    assert _topics(["--ros-args", "-r", "__ns:=/rear"], {"camera_info_topic": "info"})[1] == "/rear/info"


def test_qos_overrides_apply_to_image_and_camera_info() -> None:
    """qos.* set both; rclpy's qos_overrides.<topic>.subscription.* override per topic; a
    qos_overrides key of a topic the node does not subscribe is reported as unknown."""
    _, _, qos, unknown = _topics()
    assert qos["image"] == qos["camera_info"] == ReliabilityPolicy.BEST_EFFORT and qos["depth"] == 5
    _, _, qos, unknown = _topics(["--ros-args", "-p",
                                  "qos_overrides./image.subscription.reliability:=reliable",
                                  "-p", "qos_overrides./image.subscription.depth:=2",
                                  "-p", "qos_overrides./imgae.subscription.depth:=3"])
    assert qos["image"] == ReliabilityPolicy.RELIABLE and qos["depth"] == 2
    assert qos["camera_info"] == ReliabilityPolicy.BEST_EFFORT  # its own key was not given
    assert unknown == ["qos_overrides./imgae.subscription.depth"]
    _, _, qos, _ = _topics(["--ros-args", "-r", "image:=/rear/image_raw", "-p",
                            "qos_overrides./rear/camera_info.subscription.reliability:=reliable"],
                           {"qos.depth": 7})
    assert qos["camera_info"] == ReliabilityPolicy.RELIABLE and qos["depth"] == 7
    with pytest.raises(ConfigError, match="qos_overrides"):
        _topics(["--ros-args", "-p", "qos_overrides./image.subscription.reliability:=sometimes"])


def test_a_remapped_image_with_its_camera_info_gives_poses(harness_factory, posed_frames) -> None:
    """ficap_node --ros-args -r image:=/rear_cam/image_raw with CameraInfo on /rear_cam/camera_info
    (and nothing on /camera_info) publishes poses."""
    scene, frames = posed_frames
    h = harness_factory(cli_args=["--ros-args", "-r", "image:=/rear_cam/image_raw"],
                        image_topic="/rear_cam/image_raw", info_topic="/rear_cam/camera_info")
    assert h.node._inputs.camera_info.topic_name == "/rear_cam/camera_info"
    truth, image = frames[0]
    msg = messages.image(ros_msgs.RCLPY, header_at(truth.stamp_ns), image, "mono8")
    status = h.publish_and_wait(msg, info_at(scene.camera, truth.stamp_ns))
    assert status.message == "pose", status.message
    h.wait_for(lambda: bool(h.head), what="head_pose")
    with h.lock:
        p = h.head[0].pose.position
        assert np.allclose([p.x, p.y, p.z], truth.T_cam_cap.translation_m, atol=0.01)
