"""ficap synth -> ficap replay/stats/calibrate/evaluate on a rendered drive with exact ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from ficap_ros.cli import synth as synth_cmd
from ficap_ros.cli.main import main
from ficap_ros.io.labels import read_labels
from ficap_ros.tools.evaluation import read_series_bag

FRAMES = 45
FPS = 5.0  # 9 s of drive: the 3 s frontal segment, then mirror and cluster glances


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("synth") / "drive"
    assert main(["synth", "--out", str(bag), "--resolution", "540p", "--frames", str(FRAMES),
                 "--fps", str(FPS), "--seed", "3", "--quiet"]) == 0
    return bag


@pytest.fixture(scope="module")
def replayed(drive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("replay") / "out"
    assert main(["replay", str(drive), "--out", str(out), "--calibrate-frontal", "0:2.9",
                 "--quiet"]) == 0
    return out


def _true_R_cap_head(bag: Path) -> Rotation:
    import yaml

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    w, x, y, z = json.loads(meta["custom_data"]["ficap.R_cap_head_q_wxyz"])
    return Rotation.from_quat([x, y, z, w])


def _true_positions(bag: Path) -> np.ndarray:
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == synth_cmd.TRUTH_CAP_TOPIC]
        out = []
        for conn, _, raw in reader.messages(connections=conns):
            p = reader.deserialize(raw, conn.msgtype).pose.position
            out.append([p.x, p.y, p.z])
    return np.array(out)


def test_synth_bag_contents(drive: Path) -> None:
    with AnyReader([drive]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {t: FRAMES for t in (
        synth_cmd.IMAGE_TOPIC, synth_cmd.CAMERA_INFO_TOPIC, synth_cmd.TRUTH_CAP_TOPIC,
        synth_cmd.TRUTH_HEAD_TOPIC, synth_cmd.TRUTH_HEAD_CAMERA_TOPIC, synth_cmd.TRUTH_FRONTAL_TOPIC)}


def test_replay_recovers_ground_truth(drive: Path, replayed: Path) -> None:
    labels = read_labels(replayed)
    truth = read_series_bag(drive, synth_cmd.TRUTH_CAP_TOPIC)
    assert len(labels) == FRAMES and labels.has_pose.all()
    np.testing.assert_array_equal(labels.stamp_ns, truth.stamp_ns)  # stamped with image stamps
    err_deg = np.degrees((labels.cap_rotations().inv() * truth.rotations).magnitude())
    # The foundation's accuracy at 540p: cap orientation median well under 0.5 deg.
    assert np.median(err_deg) < 0.5 and np.percentile(err_deg, 95) < 1.0
    # Frontal calibration from the first 2.9 s recovers how the cap sits on the head.
    summary = json.loads((replayed / "summary.json").read_text())
    w, x, y, z = summary["calibration"]["R_cap_head_q_wxyz"]
    cal_err = np.degrees((Rotation.from_quat([x, y, z, w]).inv() * _true_R_cap_head(drive)).magnitude())
    assert cal_err < 0.5
    assert summary["frames"] == FRAMES and summary["frames_skipped"] == 0
    assert summary["pct_ge4_tags"] == 100.0 and summary["throughput_fps"] > 0
    # Every label says how wrong it may be: finite, positive 95 % bounds that hold for the
    # frames' true errors, and a reliability that is the bound's.
    assert np.all(np.isfinite(labels.rot_err95_deg)) and np.all(labels.rot_err95_deg > 0)
    assert np.all(np.isfinite(labels.trans_err95_mm)) and np.all(labels.trans_err95_mm > 0)
    assert np.mean(err_deg <= labels.rot_err95_deg) >= 0.85
    t_err_mm = 1e3 * np.linalg.norm(labels.t_cam_cap_m - _true_positions(drive), axis=1)
    assert np.mean(t_err_mm <= labels.trans_err95_mm) >= 0.85
    np.testing.assert_allclose(labels.reliability, 0.5 ** labels.rot_err95_deg, atol=2e-3)


def test_labels_bag_matches_csv(replayed: Path) -> None:
    labels = read_labels(replayed)
    for path in (replayed / "labels.mcap", replayed):  # single file, and the folder as a bag
        with AnyReader([path]) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
            assert counts == {t: FRAMES for t in (
                "/head_pose", "/head_pose/with_covariance", "/cap_pose", "/head_pose/frontal",
                "/head_rpy_deg", "/quality", "/status", "/tf")}
            conns = [c for c in reader.connections if c.topic == "/cap_pose"]
            stamps, quats = [], []
            for conn, t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                s = msg.header.stamp
                assert t == s.sec * 10**9 + s.nanosec
                stamps.append(t)
                o = msg.pose.orientation
                quats.append([o.x, o.y, o.z, o.w])
    np.testing.assert_array_equal(stamps, labels.stamp_ns)
    err = np.degrees((Rotation.from_quat(quats).inv() * labels.cap_rotations()).magnitude())
    assert err.max() < 1e-4


def _tf_matrix(tr) -> np.ndarray:  # noqa: ANN001 - a decoded geometry_msgs/Transform
    """4x4 by the textbook quaternion formula (independent of ficap_ros and scipy)."""
    x, y, z, w = tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [tr.translation.x, tr.translation.y, tr.translation.z]
    return m


def test_labels_tf_decodes_with_mcap_ros2(replayed: Path) -> None:
    """labels.mcap's /tf, /head_rpy_deg and /quality read by the MCAP project's own ROS 2 decoder
    (mcap-ros2-support, as Foxglove's tooling does), and the TF chain composes to the labels."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    labels = read_labels(replayed)
    summary = json.loads((replayed / "summary.json").read_text())
    w, x, y, z = summary["calibration"]["R_cap_head_q_wxyz"]
    R_cap_head = Rotation.from_quat([x, y, z, w]).as_matrix()
    tf, rpy, quality, schemas = {}, {}, {}, {}
    with open(replayed / "labels.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages(
                topics=["/tf", "/head_rpy_deg", "/quality"]):
            schemas[channel.topic] = schema.name
            {"/tf": tf, "/head_rpy_deg": rpy, "/quality": quality}[channel.topic][message.log_time] = msg
    assert schemas == {"/tf": "tf2_msgs/msg/TFMessage", "/head_rpy_deg": "geometry_msgs/msg/Vector3Stamped",
                       "/quality": "sensor_msgs/msg/JointState"}
    assert sorted(tf) == list(labels.stamp_ns)
    for k, stamp in enumerate(labels.stamp_ns):
        chain = {(t.header.frame_id, t.child_frame_id): t for t in tf[stamp].transforms}
        cam = next(c for p, c in chain if p == "ficap_frontal")  # the image's frame_id
        assert set(chain) == {("ficap_frontal", cam), (cam, "ficap_cap"), ("ficap_cap", "ficap_head")}
        assert all(t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == stamp
                                    for t in chain.values())
        M_cam_cap = _tf_matrix(chain[(cam, "ficap_cap")].transform)
        np.testing.assert_allclose(M_cam_cap[:3, 3], labels.t_cam_cap_m[k], atol=2e-6)
        M_cap_head = _tf_matrix(chain[("ficap_cap", "ficap_head")].transform)
        np.testing.assert_allclose(M_cap_head[:3, :3], R_cap_head, atol=1e-6)
        M = _tf_matrix(chain[("ficap_frontal", cam)].transform) @ M_cam_cap @ M_cap_head
        qw, qx, qy, qz = labels.q_frontal_head_wxyz[k]
        R_csv = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        np.testing.assert_allclose(M[:3, :3], R_csv, atol=1e-6)
        # head_rpy_deg: x roll, y pitch, z yaw = the CSV's REP-103 angles.
        v = rpy[stamp].vector
        yaw, pitch, roll = labels.head_ypr_deg[k]
        np.testing.assert_allclose([v.x, v.y, v.z], [roll, pitch, yaw], atol=1e-3)
        values = dict(zip(quality[stamp].name, quality[stamp].position))
        assert values["tags_detected"] == labels.tags_detected[k]
        assert values["reliability"] == pytest.approx(labels.reliability[k], abs=1e-4)


def test_jobs_2_identical_to_jobs_1(drive: Path, replayed: Path, tmp_path: Path) -> None:
    out = tmp_path / "j2"
    assert main(["replay", str(drive), "--out", str(out), "--calibrate-frontal", "0:2.9",
                 "--jobs", "2", "--quiet"]) == 0
    assert (out / "labels.csv").read_bytes() == (replayed / "labels.csv").read_bytes()
    assert (out / "labels.mcap").read_bytes() == (replayed / "labels.mcap").read_bytes()


def test_jobs_2_progress_moves_frame_by_frame(drive: Path) -> None:
    """With --jobs the results come back a whole segment at a time, but the bar is fed the
    workers' shared frame counter: it moves through intermediate counts, never backwards."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools.replay import process_frames
    from ficap_ros.vision.pose import PoseConfig

    seen: list[int] = []
    source = open_frames(drive)
    frames = list(process_frames(source.raw_frames(), nominal_model(), PoseConfig(), jobs=2,
                                 on_progress=seen.append))
    assert len(frames) == FRAMES and seen[-1] == FRAMES
    assert all(a <= b for a, b in zip(seen, seen[1:]))
    assert len({n for n in seen if 0 < n < FRAMES}) >= 2  # not one jump from 0 to the segment


def test_evaluate_head_against_truth(drive: Path, replayed: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    assert main(["evaluate", "--truth", str(replayed), "--estimate",
                 f"{drive}:{synth_cmd.TRUTH_HEAD_TOPIC}", "--out", str(out), "--no-plots"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_paired"] == FRAMES
    assert rep["geodesic_deg"]["median"] < 0.5 and rep["geodesic_deg"]["p95"] < 1.0


def test_stats_from_labels_and_bag_agree(drive: Path, replayed: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stats", str(replayed), "--out", str(tmp_path / "s1")]) == 0
    from_labels = json.loads((tmp_path / "s1" / "stats.json").read_text())
    summary = json.loads((replayed / "summary.json").read_text())
    assert from_labels["frames"] == summary["frames"]
    assert from_labels["frames_ge4_tags"] == summary["frames_ge4_tags"]
    assert sum(from_labels["reliability_histogram"]["counts"]) == summary["frames_with_pose"]
    rates = from_labels["tag_detection_rate"]
    assert len(rates) == 23 and all(0.0 <= v <= 1.0 for v in rates.values())
    labels = read_labels(replayed)
    assert sum(rates.values()) * FRAMES == pytest.approx(labels.tags_detected.sum())
    assert (tmp_path / "s1" / "reliability_histogram.png").read_bytes()[:4] == b"\x89PNG"


def test_calibrate_frontal_from_labels(drive: Path, replayed: Path, tmp_path: Path) -> None:
    from ficap_ros.io.calibration_file import load_calibration

    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(replayed), "--frontal", "0:2.9", "--min-frames", "10",
                 "--out", str(out)]) == 0
    cal = load_calibration(out)
    err = np.degrees((cal.R_cap_head.inv() * _true_R_cap_head(drive)).magnitude())
    assert cal.calibrated and err < 0.5
    # The file drives a replay: same head poses as the in-replay frontal calibration.
    out2 = tmp_path / "withcal"
    assert main(["replay", str(drive), "--out", str(out2), "--calibration", str(out),
                 "--quiet"]) == 0
    a, b = read_labels(replayed), read_labels(out2)
    diff = np.degrees((a.head_rotations().inv() * b.head_rotations()).magnitude())
    assert diff.max() < 1e-3


def test_ctrl_c_leaves_no_partial_output(drive: Path, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import ficap_ros.tools.replay as replay_mod

    calls = {"n": 0}
    real = replay_mod._process_one

    def interrupted(raw):  # noqa: ANN001, ANN202
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(raw)

    monkeypatch.setattr(replay_mod, "_process_one", interrupted)
    out = tmp_path / "out"
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 130
    assert list(tmp_path.iterdir()) == []  # no output, no temporary folder left beside it
    # A previous output survives an interrupted re-run whole (replaced as a unit, or not at all).
    monkeypatch.setattr(replay_mod, "_process_one", real)
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    calls["n"] = 0
    monkeypatch.setattr(replay_mod, "_process_one", interrupted)
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_replay_bad_inputs(drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("x")
    cases = [
        [str(tmp_path / "missing"), "--out", str(tmp_path / "o")],
        [str(drive), "--out", str(blocked / "sub")],  # output under a file: not creatable
        [str(drive), "--out", str(tmp_path / "o"), "--image-topic", "/nope"],
        [str(drive), "--out", str(tmp_path / "o"), "--camera-info-topic", "/nope"],
        [str(blocked), "--out", str(tmp_path / "o")],  # not a bag, not a video
    ]
    for args in cases:
        assert main(["replay", *args, "--quiet"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ficap: error:"), err


def test_keep_freed_memory_takes_on_glibc() -> None:
    """The replay's allocator setting (replay.keep_freed_memory): glibc takes it (this project's
    platform); elsewhere it says it did nothing, and the labels never depend on it."""
    import platform
    import sys

    from ficap_ros.tools.replay import keep_freed_memory

    expected = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert keep_freed_memory() is expected


def test_records_take_the_runs_calibration_and_say_what_was_lost(drive: Path, tmp_path: Path) -> None:
    """An engine hands back each frame's record (uncalibrated) and timings; replay applies the
    run's calibration to every record, and an undecodable frame is one by its status: labels.csv
    says ``undecodable: ...``, summary.json counts it lost with its plain reason."""
    from scipy.spatial.transform import Rotation as R

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.labels import UNCALIBRATED, FrameRecord
    from ficap_ros.io.sources import open_frames
    from ficap_ros.io.status import FrameStatus
    from ficap_ros.tools.replay import ReplayedFrame, process_frames, replay
    from ficap_ros.vision.calibration import HeadCalibration
    from ficap_ros.vision.pose import PoseConfig

    model, pose = nominal_model(), PoseConfig()
    handed: list[ReplayedFrame] = []

    def engine(raws):  # noqa: ANN001, ANN202
        for f in process_frames(raws, model, pose):
            if f.record.index == 2:
                f = ReplayedFrame(FrameRecord.unprocessed(2, f.record.stamp_ns, f.record.frame_id,
                                                          "bad JPEG", method=pose.method))
            handed.append(f)
            yield f

    cal = HeadCalibration(R.from_euler("y", 5.0, degrees=True), calibrated=True)
    out = replay(open_frames(drive), tmp_path / "out", model, pose, cal, engine=engine,
                 progress=False)
    assert all(f.record.calibration is UNCALIBRATED for f in handed)
    assert len(out.records) == FRAMES and all(r.calibration is cal for r in out.records)
    assert all(r.calibrated for r in out.records)
    assert [r.status for r in out.records].count(FrameStatus.UNDECODABLE) == 1
    assert out.summary["frames_skipped"] == 1 and out.summary["skipped_reasons"] == {"bad JPEG": 1}
    assert out.summary["frames_decoded"] == FRAMES - 1
    labels = read_labels(tmp_path / "out")
    assert labels.reasons[2] == "undecodable: bad JPEG" and labels.skipped.tolist().count(True) == 1
    assert labels.calibrated.all()
    posed = next(r for r in out.records if r.pose is not None)
    R_frontal_head = cal.R_cam_frontal.inv() * posed.T_cam_cap.rotation * cal.R_cap_head
    assert np.degrees((posed.T_frontal_head.rotation.inv() * R_frontal_head).magnitude()) < 1e-9
