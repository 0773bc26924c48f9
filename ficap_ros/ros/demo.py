"""The demo: the sample drive recording played into a live ``ficap_node`` over real ROS topics.

A player node publishes the recording's CompressedImage and CameraInfo messages to the node (one
frame at a time: the next frame goes out when the node's status and head pose for the previous one
came back, so every frame is processed), calls ``~/calibrate`` at the end of the recording's frontal segment, and
compares the published ``head_pose`` with the recording's ground truth.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, CompressedImage
from std_srvs.srv import Trigger

from ficap_ros.errors import BagError
from ficap_ros.geometry.metrics import (
    angle_deg,
    phi3_deg,
    summarize_errors,
    yaw_pitch_roll_deg,
)
from ficap_ros.geometry.transform import CAM_FROM_FORWARD
from ficap_ros.io.sources import open_bag_reader
from ficap_ros.ros.node import FicapNode
from ficap_ros.ros.spin import make_executor
from ficap_ros.stamps import stamp_to_ns

IMAGE_TOPIC = "/camera/image_raw/compressed"
INFO_TOPIC = "/camera/camera_info"
TRUTH_TOPIC = "/ficap/truth/head_pose"


@dataclass(frozen=True)
class _Recorded:
    stamp_ns: int
    jpeg: bytes
    info: dict
    R_frontal_head: Rotation | None


def load_recording(bag: Path) -> list[_Recorded]:
    """Images, camera infos and truth of a ``ficap synth`` recording, in stamp order."""
    infos: dict[int, dict] = {}
    truth: dict[int, Rotation] = {}
    images: list[tuple[int, bytes]] = []
    reader = open_bag_reader(bag)
    try:
        wanted = [c for c in reader.connections if c.topic in (IMAGE_TOPIC, INFO_TOPIC, TRUTH_TOPIC)]
        if not any(c.topic == IMAGE_TOPIC for c in wanted):
            raise BagError(f"{bag}: no {IMAGE_TOPIC} topic")
        for conn, _, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = stamp_to_ns(msg.header.stamp)
            if conn.topic == IMAGE_TOPIC:
                images.append((stamp, bytes(msg.data)))
            elif conn.topic == INFO_TOPIC:
                infos[stamp] = {
                    "width": int(msg.width), "height": int(msg.height),
                    "distortion_model": str(msg.distortion_model),
                    "d": [float(v) for v in msg.d], "k": [float(v) for v in msg.k],
                    "r": [float(v) for v in msg.r], "p": [float(v) for v in msg.p],
                    "frame_id": str(msg.header.frame_id),
                }
            else:
                o = msg.pose.orientation
                truth[stamp] = Rotation.from_quat([o.x, o.y, o.z, o.w])
    finally:
        reader.close()
    if not infos:
        raise BagError(f"{bag}: no {INFO_TOPIC} messages")
    fallback = next(iter(infos.values()))
    return [_Recorded(s, data, infos.get(s, fallback), truth.get(s)) for s, data in sorted(images)]


class _Player(Node):
    def __init__(self) -> None:
        super().__init__("ficap_demo_player")
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_image = self.create_publisher(CompressedImage, "image/compressed", qos)
        self.pub_info = self.create_publisher(CameraInfo, "camera_info", qos)
        self.calibrate = self.create_client(Trigger, "ficap_node/calibrate")
        self.lock = threading.Lock()
        self.status: dict[int, dict[str, str]] = {}
        self.head: dict[int, Rotation] = {}
        self.received_ns: dict[int, int] = {}
        self.event = threading.Event()
        # head_pose first: the node publishes it just before the frame's status, and one executor
        # thread takes the ready subscriptions in this order.
        self.create_subscription(PoseStamped, "head_pose", self._on_head, 50)
        self.create_subscription(DiagnosticArray, "status", self._on_status, 50)

    def _on_status(self, msg: DiagnosticArray) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        values = {kv.key: kv.value for s in msg.status for kv in s.values}
        with self.lock:
            self.status[stamp] = values
        self.event.set()

    def _on_head(self, msg: PoseStamped) -> None:
        o = msg.pose.orientation
        with self.lock:
            stamp = stamp_to_ns(msg.header.stamp)
            self.head[stamp] = Rotation.from_quat([o.x, o.y, o.z, o.w])
            self.received_ns[stamp] = time.monotonic_ns()
        self.event.set()

    def answered(self, stamp_ns: int) -> bool:
        """The node's status for this frame came, and its head pose if the status has head angles
        (report.status_values: the frame has a head pose, published at the demo's default
        publish_min_reliability 0)."""
        with self.lock:
            values = self.status.get(stamp_ns)
            return values is not None and (stamp_ns in self.head or "yaw_deg" not in values)

    def publish(self, rec: _Recorded) -> None:
        stamp = rclpy.time.Time(nanoseconds=rec.stamp_ns).to_msg()
        info = CameraInfo()
        info.header.stamp = stamp
        info.header.frame_id = rec.info["frame_id"]
        info.width, info.height = rec.info["width"], rec.info["height"]
        info.distortion_model = rec.info["distortion_model"]
        info.d, info.k, info.r, info.p = rec.info["d"], rec.info["k"], rec.info["r"], rec.info["p"]
        image = CompressedImage()
        image.header = info.header
        image.format = "jpeg"
        image.data = rec.jpeg
        self.pub_info.publish(info)
        self.pub_image.publish(image)


def run_demo(bag: Path, frontal_s: float, every: int, method: str = "joint") -> int:
    """Play ``bag`` into a live node (``pose.method`` = ``method``) and print head pose against
    truth; returns an exit code."""
    recording = load_recording(bag)
    rclpy.init()
    node = FicapNode(parameter_overrides=[
        Parameter("image_transport", value="compressed"),
        Parameter("pose.method", value=method),
        Parameter("calibration.window_s", value=float(frontal_s) - 0.2),
    ])
    player = _Player()
    # One spin thread for both nodes, as ficap_node spins (spin.make_executor says why not more).
    executor = make_executor()
    executor.add_node(node)
    executor.add_node(player)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        return _play(player, recording, frontal_s, every)
    finally:
        executor.shutdown()
        node.destroy_node()
        player.destroy_node()
        rclpy.try_shutdown()


def _wait_for_node(player: _Player, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (player.pub_image.get_subscription_count() > 0
                and player.calibrate.service_is_ready()):
            return
        time.sleep(0.05)
    raise BagError("ficap_node did not come up on the demo's topics within 20 s")


def _play(player: _Player, recording: list[_Recorded], frontal_s: float, every: int) -> int:
    _wait_for_node(player)
    t0_ns = recording[0].stamp_ns
    print(f"ficap demo: {len(recording)} frames of the sample drive -> ficap_node over ROS 2 topics "
          f"(image/compressed, camera_info -> head_pose, status); calibrate after {frontal_s:.1f} s "
          f"of looking ahead")
    print(f"{'t_s':>6} {'tags':>4} {'used':>4} {'rel':>5} | {'yaw':>7} {'pitch':>7} {'roll':>7} "
          f"| {'true_yaw':>8} {'pitch':>7} {'roll':>7} | {'err_deg':>7}")
    calibrated = False
    sent_ns: dict[int, int] = {}
    errors_after: list[float] = []
    phi3_after: list[float] = []
    start = time.monotonic()
    for k, rec in enumerate(recording):
        t_s = (rec.stamp_ns - t0_ns) / 1e9
        if not calibrated and t_s >= frontal_s:
            calibrated = _calibrate(player)
        player.event.clear()
        sent_ns[rec.stamp_ns] = time.monotonic_ns()
        player.publish(rec)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not player.answered(rec.stamp_ns):
            player.event.wait(0.05)
            player.event.clear()
        with player.lock:
            values = player.status.get(rec.stamp_ns)
            head_cam = player.head.get(rec.stamp_ns)
        if values is None:
            print(f"{t_s:>6.2f} no status from the node within 10 s")
            continue
        est = None if head_cam is None else CAM_FROM_FORWARD.inv() * head_cam
        err = float("nan")
        if est is not None and rec.R_frontal_head is not None:
            err = float(angle_deg(est, rec.R_frontal_head))
            if calibrated:
                errors_after.append(err)
                phi3_after.append(float(phi3_deg(est, rec.R_frontal_head)))
        if k % every == 0:
            e = yaw_pitch_roll_deg(est) if est is not None else [np.nan] * 3
            tr = yaw_pitch_roll_deg(rec.R_frontal_head) if rec.R_frontal_head is not None else [np.nan] * 3
            print(f"{t_s:>6.2f} {values.get('tags_detected', '?'):>4} {values.get('tags_used', '?'):>4} "
                  f"{float(values.get('reliability', 'nan')):>5.2f} | {e[0]:>7.2f} {e[1]:>7.2f} {e[2]:>7.2f} "
                  f"| {tr[0]:>8.2f} {tr[1]:>7.2f} {tr[2]:>7.2f} | {err:>7.3f}"
                  + ("" if calibrated else "  (uncalibrated)"))
    elapsed = time.monotonic() - start
    with player.lock:
        latencies = [(player.received_ns[s] - sent_ns[s]) / 1e6 for s in sent_ns if s in player.received_ns]
        with_pose = len(player.head)
    s = summarize_errors(np.array(errors_after))
    p = summarize_errors(np.array(phi3_after))
    print(f"\nframes: {len(recording)}, with head pose: {with_pose}, played in {elapsed:.1f} s "
          f"({len(recording) / elapsed:.1f} frames/s, lock-step)")
    if calibrated:
        print(f"head pose error after calibration, geodesic: mean {s['mean']:.3f}  median {s['median']:.3f}  "
              f"p95 {s['p95']:.3f}  max {s['max']:.3f} deg over {s['n']} frames")
        print(f"head pose error after calibration, paper's Phi3: mean {p['mean']:.3f}  median {p['median']:.3f}  "
              f"p95 {p['p95']:.3f} deg")
    if latencies:
        print(f"node latency (publish -> head_pose received): p50 {np.percentile(latencies, 50):.1f} ms, "
              f"p99 {np.percentile(latencies, 99):.1f} ms")
    return 0 if calibrated and with_pose > 0 else 1


def _calibrate(player: _Player) -> bool:
    future = player.calibrate.call_async(Trigger.Request())
    deadline = time.monotonic() + 10.0
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not future.done():
        print("calibrate: no answer within 10 s")
        return False
    response = future.result()
    print(f"~/calibrate -> success={response.success}: {response.message}")
    return bool(response.success)
