"""ficap model build: end to end from bags of rendered frames and from a synth drive, an unconverged
build refused unless --allow-partial, bad numbers refused by argparse naming the flag."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cap_views import corner_rms_mm, perturbed_model, rigid_rms_mm
from recordings import FRAMES, cut_copy, one_error_line

from ficap_ros.cli.main import main
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import load_model, nominal_model
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import open_frames
from ficap_ros.tools.synth import REALISTIC, RenderConfig, render


def test_cli_builds_from_a_bag_of_rendered_frames(tmp_path, capsys) -> None:
    """End to end: synth renders the perturbed cap (held in the hand: no head) through the realistic
    image chain (lens PSF in linear light, sensor noise, sRGB tone curve: today's corners come out
    biased inward), frames go into a real MCAP bag with CameraInfo, ``ficap model build`` detects,
    adjusts and replays with both models."""
    camera = CameraModel.pinhole(960, 720, hfov_deg=50.0)
    truth = perturbed_model(seed=11)
    rng = np.random.default_rng(12)
    bag = tmp_path / "cap_views"
    with BagWriter(bag) as writer:
        writer.add_topic("/cam/image_raw", "sensor_msgs/msg/Image")
        writer.add_topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo")
        for k in range(24):
            yaw, pitch, roll = rng.uniform([-50.0, -40.0, -20.0], [50.0, 40.0, 20.0])
            T = Transform(CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, roll),
                          [rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), rng.uniform(0.38, 0.48)])
            frame = render(truth, camera, T, RenderConfig(head=False, **REALISTIC), seed=k)
            stamp = 1_000_000_000 + k * 100_000_000
            head = messages.header(ROSBAGS, stamp, "cam")
            writer.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, camera))
            writer.write("/cam/image_raw", stamp, messages.image(ROSBAGS, head, frame.image, "mono8"))
    out = tmp_path / "cap_asbuilt.yaml"
    report = tmp_path / "report.json"
    plot = tmp_path / "deviations.png"
    assert main(["model", "build", str(bag), "--out", str(out), "--report", str(report),
                 "--plot", str(plot), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "reprojection rms" in printed and str(out) in printed
    assert "replay check" in printed and "nominal" in printed and "built" in printed
    built_model = load_model(out)
    print(f"rendered: built {rigid_rms_mm(built_model, truth):.3f} mm rigid rms from the truth, "
          f"edge offset {json.loads(report.read_text())['edge_offset_px']:+.3f} px")
    assert rigid_rms_mm(built_model, truth) < 0.1 < 0.2 < corner_rms_mm(nominal_model(), truth)
    data = json.loads(report.read_text())
    assert len(data["tags"]) == 23 and data["rms_px"] < 1.0 and data["trusted"]
    assert data["replay_check"]["problems"] == [] and abs(data["replay_check"]["depth_change"]) < 1e-3
    assert plot.read_bytes().startswith(b"\x89PNG")
    # Too strict a coverage demand: one clear line, non-zero exit, no file written.
    refused = tmp_path / "refused.yaml"
    assert main(["model", "build", str(bag), "--out", str(refused), "--min-frames-per-tag", "30",
                 "--quiet"]) == 1
    assert "seen in too few frames" in capsys.readouterr().err
    assert not refused.exists()


def test_unconverged_build_exits_non_zero(tmp_path, capsys) -> None:
    """A solver that runs out of budget is not trusted: exit 1 and no file, unless --allow-partial."""
    camera = CameraModel.pinhole(640, 480, hfov_deg=50.0)
    truth = perturbed_model(seed=21)
    rng = np.random.default_rng(22)
    bag = tmp_path / "few_views"
    with BagWriter(bag) as writer:
        writer.add_topic("/cam/image_raw", "sensor_msgs/msg/Image")
        writer.add_topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo")
        for k in range(8):
            yaw, pitch = rng.uniform([-40.0, -30.0], [40.0, 30.0])
            T = Transform(CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, 0.0), [0.0, 0.0, 0.42])
            frame = render(truth, camera, T, RenderConfig(head=False, supersample=2), seed=k)
            stamp = 1_000_000_000 + k * 100_000_000
            head = messages.header(ROSBAGS, stamp, "cam")
            writer.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, camera))
            writer.write("/cam/image_raw", stamp, messages.image(ROSBAGS, head, frame.image, "mono8"))
    out = tmp_path / "cap.yaml"
    args = ["model", "build", str(bag), "--out", str(out), "--max-nfev", "2", "--min-frames-per-tag", "1",
            "--quiet"]
    assert main(args) == 1
    captured = capsys.readouterr()
    assert "NOT CONVERGED" in captured.out and "did not converge" not in captured.out
    assert "without converging" in captured.err and "not writing" in captured.err
    assert not out.exists()
    assert main(args + ["--allow-partial"]) == 0
    captured = capsys.readouterr()
    assert "warning: the solver stopped at its budget" in captured.err
    assert out.exists() and "partial" in captured.out


def test_cli_builds_from_a_synth_drive(tmp_path, capsys) -> None:
    """``ficap synth --model`` renders a drive of a hand-built cap on a head (occluder, car interior,
    the realistic image chain: PSF in linear light, sensor noise, sRGB tone curve, JPEG);
    ``ficap model build`` on that bag is within 0.1 mm of the truth and its replay check passes."""
    truth = perturbed_model(seed=11)
    truth_path = tmp_path / "truth.yaml"
    truth.save(truth_path)
    bag = tmp_path / "drive"
    # One frame a second of a 30 s drive: glances at mirrors, cluster and screen.
    assert main(["synth", "--out", str(bag), "--model", str(truth_path), "--resolution", "540p",
                 "--frames", "30", "--fps", "1", "--seed", "3", "--quiet"]) == 0
    capsys.readouterr()
    out = tmp_path / "cap_asbuilt.yaml"
    report = tmp_path / "report.json"
    assert main(["model", "build", str(bag), "--out", str(out), "--report", str(report), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "replay check" in printed
    built_model = load_model(out)
    assert rigid_rms_mm(built_model, truth) < 0.1 < 0.3 < rigid_rms_mm(nominal_model(), truth)
    data = json.loads(report.read_text())
    assert data["trusted"] and data["frames_used"] >= 25
    check = data["replay_check"]
    assert check["rms_px_built"] < check["rms_px_nominal"] and not check["problems"]
    assert abs(data["edge_offset_px"]) < 0.6
    print(f"synth drive: built {rigid_rms_mm(built_model, truth):.3f} mm rigid rms from the truth, "
          f"edge offset {data['edge_offset_px']:+.3f} px")


def test_cli_bad_numbers_are_argparse_errors_naming_the_flag(tmp_path, capsys) -> None:  # noqa: ANN001
    """Exit 2 with the flag named (not BuildConfig's field), before any input is read; a NaN
    frame rate is one of them."""
    for flag, value in (("--every", "0"), ("--max-frames", "1"), ("--min-tags", "0"),
                        ("--min-frames-per-tag", "-1"), ("--max-nfev", "0"),
                        ("--assembly-sigma-mm", "nan"), ("--assembly-sigma-mm", "-1"), ("--fps", "nan")):
        with pytest.raises(SystemExit) as exc:
            main(["model", "build", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "m.yaml"),
                  flag, value])
        assert exc.value.code == 2, (flag, value)
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"argument {flag}:" in err, err


def test_model_build_reads_a_cut_mcap(drive: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    cut = cut_copy(drive, tmp_path / "cut", 0.9)
    main(["model", "build", str(cut), "--out", str(tmp_path / "m.yaml"), "--quiet",
          "--max-frames", "20"])
    assert f"{cut}: LOST " in capsys.readouterr().err
    frames = list(open_frames(cut).frames())
    assert len(frames) >= 0.8 * FRAMES and all(f.image is not None for f in frames)


def test_outputs_are_checked_before_any_input_is_read(replayed: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    import ficap_ros.io.sources as bag_io

    def never(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("inputs read before the output was checked")

    monkeypatch.setattr(bag_io, "open_frames", never)
    assert main(["model", "build", str(replayed), "--out",
                 str(tmp_path / "nodir" / "m.yaml")]) == 1
    one_error_line(capsys)
