"""The node test harness: a real FicapNode and a peer node in one private rclpy Context on the
ROS_DOMAIN_ID conftest sets, spinning in a thread; every wait is bounded."""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Iterator

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.node import FicapNode
from ficap_ros.ros.spin import make_executor

WAIT_S = 10.0


class Spinning:
    """A node and a peer node in one context, spinning in one thread as ficap_node spins
    (``spin.make_executor`` says why); ``call`` a service, ``close`` it all."""

    context: Context
    node: Any
    peer: Any

    def _spin(self) -> None:
        self.executor = make_executor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait_for(self, pred: Callable[[], bool], timeout: float = WAIT_S, what: str = "") -> None:
        wait_for(pred, timeout, what)

    def call(self, client, request, timeout: float = WAIT_S):
        assert client.wait_for_service(timeout_sec=timeout), "service not available"
        future = client.call_async(request)
        self.wait_for(future.done, timeout, what="service response")
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.peer.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=5.0)


def closing_factory(make: Callable[..., Any]) -> Iterator[Callable[..., Any]]:
    """A fixture's body: yields ``make`` (keyword arguments passed on) and closes everything it
    made after the test."""
    made: list[Any] = []

    def build(**kw: Any) -> Any:
        made.append(make(**kw))
        return made[-1]

    yield build
    for item in made:
        item.close()


class Harness(Spinning):
    """A FicapNode and a peer node (publishes inputs, records outputs) spinning in a thread."""

    def __init__(self, overrides: dict[str, Any] | None = None, cli_args: list[str] | None = None,
                 reference_topic: str | None = None, image_topic: str = "image",
                 info_topic: str = "camera_info") -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        params = [Parameter(k, value=v) for k, v in (overrides or {}).items()]
        try:
            self.node = FicapNode(context=self.context, parameter_overrides=params,
                                  cli_args=cli_args)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise
        self.peer = rclpy.create_node("ficap_test_peer", context=self.context)
        self.lock = threading.Lock()
        self.head: list[PoseStamped] = []
        self.cap: list[PoseStamped] = []
        self.status: list[DiagnosticArray] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.peer.create_subscription(PoseStamped, "head_pose", self._rec(self.head), 100)
        self.peer.create_subscription(PoseStamped, "cap_pose", self._rec(self.cap), 100)
        self.peer.create_subscription(DiagnosticArray, "status", self._rec(self.status), 100)
        self.peer.create_subscription(DiagnosticArray, "/diagnostics", self._rec(self.diagnostics),
                                      10)
        self.pub_image = self.peer.create_publisher(Image, image_topic, 5)
        self.pub_compressed = self.peer.create_publisher(CompressedImage, f"{image_topic}/compressed", 5)
        self.pub_info = self.peer.create_publisher(CameraInfo, info_topic, 5)
        self.pub_ref = (self.peer.create_publisher(PoseStamped, reference_topic, 100)
                        if reference_topic else None)
        self.calibrate = self.peer.create_client(Trigger, "/ficap_node/calibrate")
        self.clear = self.peer.create_client(Trigger, "/ficap_node/clear_calibration")
        self.set_params = self.peer.create_client(SetParameters, "/ficap_node/set_parameters")
        self._spin()
        image_pub = self.pub_compressed if self.node._config.image_transport == "compressed" \
            else self.pub_image
        self.wait_for(lambda: image_pub.get_subscription_count() > 0
                      and self.pub_info.get_subscription_count() > 0
                      and self.peer.count_publishers("status") > 0, what="discovery")

    def _rec(self, store: list) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            with self.lock:
                store.append(msg)
        return cb

    def statuses_for(self, stamp_ns: int) -> list:
        with self.lock:
            return [s.status[0] for s in self.status
                    if ros_msgs.stamp_to_ns(s.header.stamp) == stamp_ns]

    def publish_and_wait(self, msg: Image | CompressedImage, info: CameraInfo | None = None,
                         attempts: int = 3):
        """Publish (CameraInfo first), wait for this frame's status; re-send on a lost frame."""
        stamp_ns = ros_msgs.stamp_to_ns(msg.header.stamp)
        for _ in range(attempts):
            if info is not None:
                self.pub_info.publish(info)
                # Two topics: without this the image can overtake its CameraInfo (seen under
                # load: "no CameraInfo received yet", a frame without a pose).
                info_ns = ros_msgs.stamp_to_ns(info.header.stamp)
                try:
                    self.wait_for(lambda: self.node._cameras.has(info_ns),
                                  timeout=WAIT_S / attempts, what="camera_info")
                except AssertionError:
                    continue  # lost (best effort): send both again
            (self.pub_compressed if isinstance(msg, CompressedImage) else self.pub_image).publish(msg)
            try:
                self.wait_for(lambda: bool(self.statuses_for(stamp_ns)), timeout=WAIT_S / attempts)
                return self.statuses_for(stamp_ns)[0]
            except AssertionError:
                continue
        raise AssertionError(f"no status for frame {stamp_ns}")



def wait_for(pred: Callable[[], bool], timeout: float = WAIT_S, what: str = "") -> None:
    """Poll ``pred`` every 10 ms until it holds; AssertionError after ``timeout`` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what or pred}")


def header_at(stamp_ns: int) -> Header:
    return Header(stamp=messages.time(ros_msgs.RCLPY, stamp_ns), frame_id="rear_cam_optical")


def info_at(camera: CameraModel, stamp_ns: int) -> CameraInfo:
    return messages.camera_info(ros_msgs.RCLPY, header_at(stamp_ns), camera)


def level_of(status) -> bytes:
    return bytes(status.level) if not isinstance(status.level, bytes) else status.level
