"""ficap_ros.ros.params: the parameter table read into one frozen, typed NodeConfig."""

from __future__ import annotations

import dataclasses

import pytest

from ficap_ros.errors import ConfigError
from ficap_ros.ros.params import PARAMETERS, CalibrationMode, NodeConfig


def _defaults(**changes: object) -> dict[str, object]:
    values = {p.name: p.default for p in PARAMETERS}
    values.update(changes)
    return values


def test_config_is_typed_and_frozen() -> None:
    cfg = NodeConfig.from_values(_defaults(**{"calibration.window_s": 2, "pose.method": "paper"}))
    assert cfg.calibration_window_s == 2.0 and isinstance(cfg.calibration_window_s, float)
    assert cfg.calibration_mode is CalibrationMode.AUTO and cfg.camera_mount == (0.0,) * 7
    assert cfg.mount is None and cfg.pose_config.method == "paper"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.tracking = False  # type: ignore[misc]


def test_calibration_mode_resolves_auto() -> None:
    assert NodeConfig.from_values(_defaults()).effective_calibration_mode is CalibrationMode.FRONTAL
    ref = NodeConfig.from_values(_defaults(**{"calibration.reference_topic": "/ref"}))
    assert ref.effective_calibration_mode is CalibrationMode.REFERENCE
    forced = NodeConfig.from_values(_defaults(**{"calibration.reference_topic": "/ref",
                                                 "calibration.mode": "frontal"}))
    assert forced.effective_calibration_mode is CalibrationMode.FRONTAL


def test_mount_is_a_transform() -> None:
    cfg = NodeConfig.from_values(_defaults(camera_mount=[0.1, 0.0, 1.2, 0.5, -0.5, 0.5, -0.5]))
    assert cfg.mount is not None and abs(cfg.mount.translation_m[2] - 1.2) < 1e-12
    with pytest.raises(ConfigError):
        NodeConfig.from_values(_defaults(camera_mount=[0.0] * 6 + [2.0])).mount


def test_every_uncertainty_setting_is_a_parameter_with_its_default() -> None:
    from ficap_ros.vision.uncertainty import UncertaintyConfig

    names = {p.name for p in PARAMETERS}
    for f in dataclasses.fields(UncertaintyConfig):
        assert f"uncertainty.{f.name}" in names, f.name
    cfg = NodeConfig.from_values(_defaults(**{"uncertainty.tilt_shift_px": 0.06,
                                              "uncertainty.weight_tags": False,
                                              "uncertainty.light_gradient_gain": 1}))
    u = cfg.pose_config.uncertainty
    assert (u.tilt_shift_px, u.weight_tags, u.light_gradient_gain) == (0.06, False, 1.0)
    assert isinstance(u.light_gradient_gain, float)
    # Parameters cannot be unset: all at their defaults is "not set", the corner estimator's
    # profile (applied by the pipeline); any one changed sets them all.
    assert NodeConfig.from_values(_defaults()).pose_config.uncertainty is None
    one = NodeConfig.from_values(_defaults(**{"uncertainty.focal_rel": 0.01})).pose_config.uncertainty
    assert one == UncertaintyConfig(focal_rel=0.01)


def test_node_defaults_are_the_offline_pipeline_and_the_shipped_file() -> None:
    """The node's defaults are replay's (README: one pipeline live and offline) and
    config/ficap.yaml ships exactly the declared defaults; the node's search_decimate was 1, so a
    1080p camera was searched at full size live and at half size by ficap replay."""
    from pathlib import Path

    import yaml

    from ficap_ros.vision.detector import DetectorConfig

    cfg = NodeConfig.from_values(_defaults())
    assert cfg.detector_search_decimate == DetectorConfig().search_decimate == 0
    assert (cfg.detector_backend, cfg.detector_corner_refine) == (
        DetectorConfig().backend, DetectorConfig().corner_refine)
    shipped = yaml.safe_load((Path(__file__).resolve().parents[2] / "config" / "ficap.yaml")
                             .read_text())["/**"]["ros__parameters"]
    assert shipped == {p.name: p.default for p in PARAMETERS}


def test_detector_photometric_reaches_the_detector() -> None:
    # The node's detector.photometric is the CLI's --photometric: DetectorConfig.edge_photometric
    # of its detector settings; with another corner refinement the node refuses to start.
    on = NodeConfig.from_values(_defaults(**{"detector.photometric": True}))
    assert on.detector_config.edge_photometric is True
    assert NodeConfig.from_values(_defaults()).detector_config.edge_photometric is False
    off = NodeConfig.from_values(_defaults(**{"detector.photometric": True, "detector.corner_refine": "subpix"}))
    with pytest.raises(ConfigError, match="photometric"):
        off.detector_config


def test_detector_photometric_auto_reaches_the_detector() -> None:
    # The node's detector.photometric_auto is the CLI's default (neither --photometric nor
    # --no-photometric): on by default, as there.
    assert NodeConfig.from_values(_defaults()).detector_config.edge_photometric_auto is True
    off = NodeConfig.from_values(_defaults(**{"detector.photometric_auto": False}))
    assert off.detector_config.edge_photometric_auto is False


def test_detector_motion_corners_reaches_the_detector() -> None:
    # The node's detector.motion_corners is the CLI's --motion-corners: on by default, as there.
    assert NodeConfig.from_values(_defaults()).detector_config.motion_corners is True
    off = NodeConfig.from_values(_defaults(**{"detector.motion_corners": False}))
    assert off.detector_config.motion_corners is False


def test_parameter_changes_are_log_lines() -> None:
    from rclpy.parameter import Parameter

    from ficap_ros.ros.params import change_lines

    old = _defaults()
    lines = change_lines(old, [Parameter("pose.method", value="paper"),
                               Parameter("pose.min_tags", value=1),  # unchanged: no line
                               Parameter("qos_overrides./image.subscription.depth", value=3)])
    assert lines == ["parameter pose.method: 'joint' -> 'paper'"]


def test_help_lists_every_parameter_and_every_pose_method() -> None:
    from ficap_ros.ros.params import usage
    from ficap_ros.vision.pose import POSE_METHODS

    text = usage("``ficap_node``: the node.\n\nSubscribes ...")
    assert text.startswith("usage: ficap_node [--ros-args")
    assert all(f"  {p.name} (default " in text for p in PARAMETERS)
    method = next(p for p in PARAMETERS if p.name == "pose.method")
    assert method.choices == tuple(POSE_METHODS)
    assert all(f"'{m}'" in method.description for m in POSE_METHODS)  # naive too


def test_a_calibration_file_in_a_missing_folder_is_warned(tmp_path) -> None:
    from ficap_ros.ros.params import calibration_folder_warning

    assert calibration_folder_warning("") == ""
    assert calibration_folder_warning(str(tmp_path / "cal.yaml")) == ""
    warning = calibration_folder_warning(str(tmp_path / "typo" / "cal.yaml"))
    assert "folder" in warning and "does not exist" in warning and "typo" in warning


def test_the_config_gives_the_output_frames() -> None:
    mount = [0.2, 0.0, 1.1, -0.5, 0.5, -0.5, 0.5]
    frames = NodeConfig.from_values(_defaults(output_frame="base_link", camera_mount=mount)).frames
    assert (frames.output_frame, frames.frontal_frame, frames.moved) == ("base_link", "ficap_frontal", True)
    frames = NodeConfig.from_values(_defaults()).frames
    assert frames.mount is None and frames.frontal == "ficap_frontal"


def test_camera_timing_parameters() -> None:
    """``camera.*``: the camera's timing (None while all are at their defaults: not set), each
    validated against its declared range or choices, none read-only (they may follow the camera)."""
    from ficap_ros.geometry.camera import ROW_ORDERS, CameraTiming
    from ficap_ros.ros.params import descriptor, validate_parameter

    assert NodeConfig.from_values(_defaults()).camera_timing is None
    cfg = NodeConfig.from_values(_defaults(**{"camera.exposure_ms": 16, "camera.readout_ms": 22.0,
                                              "camera.row_order": "bottom_to_top",
                                              "camera.stamp_offset_ms": -19.3}))
    assert cfg.camera_timing == CameraTiming(16.0, 22.0, "bottom_to_top", -19.3)
    assert isinstance(cfg.camera_exposure_ms, float)
    specs = {p.name: p for p in PARAMETERS if p.name.startswith("camera.")}
    assert set(specs) == {"camera.exposure_ms", "camera.readout_ms", "camera.row_order",
                          "camera.stamp_offset_ms"}
    assert not any(p.read_only for p in specs.values())
    assert specs["camera.row_order"].choices == ROW_ORDERS
    for name, lo, hi in (("camera.exposure_ms", 0.0, 1000.0), ("camera.readout_ms", 0.0, 1000.0),
                         ("camera.stamp_offset_ms", -1000.0, 1000.0)):
        r = descriptor(specs[name]).floating_point_range[0]
        assert (r.from_value, r.to_value) == (lo, hi)
        assert validate_parameter(name, hi) == "" and validate_parameter(name, lo) == ""
        assert "within" in validate_parameter(name, hi + 1.0)
        assert "within" in validate_parameter(name, lo - 1.0)
        assert "finite" in validate_parameter(name, float("nan"))
        # Every value the parameter accepts is a valid timing.
        CameraTiming(**{name.split(".")[1]: lo}), CameraTiming(**{name.split(".")[1]: hi})
    assert "one of" in validate_parameter("camera.row_order", "left_to_right")
