"""The lifecycle node (ficap_ros.ros.lifecycle): the plain node's steps on the transitions, driven
through the lifecycle services on real DDS as ``ros2 lifecycle set`` does."""

from __future__ import annotations

import subprocess
import sys

import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from node_harness import Spinning, closing_factory, header_at, info_at
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from ficap_ros.io import messages
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.lifecycle import FicapLifecycleNode


class _Managed(Spinning):
    """A lifecycle node and a peer (lifecycle client, image publisher, pose recorder) spinning."""

    def __init__(self, overrides: dict | None = None) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = FicapLifecycleNode(context=self.context, parameter_overrides=[
            Parameter(k, value=v) for k, v in (overrides or {}).items()])
        self.peer = rclpy.create_node("lifecycle_peer", context=self.context)
        self.change = self.peer.create_client(ChangeState, "/ficap_node/change_state")
        self.get = self.peer.create_client(GetState, "/ficap_node/get_state")
        self.pub_image = self.peer.create_publisher(Image, "image", 5)
        self.pub_info = self.peer.create_publisher(CameraInfo, "camera_info", 5)
        self.head: list = []
        self.peer.create_subscription(PoseStamped, "head_pose", self.head.append, 10)
        self._spin()

    def transition(self, transition_id: int) -> bool:
        return self.call(self.change, ChangeState.Request(
            transition=Transition(id=transition_id))).success

    def state(self) -> int:
        return self.call(self.get, GetState.Request()).current_state.id


@pytest.fixture
def managed():
    yield from closing_factory(_Managed)


def _subscribed(m: _Managed) -> bool:
    return m.pub_image.get_subscription_count() > 0


def _publishes(m: _Managed, topic: str) -> bool:
    """The node itself has a publisher on ``topic`` (its own entities, not the DDS graph, where a
    node of an earlier test may linger)."""
    return topic in {p.topic_name for p in m.node.publishers}


def test_configure_loads_activate_subscribes_deactivate_unsubscribes(managed, posed_frames) -> None:
    scene, frames = posed_frames
    m = managed(overrides={"pose.min_tags": 2})
    assert m.state() == State.PRIMARY_STATE_UNCONFIGURED
    assert not m.node.has_parameter("pose.min_tags")  # parameters are read on configure
    assert m.transition(Transition.TRANSITION_CONFIGURE)
    assert m.state() == State.PRIMARY_STATE_INACTIVE
    assert m.node.get_parameter("pose.min_tags").value == 2
    assert m.node._processor.pose_config.min_tags == 2
    assert _publishes(m, "/head_pose") and _publishes(m, "/detections") and not _subscribed(m)
    assert m.transition(Transition.TRANSITION_ACTIVATE)
    m.wait_for(lambda: _subscribed(m) and m.pub_info.get_subscription_count() > 0,
               what="subscriptions on activate")
    truth, image = frames[0]
    for _ in range(3):  # best effort: send again if a frame is lost
        m.pub_info.publish(info_at(scene.camera, truth.stamp_ns))
        m.wait_for(lambda: m.node._cameras.has(truth.stamp_ns), what="camera_info")
        m.pub_image.publish(messages.image(ros_msgs.RCLPY, header_at(truth.stamp_ns), image, "mono8"))
        try:
            m.wait_for(lambda: bool(m.head), timeout=3.0, what="head_pose")
            break
        except AssertionError:
            continue
    assert ros_msgs.stamp_to_ns(m.head[0].header.stamp) == truth.stamp_ns
    assert m.transition(Transition.TRANSITION_DEACTIVATE)
    m.wait_for(lambda: not _subscribed(m), what="unsubscribed on deactivate")
    assert m.transition(Transition.TRANSITION_CLEANUP)
    assert m.state() == State.PRIMARY_STATE_UNCONFIGURED
    assert not _publishes(m, "/head_pose") and not _publishes(m, "/tf")  # outputs removed
    # Configure again: the parameters keep their values.
    assert m.transition(Transition.TRANSITION_CONFIGURE)
    assert m.node._processor.pose_config.min_tags == 2


def test_a_bad_parameter_fails_configure_in_one_line(managed, capfd) -> None:
    m = managed(overrides={"output_frame": "base_link"})  # no camera_mount
    assert not m.transition(Transition.TRANSITION_CONFIGURE)
    assert m.state() == State.PRIMARY_STATE_UNCONFIGURED
    err = capfd.readouterr().err
    assert "configure failed: output_frame 'base_link' needs camera_mount" in err
    assert "Traceback" not in err


def test_the_lifecycle_executable_answers_help_without_starting() -> None:
    run = subprocess.run([sys.executable, "-m", "ficap_ros.ros.lifecycle", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and run.stdout.startswith("usage: ficap_lifecycle_node")
    assert "configure" in run.stdout and "pose.method" in run.stdout
