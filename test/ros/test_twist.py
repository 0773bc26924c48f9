"""ficap_ros.ros.twist: the head's twist message (the cap's velocity, turned into the output frame
through the mount, absent without a measured velocity); then ficap_node on rendered rolling-shutter
glance frames through real DDS, with the camera's timing as parameters: every frame posed with
its image's stamp, near the truth in fast frames as in slow ones, and twists with those stamps
near the true angular velocity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped
from node_harness import header_at
from recordings import RS_EXPOSURE_MS, RS_READOUT_MS
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.camera_info import camera_from_info
from ficap_ros.io.labels import FrameRecord
from ficap_ros.io.sources import open_bag_reader
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.twist import TOPIC, head_twist
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pose import CapPose

W = np.array([0.12, -0.03, 0.01, 0.5, -3.9, 0.2])


def _record(velocity: np.ndarray | None) -> FrameRecord:
    pose = CapPose(Transform(Rotation.from_euler("xyz", [170.0, 5.0, -20.0], degrees=True),
                             [0.01, 0.05, 0.6]), 5, 5, (1, 2, 3, 4, 5), 0.1, np.eye(6) * 1e-6,
                   0.9, "joint", velocity=velocity)
    cal = HeadCalibration(Rotation.from_euler("y", 10.0, degrees=True), calibrated=True)
    return FrameRecord.processed(0, 10, "cam", pose, (1, 2, 3, 4, 5), calibration=cal)


def test_the_head_twist_is_the_caps_in_the_output_frame() -> None:
    """The head shares the cap's origin and turns with it: the twist is the cap's velocity
    whatever the calibration; in output_frame both vectors turn by the mount's rotation (its
    translation adds nothing); no velocity, no message."""
    header = Header(stamp=messages.time(ros_msgs.RCLPY, 1_234_000_000_567), frame_id="cam")
    msg = head_twist(header, _record(W), "", None)
    assert isinstance(msg, TwistStamped) and TOPIC == "head_twist"
    assert msg.header == header
    np.testing.assert_array_equal(messages.twist_to_array(msg), W)
    mount = Transform(Rotation.from_euler("zyx", [-90.0, 0.0, -100.0], degrees=True),
                      [0.9, -0.1, 1.2])
    moved = head_twist(header, _record(W), "base_link", mount)
    assert moved.header.frame_id == "base_link" and moved.header.stamp == header.stamp
    R = mount.rotation.as_matrix()
    np.testing.assert_allclose(messages.twist_to_array(moved),
                               np.concatenate([R @ W[:3], R @ W[3:]]), atol=1e-15)
    assert head_twist(header, _record(None), "", None) is None
    unposed = FrameRecord.processed(0, 10, "cam", None, (), "no tags")
    assert head_twist(header, unposed, "", None) is None


def _recording(bag: Path) -> list[dict]:
    """Per image of a synth bag, in stamp order: its stamp, JPEG, CameraInfo, true cap pose and
    true cap twist."""
    topics = {"/camera/image_raw/compressed": "jpeg", "/camera/camera_info": "info",
              "/ficap/truth/cap_pose": "cap", "/ficap/truth/cap_twist": "twist"}
    frames: dict[int, dict] = {}
    reader = open_bag_reader(bag)
    try:
        for conn, _, raw in reader.messages([c for c in reader.connections if c.topic in topics]):
            msg = reader.deserialize(raw, conn.msgtype)
            frames.setdefault(ros_msgs.stamp_to_ns(msg.header.stamp), {})[topics[conn.topic]] = msg
    finally:
        reader.close()
    return [{"stamp": s, "jpeg": bytes(f["jpeg"].data), "camera": camera_from_info(f["info"]),
             "T": messages.pose_to_transform(f["cap"]), "twist": messages.twist_to_array(f["twist"])}
            for s, f in sorted(frames.items())]


def _offline_velocities(frames: list[dict], timing: CameraTiming) -> list[np.ndarray | None]:
    """What the pipeline (the node's, with the same timing) measures as each frame's velocity."""
    import cv2

    from ficap_ros.vision.pipeline import FrameProcessor

    proc = FrameProcessor(timing=timing)
    out = []
    for f in frames:
        image = cv2.imdecode(np.frombuffer(f["jpeg"], np.uint8), cv2.IMREAD_GRAYSCALE)
        result = proc.process(image, f["camera"], f["stamp"])
        out.append(None if result.pose is None else result.pose.velocity)
    return out


def test_node_on_rolling_shutter_glance_frames(glance_rs_drive: Path, harness_factory) -> None:
    frames = _recording(glance_rs_drive)
    timing = CameraTiming(exposure_ms=RS_EXPOSURE_MS, readout_ms=RS_READOUT_MS)
    h = harness_factory(overrides={"image_transport": "compressed",
                                   "camera.exposure_ms": RS_EXPOSURE_MS,
                                   "camera.readout_ms": RS_READOUT_MS,
                                   "camera.row_order": "top_to_bottom"})
    assert h.node._processor.timing == timing
    twists: list[TwistStamped] = []
    h.peer.create_subscription(TwistStamped, TOPIC, h._rec(twists), 100)
    h.wait_for(lambda: h.node._pubs["twist"].get_subscription_count() > 0, what="twist subscriber")
    statuses = []
    for f in frames:
        msg = CompressedImage(header=header_at(f["stamp"]), format="jpeg", data=f["jpeg"])
        statuses.append(h.publish_and_wait(msg, messages.camera_info(
            ros_msgs.RCLPY, header_at(f["stamp"]), f["camera"])))
    h.wait_for(lambda: len(h.cap) >= len(frames), timeout=5.0, what="every cap pose")
    with h.lock:
        caps = {ros_msgs.stamp_to_ns(m.header.stamp): m for m in h.cap}
    assert sorted(caps) == [f["stamp"] for f in frames]  # every frame posed, its stamp copied
    assert all(s.level in (ros_msgs.LEVEL_OK, ros_msgs.LEVEL_WARN) for s in statuses)
    speed = np.array([np.degrees(np.linalg.norm(f["twist"][3:])) for f in frames])
    err = np.array([angle_deg(_rotation(caps[f["stamp"]]), f["T"].rotation) for f in frames])
    fast = speed >= 90.0
    print(f"\nnode on rolling-shutter glance frames: {fast.sum()} of {len(frames)} at >= 90 deg/s "
          f"(peak {speed.max():.0f}); rotation error median {np.median(err[~fast]):.3f} deg slow, "
          f"{np.median(err[fast]):.3f} deg fast, max {err.max():.3f} deg")
    assert fast.sum() >= 5
    # The rolling-shutter pose (the cap's velocity over the readout) keeps fast frames near slow.
    assert np.median(err[~fast]) < 0.05 and np.median(err[fast]) < 0.15 and err.max() < 0.3
    _check_twists(h, twists, frames, timing)


def _rotation(msg: PoseStamped) -> Rotation:
    q = msg.pose.orientation
    return Rotation.from_quat([q.x, q.y, q.z, q.w])


def _check_twists(h, twists: list[TwistStamped], frames: list[dict], timing: CameraTiming) -> None:
    """A twist for every frame (a rolling shutter's pose is solved with the cap's velocity, the
    first frame's under a prior around rest), with the image's stamp and frame, near the truth's
    angular velocity."""
    measured = _offline_velocities(frames, timing)
    assert all(v is not None for v in measured)
    h.wait_for(lambda: len(twists) >= sum(v is not None for v in measured), timeout=5.0,
               what="twists")
    with h.lock:
        got = {ros_msgs.stamp_to_ns(m.header.stamp): m for m in twists}
    assert sorted(got) == [f["stamp"] for f, v in zip(frames, measured) if v is not None]
    w_err = [np.degrees(np.linalg.norm(messages.twist_to_array(got[f["stamp"]])[3:] - f["twist"][3:]))
             for f in frames if f["stamp"] in got]
    assert all(m.header.frame_id == "rear_cam_optical" for m in got.values())
    print(f"angular velocity error median {np.median(w_err):.1f} deg/s, max {max(w_err):.1f}")
    assert np.median(w_err) < 5.0 and max(w_err) < 40.0
