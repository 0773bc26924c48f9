"""ficap_node's subscriptions: the image (``image``, or ``image/compressed`` with
``image_transport`` compressed), its CameraInfo and the reference head pose.

The CameraInfo topic is ``camera_info_topic`` when set, else ``camera_info`` when that name is
remapped, else beside the image topic as image_transport places it (``<the resolved image topic's
namespace>/camera_info``: ``-r image:=/rear_cam/image_raw`` reads ``/rear_cam/camera_info``, as
``ficap replay`` does offline).

QoS of the image and CameraInfo subscriptions: the project's ``qos.reliability`` and ``qos.depth``
give the profile of both at once (names independent of topics, remaps and namespaces, so one
``/**`` params file serves every camera), and rclpy's ``qos_overrides.<topic>.subscription.``
``history|depth|reliability`` (``QoSOverridingOptions.with_default_policies``) override it per
topic, as in any ROS 2 node.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from geometry_msgs.msg import PoseStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import (
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from ficap_ros.errors import ConfigError
from ficap_ros.io.camera_info import camera_info_beside

__all__ = ["Inputs", "camera_info_topic", "sensor_qos", "subscribe"]


def camera_info_topic(node: Node, config: Any) -> str:
    """The fully qualified CameraInfo topic (module docstring's rule)."""
    if config.camera_info_topic:
        return node.resolve_topic_name(config.camera_info_topic)
    remapped = node.resolve_topic_name("camera_info")
    if remapped != node.resolve_topic_name("camera_info", only_expand=True):
        return remapped
    return camera_info_beside(node.resolve_topic_name("image"))


def sensor_qos(config: Any) -> QoSProfile:
    """The image and CameraInfo subscriptions' profile from ``qos.*`` (before any override)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=config.qos_depth,
        reliability=(ReliabilityPolicy.BEST_EFFORT if config.qos_reliability == "best_effort"
                     else ReliabilityPolicy.RELIABLE),
        durability=qos_profile_sensor_data.durability)


@dataclass(frozen=True)
class Inputs:
    """The subscriptions made (``reference`` None without a reference topic)."""

    image: Any
    camera_info: Any
    reference: Any | None

    def destroy(self, node: Node) -> None:
        for sub in (self.image, self.camera_info, self.reference):
            if sub is not None:
                node.destroy_subscription(sub)


def subscribe(node: Node, config: Any, on_image: Callable[[Any], None],
              on_camera_info: Callable[[Any], None],
              on_reference: Callable[[Any], None]) -> Inputs:
    """Make the subscriptions. Callback groups: frames and side inputs never wait on each other
    in a multi-threaded executor (ficap_node itself spins one thread, ``spin.make_executor``,
    where every callback is short).

    Raises:
        ConfigError: a ``qos_overrides`` value rclpy cannot apply.
    """
    frames, side = MutuallyExclusiveCallbackGroup(), ReentrantCallbackGroup()
    overrides = QoSOverridingOptions.with_default_policies()
    try:
        # CameraInfo before the image: one executor thread takes the ready subscriptions in the
        # order they were created, so a frame's CameraInfo that came with it is in place first.
        info = node.create_subscription(
            CameraInfo, camera_info_topic(node, config), on_camera_info, sensor_qos(config),
            callback_group=side, qos_overriding_options=overrides)
        if config.image_transport == "compressed":
            # image_transport's naming: <base topic>/compressed, so remapping `image` moves both.
            image = node.create_subscription(
                CompressedImage, node.resolve_topic_name("image") + "/compressed", on_image,
                sensor_qos(config), callback_group=frames, qos_overriding_options=overrides)
        else:
            image = node.create_subscription(Image, "image", on_image, sensor_qos(config),
                                             callback_group=frames,
                                             qos_overriding_options=overrides)
    except (InvalidQosOverridesError, ParameterException, RuntimeError, KeyError, ValueError) as err:
        raise ConfigError(f"qos_overrides: {err}") from err
    reference = None
    if config.calibration_reference_topic:
        ref_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.BEST_EFFORT)
        reference = node.create_subscription(PoseStamped, config.calibration_reference_topic,
                                             on_reference, ref_qos, callback_group=side)
    return Inputs(image, info, reference)
