"""Reading frames from bags (sqlite3 / MCAP folders, single .mcap) and videos; bad inputs."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from recordings import cut_copy, small_bag

from ficap_ros.errors import BagError, ImageError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import (
    CAMERA_INFO_TYPE,
    COMPRESSED_TYPE,
    IMAGE_TYPE,
    open_bag_reader,
    open_frames,
)

W, H = 64, 48
T0 = 1_700_000_000_000_000_000
CAM = CameraModel(W, H, np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]),
                  np.array([0.1, -0.05, 0.001, 0.002, 0.0]), "plumb_bob")


def _grey(i: int) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, (H, W), dtype=np.uint8)


def _write_bag(path: Path, storage: str = "mcap", layout: str = "folder", n: int = 5,
               compressed: bool = False, info: bool = True, bad_frame: int | None = None,
               extra_image_topic: bool = False, custom: dict[str, str] | None = None,
               ) -> list[np.ndarray]:
    images = [_grey(i) for i in range(n)]
    topic = "/cam/image_raw/compressed" if compressed else "/cam/image_raw"
    with BagWriter(path, storage=storage, layout=layout) as w:
        for key, value in (custom or {}).items():
            w.set_custom_data(key, value)
        w.add_topic(topic, COMPRESSED_TYPE if compressed else IMAGE_TYPE)
        if info:
            w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        if extra_image_topic:
            w.add_topic("/other/image_raw", IMAGE_TYPE)
        for i, img in enumerate(images):
            stamp = T0 + i * 33_333_333
            head = messages.header(ROSBAGS, stamp, "cam_optical")
            if info:
                w.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, CAM))
            if compressed:
                data = cv2.imencode(".png", img)[1].tobytes() if i != bad_frame else b"\x00junk"
                w.write(topic, stamp, messages.compressed_image(ROSBAGS, head, data, "png"))
            else:
                w.write(topic, stamp, messages.image(ROSBAGS, head, img, "mono8"))
            if extra_image_topic:
                w.write("/other/image_raw", stamp,
                        messages.image(ROSBAGS, messages.header(ROSBAGS, stamp, "x"), img, "mono8"))
    return images


# -- bag round trips -----------------------------------------------------------------------------
@pytest.mark.parametrize("storage,layout,compressed", [
    ("sqlite3", "folder", False), ("mcap", "folder", False), ("mcap", "folder", True),
    ("mcap", "file", False),
])
def test_round_trip(tmp_path: Path, storage: str, layout: str, compressed: bool) -> None:
    path = tmp_path / ("drive.mcap" if layout == "file" else "drive")
    images = _write_bag(path, storage, layout, compressed=compressed)
    src = open_frames(path)
    assert src.image_topic.startswith("/cam/image_raw") and src.camera_info_topic == "/cam/camera_info"
    assert src.count == len(images) and src.start_ns == T0
    frames = list(src)
    assert [f.index for f in frames] == list(range(len(images)))
    for f, img in zip(frames, images):
        assert f.error is None and f.frame_id == "cam_optical"
        np.testing.assert_array_equal(f.image, img)  # mono8 and PNG are lossless
        assert f.camera.distortion_model == "plumb_bob"
        np.testing.assert_allclose(f.camera.K, CAM.K)
        np.testing.assert_allclose(f.camera.D, CAM.D)
    assert frames[3].stamp_ns == T0 + 3 * 33_333_333
    if layout == "file":  # the folder holding the file is itself a rosbag2 bag
        assert (tmp_path / "metadata.yaml").exists()
        assert len(list(open_frames(tmp_path))) == len(images)


def test_intrinsics_file_replaces_camera_info(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    _write_bag(path, info=False)
    with pytest.raises(BagError, match="CameraInfo"):
        open_frames(path)
    yml = tmp_path / "cam.yaml"
    yml.write_text(yaml.safe_dump(CAM.to_camera_yaml()))
    frames = list(open_frames(path, intrinsics=yml))
    assert len(frames) == 5 and all(f.camera.width_px == W for f in frames)


def test_the_recordings_own_camera_timing(tmp_path: Path) -> None:
    """``FrameSource.timing``: the --intrinsics file's ``camera_timing``, else a bag folder's
    metadata ``ficap.camera_timing`` (``ficap synth`` writes it), else None (not known); a
    malformed one is one clear error."""
    import json

    from ficap_ros.errors import IntrinsicsError
    from ficap_ros.geometry.camera import CameraTiming
    from ficap_ros.io.sources import TIMING_METADATA_KEY

    in_bag = CameraTiming(exposure_ms=16.7, readout_ms=22.0)
    path = tmp_path / "bag"
    _write_bag(path, custom={TIMING_METADATA_KEY: json.dumps(in_bag.to_dict())})
    src = open_frames(path)
    assert (src.timing, src.timing_source) == (in_bag, "bag metadata")
    in_file = CameraTiming(exposure_ms=4.0, row_order="bottom_to_top", stamp_offset_ms=-3.0)
    yml = tmp_path / "cam.yaml"
    yml.write_text(yaml.safe_dump(CAM.to_camera_yaml("cam", in_file)))
    src = open_frames(path, intrinsics=yml)
    assert (src.timing, src.timing_source) == (in_file, "intrinsics")
    yml.write_text(yaml.safe_dump(CAM.to_camera_yaml("cam")))
    assert open_frames(path, intrinsics=yml).timing == in_bag  # the file says nothing of it
    plain = tmp_path / "plain"
    _write_bag(plain)
    assert (open_frames(plain).timing, open_frames(plain).timing_source) == (None, "")
    single = tmp_path / "single.mcap"
    _write_bag(single, layout="file", custom={TIMING_METADATA_KEY: json.dumps(in_bag.to_dict())})
    assert open_frames(single).timing is None  # only a bag folder's metadata is read
    bad = tmp_path / "bad"
    _write_bag(bad, custom={TIMING_METADATA_KEY: json.dumps({"readout_ms": -2.0})})
    with pytest.raises(BagError, match=r"ficap.camera_timing: readout_ms must be in \[0, 1000\]"):
        open_frames(bad)
    deep = tmp_path / "deep"  # JSON nested past Python's recursion limit: one line, no RecursionError
    _write_bag(deep, custom={TIMING_METADATA_KEY: "[" * 100_000 + "]" * 100_000})
    with pytest.raises(BagError, match=r"bag .*deep: "):
        open_frames(deep)
    yml.write_text(yaml.safe_dump({**CAM.to_camera_yaml(), "camera_timing": {"exposure_ms": "x"}}))
    with pytest.raises(IntrinsicsError, match="exposure_ms must be a number"):
        open_frames(plain, intrinsics=yml)


def test_undecodable_frame_is_reported_not_fatal(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    _write_bag(path, compressed=True, bad_frame=2)
    frames = list(open_frames(path))
    assert [f.error is None for f in frames] == [True, True, False, True, True]
    assert isinstance(frames[2].error, ImageError)


def test_topic_selection_errors(tmp_path: Path) -> None:
    path = tmp_path / "two"
    _write_bag(path, extra_image_topic=True)
    with pytest.raises(BagError, match="--image-topic"):
        open_frames(path)
    assert open_frames(path, image_topic="/cam/image_raw").count == 5
    with pytest.raises(BagError, match="no topic /nope"):
        open_frames(path, image_topic="/nope")
    with pytest.raises(BagError, match="not an Image"):
        open_frames(path, image_topic="/cam/camera_info")
    with pytest.raises(BagError, match="no topic /nope"):
        open_frames(path, image_topic="/cam/image_raw", camera_info_topic="/nope")


def test_corrupt_and_truncated_bags(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        open_frames(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="metadata.yaml"):
        open_frames(tmp_path / "empty")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(BagError):
        open_frames(junk)
    # A truncated MCAP (recording killed mid-write): no footer, yet every complete image before
    # the cut is recovered (test_damaged_inputs.py covers the recovery in depth).
    good = tmp_path / "good.mcap"
    images = _write_bag(good, layout="file", n=20)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    source = open_frames(cut)
    frames = list(source)
    assert 5 <= len(frames) < 20
    for frame, image in zip(frames, images):
        np.testing.assert_array_equal(frame.image, image)
    assert source.loss is not None and source.loss.frames_lost == 20 - len(frames)
    # Cut inside the first record: nothing to recover.
    cut.write_bytes(good.read_bytes()[:40])
    with pytest.raises(BagError):
        list(open_frames(cut))
    # A sqlite3 bag whose database is garbage.
    sq = tmp_path / "sq"
    _write_bag(sq, storage="sqlite3")
    db = next(sq.glob("*.db3"))
    db.write_bytes(b"\x00" * 100 + db.read_bytes()[100:2000])
    with pytest.raises(BagError):
        list(open_frames(sq))


def test_video_needs_intrinsics_and_reads_frames(tmp_path: Path) -> None:
    import yaml

    video = tmp_path / "drive.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W * 2, H * 2))
    assert writer.isOpened()
    for i in range(6):
        writer.write(cv2.cvtColor(cv2.resize(_grey(i), (W * 2, H * 2)), cv2.COLOR_GRAY2BGR))
    writer.release()
    with pytest.raises(BagError, match="--intrinsics"):
        open_frames(video)
    yml = tmp_path / "cam.yaml"
    yml.write_text(yaml.safe_dump(CAM.to_camera_yaml()))
    frames = list(open_frames(video, intrinsics=yml))  # intrinsics at half size: rescaled
    assert len(frames) == 6
    assert frames[1].stamp_ns == 40_000_000  # 25 fps from the container
    assert frames[0].camera.width_px == 2 * W
    np.testing.assert_allclose(frames[0].camera.K[0, 0], 2 * CAM.K[0, 0])
    frames = list(open_frames(video, intrinsics=yml, fps=10.0))
    assert frames[2].stamp_ns == 200_000_000
    bogus = tmp_path / "bogus.mp4"
    bogus.write_bytes(b"nope")
    with pytest.raises(BagError):
        open_frames(bogus, intrinsics=yml)


def test_sources_are_built_in_one_step(tmp_path: Path) -> None:
    """``open_frames`` picks ``BagSource`` or ``VideoSource``; each constructor opens completely."""
    from ficap_ros.io.sources import BagSource, RecordingKind, VideoSource

    bag = tmp_path / "bag"
    _write_bag(bag)
    src = open_frames(bag)
    assert isinstance(src, BagSource) and src.kind is RecordingKind.BAG and src.kind == "bag"
    direct = BagSource(bag)
    assert (direct.count, direct.start_ns, direct.image_topic) == (src.count, src.start_ns,
                                                                  src.image_topic) and src.count == 5
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    for i in range(2):
        writer.write(cv2.cvtColor(_grey(i), cv2.COLOR_GRAY2BGR))
    writer.release()
    v = open_frames(video, intrinsics=CAM)
    assert isinstance(v, VideoSource) and v.kind is RecordingKind.VIDEO and len(list(v)) == 2
    with pytest.raises(BagError, match="--intrinsics"):
        VideoSource(video, None)


@pytest.mark.parametrize("fraction", [0.9, 0.5])
def test_sqlite3_with_a_torn_tail_yields_the_frames_before_it(tmp_path: Path,
                                                              fraction: float) -> None:
    bag = tmp_path / "sq"
    images = small_bag(bag, "sqlite3")
    db = next(bag.glob("*.db3"))
    before = db.read_bytes()
    db.write_bytes(before[: int(len(before) * fraction)])
    torn = db.read_bytes()
    source = open_frames(bag)
    frames = list(source.frames())
    assert 0 < len(frames) < 40
    for frame, image in zip(frames, images):
        np.testing.assert_array_equal(frame.image, image)
    assert source.loss is not None and source.loss.frames_lost == 40 - len(frames)
    assert not source.loss.estimated
    assert db.read_bytes() == torn  # the input is only read


def test_video_cut_mid_frame(tmp_path: Path) -> None:
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    for i in range(30):
        writer.write(np.random.default_rng(i).integers(0, 256, (120, 160, 3), dtype=np.uint8))
    writer.release()
    data = video.read_bytes()
    video.write_bytes(data[: int(len(data) * 0.9)])
    intrinsics = tmp_path / "cam.yaml"
    intrinsics.write_text(yaml.safe_dump(CameraModel.pinhole(160, 120, f_px=100.0)
                                         .to_camera_yaml()))
    source = open_frames(video, intrinsics=intrinsics)
    n = len(list(source.raw_frames()))
    assert 20 <= n < 30
    assert source.loss is not None and source.loss.frames_lost == 30 - n
    assert source.loss.until_ns == pytest.approx(29 / 25 * 1e9, abs=1)


def test_video_above_the_pixel_budget(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    for i in range(3):
        writer.write(np.full((120, 160, 3), 40 * i, np.uint8))
    writer.release()
    intrinsics = tmp_path / "cam.yaml"
    intrinsics.write_text(yaml.safe_dump(CameraModel.pinhole(160, 120, f_px=100.0)
                                         .to_camera_yaml()))
    monkeypatch.setenv("FICAP_MAX_PIXELS", str(160 * 120 - 1))
    with pytest.raises(BagError, match="budget"):
        list(open_frames(video, intrinsics=intrinsics).raw_frames())


def test_folder_of_a_recorder_killed_before_metadata(drive: Path, tmp_path: Path) -> None:
    cut = cut_copy(drive, tmp_path / "cut", 0.9)
    (cut / "metadata.yaml").unlink()
    reader = open_bag_reader(cut)
    try:
        assert reader.damage is not None
        assert {c.topic for c in reader.connections} >= {"/camera/image_raw/compressed"}
    finally:
        reader.close()


def test_camera_info_topic_of_an_image_is_the_one_beside_it() -> None:
    """Offline as live: the CameraInfo beside the image topic first (of a CompressedImage topic,
    beside its base topic), else the only one, else the nearest enclosing namespace's."""
    from ficap_ros.io.sources import COMPRESSED_TYPE, IMAGE_TYPE, _pick_camera_info

    info = "sensor_msgs/msg/CameraInfo"
    topics = {"/cam/image_raw": IMAGE_TYPE, "/cam/camera_info": info, "/other/camera_info": info}
    assert _pick_camera_info(topics, "/cam/image_raw") == "/cam/camera_info"
    topics = {"/cam/image/compressed": COMPRESSED_TYPE, "/cam/camera_info": info,
              "/cam/image/camera_info": info}
    assert _pick_camera_info(topics, "/cam/image/compressed") == "/cam/camera_info"
    topics = {"/cam/image_raw": IMAGE_TYPE, "/calib/info": info}
    assert _pick_camera_info(topics, "/cam/image_raw") == "/calib/info"  # the only one
    topics = {"/car/cam/image_raw": IMAGE_TYPE, "/car/camera_info": info, "/x/camera_info": info}
    assert _pick_camera_info(topics, "/car/cam/image_raw") == "/car/camera_info"
    assert _pick_camera_info({"/cam/image_raw": IMAGE_TYPE}, "/cam/image_raw") is None


def test_a_loss_is_told_in_recording_time() -> None:
    """Seconds from the first frame; without any frame read, never an epoch taken for seconds;
    a damaged container that lost no frame says so."""
    from ficap_ros.io.sources import Loss

    start = 1_700_000_000_000_000_000
    assert Loss("cut", 3, False, start + 2_000_000_000, start + 2_100_000_000).describe(start) == \
        "LOST 3 frames between 2.000 s and 2.100 s (cut)"
    line = Loss("cut", None, False, 0, start + 267_000_000).describe(0)
    assert line == "LOST an unknown number of frames from the start, before any frame could be " \
                   "read (cut)" and "1700000000" not in line
    assert Loss("index", 0, False, start, start).describe(start) == \
        "DAMAGED, but every frame it lists was read (index)"
    assert Loss("cut", None, False, 0, start).to_dict(0)["until_s"] is None
