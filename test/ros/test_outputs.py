"""What the node publishes per image (ficap_ros.ros.outputs), on real DDS: the per-tag detections
in apriltag_ros' message and conventions with their fits by name, the head angles in radians and
the quality's SI bounds; the head twist on rendered rolling-shutter glance frames with the
camera's timing as parameters (every frame posed with its image's stamp, near the truth in fast
frames as in slow ones, and a twist with that stamp near the true angular velocity); without
apriltag_msgs one log line; the lifecycle's removal of it all."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from apriltag_msgs.msg import AprilTagDetectionArray
from geometry_msgs.msg import PoseStamped, TwistStamped, Vector3Stamped
from node_harness import header_at, info_at
from recordings import RS_EXPOSURE_MS, RS_READOUT_MS
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage, JointState

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.io import messages
from ficap_ros.io.camera_info import camera_from_info
from ficap_ros.io.sources import open_bag_reader
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.outputs import NodeOutputs


def test_detections_rpy_and_quality_of_a_posed_image(harness_factory, posed_frames) -> None:
    scene, frames = posed_frames
    h = harness_factory()
    dets, fits, rpy_deg, rpy_rad, quality = [], [], [], [], []
    h.peer.create_subscription(AprilTagDetectionArray, "detections", h._rec(dets), 10)
    h.peer.create_subscription(JointState, "detections/fit", h._rec(fits), 10)
    h.peer.create_subscription(Vector3Stamped, "head_rpy_deg", h._rec(rpy_deg), 10)
    h.peer.create_subscription(Vector3Stamped, "head_rpy", h._rec(rpy_rad), 10)
    h.peer.create_subscription(JointState, "quality", h._rec(quality), 10)
    out = h.node._out
    h.wait_for(lambda: all(p.get_subscription_count() > 0 for p in (
        out.detections, out.fit, out.pubs["rpy_deg"], out.pubs["rpy_rad"], out.quality)),
        what="subscribers")
    truth, image = frames[0]
    status = h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(truth.stamp_ns), image,
                                               "mono8"), info_at(scene.camera, truth.stamp_ns))
    h.wait_for(lambda: all((dets, fits, rpy_deg, rpy_rad, quality)), what="outputs")
    values = {kv.key: kv.value for kv in status.values}
    with h.lock:
        det, fit = dets[0], fits[0]
        assert ros_msgs.stamp_to_ns(det.header.stamp) == truth.stamp_ns
        assert det.header.frame_id == "rear_cam_optical"
        assert len(det.detections) == int(values["tags_detected"]) >= 4
        named = dict(zip(fit.name, fit.position))
        model = nominal_model()
        offsets = []
        for d in det.detections:
            assert d.family == "tag36h11" and d.goodness == 0.0
            # AprilTag's corners: p_i = OpenCV's c_[1,0,3,2][i] + 0.5 px, against the truth's
            # projection (OpenCV's order and convention).
            truth_px = scene.camera.project(truth.T_cam_cap.apply(model.corners_of(d.id) / 1000.0))
            got = np.array([[c.x, c.y] for c in d.corners])
            offsets.append(got - truth_px[[1, 0, 3, 2]])
            assert np.abs(offsets[-1] - 0.5).max() < 0.4, d.id  # each corner p_i, not another
            H = np.reshape(d.homography, (3, 3))
            c = H @ [0.0, 0.0, 1.0]
            assert np.allclose(c[:2] / c[2], [d.centre.x, d.centre.y])
            assert named[f"tag{d.id}/used"] == 1.0  # every tag of a clean frame
            assert 0.0 <= named[f"tag{d.id}/residual_px"] < 0.5
        assert len(fit.name) == 2 * len(det.detections)
        # The corners are unbiased, so over all of them the offset is AprilTag's half pixel.
        np.testing.assert_allclose(np.mean(np.concatenate(offsets), axis=0), [0.5, 0.5], atol=0.08)
        # Head angles: radians beside degrees; quality's bounds in SI beside deg and mm.
        d, r = rpy_deg[0].vector, rpy_rad[0].vector
        assert np.allclose(np.radians([d.x, d.y, d.z]), [r.x, r.y, r.z], rtol=1e-12, atol=1e-15)
        assert rpy_rad[0].header.frame_id == rpy_deg[0].header.frame_id == "ficap_frontal"
        q = dict(zip(quality[0].name, quality[0].position))
        assert q["rot_err95_rad"] == pytest.approx(math.radians(q["rot_err95_deg"]), rel=1e-12)
        assert q["trans_err95_m"] == pytest.approx(q["trans_err95_mm"] / 1000.0, rel=1e-12)
        assert q["latency_s"] == pytest.approx(q["latency_ms"] / 1000.0, rel=1e-12)


def _published(node) -> set[str]:  # noqa: ANN001
    return {name for name, _ in node.get_publisher_names_and_types_by_node(node.get_name(), "/")}


def test_without_apriltag_msgs_one_line_and_the_fits_still(monkeypatch, node, capfd) -> None:
    monkeypatch.setitem(sys.modules, "apriltag_msgs", None)
    monkeypatch.setitem(sys.modules, "apriltag_msgs.msg", None)
    out = NodeOutputs(node)
    assert out.detections is None and out.fit is not None
    err = capfd.readouterr().err
    assert err.count("no detections topic") == 1 and "Traceback" not in err
    assert "/detections/fit" in _published(node) and "/detections" not in _published(node)


def test_destroy_removes_every_publisher(node) -> None:
    before = _published(node)
    out = NodeOutputs(node)
    made = _published(node) - before
    assert {"/head_pose", "/head_rpy", "/head_rpy_deg", "/head_twist", "/quality", "/status",
            "/detections", "/detections/fit", "/tf"} <= made
    out.destroy()
    assert _published(node) == before


def test_the_readme_output_table_has_every_output_with_its_type(node) -> None:
    """The README's node table names every topic NodeOutputs advertises (and /tf_static), each
    row with its message type and what it holds."""
    import re

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    table = readme[readme.index("| output | type | what, in which unit |"):]
    table = table[:table.index("\n\n")]
    rows: dict[str, str] = {}
    for line in table.splitlines()[2:]:
        first, kind, what = (c.strip() for c in line.strip("|").split(" | ", 2))
        for name in re.findall(r"`([^`]+)`", first):
            rows["/" + name.lstrip("/")] = f"{kind} {what}"
    before = _published(node)
    out = NodeOutputs(node)
    advertised = (_published(node) - before) | {"/tf_static"}
    out.destroy()
    assert advertised <= set(rows), f"outputs missing from README: {sorted(advertised - set(rows))}"
    for name in advertised:
        kind, what = rows[name].split(" ", 1)
        assert "/" in kind and len(what) > 10, name
    for name, unit in (("/head_rpy", "radians"), ("/head_rpy_deg", "degrees"),
                       ("/head_twist", "m/s"), ("/quality", "rot_err95_rad"), ("/tf", "metres")):
        assert unit in rows[name], (name, unit)


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
    h.peer.create_subscription(TwistStamped, "head_twist", h._rec(twists), 100)
    h.wait_for(lambda: h.node._out.pubs["twist"].get_subscription_count() > 0, what="twist subscriber")
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
