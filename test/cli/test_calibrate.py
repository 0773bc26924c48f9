"""ficap calibrate: the paper's Table 2 protocols from labels with a known cap mounting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from recordings import one_error_line, true_R_cap_head
from scipy.spatial.transform import Rotation

from ficap_ros.cli.main import main
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.calibration_file import load_calibration
from ficap_ros.io.labels import FrameRecord, labels_csv_text, read_labels
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pose import CapPose

N = 300
FPS = 30.0
T0 = 1_700_000_000_000_000_000
R_CAP_HEAD = Rotation.from_rotvec(np.radians([4.0, -12.0, 6.0]))
R_CAM_REF = CAM_FROM_FORWARD * rotation_from_ypr_deg(2.0, -5.0, 1.0)


def _drive(tmp_path: Path, noise_deg: float = 0.2) -> tuple[Path, np.ndarray, Rotation]:
    """Labels (uncalibrated) of a head that looks ahead for 2 s, then moves about all axes."""
    rng = np.random.default_rng(11)
    t = np.arange(N) / FPS
    ypr = np.column_stack([40 * np.sin(0.9 * t), 12 * np.sin(1.3 * t + 1), 6 * np.sin(0.7 * t)])
    ypr[t < 2.0] = 0.0
    R_frontal_head = Rotation.from_euler("ZYX", ypr * [1, -1, 1], degrees=True)
    noise = Rotation.from_rotvec(np.radians(rng.normal(0, noise_deg, (N, 3))))
    R_cam_cap = CAM_FROM_FORWARD * R_frontal_head * R_CAP_HEAD.inv() * noise
    stamps = T0 + np.round(np.arange(N) * 1e9 / FPS).astype(np.int64)
    cal = HeadCalibration()
    recs = []
    for i in range(N):
        pose = CapPose(Transform(R_cam_cap[i], [0.0, 0.06, 0.54]), 8, 8, tuple(range(8)), 0.2,
                       np.eye(6) * 1e-6, 0.95, "joint")
        recs.append(FrameRecord.processed(i, int(stamps[i]), "cam", pose, tuple(range(8)), "", cal))
    path = tmp_path / "labels.csv"
    path.write_text(labels_csv_text(recs))
    return path, stamps, R_frontal_head


def test_frontal(tmp_path: Path) -> None:
    labels, _, _ = _drive(tmp_path)
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(labels), "--frontal", "0:1.9", "--out", str(out)]) == 0
    cal = load_calibration(out)
    err = np.degrees((cal.R_cap_head.inv() * R_CAP_HEAD).magnitude())
    assert err < 0.2  # 57 frames of 0.2 deg/axis noise


# The first 100 frames hold only 1.3 s of motion after the 2 s frontal hold, so they pin the
# rotations less well than 100 frames spread over the drive (the paper's First vs Random rows).
@pytest.mark.parametrize("pick,tol_deg", [
    (["--first", "100"], 1.0), (["--random", "100", "--seed", "4"], 0.3), ([], 0.3),
])
def test_reference(tmp_path: Path, pick: list[str], tol_deg: float) -> None:
    labels, stamps, R_frontal_head = _drive(tmp_path)
    # A reference estimator reports the head in its own frame (R_cam_ref unknown to us), 2 ms late.
    R_ref_head = R_CAM_REF.inv() * CAM_FROM_FORWARD * R_frontal_head
    bag = tmp_path / "ref"
    with BagWriter(bag, storage="mcap") as w:
        w.add_topic("/face/head_pose", "geometry_msgs/msg/PoseStamped")
        for i in range(N):
            s = int(stamps[i]) + 2_000_000
            w.write("/face/head_pose", s, messages.pose_stamped(
                ROSBAGS, messages.header(ROSBAGS, s, "face"), Transform(R_ref_head[i], np.zeros(3))))
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(labels), "--reference", f"{bag}:/face/head_pose", *pick,
                 "--out", str(out)]) == 0
    cal = load_calibration(out)
    assert np.degrees((cal.R_cap_head.inv() * R_CAP_HEAD).magnitude()) < tol_deg
    assert np.degrees((cal.R_cam_frontal.inv() * R_CAM_REF).magnitude()) < tol_deg


def test_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    labels, _, _ = _drive(tmp_path)
    cases = [
        [str(tmp_path / "none.csv"), "--frontal", "0:2"],
        [str(labels), "--frontal", "100:200"],  # no frame in the window
        [str(labels), "--frontal", "3:10"],  # the head moves: spread too large
        [str(labels), "--reference", f"{tmp_path / 'nobag'}:/x"],
        [str(labels), "--reference", "justapath"],
    ]
    for args in cases:
        assert main(["calibrate", *args, "--out", str(tmp_path / "c.yaml")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ficap: error:"), err
    assert not (tmp_path / "c.yaml").exists()


def test_time_windows_and_counts_are_checked_with_one_clear_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bad START:END windows and --retries are exit 2 with a message that says what is wanted
    (not Python's 'could not convert string to float'); an open END is the end of the recording."""
    from ficap_ros.tools.replay import parse_window

    assert parse_window("2:") == (2.0, float("inf")) and parse_window(":3") == (0.0, 3.0)
    for bad, says in (("a:b", "expected START:END in seconds"), ("1:2:3", "expected START:END"),
                      (":", "expected START:END"), ("3", "expected START:END"),
                      ("nan:1", "finite"), ("0:inf", "finite"), ("0:nan", "finite"),
                      ("2:1", "0 <= START < END")):
        for argv in (["calibrate", "labels.csv", "--frontal", bad, "--out", "c.yaml"],
                     ["replay", "in", "--out", "o", "--calibrate-frontal", bad]):
            with pytest.raises(SystemExit) as exc:
                main(argv)
            assert exc.value.code == 2, (argv, bad)
            err = capsys.readouterr().err.strip().splitlines()[-1]
            assert says in err and "could not convert" not in err, (bad, err)
    with pytest.raises(SystemExit) as exc:
        main(["replay", "in", "--out", str(tmp_path / "o"), "--retries", "-1"])
    assert exc.value.code == 2 and "--retries" in capsys.readouterr().err


def test_a_short_frontal_window_points_at_min_frames(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """16 frames in 0-0.5 s (both ends in) are fewer than the default 30: the one line says how
    to get past it, and --min-frames 10 then calibrates from those same frames."""
    labels, _, _ = _drive(tmp_path)
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(labels), "--frontal", "0:0.5", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ficap: error:"), err
    assert "needs 30 frames" in err[0] and "has 16" in err[0] and "--min-frames" in err[0], err
    assert not out.exists()
    assert main(["calibrate", str(labels), "--frontal", "0:0.5", "--min-frames", "10",
                 "--out", str(out)]) == 0
    err_deg = np.degrees((load_calibration(out).R_cap_head.inv() * R_CAP_HEAD).magnitude())
    assert err_deg < 0.3  # 16 frames of 0.2 deg/axis noise


def test_replay_frontal_window_too_short_says_what_to_do() -> None:
    """replay's --calibrate-frontal needs 5 posed frames; with 3 the message names the option to
    widen and the calibrate command that has --min-frames."""
    from types import SimpleNamespace

    from ficap_ros.errors import CalibrationError
    from ficap_ros.tools.replay import frontal_calibration

    frames = []
    for i in range(3):
        pose = CapPose(Transform(CAM_FROM_FORWARD * R_CAP_HEAD.inv(), [0.0, 0.06, 0.54]), 8, 8,
                       tuple(range(8)), 0.2, np.eye(6) * 1e-6, 0.95, "joint")
        frames.append(SimpleNamespace(pose=pose, stamp_ns=T0 + i * 33_000_000))
    with pytest.raises(CalibrationError) as exc:
        frontal_calibration(frames, T0, (0.0, 1.0), HeadCalibration())
    msg = str(exc.value)
    assert "\n" not in msg and "has 3" in msg and "--calibrate-frontal" in msg, msg
    assert "--min-frames" in msg, msg


def test_calibrate_frontal_from_labels(drive: Path, replayed_calibrated: Path, tmp_path: Path) -> None:
    from ficap_ros.io.calibration_file import load_calibration

    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(replayed_calibrated), "--frontal", "0:2.9", "--min-frames", "10",
                 "--out", str(out)]) == 0
    cal = load_calibration(out)
    err = np.degrees((cal.R_cap_head.inv() * true_R_cap_head(drive)).magnitude())
    assert cal.calibrated and err < 0.5
    # The file drives a replay: same head poses as the in-replay frontal calibration.
    out2 = tmp_path / "withcal"
    assert main(["replay", str(drive), "--out", str(out2), "--calibration", str(out),
                 "--quiet"]) == 0
    a, b = read_labels(replayed_calibrated), read_labels(out2)
    diff = np.degrees((a.head_rotations().inv() * b.head_rotations()).magnitude())
    assert diff.max() < 1e-3


def test_a_folder_as_output_is_one_line(replayed: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", str(replayed), "--frontal", "0:2", "--out", str(tmp_path)]) == 1
    one_error_line(capsys)
