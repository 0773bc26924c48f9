"""The output frames (ficap_ros.io.frames): the camera mount, the frame rules, the TF tree and the
pose messages of a frame record in those frames (rosbags' classes: no ROS install)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.metrics import yaw_pitch_roll_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.frames import (
    OutputFrames,
    camera_mount_transform,
    frame_transforms,
    parse_camera_mount,
    pose_outputs,
    static_transforms,
    tf_message,
)
from ficap_ros.io.labels import FrameRecord
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.vision.calibration import HeadCalibration, frontal_from_camera_mount
from ficap_ros.vision.pose import CapPose

MOUNT = Transform(Rotation.from_euler("y", 10.0, degrees=True) * frontal_from_camera_mount(None).inv(),
                  [0.2, 0.0, 1.1])


def _record(T_cam_cap: Transform, R_cap_head: Rotation, R_cam_frontal: Rotation | None = None,
            frame_id: str = "cam") -> FrameRecord:
    pose = CapPose(T_cam_cap, 5, 5, (1, 2, 3, 4, 5), 0.1, np.diag([1e-6] * 3 + [1e-5] * 3), 0.9, "joint")
    cal = HeadCalibration(R_cap_head, R_cam_frontal if R_cam_frontal is not None
                          else frontal_from_camera_mount(None), calibrated=True)
    return FrameRecord.processed(0, 10, frame_id, pose, (1, 2, 3, 4, 5), calibration=cal)


def _q(msg) -> np.ndarray:  # noqa: ANN001 - a PoseStamped
    o = msg.pose.orientation
    return np.array([o.x, o.y, o.z, o.w])


def test_pose_outputs_are_the_records_head_pose() -> None:
    """The pose messages are the frame record's poses (labels.mcap's, the node's): in the camera's
    frame and the frontal frame without a mount; through the mount into output_frame with one."""
    T_cam_cap = Transform(Rotation.from_euler("xyz", [160.0, 15.0, -5.0], degrees=True), [0.02, 0.05, 0.6])
    rec = _record(T_cam_cap, Rotation.from_euler("y", 10.0, degrees=True))
    pose = rec.pose
    assert pose is not None

    out = pose_outputs(ROSBAGS, 10, rec, OutputFrames())
    assert out["head"].header.frame_id == "cam" and out["head_frontal"].header.frame_id == "ficap_frontal"
    assert np.allclose(_q(out["head"]), rec.T_cam_head.q_xyzw, rtol=0, atol=1e-15)
    assert np.allclose(_q(out["cap"]), T_cam_cap.q_xyzw, rtol=0, atol=1e-15)
    assert np.array_equal(_q(out["head_frontal"]), rec.T_frontal_head.q_xyzw)
    ypr = yaw_pitch_roll_deg(rec.T_frontal_head.rotation)
    rpy = out["rpy_deg"].vector
    assert (rpy.z, rpy.y, rpy.x) == pytest.approx(tuple(ypr))
    rad = out["rpy_rad"].vector
    assert (rad.z, rad.y, rad.x) == pytest.approx(tuple(np.radians(ypr)), rel=1e-12, abs=1e-15)
    assert out["rpy_rad"].header.frame_id == "ficap_frontal"
    assert np.allclose(np.reshape(out["head_cov"].pose.covariance, (6, 6)), pose.covariance)

    out = pose_outputs(ROSBAGS, 10, rec, OutputFrames("base_link", MOUNT))
    assert out["head"].header.frame_id == out["head_frontal"].header.frame_id == "base_link"
    p = out["head"].pose.position
    assert np.allclose([p.x, p.y, p.z], (MOUNT * rec.T_cam_head).translation_m, atol=1e-12)
    cov = np.reshape(out["head_cov"].pose.covariance, (6, 6))
    assert np.trace(cov) == pytest.approx(np.trace(pose.covariance))  # rotated, not rescaled


def test_the_head_twist_is_the_caps_in_the_poses_frame() -> None:
    """The head shares the cap's origin and turns with it: ``twist`` is the cap's velocity
    whatever the head calibration, in the frame of ``head``; into output_frame both vectors turn
    by the mount's rotation (its translation adds nothing); no measured velocity, no twist and the
    same poses."""
    from dataclasses import replace

    w = np.array([0.12, -0.03, 0.01, 0.5, -3.9, 0.2])
    still = _record(Transform(Rotation.from_euler("xyz", [170.0, 5.0, -20.0], degrees=True),
                              [0.01, 0.05, 0.6]), Rotation.from_euler("y", 10.0, degrees=True))
    assert still.pose is not None
    moving = replace(still, pose=replace(still.pose, velocity=w))
    without = pose_outputs(ROSBAGS, 1_234_000_000_567, still, OutputFrames())
    out = pose_outputs(ROSBAGS, 1_234_000_000_567, moving, OutputFrames())
    assert "twist" not in without and set(out) == set(without) | {"twist"}
    assert all(repr(out[k]) == repr(without[k]) for k in without)
    assert out["twist"].header == out["head"].header
    np.testing.assert_array_equal(messages.twist_to_array(out["twist"]), w)
    moved = pose_outputs(ROSBAGS, 10, moving, OutputFrames("base_link", MOUNT))["twist"]
    assert moved.header.frame_id == "base_link"
    R = MOUNT.rotation.as_matrix()
    np.testing.assert_allclose(messages.twist_to_array(moved),
                               np.concatenate([R @ w[:3], R @ w[3:]]), atol=1e-15)


def test_camera_mount_parsing_and_the_frame_rule() -> None:
    assert camera_mount_transform([0.0] * 7) is None  # all zeros: not set
    T = parse_camera_mount("0.1, 0 1.2 0.5 -0.5 0.5 -0.5")
    assert T is not None and np.allclose(T.translation_m, [0.1, 0.0, 1.2])
    assert abs(np.dot(T.q_xyzw, [0.5, -0.5, 0.5, -0.5])) == pytest.approx(1.0)  # q and -q alike
    assert parse_camera_mount("0 0 0 0 0 0 0") is None
    for bad, says in (("1 2 3", "7 finite"), ("a b c d e f g", "7 numbers"),
                      ("0 0 0 0 0 0 2", "unit length")):
        with pytest.raises(ConfigError, match=says):
            parse_camera_mount(bad)
    with pytest.raises(ConfigError, match="needs camera_mount"):
        OutputFrames("base_link")
    assert OutputFrames().frontal == "ficap_frontal" and not OutputFrames().moved
    assert OutputFrames("", MOUNT).frontal == "ficap_frontal" and not OutputFrames("", MOUNT).moved
    assert OutputFrames("base_link", MOUNT).frontal == "base_link"
    assert OutputFrames("base_link", MOUNT).moved


def test_tf_tree_without_a_mount_leaves_the_camera_without_parent() -> None:
    rec = _record(Transform(Rotation.from_euler("x", 170.0, degrees=True), [0.0, 0.05, 0.6]),
                  Rotation.from_euler("z", 5.0, degrees=True))
    assert static_transforms(OutputFrames(), "cam") == ()
    edges = frame_transforms(rec, OutputFrames())
    assert [(e.parent, e.child) for e in edges] == [("cam", "ficap_cap"), ("ficap_cap", "ficap_head"),
                                                   ("cam", "ficap_frontal")]
    assert all(e.child != "cam" for e in edges)  # a robot's tree may give the camera its parent
    unposed = FrameRecord.processed(0, 10, "cam", None, ())
    assert frame_transforms(unposed, OutputFrames()) == ()
    msg = tf_message(ROSBAGS, 1_500_000_000_123, edges)
    assert [t.header.stamp.sec * 10**9 + t.header.stamp.nanosec for t in msg.transforms] == [
        1_500_000_000_123] * 3


_angles = st.tuples(*[st.floats(-170.0, 170.0)] * 3)


@given(cap=_angles, head=_angles, mount=_angles,
       t=st.tuples(*[st.floats(-0.5, 0.5)] * 3), frame=st.sampled_from(["", "base_link"]))
def test_the_tf_tree_composes_to_the_pose_outputs(cap, head, mount, t, frame) -> None:  # noqa: ANN001
    """Walking the TF tree from the frontal frame (the mount's parent) to the head gives
    head_pose/frontal, with or without a mount, whatever the output frame."""
    T_mount = Transform(Rotation.from_euler("xyz", mount, degrees=True), np.array(t))
    frames = OutputFrames(frame, T_mount) if frame else OutputFrames()
    R_cam_frontal = frontal_from_camera_mount(frames.mount)
    rec = _record(Transform(Rotation.from_euler("xyz", cap, degrees=True), [0.01, -0.02, 0.7]),
                  Rotation.from_euler("zyx", head, degrees=True), R_cam_frontal)
    edges = {(e.parent, e.child): e.T for e in
             (*static_transforms(frames, "cam"), *frame_transforms(rec, frames))}
    T_cam_head = edges[("cam", "ficap_cap")] * edges[("ficap_cap", "ficap_head")]
    if frames.mount is not None:
        T_frontal_head = edges[(frames.frontal, "cam")] * T_cam_head
    else:
        T_frontal_head = edges[("cam", frames.frontal)].inv() * T_cam_head
    out = pose_outputs(ROSBAGS, 10, rec, frames)["head_frontal"]
    assert out.header.frame_id == frames.frontal
    p = out.pose.position
    assert np.allclose([p.x, p.y, p.z], T_frontal_head.translation_m, atol=1e-12)
    dq = Rotation.from_quat(_q(out)).inv() * T_frontal_head.rotation
    assert dq.magnitude() < 1e-9


def test_messages_build_with_either_class_set() -> None:
    """The TF message's transforms are the record's, each stamped with the image."""
    rec = _record(Transform(Rotation.from_euler("x", 175.0, degrees=True), [0.0, 0.0, 0.6]),
                  Rotation.identity())
    msg = tf_message(ROSBAGS, 42, frame_transforms(rec, OutputFrames()))
    cap = msg.transforms[0]
    assert (cap.header.frame_id, cap.child_frame_id) == ("cam", "ficap_cap")
    r = cap.transform.rotation
    assert np.allclose([r.x, r.y, r.z, r.w], rec.T_cam_cap.q_xyzw)
    raw = messages.jazzy_typestore().serialize_cdr(msg, "tf2_msgs/msg/TFMessage")
    assert len(raw) > 0
