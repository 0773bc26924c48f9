"""ficap_ros.tools.replay on a rendered drive with exact ground truth: labels as accurate as they
say, labels.mcap the same as labels.csv (and read by the MCAP project's own decoder), parallel
progress frame by frame, the run's calibration applied to every record, the progress bar, --jobs
capped at the cores available, the allocator setting and the start-up freeze."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from probe_cases import kill_pool_workers
from recordings import FRAMES, true_R_cap_head
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation
from textbook import pose_matrix

from ficap_ros.cli import synth as synth_cmd
from ficap_ros.io.labels import read_labels
from ficap_ros.tools.evaluation import read_series_bag


def _true_positions(bag: Path) -> np.ndarray:
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == synth_cmd.TRUTH_CAP_TOPIC]
        out = []
        for conn, _, raw in reader.messages(connections=conns):
            p = reader.deserialize(raw, conn.msgtype).pose.position
            out.append([p.x, p.y, p.z])
    return np.array(out)


def test_replay_recovers_ground_truth(drive: Path, replayed_calibrated: Path) -> None:
    labels = read_labels(replayed_calibrated)
    truth = read_series_bag(drive, synth_cmd.TRUTH_CAP_TOPIC)
    assert len(labels) == FRAMES and labels.has_pose.all()
    np.testing.assert_array_equal(labels.stamp_ns, truth.stamp_ns)  # stamped with image stamps
    err_deg = np.degrees((labels.cap_rotations().inv() * truth.rotations).magnitude())
    # The foundation's accuracy at 540p: cap orientation median well under 0.5 deg.
    assert np.median(err_deg) < 0.5 and np.percentile(err_deg, 95) < 1.0
    # Frontal calibration from the first 2.9 s recovers how the cap sits on the head.
    summary = json.loads((replayed_calibrated / "summary.json").read_text())
    w, x, y, z = summary["calibration"]["R_cap_head_q_wxyz"]
    cal_err = np.degrees((Rotation.from_quat([x, y, z, w]).inv() * true_R_cap_head(drive)).magnitude())
    assert cal_err < 0.5
    assert summary["frames"] == FRAMES and summary["frames_skipped"] == 0
    assert summary["pct_ge4_tags"] == 100.0 and summary["throughput_fps"] > 0
    # The synth camera is a global shutter: the readout read from the moving frames is none,
    # within a few of its standard errors.
    timing = summary["timing_estimate"]
    assert timing["readout_frames"] > 0 and abs(timing["readout_ms"]) < 4.0 * timing["readout_se_ms"]
    # Every label says how wrong it may be: finite, positive 95 % bounds that hold for the
    # frames' true errors, and a reliability that is the bound's.
    assert np.all(np.isfinite(labels.rot_err95_deg)) and np.all(labels.rot_err95_deg > 0)
    assert np.all(np.isfinite(labels.trans_err95_mm)) and np.all(labels.trans_err95_mm > 0)
    assert np.mean(err_deg <= labels.rot_err95_deg) >= 0.85
    t_err_mm = 1e3 * np.linalg.norm(labels.t_cam_cap_m - _true_positions(drive), axis=1)
    assert np.mean(t_err_mm <= labels.trans_err95_mm) >= 0.85
    np.testing.assert_allclose(labels.reliability, 0.5 ** labels.rot_err95_deg, atol=2e-3)


def test_labels_bag_matches_csv(replayed_calibrated: Path) -> None:
    labels = read_labels(replayed_calibrated)
    for path in (replayed_calibrated / "labels.mcap", replayed_calibrated):  # single file, and the folder as a bag
        with AnyReader([path]) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
            assert counts == {**{t: FRAMES for t in (
                "/head_pose", "/head_pose/with_covariance", "/cap_pose", "/head_pose/frontal",
                "/head_rpy_deg", "/head_rpy", "/quality", "/status", "/tf", "/detections",
                "/detections/fit")},
                "/head_twist": int(np.isfinite(labels.head_twist).all(axis=1).sum())}
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
    r, t = tr.rotation, tr.translation
    return pose_matrix((r.x, r.y, r.z, r.w), (t.x, t.y, t.z))


def test_labels_tf_decodes_with_mcap_ros2(replayed_calibrated: Path) -> None:
    """labels.mcap's /tf, /head_rpy_deg and /quality read by the MCAP project's own ROS 2 decoder
    (mcap-ros2-support, as Foxglove's tooling does), and the TF chain composes to the labels: the
    camera (no mount) has no parent; the cap, the head and the frontal frame are its children."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    labels = read_labels(replayed_calibrated)
    summary = json.loads((replayed_calibrated / "summary.json").read_text())
    w, x, y, z = summary["calibration"]["R_cap_head_q_wxyz"]
    R_cap_head = Rotation.from_quat([x, y, z, w]).as_matrix()
    tf, rpy, quality, schemas = {}, {}, {}, {}
    with open(replayed_calibrated / "labels.mcap", "rb") as f:
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
        cam = next(p for p, c in chain if c == "ficap_cap")  # the image's frame_id
        assert set(chain) == {(cam, "ficap_frontal"), (cam, "ficap_cap"), ("ficap_cap", "ficap_head")}
        assert all(t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == stamp
                                    for t in chain.values())
        M_cam_cap = _tf_matrix(chain[(cam, "ficap_cap")].transform)
        np.testing.assert_allclose(M_cam_cap[:3, 3], labels.t_cam_cap_m[k], atol=2e-6)
        M_cap_head = _tf_matrix(chain[("ficap_cap", "ficap_head")].transform)
        np.testing.assert_allclose(M_cap_head[:3, :3], R_cap_head, atol=1e-6)
        M_cam_frontal = _tf_matrix(chain[(cam, "ficap_frontal")].transform)
        np.testing.assert_array_equal(M_cam_frontal[:3, 3], 0.0)  # F's origin at the camera
        M = np.linalg.inv(M_cam_frontal) @ M_cam_cap @ M_cap_head
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


def test_progress_is_per_frame_and_quiet_off_a_terminal() -> None:
    from ficap_ros.tools.replay import Progress

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    bar = Progress(5, "frames", tty)
    for n in range(1, 6):
        bar.update(1)
        assert bar.n == n
    bar.close()
    assert "5/5" in tty.getvalue() and "frame/s" in tty.getvalue()
    plain = io.StringIO()  # a log file: nothing
    bar = Progress(5, "frames", plain)
    bar.update(5)
    bar.close()
    assert plain.getvalue() == ""
    off = Progress(5, "frames", tty, enabled=False)  # --quiet: nothing even on a terminal
    before = tty.getvalue()
    off.update(3)
    off.update(off.n + 2)
    off.close()
    assert tty.getvalue() == before and off.n == 0


def test_jobs_are_capped_at_the_cores_available() -> None:
    from ficap_ros.tools.replay import available_cores, capped_jobs

    cores = available_cores()
    assert capped_jobs(cores + 14) == (cores, f"--jobs {cores + 14} capped at {cores}, "
                                              "the cores available")
    assert capped_jobs(1) == (1, "")


@pytest.mark.parametrize("kills", [1, 100])
def test_a_killed_worker_is_retried_and_never_hangs(drive: Path, kills: int) -> None:
    """--jobs 2 with a worker killed outright (SIGKILL: out of memory, a crash): its segment is
    run again in a new pool and the frames are those of one process; a segment whose workers
    keep dying fails in one line (WorkerError) instead of waiting for ever."""
    import threading
    import time

    from ficap_ros.errors import WorkerError
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools.replay import available_cores, process_frames
    from ficap_ros.vision.pose import PoseConfig

    if available_cores() < 2:
        pytest.skip("--jobs 2 needs two cores")
    model, pose = nominal_model(), PoseConfig()
    one = [f.record for f in process_frames(open_frames(drive).raw_frames(), model, pose, 1)]
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=kill_pool_workers, args=(stop, kills, killed), daemon=True)
    killer.start()
    t0 = time.monotonic()
    try:
        if kills == 1:
            two = [f.record for f in process_frames(open_frames(drive).raw_frames(), model, pose,
                                                    2)]
            assert len(killed) == 1
            from ficap_ros.io.labels import labels_csv_text

            assert labels_csv_text(two) == labels_csv_text(one)
        else:
            with pytest.raises(WorkerError, match=r"a worker process died twice on frames 0-"):
                list(process_frames(open_frames(drive).raw_frames(), model, pose, 2))
    finally:
        stop.set()
        killer.join(timeout=10)
    assert time.monotonic() - t0 < 120.0


def test_the_camera_timing_given_over_the_recordings_own(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``recording_timing``: the given fields over the recording's own timing, else not known;
    every frame is processed with it (jobs 1 in this process; a worker's segments carry it), and
    summary.json records it with its source."""
    import yaml
    from recordings import small_bag

    from ficap_ros.geometry.camera import CameraModel, CameraTiming
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools import replay as replay_mod
    from ficap_ros.vision.pipeline import FrameProcessor
    from ficap_ros.vision.pose import PoseConfig

    bag = tmp_path / "bag"
    small_bag(bag, "mcap", n=6)
    src = open_frames(bag)
    assert replay_mod.recording_timing(src) == (CameraTiming(), "not known")
    assert replay_mod.recording_timing(src, {"readout_ms": 22.0}) == (
        CameraTiming(readout_ms=22.0), "command line")
    yml = tmp_path / "cam.yaml"
    own = CameraTiming(exposure_ms=8.0, readout_ms=30.0, stamp_offset_ms=19.0)
    yml.write_text(yaml.safe_dump(CameraModel.pinhole(64, 48, f_px=50.0).to_camera_yaml("c", own)))
    with_file = open_frames(bag, intrinsics=yml)
    assert replay_mod.recording_timing(with_file) == (own, "intrinsics")
    given = {"readout_ms": 22.0, "stamp_offset_ms": 0.0}
    timing, source = replay_mod.recording_timing(with_file, given)
    assert timing == CameraTiming(exposure_ms=8.0, readout_ms=22.0) and source == \
        "command line over intrinsics"

    seen: list[CameraTiming] = []
    process = FrameProcessor.process

    def spy(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append(self.timing)
        return process(self, *args, **kwargs)

    monkeypatch.setattr(FrameProcessor, "process", spy)
    out = replay_mod.replay(with_file, tmp_path / "out", nominal_model(), PoseConfig(),
                            progress=False, timing=given)
    assert seen == [timing] * 6
    recorded = json.loads((tmp_path / "out" / "summary.json").read_text())["camera_timing"]
    assert recorded == {**timing.to_dict(), "source": "command line over intrinsics"}
    assert out.summary["camera_timing"] == recorded
    # A worker's segment sets the timing it is sent before its first frame.
    replay_mod._init_worker(nominal_model(), PoseConfig(), single_thread=False)
    seen.clear()
    replay_mod._process_segment(list(src.raw_frames())[:2], own)
    assert seen == [own, own] and replay_mod._PROCESSOR.timing == own
    replay_mod._process_segment(list(src.raw_frames())[:1])
    assert seen[-1] == CameraTiming()


def test_two_sided_segments_give_the_same_labels_whatever_the_jobs(
        glance_rs_drive: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A rolling-shutter glance (its timing in the bag) cut into segments of 8 frames: every
    segment carries the next one's first frame as its look-ahead, so --jobs 2 gives labels
    byte-identical to --jobs 1; the two-sided labels differ from the causal ones
    (``two_sided=False``), among them each segment's last frame (solved with its look-ahead);
    summary.json names the motion model."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools import replay as replay_mod
    from ficap_ros.vision.pose import PoseConfig

    monkeypatch.setattr(replay_mod, "SEGMENT_FRAMES", 8)
    runs = {}
    for name, jobs, two_sided in (("j1", 1, True), ("j2", 2, True), ("causal", 1, False)):
        out = replay_mod.replay(open_frames(glance_rs_drive), tmp_path / name, nominal_model(),
                                PoseConfig(), jobs=jobs, progress=False, two_sided=two_sided)
        assert out.summary["motion_model"] == ("two-sided" if two_sided else "causal")
        runs[name] = {f: (tmp_path / name / f).read_bytes() for f in ("labels.csv", "labels.mcap")}
    assert runs["j1"] == runs["j2"]
    rows = {k: (tmp_path / k / "labels.csv").read_text().splitlines()[1:] for k in ("j1", "causal")}
    assert len(rows["j1"]) == 30
    differ = [i for i, (a, b) in enumerate(zip(rows["j1"], rows["causal"])) if a != b]
    assert 7 in differ and 15 in differ and len(differ) >= len(rows["j1"]) // 2
    assert rows["j1"][-1] == rows["causal"][-1]  # the recording's last frame has no next one
