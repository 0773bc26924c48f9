"""ficap_ros.ros.live: the node's frame without ROS, driven here by rosbags messages (the node feeds
rclpy's); then the same input live (ficap_node, real rclpy) and offline (a real bag through
``replay`` and ``ficap calibrate``) gives the same answer: CameraInfo rules and choice,
rectification, the frontal window and status levels."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from node_harness import header_at
from scipy.spatial.transform import Rotation
from std_srvs.srv import Trigger

from ficap_ros.cli.main import main
from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.calibration_file import load_calibration
from ficap_ros.io.camera_info import CameraInfoCache
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import open_frames
from ficap_ros.io.status import ERROR, OK, WARN, FrameStatus
from ficap_ros.ros import msgs as ros_msgs
from ficap_ros.ros.live import (
    apply_settings,
    camera_timing,
    failed_frame,
    frame_processor,
    process_image,
    reference_q_xyzw,
)
from ficap_ros.tools.replay import replay
from ficap_ros.tools.synth import RenderConfig, default_scene, render
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pipeline import FrameProcessor
from ficap_ros.vision.pose import PoseConfig

CONFIG = SimpleNamespace(camera_info_max_stamp_diff_ms=1.0, image_is_rectified=False,
                         publish_min_reliability=0.0, warn_reliability=0.5)
S = 5_000_000_000


def test_a_rendered_image_gives_its_pose_and_an_ok_status() -> None:
    scene = default_scene("540p")
    truth = scene.cap_pose(Transform.identity().rotation)
    image = render(nominal_model(), scene.camera, truth, RenderConfig(), seed=11).image
    cameras = CameraInfoCache()
    cameras.add(S, messages.camera_info(ROSBAGS, messages.header(ROSBAGS, S, "cam"), scene.camera))
    msg = messages.image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), image, "mono8")
    frame = process_image(msg, FrameProcessor(model=nominal_model()), cameras, HeadCalibration(),
                          CONFIG)
    assert (frame.level, frame.message) == (OK, "pose") and frame.publish_pose
    rec = frame.record
    assert rec.status is FrameStatus.POSE and rec.T_cam_cap is not None and not frame.failed
    assert angle_deg(rec.T_cam_cap.rotation, truth.rotation) < 0.2
    assert np.abs(rec.T_cam_cap.translation_m - truth.translation_m).max() < 0.005
    assert rec.stamp_ns == S and rec.frame_id == "cam" and frame.image is not None
    assert rec.detected_ids == tuple(sorted({d.tag_id for d in frame.detections}))
    assert rec.T_cam_head is not None and not rec.calibrated
    values = frame.status_values(12.5, 3)
    assert values["search"] == frame.search == "image" and values["dropped_frames"] == 3
    assert frame.quality_values(12.5)["latency_ms"] == 12.5
    # Not reliable enough to publish: the status says so, the pose is kept back.
    strict = SimpleNamespace(**{**vars(CONFIG), "publish_min_reliability": 1.01,
                                "warn_reliability": 1.01})
    frame = process_image(msg, FrameProcessor(model=nominal_model()), cameras, HeadCalibration(),
                          strict)
    assert frame.level == WARN and frame.message.startswith("low reliability")
    assert not frame.publish_pose


def test_errors_become_failed_frames() -> None:
    grey = np.zeros((540, 960), np.uint8)
    msg = messages.image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), grey, "mono8")
    frame = process_image(msg, FrameProcessor(model=nominal_model()), CameraInfoCache(),
                          HeadCalibration(), CONFIG)
    assert frame.level == ERROR and "no CameraInfo" in frame.message and frame.failed
    assert frame.record.reason == frame.message and frame.image is None
    bad = messages.compressed_image(ROSBAGS, messages.header(ROSBAGS, S, "cam"), b"not a jpeg", "jpeg")
    frame = process_image(bad, FrameProcessor(model=nominal_model()), CameraInfoCache(),
                          HeadCalibration(), CONFIG)
    assert frame.level == ERROR and frame.failed and frame.record.stamp_ns == S
    frame = failed_frame(S, "cam", "internal error: boom", HeadCalibration())
    assert (frame.level, frame.message, frame.record.reason) == (
        ERROR, "internal error: boom", "internal error: boom")
    assert frame.record.status is FrameStatus.FAILED and not frame.record.skipped


def test_the_node_settings_build_its_pipeline() -> None:
    """``frame_processor``: the cap model, detector, pose and tracking of the node's settings."""
    from ficap_ros.vision.detector import DetectorConfig

    cfg = SimpleNamespace(model_file="", detector_config=DetectorConfig(edge_photometric=True),
                          pose_config=PoseConfig(method="paper"), tracking=False,
                          camera_timing=None, camera_info_file="")
    proc = frame_processor(cfg)
    assert proc.timing == CameraTiming()
    assert proc.tracker is None and proc.detector.config.edge_photometric
    assert proc.pose_config.method == "paper" and proc.model.ids == nominal_model().ids
    # The pose settings resolved for photometric corners: that profile's uncertainty.
    assert proc.effective_pose_config.uncertainty.light_gradient_tilt_gain == 0.1


def test_the_camera_timing_comes_from_the_parameters_else_the_camera_file(tmp_path: Path) -> None:
    """``camera_timing``: the ``camera.*`` parameters when any is set, else the camera_info_file's
    ``camera_timing`` mapping, else not known; a malformed mapping in a file whose intrinsics read
    refuses to start, an unreadable file is the CameraInfo cache's error (reported there)."""
    import yaml

    from ficap_ros.ros.params import PARAMETERS, NodeConfig

    camera = CameraModel.pinhole(960, 540, hfov_deg=60.0)
    in_file = CameraTiming(exposure_ms=8.0, readout_ms=20.0, stamp_offset_ms=14.0)
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(camera.to_camera_yaml("rear", in_file)))

    def config(**values: object) -> NodeConfig:
        return NodeConfig.from_values({**{p.name: p.default for p in PARAMETERS}, **values})

    assert camera_timing(config()) == CameraTiming()
    assert camera_timing(config(camera_info_file=str(path))) == in_file
    given = {"camera.readout_ms": 22.0, "camera.row_order": "bottom_to_top"}
    assert camera_timing(config(camera_info_file=str(path), **given)) == CameraTiming(
        readout_ms=22.0, row_order="bottom_to_top")
    assert frame_processor(config(camera_info_file=str(path))).timing == in_file
    path.write_text(yaml.safe_dump({**camera.to_camera_yaml(), "camera_timing": {"readout": 3}}))
    with pytest.raises(ConfigError, match="unknown key 'readout'"):
        camera_timing(config(camera_info_file=str(path)))
    assert camera_timing(config(camera_info_file=str(tmp_path / "missing.yaml"))) == CameraTiming()
    # Changed under a running node into a malformed mapping: the parameters' change applies, the
    # timing in use is kept and the reason returned (the node logs it), nothing raised.
    running = frame_processor(config())
    running.timing = in_file
    for block in ({"readout": 3}, {"readout_ms": "fast"}, {"stamp_offset_ms": 1e300}):
        path.write_text(yaml.safe_dump({**camera.to_camera_yaml(), "camera_timing": block}))
        kept = apply_settings(running, config(camera_info_file=str(path), **{"pose.method": "paper"}))
        assert kept.startswith("camera timing kept: ") and "\n" not in kept, kept
        assert running.timing == in_file and running.pose_config.method == "paper"
    path.write_text(yaml.safe_dump(camera.to_camera_yaml("rear", in_file)))
    assert apply_settings(running, config(camera_info_file=str(path), **given)) == ""
    assert running.timing == CameraTiming(readout_ms=22.0, row_order="bottom_to_top")


def test_reference_quaternions_are_checked_and_normalised() -> None:
    T = Transform.identity()
    msg = messages.pose_stamped(ROSBAGS, messages.header(ROSBAGS, S, "ref"), T)
    msg.pose.orientation.w = 2.0
    assert reference_q_xyzw(msg) == pytest.approx([0.0, 0.0, 0.0, 1.0])
    msg.pose.orientation.w = 0.0
    assert reference_q_xyzw(msg) is None
    msg.pose.orientation.x = float("nan")
    assert reference_q_xyzw(msg) is None


# -- the same input live (ficap_node, real rclpy) and offline (a bag through replay) --------------


T0 = 10**9
DT = 33_333_333


def _renders(n: int, ypr_deg: list[tuple[float, float, float]] | None = None) -> list[np.ndarray]:
    scene = default_scene("540p")
    model = nominal_model()
    angles = ypr_deg or [(0.0, 0.0, 0.0)] * n
    return [render(model, scene.camera, scene.cap_pose(rotation_from_ypr_deg(*a)), RenderConfig(),
                   seed=300 + i).image for i, a in enumerate(angles[:n])]


def _write_bag(path: Path, topic: str, images: list[np.ndarray], info_fields: dict) -> None:
    """A bag of mono8 images and one CameraInfo per image (fields overridden by ``info_fields``)."""
    camera = default_scene("540p").camera
    with BagWriter(path, storage="mcap") as w:
        w.add_topic(topic, "sensor_msgs/msg/Image")
        w.add_topic("/camera/camera_info", "sensor_msgs/msg/CameraInfo")
        for i, image in enumerate(images):
            s = T0 + i * DT
            head = messages.header(ROSBAGS, s, "rear_cam_optical")
            info = dataclasses.replace(messages.camera_info(ROSBAGS, head, camera),
                                       **{k: np.asarray(v, dtype=np.float64)
                                          for k, v in info_fields.items()})
            w.write("/camera/camera_info", s, info)
            w.write(topic, s, messages.image(ROSBAGS, head, image, "mono8"))


def _live_info(stamp_ns: int, info_fields: dict):
    msg = messages.camera_info(ros_msgs.RCLPY, header_at(stamp_ns), default_scene("540p").camera)
    for k, v in info_fields.items():
        setattr(msg, k, [float(x) for x in np.asarray(v).reshape(-1)])
    return msg


def _live_caps(h, images: list[np.ndarray], info_fields: dict) -> list:
    statuses = []
    for i, image in enumerate(images):
        s = T0 + i * DT
        statuses.append(h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(s), image, "mono8"),
                                           _live_info(s, info_fields)))
    h.wait_for(lambda: len(h.cap) >= sum(st.message == "pose" for st in statuses), what="cap poses")
    return statuses


def _T(msg) -> Transform:
    p, o = msg.pose.position, msg.pose.orientation
    return Transform(Rotation.from_quat([o.x, o.y, o.z, o.w]), np.array([p.x, p.y, p.z]))


def _assert_same_poses(live: list, offline: list) -> None:
    assert len(live) == len(offline) > 0
    for msg, rec in zip(live, offline):
        assert rec.T_cam_cap is not None
        assert angle_deg(_T(msg).rotation, rec.T_cam_cap.rotation) < 1e-6
        assert np.abs(_T(msg).translation_m - rec.T_cam_cap.translation_m).max() < 1e-9


_K = default_scene("540p").camera.K
_RAW_LENS = {"k": (_K * [[1.05], [1.05], [1]]).reshape(-1), "d": [0.2, -0.1, 0.0, 0.0, 0.0]}


@pytest.mark.parametrize("case,info,live_params,offline_rectified", [
    # Some drivers fill only P: both sides take the image as rectified (camera_from_info).
    ("k_zero", {"k": np.zeros(9), "d": np.zeros(5)}, {}, False),
    # Rectification is the node's parameter live and replay's --rectified offline.
    ("rectified", _RAW_LENS, {"image_is_rectified": True}, True),
])
def test_camera_info_rules_live_and_offline(harness_factory, tmp_path: Path, case: str,  # noqa: F811
                                            info: dict, live_params: dict,
                                            offline_rectified: bool) -> None:
    images = _renders(2)
    h = harness_factory(overrides=live_params)
    _live_caps(h, images, info)
    bag = tmp_path / "bag"
    _write_bag(bag, "/camera/image_raw", images, info)
    out = replay(open_frames(bag, rectified=offline_rectified), tmp_path / "out", nominal_model(),
                 PoseConfig(), progress=False)
    with h.lock:
        live = list(h.cap)
    _assert_same_poses(live, out.records)


def test_camera_info_choice_live_and_offline(harness_factory, tmp_path: Path) -> None:  # noqa: F811
    """CameraInfo stamped around the images, two intrinsics (A true, B 4 % longer focal): the node
    and a bag pick the same one per image (camera_info.pick_camera_info: the nearest within 1 ms, else
    the last at or before the image), so their poses agree. Images 0 and 1 tell the rule from
    "the latest received" and from "the last at or before" alone."""
    a = default_scene("540p").camera
    b = dataclasses.replace(a, K=a.K * [[1.04], [1.04], [1.0]])
    ms = 1_000_000
    # Per image: (offset from its stamp in ns, camera) of the CameraInfo published before it.
    infos = [[(-5 * ms, b), (ms // 2, a)],  # the one 0.5 ms after is within the tolerance
             [(-10 * ms, a), (10 * ms, b)],  # none within: the last before, not the latest
             [(-800_000, b), (300_000, a)],  # both within: the nearer
             [(-20 * ms, a), (-200_000, b), (5 * ms, a)]]  # within, before the image
    want = [a, a, a, b]
    images = _renders(len(infos))
    h = harness_factory()
    statuses = []
    for i, image in enumerate(images):
        s = T0 + i * DT
        for offset_ns, camera in infos[i]:
            msg = messages.camera_info(ros_msgs.RCLPY, header_at(s + offset_ns), camera)
            for _ in range(3):  # best effort: re-send a lost one
                h.pub_info.publish(msg)
                try:
                    h.wait_for(lambda: h.node._cameras.has(s + offset_ns), timeout=3.0)
                    break
                except AssertionError:
                    continue
        statuses.append(h.publish_and_wait(messages.image(ros_msgs.RCLPY, header_at(s), image,
                                                          "mono8")))
    assert [st.message for st in statuses] == ["pose"] * len(images)
    h.wait_for(lambda: len(h.cap) >= len(images), what="cap poses")

    bag = tmp_path / "bag"
    with BagWriter(bag, storage="mcap") as w:
        w.add_topic("/camera/image_raw", "sensor_msgs/msg/Image")
        w.add_topic("/camera/camera_info", "sensor_msgs/msg/CameraInfo")
        for i, image in enumerate(images):
            s = T0 + i * DT
            for offset_ns, camera in infos[i]:
                head = messages.header(ROSBAGS, s + offset_ns, "rear_cam_optical")
                w.write("/camera/camera_info", s + offset_ns,
                        messages.camera_info(ROSBAGS, head, camera))
            w.write("/camera/image_raw", s, messages.image(
                ROSBAGS, messages.header(ROSBAGS, s, "rear_cam_optical"), image, "mono8"))
    src = open_frames(bag)
    assert [raw.camera.K[0, 0] for raw in src.raw_frames()] == [c.K[0, 0] for c in want]
    out = replay(src, tmp_path / "out", nominal_model(), PoseConfig(), progress=False)
    with h.lock:
        live = list(h.cap)
    _assert_same_poses(live, out.records)
    # The choice matters: B's poses are centimetres off A's.
    far = replay(open_frames(bag, intrinsics=b), tmp_path / "out_b", nominal_model(),
                 PoseConfig(), progress=False).records[0].T_cam_cap
    assert np.abs(far.translation_m - out.records[0].T_cam_cap.translation_m).max() > 0.01


def test_rectification_is_not_guessed_from_the_topic_name(tmp_path: Path) -> None:
    images = _renders(1)
    poses = {}
    for topic, rectified in (("/camera/image_rect", False), ("/camera/image_raw", True),
                             ("/camera/image_rect_2", True)):
        bag = tmp_path / topic.rsplit("/", 1)[-1] / str(rectified)
        _write_bag(bag, topic, images, _RAW_LENS)
        src = open_frames(bag, rectified=rectified)
        raw = next(iter(src.raw_frames()))
        assert raw.camera is not None
        assert (raw.camera.distortion_model == "none") == rectified
        poses[(topic, rectified)] = replay(src, tmp_path / f"out{len(poses)}", nominal_model(),
                                           PoseConfig(), progress=False).records[0].T_cam_cap
    # "rect" in the topic name changes nothing; the option does.
    T_raw = poses[("/camera/image_rect", False)]
    T_rect = poses[("/camera/image_raw", True)]
    assert np.abs(poses[("/camera/image_rect_2", True)].translation_m - T_rect.translation_m).max() < 1e-12
    assert np.abs(T_raw.translation_m - T_rect.translation_m).max() > 0.005


def test_frontal_window_and_status_live_and_offline(harness_factory, tmp_path: Path) -> None:  # noqa: F811
    """8 frontal frames and a frame without the cap: the node's ~/calibrate, replay
    --calibrate-frontal and ``ficap calibrate --frontal`` pick the same frames and agree; the
    node's status and labels.mcap's status give the same levels and messages."""
    n = 8
    ypr = [tuple(np.random.default_rng(i).normal(0.0, 0.3, 3)) for i in range(n)]  # a still head
    images = _renders(n, ypr) + [np.full((540, 960), 128, np.uint8)]
    h = harness_factory(overrides={"calibration.min_frames": 5, "calibration.window_s": 3.0})
    statuses = _live_caps(h, images, {})
    resp = h.call(h.calibrate, Trigger.Request())
    assert resp.success, resp.message
    assert f"from {n} frames" in resp.message
    live_cal = h.node.calibration

    bag = tmp_path / "bag"
    _write_bag(bag, "/camera/image_raw", images, {})
    out = replay(open_frames(bag), tmp_path / "out", nominal_model(), PoseConfig(),
                 calibrate_window_s=(0.0, 3.0), progress=False)
    assert out.summary["calibration"]["frames_used"] == n
    q = out.summary["calibration"]["R_cap_head_q_wxyz"]
    assert angle_deg(Rotation.from_quat([q[1], q[2], q[3], q[0]]), live_cal.R_cap_head) < 1e-4
    assert main(["calibrate", str(tmp_path / "out"), "--frontal", "0:3", "--min-frames", "5",
                 "--out", str(tmp_path / "cal.yaml")]) == 0
    cli_cal = load_calibration(tmp_path / "cal.yaml")
    assert angle_deg(cli_cal.R_cap_head, live_cal.R_cap_head) < 1e-4
    assert angle_deg(cli_cal.R_cam_frontal, live_cal.R_cam_frontal) < 1e-9

    # Status: the same level and message per frame (OK "pose" and WARN "no pose: ...").
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "out"]) as reader:
        conns = [c for c in reader.connections if c.topic == "/status"]
        offline = [reader.deserialize(raw, c.msgtype).status[0]
                   for c, _, raw in reader.messages(connections=conns)]
    assert len(offline) == len(statuses) == n + 1
    for live_st, off_st in zip(statuses, offline):
        level = live_st.level if isinstance(live_st.level, bytes) else bytes([live_st.level])
        assert level == bytes([off_st.level])
        assert live_st.message == off_st.message
    assert offline[-1].level == 1 and offline[-1].message.startswith("no pose: ")
