"""Property tests (hypothesis) of the readers and decoders: random and mutated inputs raise only
``FicapError`` subclasses (or decode), never anything else.

The profile (conftest.py) is derandomized, so a failure reproduces on every run and machine.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ficap_ros.errors import FicapError, ImageError
from ficap_ros.geometry.camera import CameraModel, load_camera_yaml
from ficap_ros.geometry.cap_model import load_model, nominal_model
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.calibration_file import load_calibration
from ficap_ros.io.image_codec import ENCODINGS, decode_compressed, decode_image
from ficap_ros.io.labels import read_labels
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import CAMERA_INFO_TYPE, IMAGE_TYPE, open_frames

CAM = CameraModel(64, 48, np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]),
                  np.array([0.1, -0.05, 0.0, 0.0, 0.0]), "plumb_bob")
IMAGE = np.random.default_rng(1).integers(0, 256, (48, 64), dtype=np.uint8)
JPEG = cv2.imencode(".jpg", IMAGE)[1].tobytes()
PNG = cv2.imencode(".png", IMAGE)[1].tobytes()
CAMERA_YAML = yaml.safe_dump(CAM.to_camera_yaml())
CALIBRATION_YAML = ("format: ficap_calibration/1\nquaternion_order: wxyz\ncalibrated: true\n"
                    "R_cap_head_q_wxyz: [0.99, 0.01, -0.1, 0.02]\n"
                    "R_cam_frontal_q_wxyz: [0.5, -0.5, 0.5, -0.5]\n")
LABELS_CSV = (
    "frame,stamp_ns,frame_id,tags_detected,tags_used,rms_px,reliability,cap_qw,cap_qx,cap_qy,"
    "cap_qz,cap_x_m,cap_y_m,cap_z_m,head_qw,head_qx,head_qy,head_qz,head_yaw_deg,"
    "head_pitch_deg,head_roll_deg,calibrated,detected_ids,reason\n"
    "0,1000,cam,2,2,0.1,0.9,1,0,0,0,0,0,0.6,1,0,0,0,0,0,0,0,3 7,\n"
    "1,2000,cam,0,0,,,,,,,,,,,,,,,,,0,,no tag\n")


@st.composite
def mutated(draw: st.DrawFn, original: bytes) -> bytes:
    """``original`` cut short, with bytes flipped, inserted or deleted: what damage looks like."""
    data = bytearray(original)
    for _ in range(draw(st.integers(0, 6))):
        if not data:
            break
        kind = draw(st.sampled_from(["flip", "insert", "delete", "cut"]))
        pos = draw(st.integers(0, len(data) - 1))
        if kind == "flip":
            data[pos] ^= draw(st.integers(1, 255))
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "delete":
            del data[pos:pos + draw(st.integers(1, 16))]
        else:
            del data[pos:]
    return bytes(data)


def _write(tmp: Path, name: str, data: bytes) -> Path:
    path = tmp / name
    path.write_bytes(data)
    return path


@pytest.fixture(scope="module")
def scratch() -> Path:
    path = Path(tempfile.mkdtemp(prefix="ficap-fuzz-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(encoding=st.one_of(st.sampled_from(ENCODINGS), st.text(max_size=12)),
       height=st.integers(-3, 70), width=st.integers(-3, 70), step=st.integers(-3, 300),
       data=st.binary(max_size=6000), big_endian=st.booleans())
def test_decode_image_raises_only_image_error(encoding: str, height: int, width: int, step: int,
                                              data: bytes, big_endian: bool) -> None:
    try:
        img = decode_image(encoding, height, width, step, data, big_endian)
    except ImageError:
        return
    assert img.shape == (height, width)


@given(data=st.one_of(st.binary(max_size=3000), mutated(JPEG), mutated(PNG)))
def test_decode_compressed_raises_only_image_error(data: bytes) -> None:
    try:
        img = decode_compressed(data, "jpeg")
    except ImageError:
        return
    assert img.ndim == 2 and img.dtype == np.uint8


@given(data=st.one_of(st.binary(max_size=2000), mutated(CAMERA_YAML.encode())))
def test_camera_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        load_camera_yaml(_write(scratch, "camera.yaml", data))
    except FicapError:
        pass


@given(data=st.one_of(st.binary(max_size=2000), mutated(CALIBRATION_YAML.encode())))
def test_calibration_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        cal = load_calibration(_write(scratch, "calibration.yaml", data))
    except FicapError:
        return
    assert isinstance(cal.calibrated, bool)


@given(data=mutated(nominal_model().to_yaml().encode()))
def test_model_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        load_model(_write(scratch, "model.yaml", data))
    except FicapError:
        pass


@given(data=st.one_of(st.binary(max_size=2000), mutated(LABELS_CSV.encode())))
def test_labels_csv_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        labels = read_labels(_write(scratch, "labels.csv", data))
    except FicapError:
        return
    assert len(labels.stamp_ns) == len(labels.reliability)


@pytest.fixture(scope="module")
def bag(scratch: Path) -> Path:
    path = scratch / "bag"
    with BagWriter(path) as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i in range(4):
            head = messages.header(ROSBAGS, i + 1, "cam")
            w.write("/cam/camera_info", i + 1, messages.camera_info(ROSBAGS, head, CAM))
            w.write("/cam/image_raw", i + 1, messages.image(ROSBAGS, head, IMAGE, "mono8"))
    return path


def _read_all(path: Path) -> None:
    try:
        source = open_frames(path)
        for frame in source.frames():
            assert (frame.image is None) == (frame.error is not None)
        if source.loss is not None:
            assert "\n" not in source.loss.describe(source.start_ns)
    except FicapError:
        pass


@settings(max_examples=40)
@given(data=st.data())
def test_bag_metadata_raises_only_ficap_errors(bag: Path, scratch: Path, data: st.DataObject
                                               ) -> None:
    meta = (bag / "metadata.yaml").read_bytes()
    target = scratch / "meta_bag"
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(bag, target)
    (target / "metadata.yaml").write_bytes(data.draw(mutated(meta)))
    _read_all(target)


@settings(max_examples=40)
@given(data=st.data())
def test_mcap_bytes_raise_only_ficap_errors(bag: Path, scratch: Path, data: st.DataObject
                                            ) -> None:
    mcap = next(bag.glob("*.mcap")).read_bytes()
    _read_all(_write(scratch, "fuzzed.mcap", data.draw(mutated(mcap))))
