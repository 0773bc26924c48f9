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
    return CapPose(T, len(used), len(used), used, draw(st.floats(0.0, 5.0)), np.eye(6) * 1e-8,
                   draw(st.floats(0.0, 1.0)), "joint", draw(st.floats(0.0, 30.0)),
                   draw(st.floats(0.0, 500.0)))


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
        assert lab.trans_err95_mm[k] == pytest.approx(r.trans_err95_mm, abs=5e-4)
        assert np.abs(lab.t_cam_cap_m[k] - r.T_cam_cap.translation_m).max() <= 5e-7
        assert np.abs(lab.q_cam_cap_wxyz[k] - r.T_cam_cap.q_wxyz).max() <= 5e-10
        assert np.abs(lab.q_frontal_head_wxyz[k] - r.T_frontal_head.q_wxyz).max() <= 5e-10
        ypr = yaw_pitch_roll_deg(r.T_frontal_head.rotation)
        assert np.abs(lab.head_ypr_deg[k] - ypr).max() <= 5e-5


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
