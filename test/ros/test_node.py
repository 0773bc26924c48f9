"""ficap_node with real rclpy: bad inputs, parameters, services (no rendered frames needed).

Every test gets its own rclpy Context on the ROS_DOMAIN_ID conftest sets; every wait is bounded.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CompressedImage
from std_srvs.srv import Trigger

from ficap_ros.errors import ConfigError, ModelError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.io import messages
from ficap_ros.io.calibration_file import load_calibration
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.node import FicapNode

CONFIG = Path(__file__).resolve().parents[2] / "config" / "ficap.yaml"


from node_harness import Harness, header_at, info_at, level_of


def test_bad_inputs_give_error_status_and_node_survives(harness_factory) -> None:
    h = harness_factory(overrides={"warn_throttle_s": 0.0})
    cam = CameraModel.pinhole(64, 48, hfov_deg=60.0)
    grey = np.full((48, 64), 128, np.uint8)
    t = 1_000_000_000

    # 1. No CameraInfo yet.
    st = h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(t), grey, "mono8"))
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "CameraInfo" in st.message

    # 2. All-zero CameraInfo (an uncalibrated camera driver).
    zero = info_at(cam, t + 1)
    zero.k = [0.0] * 9
    zero.p = [0.0] * 12
    st = h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(t + 1), grey, "mono8"), zero)
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "all zero" in st.message

    # 3. NaN CameraInfo.
    nan = info_at(cam, t + 2)
    nan.k = [float("nan")] * 9
    st = h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(t + 2), grey, "mono8"), nan)
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "NaN" in st.message

    # 4. Unknown encoding.
    img = messages.image(ros_msgs.RCLPY, header_at(t + 3), grey, "mono8")
    img.encoding = "32FC1"
    st = h.publish_and_wait(img, info_at(cam, t + 3))
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "encoding" in st.message

    # 5. Wrong data length.
    img = messages.image(ros_msgs.RCLPY, header_at(t + 4), grey, "mono8")
    img.data = bytes(img.data)[:-10]
    st = h.publish_and_wait(img, info_at(cam, t + 4))
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "bytes" in st.message

    # 6. Image and intrinsics of different sizes.
    st = h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(t + 5),
                                           np.zeros((40, 60), np.uint8), "mono8"),
                            info_at(cam, t + 5))
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "does not match" in st.message

    # The node is alive: it still answers services and reports every error, and never posed.
    resp = h.call(h.calibrate, Trigger.Request())
    assert not resp.success and "no reliable frames" in resp.message
    with h.lock:
        assert len(h.head) == 0 and len(h.cap) == 0
        assert {ros_msgs.stamp_to_ns(s.header.stamp) for s in h.status} >= set(range(t, t + 6))
        values = {kv.key for kv in h.status[-1].status[0].values}
    assert values >= {"tags_detected", "tags_used", "rms_px", "reliability", "calibrated",
                      "latency_ms", "dropped_frames"}
    # /diagnostics at 1 Hz reports the errors.
    h.wait_for(lambda: any(d.status and level_of(d.status[0]) == ros_msgs.LEVEL_ERROR
                           for d in h.diagnostics), timeout=3.5, what="/diagnostics ERROR")


def test_undecodable_jpeg_gives_error_status(harness_factory) -> None:
    h = harness_factory(overrides={"image_transport": "compressed", "warn_throttle_s": 0.0})
    cam = CameraModel.pinhole(64, 48, hfov_deg=60.0)
    t = 2_000_000_000
    bad = CompressedImage(header=header_at(t), format="jpeg", data=b"\xff\xd8\xff\xe0garbage")
    st = h.publish_and_wait(bad, info_at(cam, t))
    assert level_of(st) == ros_msgs.LEVEL_ERROR and "decode" in st.message
    assert h.node._image_sub.topic_name == "/image/compressed"


def test_parameters_out_of_range_are_rejected(harness_factory) -> None:
    h = harness_factory()
    node = h.node
    for name, value in [("pose.min_tags", 0), ("pose.min_tags", 40),
                        ("calibration.max_spread_deg", 0.0), ("calibration.window_s", 1e9),
                        ("camera_mount", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0]),
                        ("output_frame", "base_link"),  # no camera_mount: refused
                        ("warn_reliability", 1.5),
                        ("pose.method", "magic"), ("calibration.mode", "guess")]:
        res = node.set_parameters([Parameter(name, value=value)])[0]
        assert not res.successful, (name, value)
        assert node.get_parameter(name).value != value
    # Structural parameters are read-only.
    res = node.set_parameters([Parameter("image_transport", value="compressed")])[0]
    assert not res.successful
    # Through the real parameter service too.
    req = SetParameters.Request(parameters=[Parameter("pose.min_tags", value=99).to_parameter_msg()])
    resp = h.call(h.set_params, req)
    assert not resp.results[0].successful and node.get_parameter("pose.min_tags").value == 1
    # In-range values apply to the running pipeline.
    assert node.set_parameters([Parameter("pose.method", value="paper")])[0].successful
    assert node._processor.pose_config.method == "paper"
    # A camera pitched down 10 deg (REP-103: +10 about base_link's y): built from its axes.
    p = np.radians(10.0)
    R_base_cam = np.column_stack([[0.0, -1.0, 0.0], [-np.sin(p), 0.0, -np.cos(p)],
                                  [np.cos(p), 0.0, -np.sin(p)]])
    q = Rotation.from_matrix(R_base_cam).as_quat()
    mount = [0.2, 0.0, 1.1, *q]
    res = node.set_parameters([Parameter("camera_mount", value=mount),
                               Parameter("output_frame", value="base_link")])
    assert all(r.successful for r in res), res
    fwd = node.calibration.R_cam_frontal.apply([1.0, 0.0, 0.0])
    assert np.degrees(np.arccos(fwd[2])) == pytest.approx(10.0) and fwd[1] < 0


def test_params_file_loads_and_bad_overrides_refuse_to_start(tmp_path) -> None:
    h = Harness(cli_args=["--ros-args", "--params-file", str(CONFIG)])
    try:
        assert h.node.get_parameter("calibration.window_s").value == 3.0
        assert h.node.get_parameter("image_transport").value == "raw"
        assert h.node.unknown_parameters == []
    finally:
        h.close()
    with pytest.raises(ConfigError, match="pose.min_tags"):
        Harness(overrides={"pose.min_tags": 50})
    with pytest.raises(ConfigError, match="image_transport"):
        Harness(overrides={"image_transport": "theora"})
    with pytest.raises(ConfigError, match="needs camera_mount"):
        Harness(overrides={"output_frame": "base_link"})
    # The removed mount angles refuse to start, naming their replacement.
    with pytest.raises(ConfigError, match="frontal.mount_pitch_deg was replaced by camera_mount"):
        Harness(overrides={"frontal.mount_pitch_deg": -10.0})


def test_unparsable_ros_args_are_one_line_not_a_traceback(tmp_path) -> None:
    """rcl refuses a missing or malformed params file, or a bad remap, in rclpy.init: the node
    says so in one line of its own (rcl logs one more) and exits 1."""
    import os
    import subprocess
    import sys

    bad = tmp_path / "bad.yaml"
    bad.write_text("garbage: [\n")
    for ros_args, says in ((["--params-file", str(tmp_path / "none.yaml")], "Error opening YAML"),
                           (["--params-file", str(bad)], "params file"),
                           (["-r", "badremap"], "remap rule")):
        run = subprocess.run([sys.executable, "-m", "ficap_ros.ros.node", "--ros-args", *ros_args],
                             capture_output=True, text=True, timeout=120, env=dict(os.environ))
        assert run.returncode == 1, run.stderr
        assert "Traceback" not in run.stderr, run.stderr
        ours = [ln for ln in run.stderr.splitlines() if ln.startswith("ficap_node:")]
        assert len(ours) == 1 and says in ours[0] and "parser.c" not in ours[0], run.stderr


def _node_with_args(cli_args: list[str]) -> tuple[Context, FicapNode]:
    context = Context()
    rclpy.init(context=context)
    try:
        return context, FicapNode(context=context, cli_args=cli_args)
    except BaseException:
        rclpy.try_shutdown(context=context)
        raise


def test_shipped_params_file_applies_under_a_namespace_and_new_name(tmp_path) -> None:
    # The shipped file with a few values changed (and one key misspelt), given to a node that
    # runs namespaced and renamed, as a launch file or `ros2 run ... -r __ns:=/rear` would.
    data = yaml.safe_load(CONFIG.read_text())
    assert list(data) == ["/**"]
    params = data["/**"]["ros__parameters"]
    params.update({"pose.min_tags": 3, "calibration.window_s": 7.5, "warn_reliability": 0.25,
                   "frontal_frame": "rear_frontal", "pose.min_tag": 2,
                   "uncertainty.tilt_shift_px": 0.06, "uncertainty.light_gradient_gain": 0.75,
                   "uncertainty.light_gradient_tilt_gain": 0.2, "uncertainty.weight_tags": False})
    path = tmp_path / "rear.yaml"
    path.write_text(yaml.safe_dump(data))
    context, node = _node_with_args(["--ros-args", "-r", "__ns:=/rear", "-r", "__node:=ficap_rear",
                                     "--params-file", str(path)])
    try:
        assert (node.get_namespace(), node.get_name()) == ("/rear", "ficap_rear")
        assert node.get_parameter("pose.min_tags").value == 3
        assert node.get_parameter("calibration.window_s").value == 7.5
        assert node.get_parameter("warn_reliability").value == 0.25
        assert node.get_parameter("frontal_frame").value == "rear_frontal"
        assert node._processor.pose_config.min_tags == 3  # and the pipeline uses them
        u = node._processor.pose_config.uncertainty
        assert (u.tilt_shift_px, u.light_gradient_gain, u.light_gradient_tilt_gain,
                u.weight_tags) == (0.06, 0.75, 0.2, False)
        assert node.unknown_parameters == ["pose.min_tag"]  # named in the start-up warning
        assert node._image_sub.topic_name == "/rear/image"
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    # The old key 'ficap_node:' does not match the renamed node: nothing applies (what the
    # '/**' key fixes).
    old = {"ficap_node": {"ros__parameters": {"pose.min_tags": 3}}}
    path.write_text(yaml.safe_dump(old))
    context, node = _node_with_args(["--ros-args", "-r", "__node:=ficap_rear",
                                     "--params-file", str(path)])
    try:
        assert node.get_parameter("pose.min_tags").value == 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_calibration_file_loaded_at_start_and_cleared(harness_factory, tmp_path) -> None:
    from scipy.spatial.transform import Rotation

    from ficap_ros.io.calibration_file import save_calibration
    from ficap_ros.vision.calibration import CalibrationResult

    path = tmp_path / "calib.yaml"
    R = Rotation.from_euler("xyz", [3.0, -8.0, 2.0], degrees=True)
    save_calibration(path, CalibrationResult(R, 90, 0.4, "frontal"))
    h = harness_factory(overrides={"calibration.file": str(path)})
    assert h.node.calibration.calibrated
    assert angle_deg(h.node.calibration.R_cap_head, R) < 1e-6
    resp = h.call(h.clear, Trigger.Request())
    assert resp.success and not h.node.calibration.calibrated
    assert not load_calibration(path).calibrated


def test_node_survives_binary_files_and_never_overwrites_them(binary_files: dict[str, Path],
                                                              tmp_path: Path) -> None:
    from node_harness import Harness
    from std_srvs.srv import Trigger

    bad = binary_files["bin"]
    before = bad.read_bytes()
    with pytest.raises(ModelError):  # the node cannot run without its model: one line, no traceback
        Harness(overrides={"model_file": str(bad)})
    h = Harness(overrides={"calibration.file": str(bad), "camera_info_file": str(bad)})
    try:
        assert not h.node.calibration.calibrated
        resp = h.call(h.clear, Trigger.Request())
        assert not resp.success and "NOT updated" in resp.message
        assert bad.read_bytes() == before
    finally:
        h.close()


def test_node_calibrate_says_when_the_file_was_not_saved(tmp_path: Path) -> None:
    from node_harness import Harness
    from scipy.spatial.transform import Rotation
    from std_srvs.srv import Trigger

    from ficap_ros.vision.calibration import CalibrationResult

    blocker = tmp_path / "file"
    blocker.write_text("x")
    target = blocker / "calib.yaml"  # its folder is a file: cannot be written
    h = Harness(overrides={"calibration.file": str(target)})
    try:
        R = Rotation.from_euler("xyz", [2.0, -5.0, 1.0], degrees=True)
        # The solver is the one the e2e tests exercise; here only the file handling is at stake.
        h.node._run_calibration = lambda: CalibrationResult(R, 60, 0.3, "frontal")  # type: ignore[method-assign]
        resp = h.call(h.calibrate, Trigger.Request())
        assert not resp.success and "NOT saved" in resp.message
        assert h.node.calibration.calibrated  # in use for this session
        blocker.unlink()
        blocker.mkdir()  # now the folder exists: the same call saves and succeeds
        resp = h.call(h.calibrate, Trigger.Request())
        assert resp.success and load_calibration(target).calibrated
    finally:
        h.close()
