"""The node's own messages (ficap_ros.ros.msgs: diagnostics, markers, debug image) and the
parameter table, without DDS traffic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from std_msgs.msg import Header

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.params import PARAMETERS, validate_parameter

CONFIG = Path(__file__).resolve().parents[2] / "config" / "ficap.yaml"


def _grey(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


def test_status_values_are_strings() -> None:
    st = ros_msgs.diagnostic_status("ficap", ros_msgs.LEVEL_WARN, "m",
                                    {"a": 1, "b": 0.123456, "c": True})
    assert [(kv.key, kv.value) for kv in st.values] == [("a", "1"), ("b", "0.1235"), ("c", "true")]
    arr = ros_msgs.diagnostic_array(Header(frame_id="x"), st)
    assert arr.status[0].level == ros_msgs.LEVEL_WARN



# -- parameters ----------------------------------------------------------------------------------
def test_config_file_lists_every_parameter_with_its_default() -> None:
    # Keyed '/**' so it applies under any node name and namespace.
    data = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert set(data) == {p.name for p in PARAMETERS}
    for p in PARAMETERS:
        assert data[p.name] == p.default and type(data[p.name]) is type(p.default), p.name
        assert validate_parameter(p.name, p.default) == ""


def test_validation_rejects_out_of_range_and_unknown_choices() -> None:
    assert "within" in validate_parameter("pose.min_tags", 0)
    assert "within" in validate_parameter("calibration.max_spread_deg", 100.0)
    assert "finite" in validate_parameter("calibration.window_s", float("nan"))
    assert "one of" in validate_parameter("pose.method", "magic")
    assert "one of" in validate_parameter("image_transport", "theora")
    assert "must be a" in validate_parameter("pose.min_tags", "3")
    assert validate_parameter("warn_throttle_s", 2) == ""  # int accepted for a float
    assert validate_parameter("camera_mount", [0.0] * 7) == ""  # all zeros: not set
    assert validate_parameter("camera_mount", [0.1, 0.0, 1.2, 0.5, -0.5, 0.5, -0.5]) == ""
    assert "unit length" in validate_parameter("camera_mount", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])
    assert "7 finite" in validate_parameter("camera_mount", [0.0, 0.0, 1.0])
    assert "7 finite" in validate_parameter("camera_mount", [float("nan")] * 3 + [0.0, 0.0, 0.0, 1.0])
    assert validate_parameter("use_sim_time", True) == ""


def test_markers_and_debug_image_without_pose() -> None:
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.labels import FrameRecord

    rec = FrameRecord.processed(0, 0, "cam", None, (), "no tags")
    arr = ros_msgs.markers_msg(Header(frame_id="cam"), nominal_model(), rec)
    assert len(arr.markers) == 1  # only DELETEALL
    img = ros_msgs.debug_image_msg(_grey(), (), None, CameraModel.pinhole(64, 48, hfov_deg=60),
                                   Header(frame_id="cam"))
    assert img.encoding == "bgr8" and img.width == 64 and len(img.data) == 64 * 48 * 3
