"""ficap evaluate: an estimator with a known injected error gets that error reported; bad inputs
and malformed rows are one line naming the file and line."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from head_series import YAW_OFFSET_DEG, N, estimate_of, truth_labels
from recordings import FRAMES

from ficap_ros.cli import synth as synth_cmd
from ficap_ros.cli.main import main
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS


@pytest.mark.parametrize("kind", ["bag", "csv"])
def test_evaluate_reports_injected_yaw_error(tmp_path: Path, kind: str) -> None:
    truth_csv, R, stamps = truth_labels(tmp_path)
    R_est = estimate_of(R)
    # Estimator stamps jitter by up to 4 ms; one estimate every frame, including truth gaps.
    jitter = np.random.default_rng(5).integers(-4_000_000, 4_000_000, N)
    est_stamps = stamps + jitter
    if kind == "bag":
        bag = tmp_path / "estimator"
        with BagWriter(bag, storage="sqlite3") as w:
            w.add_topic("/estimator/head_pose", "geometry_msgs/msg/PoseStamped")
            for i in range(N):
                w.write("/estimator/head_pose", int(est_stamps[i]),
                        messages.pose_stamped(ROSBAGS,
                                              messages.header(ROSBAGS, int(est_stamps[i]), "frontal"),
                                              Transform(R_est[i], np.zeros(3))))
        spec = f"{bag}:/estimator/head_pose"
    else:
        spec = str(tmp_path / "estimate.csv")
        with open(spec, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["stamp_ns", "qw", "qx", "qy", "qz"])
            for i in range(N):
                x, y, z, qw = R_est[i].as_quat()
                w.writerow([int(est_stamps[i]), qw, x, y, z])
    out = tmp_path / "report"
    assert main(["evaluate", "--truth", str(truth_csv), "--estimate", spec, "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    n_pose = int(np.count_nonzero(np.arange(N) % 5 != 4))
    assert rep["n_paired"] == n_pose
    # Geodesic error of a 3 deg rotation composed with 0.3 deg/axis noise: median within 0.3 deg
    # of 3; Phi3 is half of it; the yaw bias is the offset, pitch and roll biases near zero.
    g = rep["geodesic_deg"]
    assert abs(g["median"] - YAW_OFFSET_DEG) < 0.3
    assert abs(rep["phi3_deg"]["median"] - YAW_OFFSET_DEG / 2) < 0.15
    axes = rep["axis_error_deg"]
    assert abs(axes["yaw"]["mean"] - YAW_OFFSET_DEG) < 0.1
    assert abs(axes["pitch"]["mean"]) < 0.1 and abs(axes["roll"]["mean"]) < 0.1
    assert 0.2 < axes["yaw"]["std"] < 0.6
    for name in ("report.md", "error_histogram.png", "timeseries.png", "error_vs_yaw.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "error_histogram.png").read_bytes()[:4] == b"\x89PNG"


def test_evaluate_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth_csv, _, _ = truth_labels(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    cases = [
        ["--truth", str(tmp_path / "missing.csv"), "--estimate", str(truth_csv)],
        ["--truth", str(truth_csv), "--estimate", str(bad)],
        ["--truth", str(truth_csv), "--estimate", f"{tmp_path / 'nobag'}:/x"],
    ]
    far = tmp_path / "far.csv"
    far.write_text("stamp_ns,yaw_deg,pitch_deg,roll_deg\n5,0,0,0\n")
    cases.append(["--truth", str(truth_csv), "--estimate", str(far)])
    for args in cases:
        assert main(["evaluate", *args, "--out", str(tmp_path / "r")]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ficap: error:")


def test_a_malformed_estimate_row_is_named_by_its_line(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    truth_csv, _, _ = truth_labels(tmp_path)
    est = tmp_path / "est.csv"
    est.write_text("stamp_ns,yaw_deg,pitch_deg,roll_deg\n1,0,0,0\n2,unknown,0,0\n")
    assert main(["evaluate", "--truth", str(truth_csv), "--estimate", str(est),
                 "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ficap: error: {est} line 3: malformed row (not a number: 'unknown')"]


def test_a_row_cut_short_is_named_by_its_line_not_a_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A row without its stamp (the stamp column last, the row one field short) is a malformed
    row too: one line naming it and the missing stamp_ns."""
    truth_csv, _, _ = truth_labels(tmp_path)
    est = tmp_path / "est.csv"
    est.write_text("qw,qx,qy,qz,stamp_ns\n1,0,0,0,1\n1,0,0,0\n")
    assert main(["evaluate", "--truth", str(truth_csv), "--estimate", str(est),
                 "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"ficap: error: {est} line 3: malformed row"), err
    assert "stamp_ns" in err[0], err


def test_a_folder_without_labels_csv_names_replay_output_folders(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The user most likely meant a replay output folder: say that and that labels.csv is missing."""
    truth_csv, _, _ = truth_labels(tmp_path)
    folder = tmp_path / "run"
    folder.mkdir()
    assert main(["evaluate", "--truth", str(folder), "--estimate", str(truth_csv),
                 "--out", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ficap: error:"), err
    assert "replay output folder" in err[0] and "without labels.csv" in err[0], err


def test_evaluate_head_against_truth(drive: Path, replayed_calibrated: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    assert main(["evaluate", "--truth", str(replayed_calibrated), "--estimate",
                 f"{drive}:{synth_cmd.TRUTH_HEAD_TOPIC}", "--out", str(out), "--no-plots"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["n_paired"] == FRAMES
    assert rep["geodesic_deg"]["median"] < 0.5 and rep["geodesic_deg"]["p95"] < 1.0
