"""The node's TF output: ``/tf`` per posed image (stamped with it) and ``/tf_static`` for the camera
mount, the tree of ``ficap_ros.io.frames`` (camera -> ``ficap_cap`` -> ``ficap_head``; the mount's
parent -> camera, or camera -> the frontal frame without a mount).

Sent through ``tf2_ros``' broadcasters where tf2_ros is importable (every apt or colcon Jazzy
install); else through plain publishers of ``tf2_msgs/TFMessage`` with the broadcasters' QoS (``/tf``
depth 100, ``/tf_static`` depth 1 transient local) where tf2_msgs is; else not at all, said in one
log line at start.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ficap_ros.io import messages
from ficap_ros.io.frames import (
    FrameTransform,
    OutputFrames,
    frame_transforms,
    static_transforms,
)
from ficap_ros.io.labels import FrameRecord
from ficap_ros.ros import msgs as ros_msgs

__all__ = ["TfOutput", "DYNAMIC_QOS", "STATIC_QOS"]

#: tf2_ros' broadcaster QoS (``DynamicBroadcasterQoS``, ``StaticBroadcasterQoS``).
DYNAMIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _tf2() -> tuple[Any | None, Any | None]:
    """(tf2_ros, tf2_msgs.msg), each None when it is not importable."""
    try:
        import tf2_ros
    except ImportError:
        tf2_ros = None
    try:
        import tf2_msgs.msg as tf2_msgs
    except ImportError:
        tf2_msgs = None
    return tf2_ros, tf2_msgs


class TfOutput:
    """``/tf`` and ``/tf_static`` of a node (module docstring).

    Attributes:
        backend: ``tf2_ros``, ``tf2_msgs`` or '' (no TF).
    """

    def __init__(self, node: Node) -> None:
        self._node = node
        self._static_sent: tuple = ()
        self._send_dynamic: Callable[[list[Any]], None] | None = None
        self._send_static: Callable[[list[Any]], None] | None = None
        self._publishers: list[Any] = []
        tf2_ros, tf2_msgs = _tf2()
        if tf2_ros is not None:
            self.backend = "tf2_ros"
            dynamic = tf2_ros.TransformBroadcaster(node)
            static = tf2_ros.StaticTransformBroadcaster(node)
            self._send_dynamic, self._send_static = dynamic.sendTransform, static.sendTransform
            # The broadcasters' own publishers (tf2_ros keeps them as ``pub_tf``).
            self._publishers = [p for p in (getattr(dynamic, "pub_tf", None),
                                            getattr(static, "pub_tf", None)) if p is not None]
        elif tf2_msgs is not None:
            self.backend = "tf2_msgs"
            tf_message = tf2_msgs.TFMessage
            dynamic = node.create_publisher(tf_message, "/tf", DYNAMIC_QOS)
            static = node.create_publisher(tf_message, "/tf_static", STATIC_QOS)
            self._publishers = [dynamic, static]
            self._send_dynamic = lambda ts: dynamic.publish(tf_message(transforms=ts))
            self._send_static = lambda ts: static.publish(tf_message(transforms=ts))
        else:
            self.backend = ""
            node.get_logger().warning("no /tf: neither tf2_ros nor tf2_msgs is importable "
                                      "(install ros-jazzy-tf2-ros)")

    @staticmethod
    def _stamped(stamp_ns: int, transforms: Sequence[FrameTransform]) -> list[Any]:
        return [messages.transform_stamped(ros_msgs.RCLPY,
                                           messages.header(ros_msgs.RCLPY, stamp_ns, t.parent),
                                           t.child, t.T) for t in transforms]

    def publish(self, record: FrameRecord, frames: OutputFrames, with_pose: bool = True) -> None:
        """The TF of one processed image: its mount on ``/tf_static`` when that changed (a new
        camera frame or mount), and with ``with_pose`` (its pose is published) the posed frame's
        transforms on ``/tf``, stamped with the image."""
        if self._send_dynamic is None or self._send_static is None:
            return
        static = static_transforms(frames, record.frame_id)
        key = tuple((t.parent, t.child, tuple(t.T.translation_m), tuple(t.T.q_xyzw)) for t in static)
        if key and key != self._static_sent:
            self._send_static(self._stamped(record.stamp_ns, static))
            self._static_sent = key
        dynamic = frame_transforms(record, frames) if with_pose else ()
        if dynamic:
            self._send_dynamic(self._stamped(record.stamp_ns, dynamic))

    def destroy(self) -> None:
        """Remove the publishers (the lifecycle node's cleanup)."""
        for pub in self._publishers:
            self._node.destroy_publisher(pub)
        self._publishers = []
        self._send_dynamic = self._send_static = None
