"""ficap_ros.geometry.camera.CameraModel: identity (one key, equality and hash), intrinsics checks,
rectified CameraInfo, and properties of projection, undistortion, scaling and the camera YAML."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros.errors import IntrinsicsError
from ficap_ros.geometry.camera import CameraModel, load_camera_yaml

#: Moderate lens coefficients per model: distortion stays monotonic over the sampled field.
_COEFFS = {
    "none": [],
    "plumb_bob": [(-0.3, 0.3), (-0.1, 0.1), (-0.005, 0.005), (-0.005, 0.005), (-0.05, 0.05)],
    "rational_polynomial": [(-0.3, 0.3), (-0.1, 0.1), (-0.005, 0.005), (-0.005, 0.005),
                            (-0.05, 0.05), (-0.1, 0.1), (-0.05, 0.05), (-0.02, 0.02)],
    "equidistant": [(-0.1, 0.1), (-0.03, 0.03), (-0.01, 0.01), (-0.005, 0.005)],
}


@st.composite
def cameras(draw: st.DrawFn, models: tuple[str, ...] = tuple(_COEFFS)) -> CameraModel:
    """A camera of any lens model: size, focal lengths, principal point near the centre."""
    model = draw(st.sampled_from(models))
    width = draw(st.integers(64, 4000))
    height = draw(st.integers(48, 3000))
    fx = draw(st.floats(0.3, 3.0)) * width
    fy = fx * draw(st.floats(0.95, 1.05))
    cx = draw(st.floats(0.35, 0.65)) * width
    cy = draw(st.floats(0.35, 0.65)) * height
    d = [draw(st.floats(lo, hi)) for lo, hi in _COEFFS[model]]
    return CameraModel(width, height, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
                       np.array(d), model)


def _points(seed: int, n: int = 20, max_tan: float = 0.5) -> np.ndarray:
    """Points in front of the camera within ``max_tan`` of the axis (metres, optical frame)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-max_tan, max_tan, (n, 2))
    z = rng.uniform(0.2, 5.0, (n, 1))
    return np.hstack([xy * z, z])


def test_camera_models_compare_and_hash_by_value() -> None:
    a = CameraModel.pinhole(960, 540, f_px=700.0)
    b = CameraModel(960, 540, a.K.copy(), np.zeros(0), "none")
    c = CameraModel(960, 540, a.K * [[1.0001], [1], [1]], np.zeros(0), "none")
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    assert a != c and a != "camera"
    d = CameraModel(960, 540, a.K, [0.1, 0, 0, 0, 0], "plumb_bob")
    assert d != a and d.key != a.key


@given(camera=cameras(), seed=st.integers(0, 2**32 - 1))
def test_undistort_inverts_project_to_the_ideal_pinhole(camera: CameraModel, seed: int) -> None:
    """A point projected through the lens and undistorted lands where the ideal pinhole with the
    same K puts it."""
    pts = _points(seed)
    ideal = (pts / pts[:, 2:3]) @ camera.K.T
    back = camera.undistort_px(camera.project(pts))
    np.testing.assert_allclose(back, ideal[:, :2], rtol=0, atol=1e-3)


@given(camera=cameras(), factor=st.floats(0.25, 4.0), seed=st.integers(0, 2**32 - 1))
def test_a_scaled_camera_sees_the_resized_image(camera: CameraModel, factor: float,
                                                 seed: int) -> None:
    """Pixel-centre convention: a point at u in the image sits at (u + 0.5) * f - 0.5 in the image
    resized by f; the lens is unchanged and scaling back restores K."""
    scaled = camera.scaled(factor)
    assert (scaled.width_px, scaled.height_px) == (round(camera.width_px * factor),
                                                   round(camera.height_px * factor))
    assert scaled.distortion_model == camera.distortion_model
    np.testing.assert_array_equal(scaled.D, camera.D)
    pts = _points(seed)
    np.testing.assert_allclose(scaled.project(pts), (camera.project(pts) + 0.5) * factor - 0.5,
                               rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(scaled.scaled(1.0 / factor).K, camera.K, rtol=1e-12, atol=1e-9)


@pytest.fixture(scope="module")
def scratch() -> Path:
    with tempfile.TemporaryDirectory(prefix="ficap-camera-") as path:
        yield Path(path)


@given(camera=cameras(), name=st.text(st.characters(codec="ascii", categories=("L", "N")),
                                      min_size=1, max_size=12))
def test_camera_yaml_round_trip(scratch: Path, camera: CameraModel, name: str) -> None:
    """``to_camera_yaml`` then ``load_camera_yaml`` gives the same camera (a lens without
    distortion is written as plumb_bob with five zeros, which projects the same)."""
    path = scratch / "camera.yaml"
    data = camera.to_camera_yaml(name)
    assert data["camera_name"] == name
    path.write_text(yaml.safe_dump(data))
    back = load_camera_yaml(path)
    if camera.distortion_model == "none":
        assert back.distortion_model == "plumb_bob" and not np.any(back.D)
        np.testing.assert_array_equal(back.K, camera.K)
        assert (back.width_px, back.height_px) == (camera.width_px, camera.height_px)
    else:
        assert back == camera


@pytest.mark.parametrize(
    "k, d, model, message",
    [
        ([np.nan, 0, 480, 0, 500, 270, 0, 0, 1], [], "none", "NaN"),
        ([0, 0, 0, 0, 0, 0, 0, 0, 0], [], "none", "K must be"),
        ([0, 0, 480, 0, 0, 270, 0, 0, 1], [], "none", "focal lengths .* are not sane"),
        ([1e308, 0, 480, 0, 1e308, 270, 0, 0, 1], [], "none", "focal lengths .* are not sane"),
        ([1e-300, 0, 480, 0, 1e-300, 270, 0, 0, 1], [], "none", "focal lengths .* are not sane"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 1], [0.1, 0, 0, 0, 0, 0.2], "plumb_bob",
         r"plumb_bob takes 5 coefficients \(k1 k2 p1 p2 k3\), got 6"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 1], [1e10, 0, 0, 0, 0], "plumb_bob",
         "exceed 1000 in magnitude"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 1], [0.1, 0.2], "none", "none takes 0 coefficients"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 2], [], "none", "K must be"),
        ([500, 0, 480, 0, 500, 270, 0, 0, 1], [0.1], "kannala", "unknown distortion model"),
        ([500, 0, 2000, 0, 500, 270, 0, 0, 1], [], "none", "principal point"),
    ],
)
def test_bad_intrinsics(k, d, model, message) -> None:
    with pytest.raises(IntrinsicsError, match=message):
        CameraModel(960, 540, k, d, model)


def test_extra_zero_coefficients_are_dropped_and_few_padded() -> None:
    """A CameraInfo D may carry trailing zeros (8 for plumb_bob): the model keeps as many as it
    takes; fewer are padded with zeros."""
    k = [500.0, 0, 480, 0, 500, 270, 0, 0, 1]
    cam = CameraModel(960, 540, k, [0.1, -0.05, 0, 0, 0.01, 0, 0, 0], "plumb_bob")
    np.testing.assert_array_equal(cam.D, [0.1, -0.05, 0, 0, 0.01])
    assert CameraModel(960, 540, k, [0.1], "plumb_bob").D.tolist() == [0.1, 0, 0, 0, 0]
    assert CameraModel(960, 540, k, [0, 0, 0, 0, 0], "none").D.size == 0


@pytest.mark.parametrize(
    "model, d",
    [("plumb_bob", [-0.2, 0.05, 0.001, 0.002, 0.0]),
     ("rational_polynomial", [-0.2, 0.05, 0.001, 0.002, 0.0, 0.01, 0.002, 0.0]),
     ("equidistant", [0.05, -0.01, 0.002, -0.001])],
)
def test_undistort_inverts_project(model: str, d: list[float]) -> None:
    cam = CameraModel(960, 540, [700, 0, 480, 0, 700, 270, 0, 0, 1], d, model)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, 50), rng.uniform(-0.25, 0.25, 50), np.ones(50)])
    ideal = pts[:, :2] * 700 + [480, 270]
    np.testing.assert_allclose(cam.undistort_px(cam.project(pts)), ideal, atol=1e-3)


def test_rectified_camera_info_uses_p() -> None:
    p = [600, 0, 470, 0, 0, 610, 280, 0, 0, 0, 1, 0]
    cam = CameraModel.from_camera_info(960, 540, [700, 0, 480, 0, 700, 270, 0, 0, 1],
                                       [-0.3, 0.1, 0, 0, 0], "plumb_bob", p=p, rectified=True)
    assert cam.K[0, 0] == 600 and cam.distortion_model == "none"


def test_camera_yaml_round_trip_of_a_plumb_bob_file(tmp_path) -> None:
    import yaml

    cam = CameraModel(960, 540, [700, 0, 480, 0, 701, 270, 0, 0, 1], [-0.2, 0.05, 0, 0, 0], "plumb_bob")
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(cam.to_camera_yaml()))
    back = load_camera_yaml(path)
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.D, cam.D)
    assert back.distortion_model == "plumb_bob"


def test_camera_timing_row_times_follow_the_stamp_convention() -> None:
    """The middle row is the stamp's instant; rows read top to bottom over ``readout_ms`` are
    spread evenly around it, and a global shutter (readout 0) exposes every row at the stamp."""
    from ficap_ros.geometry.camera import CameraTiming

    rs = CameraTiming(exposure_ms=16.7, readout_ms=22.0)
    h = 540
    t = rs.row_time_s(np.array([-0.5, h / 2 - 0.5, h - 0.5]), h)
    np.testing.assert_allclose(t, [-0.011, 0.0, 0.011], atol=1e-15)
    assert rs.rolling and not CameraTiming(exposure_ms=16.7).rolling
    flipped = CameraTiming(readout_ms=22.0, row_order="bottom_to_top").row_time_s(np.array([0.0]), h)
    np.testing.assert_allclose(flipped, -rs.row_time_s(np.array([0.0]), h))
    np.testing.assert_array_equal(CameraTiming().row_time_s(np.arange(4.0), 4), np.zeros(4))


@pytest.mark.parametrize("kwargs", [{"readout_ms": -1.0}, {"exposure_ms": float("nan")},
                                    {"row_order": "sideways"}, {"stamp_offset_ms": 1e9}])
def test_camera_timing_refuses_impossible_values(kwargs) -> None:
    from ficap_ros.errors import IntrinsicsError
    from ficap_ros.geometry.camera import CameraTiming

    with pytest.raises(IntrinsicsError):
        CameraTiming(**kwargs)


@st.composite
def timings(draw: st.DrawFn):
    from ficap_ros.geometry.camera import ROW_ORDERS, CameraTiming

    ms = st.floats(0.0, 1000.0, allow_nan=False)
    return CameraTiming(draw(ms), draw(ms), draw(st.sampled_from(ROW_ORDERS)),
                        draw(st.floats(-1000.0, 1000.0, allow_nan=False)))


@given(timings())
def test_camera_timing_round_trips_through_its_mapping(timing) -> None:
    from ficap_ros.geometry.camera import CameraTiming

    assert CameraTiming.from_mapping(timing.to_dict()) == timing
    # JSON and YAML carry it as plain values.
    assert CameraTiming.from_mapping(yaml.safe_load(yaml.safe_dump(timing.to_dict()))) == timing


@given(timings())
def test_camera_yaml_round_trip_with_timing(timing) -> None:
    """``to_camera_yaml(timing=...)`` writes the optional ``camera_timing`` mapping that
    ``load_camera_timing`` reads back; the intrinsics read as before; a file without the mapping
    has no timing (None: not known)."""
    from ficap_ros.geometry.camera import load_camera_timing

    cam = CameraModel(960, 540, [700, 0, 480, 0, 701, 270, 0, 0, 1], [-0.2, 0.05, 0, 0, 0],
                      "plumb_bob")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "camera.yaml"
        path.write_text(yaml.safe_dump(cam.to_camera_yaml("rear", timing)))
        assert load_camera_yaml(path) == cam
        assert load_camera_timing(path) == timing
        path.write_text(yaml.safe_dump(cam.to_camera_yaml("rear")))
        assert load_camera_timing(path) is None
        assert "camera_timing" not in cam.to_camera_yaml()


@pytest.mark.parametrize("block, message", [
    ("camera_timing: 16.7", "must be a mapping"),
    ("camera_timing: {exposure: 16.7}", "unknown key 'exposure'"),
    ("camera_timing: {exposure_ms: fast}", "exposure_ms must be a number of ms"),
    ("camera_timing: {readout_ms: true}", "readout_ms must be a number of ms"),
    ("camera_timing: {readout_ms: -3}", r"readout_ms must be in \[0, 1000\] ms"),
    ("camera_timing: {row_order: 1}", "row_order must be a string"),
    ("camera_timing: {row_order: left_to_right}", "row_order must be one of"),
    ("camera_timing: {stamp_offset_ms: .nan}", "stamp_offset_ms must be in"),
    ("camera_timing: {readout_ms: 1.0e+308}", "readout_ms must be a number of ms"),
    ("camera_timing: {readout_ms: " + "9" * 5000 + "}", "an integer of 5000 digits"),
    ("camera_timing: " + "[" * 10_000 + "]" * 10_000, "nested deeper than"),
    ("t: &t {readout_ms: 1}\ncamera_timing: *t", "aliases"),
])
def test_malformed_camera_timing_is_one_clear_error(tmp_path, block: str, message: str) -> None:
    from ficap_ros.geometry.camera import load_camera_timing

    cam = CameraModel.pinhole(960, 540, f_px=700.0)
    path = tmp_path / "camera.yaml"
    path.write_text(yaml.safe_dump(cam.to_camera_yaml()) + block + "\n")
    with pytest.raises(IntrinsicsError, match=message) as err:
        load_camera_timing(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)
