"""ficap_ros.io.labels: the frame record and its head pose; labels.csv written and read back."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.metrics import angle_deg, yaw_pitch_roll_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.io.labels import (
    LABEL_COLUMNS,
    FrameRecord,
    head_pose,
    labels_csv_text,
    read_labels,
)
from ficap_ros.io.status import FrameStatus
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pose import CapPose

_quaternions = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1)
_rotations = _quaternions.map(Rotation.from_quat)


@st.composite
def _poses(draw: st.DrawFn) -> CapPose:
    T = Transform(draw(_rotations), draw(st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3)))
    used = tuple(sorted(draw(st.sets(st.integers(0, 22), min_size=1, max_size=23))))
    velocity = draw(st.one_of(st.none(), st.lists(st.floats(-10.0, 10.0), min_size=6,
                                                  max_size=6).map(np.array)))
    return CapPose(T, len(used), len(used), used, draw(st.floats(0.0, 5.0)), np.eye(6) * 1e-8,
                   draw(st.floats(0.0, 1.0)), "joint", draw(st.floats(0.0, 30.0)),
                   draw(st.floats(0.0, 500.0)), velocity)


#: Reasons with the characters CSV must quote (comma, quote), never read as an undecodable one.
_reasons = st.text(st.sampled_from("abc xyz,\"':0123"), max_size=30).filter(
    lambda r: not r.startswith("undecodable"))


@st.composite
def _records(draw: st.DrawFn) -> FrameRecord:
    index, stamp = draw(st.integers(0, 10**6)), draw(st.integers(0, 2**62))
    status = draw(st.sampled_from([FrameStatus.POSE, FrameStatus.NO_POSE, FrameStatus.UNDECODABLE]))
    cal = HeadCalibration(draw(_rotations), draw(_rotations), draw(st.booleans()))
    if status is FrameStatus.UNDECODABLE:
        return FrameRecord.unprocessed(index, stamp, "cam", draw(_reasons), calibration=cal,
                                       method="joint")
    pose = draw(_poses()) if status is FrameStatus.POSE else None
    ids = draw(st.sets(st.integers(0, 22), max_size=23))
    return FrameRecord.processed(index, stamp, "cam", pose, ids, draw(_reasons), cal, "joint")


@given(records=st.lists(_records(), max_size=6))
def test_labels_csv_round_trip(tmp_path_factory: pytest.TempPathFactory,
                               records: list[FrameRecord]) -> None:
    """Records written as labels.csv read back as the same frames: stamps, tags, reasons and which
    are undecodable exactly; poses, head poses and quality to the digits the CSV keeps."""
    path = tmp_path_factory.mktemp("labels") / "labels.csv"
    text = labels_csv_text(records)
    path.write_text(text)
    assert text.splitlines()[0] == ",".join(LABEL_COLUMNS)
    lab = read_labels(path)
    assert len(lab) == len(records)
    assert lab.stamp_ns.tolist() == [r.stamp_ns for r in records]
    assert lab.tags_detected.tolist() == [r.tags_detected for r in records]
    assert lab.tags_used.tolist() == [r.tags_used for r in records]
    assert lab.detected_ids == tuple(r.detected_ids for r in records)
    assert lab.skipped.tolist() == [r.skipped for r in records]
    assert lab.has_pose.tolist() == [r.pose is not None for r in records]
    assert lab.calibrated.tolist() == [r.calibrated for r in records]
    assert lab.reasons == tuple(("undecodable: " if r.skipped else "") + r.reason for r in records)
    for k, r in enumerate(records):
        if r.pose is None:
            assert math.isnan(lab.reliability[k]) and math.isnan(lab.rot_err95_deg[k])
            continue
        assert lab.rms_px[k] == pytest.approx(r.rms_px, abs=5e-5)
        assert lab.reliability[k] == pytest.approx(r.reliability, abs=5e-5)
        assert lab.rot_err95_deg[k] == pytest.approx(r.rot_err95_deg, abs=5e-5)
        # Written to three decimals: half a unit, and a tie's binary rounding beyond it.
        assert lab.trans_err95_mm[k] == pytest.approx(r.trans_err95_mm, abs=5e-4 + 1e-9)
        assert np.abs(lab.t_cam_cap_m[k] - r.T_cam_cap.translation_m).max() <= 5e-7
        assert np.abs(lab.q_cam_cap_wxyz[k] - r.T_cam_cap.q_wxyz).max() <= 5e-10
        assert np.abs(lab.q_frontal_head_wxyz[k] - r.T_frontal_head.q_wxyz).max() <= 5e-10
        ypr = yaw_pitch_roll_deg(r.T_frontal_head.rotation)
        assert np.abs(lab.head_ypr_deg[k] - ypr).max() <= 5e-5
        if r.pose.velocity is None:
            assert np.isnan(lab.head_twist[k]).all()
        else:  # in F's axes, to the 6 decimals the CSV keeps
            want = np.concatenate([r.R_frontal_cam.apply(r.pose.velocity[:3]),
                                   r.R_frontal_cam.apply(r.pose.velocity[3:])])
            assert np.abs(lab.head_twist[k] - want).max() <= 5e-7
    assert all(np.isnan(lab.head_twist[k]).all() for k, r in enumerate(records) if r.pose is None)


def test_head_pose_is_the_cap_pose_turned_and_seen_from_the_frontal_frame() -> None:
    T_cam_cap = Transform(Rotation.from_euler("xyz", [170.0, 10.0, -20.0], degrees=True),
                          [0.05, -0.1, 0.7])
    cal = HeadCalibration(Rotation.from_euler("y", 12.0, degrees=True),
                          Rotation.from_euler("x", -8.0, degrees=True) * CAM_FROM_FORWARD, True)
    head = head_pose(T_cam_cap, cal)
    assert angle_deg(head.T_cam_head.rotation, T_cam_cap.rotation * cal.R_cap_head) < 1e-9
    assert np.allclose(head.T_cam_head.translation_m, T_cam_cap.translation_m, atol=1e-12)
    R_frontal_head = cal.R_cam_frontal.inv() * T_cam_cap.rotation * cal.R_cap_head
    assert angle_deg(head.T_frontal_head.rotation, R_frontal_head) < 1e-9
    assert np.allclose(head.T_frontal_head.translation_m,
                       cal.R_cam_frontal.inv().apply(np.array(T_cam_cap.translation_m)), atol=1e-12)
    # Looking straight at the camera's forward axis with the cap as the head: the zero pose.
    level = Transform(CAM_FROM_FORWARD, [0.0, 0.0, 0.6])
    assert angle_deg(head_pose(level, HeadCalibration()).T_frontal_head.rotation,
                     Rotation.identity()) < 1e-9


def test_a_record_takes_a_calibration_found_later() -> None:
    """The head pose follows the record's calibration: replay applies a frontal calibration to
    records made before it was known."""
    pose = CapPose(Transform(CAM_FROM_FORWARD * Rotation.from_euler("z", 30.0, degrees=True),
                             [0.0, 0.0, 0.6]),
                   4, 4, (1, 2, 3, 4), 0.1, np.eye(6), 0.9, "joint", 0.3, 0.5)
    rec = FrameRecord.processed(7, 100, "cam", pose, (1, 2, 3, 4))
    assert not rec.calibrated and rec.head is not None
    yaw0 = yaw_pitch_roll_deg(rec.T_frontal_head.rotation)[0]
    assert yaw0 == pytest.approx(30.0, abs=1e-9)
    cal = HeadCalibration(Rotation.from_euler("z", -30.0, degrees=True), CAM_FROM_FORWARD, True)
    later = replace(rec, calibration=cal)
    assert later.calibrated and later.T_cam_cap is rec.T_cam_cap
    assert yaw_pitch_roll_deg(later.T_frontal_head.rotation)[0] == pytest.approx(yaw0 - 30.0,
                                                                                 abs=1e-9)
    assert FrameRecord.processed(0, 0, "cam", None, ()).head is None


def test_the_head_angles_are_the_frontal_head_rotations_and_follow_the_calibration() -> None:
    """``head_ypr_deg`` (labels.csv's and the status's head angles) is ``yaw_pitch_roll_deg`` of
    ``T_frontal_head`` to the bit, read-only, under the record's own calibration; None without a
    pose."""
    pose = CapPose(Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZY", [25.0, -7.0], degrees=True),
                             [0.0, 0.0, 0.6]),
                   4, 4, (1, 2, 3, 4), 0.1, np.eye(6), 0.9, "joint", 0.3, 0.5)
    rec = FrameRecord.processed(3, 100, "cam", pose, (1, 2, 3, 4))
    ypr = rec.head_ypr_deg
    assert ypr is not None and np.array_equal(ypr, yaw_pitch_roll_deg(rec.T_frontal_head.rotation))
    assert ypr[0] == pytest.approx(25.0, abs=1e-9) and rec.head_ypr_deg is ypr
    with pytest.raises(ValueError):
        ypr[0] = 0.0
    later = replace(rec, calibration=HeadCalibration(Rotation.from_euler("z", -25.0, degrees=True),
                                                     CAM_FROM_FORWARD, True))
    assert np.array_equal(later.head_ypr_deg, yaw_pitch_roll_deg(later.T_frontal_head.rotation))
    assert abs(later.head_ypr_deg[0]) < 1.0  # the calibration turned the head back by 25 deg
    assert FrameRecord.processed(0, 0, "cam", None, ()).head_ypr_deg is None


def _posed(index: int, velocity: np.ndarray | None) -> FrameRecord:
    pose = CapPose(Transform(CAM_FROM_FORWARD * Rotation.from_euler("z", 20.0 * index, degrees=True),
                             [0.01 * index, 0.0, 0.6]),
                   4, 4, (1, 2, 3, 4), 0.1, np.eye(6) * 1e-7, 0.9, "joint", 0.3, 0.5, velocity)
    cal = HeadCalibration(Rotation.from_euler("y", 8.0, degrees=True),
                          Rotation.from_euler("x", -10.0, degrees=True) * CAM_FROM_FORWARD, True)
    return FrameRecord.processed(index, 1_000 + index, "cam", pose, (1, 2, 3, 4), calibration=cal)


def test_the_head_twist_adds_columns_and_a_topic_and_changes_nothing_else(tmp_path) -> None:
    """A measured velocity adds the six twist columns' values (F's axes) and a ``head_twist``
    message (camera axes, the image's frame and stamp); every other column and every other
    topic's messages are the same bytes as without it; the columns are the last six."""
    from ficap_ros.io.labels import TWIST_COLUMNS, label_topics, write_labels_bag
    from ficap_ros.io.messages import twist_to_array
    from ficap_ros.io.sources import open_bag_reader

    assert LABEL_COLUMNS[-6:] == TWIST_COLUMNS == (
        "head_vx_m_s", "head_vy_m_s", "head_vz_m_s", "head_wx_rad_s", "head_wy_rad_s",
        "head_wz_rad_s")
    w = np.array([0.12, -0.03, 0.01, 0.5, -3.9, 0.2])
    with_twist = [_posed(0, w), _posed(1, None), _posed(2, -w),
                  FrameRecord.processed(3, 1_003, "cam", None, (), "no tags")]
    without = [replace(r, pose=replace(r.pose, velocity=None)) if r.pose is not None else r
               for r in with_twist]
    rows_with = [line.split(",") for line in labels_csv_text(with_twist).splitlines()]
    rows_without = [line.split(",") for line in labels_csv_text(without).splitlines()]
    assert [r[:-6] for r in rows_with] == [r[:-6] for r in rows_without]
    assert all(r[-6:] == [""] * 6 for r in rows_without[1:])
    assert rows_with[2][-6:] == [""] * 6 and rows_with[4][-6:] == [""] * 6
    F = with_twist[0].R_frontal_cam
    assert [float(v) for v in rows_with[1][-6:]] == pytest.approx(
        np.concatenate([F.apply(w[:3]), F.apply(w[3:])]), abs=5e-7)

    def topics(records: list[FrameRecord], name: str) -> dict[str, list]:
        write_labels_bag(tmp_path / name / "labels.mcap", records)
        reader = open_bag_reader(tmp_path / name / "labels.mcap")
        out: dict[str, list] = {c.topic: [] for c in reader.connections}
        for conn, log_ns, raw in reader.messages():
            out[conn.topic].append((log_ns, bytes(raw), reader.deserialize(raw, conn.msgtype)))
        reader.close()
        return out

    got, base = topics(with_twist, "with"), topics(without, "without")
    twist_topic = label_topics()["head_twist"]
    assert twist_topic == "/head_twist" and set(got) == set(base) and twist_topic in base
    for topic in base:
        if topic != twist_topic:
            assert [m[:2] for m in got[topic]] == [m[:2] for m in base[topic]], topic
    assert base[twist_topic] == []
    assert [m[0] for m in got[twist_topic]] == [1_000, 1_002]
    for (_, _, msg), want in zip(got[twist_topic], (w, -w)):
        assert msg.header.frame_id == "cam"
        np.testing.assert_array_equal(twist_to_array(msg), want)
