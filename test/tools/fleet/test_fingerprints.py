"""ficap_ros.tools.fleet.fingerprints: what decides a recording's labels, and current outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.tools.fleet.fingerprints import (
    config_json,
    current_outputs,
    fingerprint,
    input_identity,
    label_settings,
    settings_key,
)
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pose import PoseConfig
from ficap_ros.vision.uncertainty import UncertaintyConfig


def test_fingerprint_follows_the_input_not_its_place(fleet_in: Path, tmp_path: Path) -> None:
    settings = {"method": "joint"}
    a = fingerprint(fleet_in / "alice/d1", settings)
    copy = tmp_path / "d1"
    copy.mkdir()
    for f in (fleet_in / "alice/d1").iterdir():
        (copy / f.name).write_bytes(f.read_bytes())
    assert fingerprint(copy, settings)["sha256"] == a["sha256"]  # a copied fleet still resumes
    mcap = next(copy.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[-100] ^= 0xFF
    mcap.write_bytes(bytes(data))
    assert fingerprint(copy, settings)["sha256"] != a["sha256"]
    assert fingerprint(fleet_in / "alice/d1", {"method": "paper"})["sha256"] != a["sha256"]
    assert set(input_identity(copy)["files"]) == {mcap.name, "metadata.yaml"}


def test_settings_are_plain_json_of_the_configs_as_applied() -> None:
    """Configs enter as ``dataclasses.asdict`` JSON, the pose as the pipeline applies it: an unset
    uncertainty and the default one are one setting (the same labels), another method is not."""
    model = nominal_model()
    unset = label_settings(model, PoseConfig())
    assert unset == label_settings(model, PoseConfig(uncertainty=UncertaintyConfig()))
    assert unset["pose"]["uncertainty"] == config_json(UncertaintyConfig())
    assert unset["detector"] == config_json(DetectorConfig()) and unset["rectified"] is False
    assert json.loads(json.dumps(unset, sort_keys=True)) == unset  # plain JSON values
    paper = label_settings(model, PoseConfig(method="paper"))
    assert paper["pose"]["method"] == "paper" and paper != unset
    photo = label_settings(model, PoseConfig(), detector=DetectorConfig(edge_photometric=True))
    assert photo["detector"]["edge_photometric"] is True
    assert photo["pose"]["uncertainty"]["light_gradient_tilt_gain"] == 0.1
    assert settings_key(model, PoseConfig(), None) == settings_key(
        model, PoseConfig(uncertainty=UncertaintyConfig()), DetectorConfig())
    assert settings_key(model, PoseConfig(), None) != settings_key(model, PoseConfig(method="paper"), None)


def test_current_outputs_need_every_output_and_the_digest(tmp_path: Path) -> None:
    for name in ("labels.mcap", "labels.csv"):
        (tmp_path / name).write_text("")
    (tmp_path / "summary.json").write_text(json.dumps({"fingerprint": {"sha256": "abc"}}))
    assert current_outputs(tmp_path, "abc") is None  # no detections.csv (an older run's outputs)
    (tmp_path / "detections.csv").write_text("")
    (tmp_path / "summary.json").unlink()
    assert current_outputs(tmp_path, "abc") is None  # no summary.json
    (tmp_path / "summary.json").write_text(json.dumps({"fingerprint": {"sha256": "abc"}}))
    assert current_outputs(tmp_path, "abc") == {"fingerprint": {"sha256": "abc"}}
    assert current_outputs(tmp_path, "other") is None
    (tmp_path / "summary.json").write_text("{cut")
    assert current_outputs(tmp_path, "abc") is None


def test_output_frames_are_in_the_settings_only_when_set() -> None:
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io.frames import OutputFrames

    model = nominal_model()
    plain = label_settings(model, PoseConfig())
    assert label_settings(model, PoseConfig(), frames=OutputFrames()) == plain  # unchanged
    mount = Transform.from_xyz_q_xyzw([0.2, 0.0, 1.1, -0.5, 0.5, -0.5, 0.5])
    moved = label_settings(model, PoseConfig(), frames=OutputFrames("base_link", mount))
    assert moved["frames"]["output_frame"] == "base_link"
    assert moved["frames"]["camera_mount"][:3] == [0.2, 0.0, 1.1]
    assert {k: v for k, v in moved.items() if k != "frames"} == plain


def test_a_change_anywhere_in_a_recording_is_a_new_identity(tmp_path: Path) -> None:
    """Every byte is hashed: one byte changed in the middle of a file (its size kept, far from
    either end) is a new identity, so its outputs are no longer current."""
    data = bytearray(np.random.default_rng(0).integers(0, 256, 5 << 20, np.uint8).tobytes())
    path = tmp_path / "drive.mcap"
    path.write_bytes(bytes(data))
    before = input_identity(path)
    assert before["files"]["drive.mcap"]["size"] == len(data)
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    after = input_identity(path)
    assert after["files"]["drive.mcap"]["size"] == len(data)
    assert after != before
