"""ficap replay: what it prints and exits with, its outputs (replaced as a unit, never over an input
or a folder ficap did not write), damaged and hostile inputs (a cut MCAP, a corrupt frame, a full
disk, every frame unusable), video input, --jobs (capped, identical to one job) and Ctrl-C."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from recordings import CORRUPT_BAG_FRAMES as N
from recordings import CORRUPT_FRAME as BAD
from recordings import FPS, FRAMES, cut_copy, digest, one_error_line, small_bag

from ficap_ros.cli.args import EXIT_FRAMES_LOST
from ficap_ros.cli.main import main
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.labels import LABEL_COLUMNS, read_labels
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import (
    CAMERA_INFO_TYPE,
    COMPRESSED_TYPE,
    IMAGE_TYPE,
    open_bag_reader,
    open_frames,
)

ROOT = Path(__file__).resolve().parents[2]
FICAP = [sys.executable, "-m", "ficap_ros.cli"]


def test_replay_counts_the_corrupt_frame(bag_with_a_corrupt_frame: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["replay", str(bag_with_a_corrupt_frame), "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == N and summary["frames_skipped"] == 1
    assert summary["frames_with_pose"] == N - 1
    assert sum(summary["skipped_reasons"].values()) == 1
    labels = read_labels(out)
    assert len(labels) == N  # one row per image, the corrupt one without pose fields
    assert labels.skipped.tolist() == [i == BAD for i in range(N)]
    assert not labels.has_pose[BAD] and labels.has_pose.sum() == N - 1
    row = (out / "labels.csv").read_text().splitlines()[1 + BAD].split(",")
    assert row[6:20] == [""] * 14 and row[LABEL_COLUMNS.index("reason")].startswith("undecodable")


def test_replay_video(rendered_frames, tmp_path: Path) -> None:  # noqa: ANN001
    images, scene = rendered_frames
    video = tmp_path / "drive.avi"
    w, h = scene.camera.width_px, scene.camera.height_px
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    for img in images:
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    intr = tmp_path / "camera.yaml"
    intr.write_text(yaml.safe_dump(scene.camera.to_camera_yaml()))
    out = tmp_path / "out"
    assert main(["replay", str(video), "--intrinsics", str(intr), "--fps", "30", "--out",
                 str(out), "--quiet"]) == 0
    labels = read_labels(out)
    assert len(labels) == N and labels.has_pose.all()
    assert labels.stamp_ns[1] == 33_333_333
    assert main(["replay", str(video), "--out", str(out), "--quiet"]) == 1  # no intrinsics


def test_replay_of_90_percent_mcap_labels_every_complete_frame(
        drive: Path, replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = cut_copy(drive, tmp_path / "cut", 0.9)
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["replay", str(cut), "--out", str(out), "--quiet"]) == EXIT_FRAMES_LOST
    line = capsys.readouterr().out.strip()
    full = (replayed / "labels.csv").read_text().splitlines()
    got = (out / "labels.csv").read_text().splitlines()
    n = len(got) - 1
    # The recovered frames are the first n of the recording, labelled exactly as from the whole.
    assert 0.8 * FRAMES <= n < FRAMES
    assert got == full[: n + 1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == n
    assert summary["frames_lost"] == FRAMES - n  # exact: metadata.yaml says 45
    lost = summary["lost"]
    assert lost["estimated"] is False
    assert lost["after_s"] == pytest.approx((n - 1) / FPS, abs=1e-6)
    assert lost["until_s"] == pytest.approx((FRAMES - 1) / FPS, abs=0.01)
    assert f"LOST {FRAMES - n} frames between {(n - 1) / FPS:.3f} s" in line
    # The same file without the folder's metadata.yaml: the count is estimated from the frame rate.
    single = tmp_path / "single.mcap"
    shutil.copy(next(cut.glob("*.mcap")), single)
    source = open_frames(single)
    assert len(list(source.raw_frames())) == n
    # Only the cut chunk's header survives: a lower bound, from its time range and the frame rate.
    assert source.loss is not None and source.loss.estimated
    assert 1 <= source.loss.frames_lost <= FRAMES - n
    assert "at least" in source.loss.describe(source.start_ns)


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


def test_every_frame_skipped_is_an_error(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "wrong"
    cam = CameraModel.pinhole(64, 48, f_px=50.0)
    with BagWriter(bag) as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i in range(5):
            head = messages.header(ROSBAGS, i + 1, "cam")
            w.write("/cam/camera_info", i + 1, messages.camera_info(ROSBAGS, head, cam))
            msg = messages.image(ROSBAGS, head, np.zeros((48, 64), np.uint8), "mono8")
            msg.encoding = "bgr8"  # wrong encoding: the data is a third of what bgr8 needs
            w.write("/cam/image_raw", i + 1, msg)
    assert main(["replay", str(bag), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "none of the 5 frames" in one_error_line(capsys)


def test_share_with_pose_counts_undecodable_frames(drive: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    damaged = tmp_path / "damaged"
    reader = open_bag_reader(drive)
    broken = 0
    try:
        with BagWriter(damaged) as w:
            for conn in reader.connections:
                w.add_topic(conn.topic, conn.msgtype)
            images = 0
            for conn, log_ns, raw in reader.messages():
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.msgtype == COMPRESSED_TYPE:
                    images += 1
                    if images % 4 == 0:
                        msg = messages.compressed_image(
                            ROSBAGS, messages.header(ROSBAGS, log_ns, msg.header.frame_id),
                            b"\xff\xd8junk")
                        broken += 1
                w.write(conn.topic, log_ns, msg)
    finally:
        reader.close()
    out = tmp_path / "out"
    assert main(["replay", str(damaged), "--out", str(out), "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == FRAMES and s["frames_skipped"] == broken > 5
    assert s["pct_with_pose"] == pytest.approx(100 * s["frames_with_pose"] / FRAMES, abs=1e-3)
    assert s["pct_with_pose"] <= 100 * (FRAMES - broken) / FRAMES + 1e-3
    assert f"({s['pct_with_pose']:.1f} %)" in capsys.readouterr().out


def test_replay_refuses_outputs_over_inputs_and_foreign_folders(
        drive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = digest(drive)
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    other_bag = tmp_path / "other"
    shutil.copytree(drive, other_bag)
    for out in (drive, drive.parent, drive / "sub", foreign, other_bag):
        assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 1
        one_error_line(capsys)
    assert digest(drive) == before
    assert (foreign / "notes.txt").read_text() == "keep me"
    assert digest(other_bag) == before


def test_replay_replaces_its_own_output(drive: Path, replayed: Path, tmp_path: Path) -> None:
    out = tmp_path / "again"
    shutil.copytree(replayed, out)
    (out / "labels.csv").write_text("stale")
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 0
    assert (out / "labels.csv").read_text() == (replayed / "labels.csv").read_text()


def test_full_disk_gives_one_line_and_no_output(drive: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    import errno

    from rosbags.rosbag2 import Writer

    real = Writer.write
    count = {"n": 0}

    def full(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        count["n"] += 1
        if count["n"] > 20:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "write", full)
    out = tmp_path / "out"
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 1
    assert "No space left on device" in one_error_line(capsys)
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_leaves_no_partial_output(drive: Path, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import ficap_ros.tools.replay as replay_mod

    calls = {"n": 0}
    real = replay_mod.decode_raw

    def interrupted(raw):  # noqa: ANN001, ANN202
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(raw)

    monkeypatch.setattr(replay_mod, "decode_raw", interrupted)
    out = tmp_path / "out"
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 130
    assert list(tmp_path.iterdir()) == []  # no output, no temporary folder left beside it
    # A previous output survives an interrupted re-run whole (replaced as a unit, or not at all).
    monkeypatch.setattr(replay_mod, "decode_raw", real)
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    calls["n"] = 0
    monkeypatch.setattr(replay_mod, "decode_raw", interrupted)
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_ctrl_c_during_parallel_replay_prints_one_line(tmp_path: Path) -> None:
    # 300 noise frames: three tracking segments of whole-image searches (~50 ms a frame), so
    # work is left in both workers when the first segment's progress line appears.
    bag = tmp_path / "noise"
    small_bag(bag, "mcap", n=300)
    out = tmp_path / "out"
    # The progress bar (tqdm) draws only on a terminal: give the command one for stderr, and
    # interrupt once the bar shows processed frames (the workers are busy then).
    import fcntl
    import pty
    import re
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 120, 0, 0))  # 120 columns
    # A command started from a background job inherits SIGINT ignored (a shell's asynchronous
    # lists ignore it): the child must get the terminal's default, as a user's command does.
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    if ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # SIG_DFL in the child after exec
    try:
        proc = subprocess.Popen([*FICAP, "replay", str(bag), "--out", str(out), "--jobs", "2"],
                                stdout=subprocess.DEVNULL, stderr=slave, cwd=ROOT,
                                start_new_session=True)
    finally:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.close(slave)
    seen = b""
    try:
        while not re.search(rb"\b[1-9]\d*/300\b", seen):
            chunk = os.read(master, 4096)  # raises OSError (EIO) if the command ended first
            seen += chunk
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:
                break
            if not chunk:
                break
            seen += chunk
    finally:
        proc.wait(timeout=120)
        os.close(master)
    text = seen.decode(errors="replace")
    lines = [ln.strip() for ln in re.split(r"[\r\n]+", text) if ln.strip()]
    other = [ln for ln in lines if not ln.startswith("frames:") and "\x1b" not in ln]
    assert proc.returncode == 130, text
    assert other == ["ficap: interrupted"], text
    assert not out.exists()


def test_jobs_2_identical_to_jobs_1(drive: Path, replayed_calibrated: Path, tmp_path: Path) -> None:
    out = tmp_path / "j2"
    assert main(["replay", str(drive), "--out", str(out), "--calibrate-frontal", "0:2.9",
                 "--jobs", "2", "--quiet"]) == 0
    assert (out / "labels.csv").read_bytes() == (replayed_calibrated / "labels.csv").read_bytes()
    assert (out / "labels.mcap").read_bytes() == (replayed_calibrated / "labels.mcap").read_bytes()


def test_jobs_capped_at_available_cores(drive: Path, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from ficap_ros.tools.replay import available_cores

    cores = available_cores()
    out = tmp_path / "out"
    assert main(["replay", str(drive), "--out", str(out), "--jobs", str(cores + 14),
                 "--quiet"]) == 0
    assert f"capped at {cores}" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["jobs"] == cores


MOUNT = ["0.2", "0", "1.1", "-0.5", "0.5", "-0.5", "0.5"]  # looking straight ahead from base_link


def test_replay_into_base_link_through_the_camera_mount(drive: Path, replayed: Path,
                                                       tmp_path: Path) -> None:
    """--camera-mount and --output-frame as the node's camera_mount and output_frame: poses in
    base_link, the mount once on /tf_static, the camera without any other parent; a mount that
    looks straight ahead leaves the head angles (labels.csv) as they were."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = tmp_path / "out"
    assert main(["replay", str(drive), "--out", str(out), "--quiet", "--camera-mount", *MOUNT,
                 "--output-frame", "base_link"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["output_frame"] == "base_link" and summary["camera_mount"][:3] == [0.2, 0.0, 1.1]
    plain, moved = read_labels(replayed), read_labels(out)
    np.testing.assert_allclose(moved.head_ypr_deg, plain.head_ypr_deg, atol=2e-4)
    np.testing.assert_array_equal(moved.t_cam_cap_m, plain.t_cam_cap_m)  # the CSV stays in the camera
    seen: dict[str, list] = {}
    with open(out / "labels.mcap", "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/tf_static", "/tf", "/head_pose", "/head_pose/frontal"]):
            seen.setdefault(channel.topic, []).append(msg)
    (static,) = seen["/tf_static"]
    (mount,) = static.transforms
    cam = mount.child_frame_id
    assert mount.header.frame_id == "base_link" and (mount.transform.translation.z == 1.1)
    assert all(t.child_frame_id != cam for m in seen["/tf"] for t in m.transforms)
    assert {m.header.frame_id for m in seen["/head_pose"]} == {"base_link"}
    assert {m.header.frame_id for m in seen["/head_pose/frontal"]} == {"base_link"}
    # The head 1.1 m up less the cap's drop below the camera: base_link's z of the head.
    assert 0.8 < seen["/head_pose"][0].pose.position.z < 1.4


def test_replay_frame_options_are_checked(drive: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(drive), "--out", str(tmp_path / "a"), "--quiet",
                 "--output-frame", "base_link"]) == 1
    assert "needs camera_mount" in one_error_line(capsys)
    assert main(["replay", str(drive), "--out", str(tmp_path / "b"), "--quiet",
                 "--camera-mount", "0", "0", "0", "0", "0", "0", "2"]) == 1
    assert "unit length" in one_error_line(capsys)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_replay_writes_the_detections_beside_the_labels(replayed: Path) -> None:
    labels = read_labels(replayed)
    rows = (replayed / "detections.csv").read_text().splitlines()
    assert rows[0].startswith("frame,stamp_ns,tag_id,used,residual_px,")
    per_frame: dict[int, set[int]] = {}
    used_residuals = []
    for row in rows[1:]:
        frame, _, tag, used, residual = row.split(",")[:5]
        per_frame.setdefault(int(frame), set()).add(int(tag))
        if used == "1":
            used_residuals.append(float(residual))
    assert np.median(used_residuals) < 0.3 and max(used_residuals) < 3.0
    assert [sorted(per_frame.get(i, ())) for i in range(len(labels))] == [
        sorted(ids) for ids in labels.detected_ids]


def test_replay_offers_every_pose_method(drive: Path, tmp_path: Path) -> None:
    from ficap_ros.cli.args import POSE_METHOD_CHOICES
    from ficap_ros.vision.pose import POSE_METHODS

    assert POSE_METHOD_CHOICES == tuple(POSE_METHODS)
    assert main(["replay", str(drive), "--out", str(tmp_path / "o"), "--quiet", "--method", "naive"]) == 0
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["method"] == "naive"


def test_replay_without_rosbags_is_one_line(drive: Path, tmp_path: Path, monkeypatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("rosbags.highlevel", "rosbags.rosbag2", "rosbags.typesys", "rosbags.serde"):
        monkeypatch.setitem(sys.modules, name, None)  # as if rosbags were not installed
    import ficap_ros.io.messages as messages_mod

    monkeypatch.setattr(messages_mod, "_TYPESTORE", None)
    assert main(["replay", str(drive), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    line = one_error_line(capsys)
    assert "the Python module rosbags is not installed (pip install rosbags" in line


def test_camera_timing_flags_reach_every_recording(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """--exposure-ms/--readout-ms/--row-order/--stamp-offset-ms: each replaces its field of the
    recording's own timing; summary.json records the timing used and its source, a fleet's
    fingerprint the fields given; values out of range are argparse's (exit 2, naming the flag)."""
    for name in ("a", "b"):
        small_bag(tmp_path / "in" / name, "mcap", n=3)
    flags = ["--readout-ms", "22", "--row-order", "bottom_to_top", "--stamp-offset-ms", "-4.5"]
    assert main(["replay", str(tmp_path / "in" / "a"), "--out", str(tmp_path / "one"),
                 "--quiet", *flags]) == 0
    want = {"exposure_ms": 0.0, "readout_ms": 22.0, "row_order": "bottom_to_top",
            "stamp_offset_ms": -4.5, "source": "command line"}
    assert json.loads((tmp_path / "one" / "summary.json").read_text())["camera_timing"] == want
    assert main(["replay", str(tmp_path / "in"), "--out", str(tmp_path / "fleet"), "--quiet",
                 "--exposure-ms", "8", *flags]) == 0
    for name in ("a", "b"):
        summary = json.loads((tmp_path / "fleet" / name / "summary.json").read_text())
        assert summary["camera_timing"] == {**want, "exposure_ms": 8.0}
        assert summary["fingerprint"]["settings"]["camera_timing"] == {
            "exposure_ms": 8.0, "readout_ms": 22.0, "row_order": "bottom_to_top",
            "stamp_offset_ms": -4.5}
    capsys.readouterr()
    for flag, value in (("--readout-ms", "-1"), ("--exposure-ms", "2000"),
                        ("--stamp-offset-ms", "nan"), ("--row-order", "sideways")):
        with pytest.raises(SystemExit) as exc:
            main(["replay", str(tmp_path / "in" / "a"), "--out", str(tmp_path / "x"), flag, value])
        assert exc.value.code == 2 and f"argument {flag}:" in capsys.readouterr().err


def test_a_zeroed_page_inside_a_sqlite3_bag(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A page of zeros anywhere after the schema (rosbags' apsw raises CorruptError there, at
    open or mid-read): the frames before it are labelled and the loss said in one line (exit 3),
    or nothing readable is one error line; never a traceback."""
    camera = CameraModel.pinhole(160, 120, f_px=120.0)
    with BagWriter(tmp_path / "good", storage="sqlite3") as w:  # images span overflow pages
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i in range(20):
            head = messages.header(ROSBAGS, 1_700_000_000_000_000_000 + i * 33_333_333, "cam")
            noise = np.random.default_rng(i).integers(0, 256, (120, 160), dtype=np.uint8)
            w.write("/cam/camera_info", head.stamp.sec * 10**9 + head.stamp.nanosec,
                    messages.camera_info(ROSBAGS, head, camera))
            w.write("/cam/image_raw", head.stamp.sec * 10**9 + head.stamp.nanosec,
                    messages.image(ROSBAGS, head, noise, "mono8"))
    good = next((tmp_path / "good").glob("*.db3")).read_bytes()
    page = int.from_bytes(good[16:18], "big")
    pages = len(good) // page
    salvaged = 0
    for k in sorted({3, pages // 3, pages // 2, pages - 2}):
        bag = tmp_path / f"zero{k}"
        shutil.copytree(tmp_path / "good", bag)
        db = next(bag.glob("*.db3"))
        data = bytearray(good)
        data[k * page: (k + 1) * page] = bytes(page)
        db.write_bytes(bytes(data))
        code = main(["replay", str(bag), "--out", str(tmp_path / f"o{k}"), "--quiet"])
        captured = capsys.readouterr()
        assert "Traceback" not in captured.err and code in (0, 1, 3), (k, code, captured)
        if code == 3:
            assert "LOST" in captured.out and not captured.err.strip()
            salvaged += 1
        if code == 1:
            assert len(captured.err.strip().splitlines()) == 1
        assert db.read_bytes() == bytes(data)
    assert salvaged >= 1  # rosbags' CorruptError mid-read: the frames before it kept


def test_no_two_sided_motion_keeps_the_causal_model(glance_rs_drive: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """--no-two-sided-motion: summary.json says ``causal`` (the default run of a timed recording
    says ``two-sided``); a fleet refuses it in one line."""
    out = tmp_path / "causal"
    assert main(["replay", str(glance_rs_drive), "--out", str(out), "--no-two-sided-motion",
                 "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["motion_model"] == "causal"
    assert main(["replay", str(glance_rs_drive), str(glance_rs_drive), "--out", str(tmp_path / "f"),
                 "--no-two-sided-motion", "--quiet"]) == 1
    assert "--no-two-sided-motion is for one recording" in one_error_line(capsys)
