"""ficap synth: its arguments (bad camera knobs are argparse's, naming the flag), the bag it writes
(topics, truth, metadata) and what its default frames do to a naive peer's corners."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from recordings import FRAMES
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation
from synth_frames import MODEL

from ficap_ros.cli import synth as synth_cmd
from ficap_ros.cli.main import main
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.tools.synth import (
    REALISTIC,
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)


def test_cli_rejects_bad_camera_knobs(tmp_path, capsys) -> None:
    from ficap_ros.cli.main import main

    # Bad arguments: exit 2 with argparse's line naming the flag, as for every verb's numbers.
    for flag, value in (("--psf-sigma-px", "nan"), ("--psf-sigma-px", "-1"), ("--exposure-ms", "inf"),
                        ("--exposure-ms", "0"), ("--gamma", "-2"), ("--gain", "nan"), ("--defocus-px", "-0.5"),
                        ("--fps", "0"), ("--fps", "nan"), ("--frontal-s", "-1"), ("--jpeg-quality", "101"),
                        ("--jpeg-quality", "x")):
        with pytest.raises(SystemExit) as exc:
            main(["synth", "--out", str(tmp_path / "bag"), "--frames", "1", flag, value, "--quiet"])
        assert exc.value.code == 2, (flag, value)
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith(f"ficap synth: error: argument {flag}:"), err
        assert not (tmp_path / "bag").exists()


def test_naive_peer_is_biased_inward_on_default_synth_frames(tmp_path) -> None:
    """Default ``ficap synth`` frames show what real cameras do to corners: the naive
    peer's (OpenCV sub-pixel) corners sit >= 0.2 px toward the tag centre."""
    from ficap_ros.cli.main import main
    from ficap_ros.geometry.metrics import corner_errors_px
    from ficap_ros.io.sources import decode_raw, open_frames
    from ficap_ros.vision.detector import DetectorConfig, TagDetector
    from ficap_ros.vision.tracking import view_angles_deg

    seed, n = 11, 3
    bag = tmp_path / "bag"
    assert main(["synth", "--out", str(bag), "--frames", str(n), "--fps", "2", "--frontal-s", "0",
                 "--seed", str(seed), "--quiet"]) == 0
    images = [decode_raw(raw) for raw in open_frames(bag).raw_frames()]
    assert len(images) == n
    scene = default_scene("540p")
    peer = TagDetector(DetectorConfig(corner_refine="subpix"))
    radial = []
    for f, image in zip(naturalistic_drive(n, fps=2.0, seed=seed, scene=scene, frontal_s=0.0), images):
        # The truth of the bag's frame (same drive, same default chain and seeds as `ficap synth`).
        truth = render(MODEL, scene.camera, f.T_cam_cap, RenderConfig(background_seed=seed, **REALISTIC),
                       seed=seed * 100003 + f.index)
        ok, jpg = cv2.imencode(".jpg", truth.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert np.array_equal(cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED), image)
        angles = dict(zip(MODEL.ids, view_angles_deg(MODEL, f.T_cam_cap)))
        clean = [t for t in truth.visible_ids(0.999) if angles[t] <= 70.0]
        found = {d.tag_id: d.corners_px for d in peer.detect(image)}
        ids = [t for t in clean if t in found]
        assert len(ids) >= 6
        _, r = corner_errors_px(np.array([found[t] for t in ids]), np.array([truth.corners_px[t] for t in ids]))
        radial.append(r.ravel())
    mean_radial = float(np.concatenate(radial).mean())
    print(f"naive peer mean radial offset {mean_radial:+.3f} px")
    assert mean_radial <= -0.2



def test_the_bag_holds_the_drive_its_truth_and_how_it_was_rendered(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "bag"
    assert main(["synth", "--out", str(bag), "--resolution", "320x180", "--frames", "3", "--fps",
                 "10", "--frontal-s", "0.15", "--seed", "4", "--jpeg-quality", "70",
                 "--quiet"]) == 0
    assert capsys.readouterr().out.startswith(f"3 frames 320x180 neutral -> {bag}")
    scene = default_scene((320, 180))
    drive = naturalistic_drive(3, fps=10.0, seed=4, scene=scene, frontal_s=0.15)
    with AnyReader([bag]) as reader:
        got: dict[str, list] = {}
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            got.setdefault(conn.topic, []).append((log_ns, msg))
    assert {t: len(v) for t, v in got.items()} == {t: 3 for t in (
        synth_cmd.IMAGE_TOPIC, synth_cmd.CAMERA_INFO_TOPIC, synth_cmd.TRUTH_CAP_TOPIC,
        synth_cmd.TRUTH_HEAD_TOPIC, synth_cmd.TRUTH_HEAD_CAMERA_TOPIC, synth_cmd.TRUTH_FRONTAL_TOPIC,
        synth_cmd.TRUTH_TWIST_TOPIC)}
    for f, (log_ns, head), (_, frontal), (_, info) in zip(
            drive, got[synth_cmd.TRUTH_HEAD_TOPIC], got[synth_cmd.TRUTH_FRONTAL_TOPIC],
            got[synth_cmd.CAMERA_INFO_TOPIC]):
        assert log_ns == synth_cmd.START_NS + f.stamp_ns
        assert head.header.frame_id == synth_cmd.FRONTAL_FRAME
        o = head.pose.orientation
        assert angle_deg(Rotation.from_quat([o.x, o.y, o.z, o.w]), f.R_frontal_head) < 1e-6
        assert frontal.data == f.frontal
        np.testing.assert_allclose(np.reshape(info.k, (3, 3)), scene.camera.K)
    assert [fr.data for _, fr in got[synth_cmd.TRUTH_FRONTAL_TOPIC]] == [True, True, False]
    image = cv2.imdecode(np.frombuffer(got[synth_cmd.IMAGE_TOPIC][0][1].data, np.uint8),
                         cv2.IMREAD_UNCHANGED)
    assert image.shape == (180, 320)
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["custom_data"]
    w, x, y, z = json.loads(custom["ficap.R_cap_head_q_wxyz"])
    assert angle_deg(Rotation.from_quat([x, y, z, w]), scene.R_cap_head) < 1e-9
    options = json.loads(custom["ficap.synth"])
    assert options["resolution"] == [320, 180] and options["jpeg_quality"] == 70
    assert options["seed"] == 4 and options["frames"] == 3 and options["tone"] == "srgb"
    assert options["psf_sigma_px"] == pytest.approx(0.7 * np.sqrt(180 / 1080))
    assert (options["motion"], options["motion_blur"], options["readout_ms"]) == (
        "naturalistic", False, 0.0)
    # Still frames: no blur, a global shutter (the timing ficap replay reads).
    assert json.loads(custom["ficap.camera_timing"]) == {
        "exposure_ms": 0.0, "readout_ms": 0.0, "row_order": "top_to_bottom", "stamp_offset_ms": 0.0}


def test_an_existing_out_is_refused_and_left_alone(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bag"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(["synth", "--out", str(out), "--frames", "1", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists already" in err[0]
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_resolution_and_jpeg_quality_types() -> None:
    import argparse

    assert synth_cmd._resolution("640x360") == (640, 360)
    assert synth_cmd._resolution("640X360") == (640, 360)
    assert synth_cmd._resolution("1080p") == "1080p"  # a name: default_scene checks it
    for bad, says in (("63x100", "too small"), ("axb", "expected WxH"),
                      ("100000x100000", "budget")):
        with pytest.raises(argparse.ArgumentTypeError, match=says):
            synth_cmd._resolution(bad)
    assert [synth_cmd._jpeg_quality(v) for v in ("1", "95", "100")] == [1, 95, 100]
    for bad in ("0", "101", "high", "9.5"):
        with pytest.raises(argparse.ArgumentTypeError, match="1..100"):
            synth_cmd._jpeg_quality(bad)


def test_synth_bag_contents(drive: Path) -> None:
    with AnyReader([drive]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts == {t: FRAMES for t in (
        synth_cmd.IMAGE_TOPIC, synth_cmd.CAMERA_INFO_TOPIC, synth_cmd.TRUTH_CAP_TOPIC,
        synth_cmd.TRUTH_HEAD_TOPIC, synth_cmd.TRUTH_HEAD_CAMERA_TOPIC, synth_cmd.TRUTH_FRONTAL_TOPIC,
        synth_cmd.TRUTH_TWIST_TOPIC)}


def _topic(bag: Path, topic: str) -> list:
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(log_ns, reader.deserialize(raw, conn.msgtype))
                for conn, log_ns, raw in reader.messages(connections=conns)]


def test_a_rolling_shutter_glance_drive(glance_rs_drive: Path) -> None:
    """``--motion glances --readout-ms --exposure-ms --motion-blur``: the frames are the glance
    drive's, each rendered through the rolling shutter (its images are ``render``'s of the
    drive's pose function with that timing, byte for byte); the timing and the true twist are in
    the bag, the truth is the pose at the stamp, and the glance is as fast as asked."""
    from recordings import RS_EXPOSURE_MS, RS_FRAMES, RS_READOUT_MS, RS_SEED

    from ficap_ros.io.messages import pose_to_transform, twist_to_array
    from ficap_ros.tools.synth import drive_motion

    custom = yaml.safe_load((glance_rs_drive / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["custom_data"]
    timing = {"exposure_ms": RS_EXPOSURE_MS, "readout_ms": RS_READOUT_MS,
              "row_order": "top_to_bottom", "stamp_offset_ms": 0.0}
    assert json.loads(custom["ficap.camera_timing"]) == timing
    options = json.loads(custom["ficap.synth"])
    assert (options["motion"], options["motion_blur"], options["readout_ms"],
            options["row_order"]) == ("glances", True, RS_READOUT_MS, "top_to_bottom")
    scene = default_scene("540p")
    motion = drive_motion("glances", RS_FRAMES / 30.0, RS_SEED, scene, frontal_s=0.2)
    caps, twists = _topic(glance_rs_drive, synth_cmd.TRUTH_CAP_TOPIC), \
        _topic(glance_rs_drive, synth_cmd.TRUTH_TWIST_TOPIC)
    assert len(caps) == len(twists) == RS_FRAMES
    speeds = []
    for i, ((log_ns, cap), (_, twist)) in enumerate(zip(caps, twists)):
        t = i / 30.0
        assert log_ns == synth_cmd.START_NS + round(t * 1e9)
        assert twist.header.frame_id == synth_cmd.CAMERA_FRAME
        T = pose_to_transform(cap)
        assert angle_deg(T.rotation, motion.T_cam_cap_at(t).rotation) < 1e-6
        np.testing.assert_allclose(twist_to_array(twist), motion.cap_velocity_at(t), atol=1e-9)
        speeds.append(np.degrees(np.linalg.norm(twist_to_array(twist)[3:])))
    assert max(speeds) > 200.0 and sum(s > 90.0 for s in speeds) >= 5
    # One fast frame's image is the renderer's, with that timing, as the bag says.
    i = int(np.argmax(speeds))
    cfg = RenderConfig(background_seed=RS_SEED, exposure_ms=RS_EXPOSURE_MS,
                       readout_ms=RS_READOUT_MS, **REALISTIC)
    want = render(MODEL, scene.camera, motion.around(i / 30.0), cfg, seed=RS_SEED * 100003 + i)
    ok, jpg = cv2.imencode(".jpg", want.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    image = _topic(glance_rs_drive, synth_cmd.IMAGE_TOPIC)[i][1]
    assert bytes(image.data) == jpg.tobytes()


def test_rolling_shutter_flags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--readout-ms without --motion-blur: rows are instants (the timing says exposure 0);
    --row-order is recorded; bad values are argparse's."""
    bag = tmp_path / "bag"
    assert main(["synth", "--out", str(bag), "--resolution", "320x180", "--frames", "2",
                 "--frontal-s", "0", "--motion", "glances", "--readout-ms", "30",
                 "--row-order", "bottom_to_top", "--quiet"]) == 0
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["custom_data"]
    assert json.loads(custom["ficap.camera_timing"]) == {
        "exposure_ms": 0.0, "readout_ms": 30.0, "row_order": "bottom_to_top",
        "stamp_offset_ms": 0.0}
    capsys.readouterr()
    for flag, value in (("--readout-ms", "-1"), ("--readout-ms", "1001"), ("--row-order", "up"),
                        ("--motion", "sneeze")):
        with pytest.raises(SystemExit) as exc:
            main(["synth", "--out", str(tmp_path / "x"), "--frames", "1", flag, value, "--quiet"])
        assert exc.value.code == 2 and f"argument {flag}:" in capsys.readouterr().err
    from ficap_ros.tools import synth

    assert synth_cmd.MOTIONS == synth.MOTIONS
