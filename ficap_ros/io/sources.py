"""Frames from recordings: rosbag2 folders (sqlite3 or MCAP), single ``.mcap``/``.db3`` files, videos.

Bags are read with rosbags' ``AnyReader`` (no ROS install needed); messages without embedded
definitions fall back to the ROS 2 Jazzy typestore. A video is read with ``cv2.VideoCapture`` and
needs intrinsics (``--intrinsics camera.yaml``) and a frame rate.

Reading is split in two so ``ficap replay --jobs N`` can decode in worker processes:
``FrameSource.raw_frames()`` yields picklable ``RawFrame`` records (stamp, camera, undecoded
payload) and ``decode_raw`` turns one into a grey image. ``FrameSource.frames()`` does both.

Errors: a container that cannot be read at all (missing, not a bag, no such topic, no intrinsics)
raises ``BagError``; one undecodable image becomes a frame whose ``error`` says why. A damaged
container (MCAP without footer, sqlite3 cut short, video cut mid-frame) yields every complete
frame before the damage (``ficap_ros.io.salvage``), and ``FrameSource.loss`` then says what was
lost: how many frames (exact when the bag's metadata or the video container says, else estimated
from the frame rate, else unknown) and their time range.
"""

from __future__ import annotations

import math
import sqlite3
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ficap_ros.errors import BagError, FicapError, ImageError, IntrinsicsError, one_line
from ficap_ros.files import VIDEO_SUFFIXES
from ficap_ros.geometry.camera import (
    CameraModel,
    CameraTiming,
    load_camera_timing,
    load_camera_yaml,
)
from ficap_ros.io.camera_info import (
    CAMERA_INFO_MAX_STAMP_DIFF_NS,
    camera_from_info,
    camera_info_beside,
    camera_info_key,
    pick_camera_info,
)
from ficap_ros.io.image_codec import check_pixel_budget, decode_compressed, decode_image
from ficap_ros.io.messages import jazzy_typestore
from ficap_ros.stamps import stamp_to_ns

__all__ = [
    "RecordingKind",
    "BagSource",
    "VideoSource",
    "IMAGE_TYPE",
    "COMPRESSED_TYPE",
    "CAMERA_INFO_TYPE",
    "VIDEO_SUFFIXES",
    "RawFrame",
    "Frame",
    "Loss",
    "FrameSource",
    "open_frames",
    "decode_raw",
    "jazzy_typestore",
    "open_bag_reader",
    "TIMING_METADATA_KEY",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: The key of a bag's ``custom_data`` (metadata.yaml) holding its camera's timing as JSON
#: (``CameraTiming.to_dict``): ``ficap synth`` writes it.
TIMING_METADATA_KEY = "ficap.camera_timing"


@dataclass(frozen=True)
class RawFrame:
    """One image, not yet decoded (picklable, so it can go to a worker process).

    Attributes:
        index: position in the recording (0-based, every image message counts).
        stamp_ns: the image's header stamp (its receive time when the header stamp is zero), ns.
        camera: intrinsics valid for this image, or None when unknown (then ``error`` is set).
        kind: ``image`` (sensor_msgs/Image), ``compressed`` (CompressedImage) or ``array``
            (already decoded, from a video).
        payload: the pixel bytes (``image``/``compressed``) or the grey array (``array``).
        encoding: Image encoding or CompressedImage format.
        height, width, step, is_bigendian: Image fields (0 otherwise).
        frame_id: the image header's frame_id (the camera optical frame).
        error: why this frame cannot be used ("" when it can).
    """

    index: int
    stamp_ns: int
    camera: CameraModel | None
    kind: str
    payload: Any
    encoding: str = ""
    height: int = 0
    width: int = 0
    step: int = 0
    is_bigendian: bool = False
    frame_id: str = ""
    error: str = ""


@dataclass(frozen=True)
class Frame:
    """One decoded frame: a grey image, or the error that made it unusable."""

    index: int
    stamp_ns: int
    image: np.ndarray | None
    error: ImageError | None
    camera: CameraModel | None
    frame_id: str = ""


@dataclass(frozen=True)
class Loss:
    """Frames a damaged recording could not give.

    Attributes:
        detail: one line: what is damaged and where.
        frames_lost: how many images were lost; None when the container cannot say.
        estimated: ``frames_lost`` is a lower bound estimated from the frame rate and the
            damaged part's time range (an MCAP chunk cut short says until when its messages ran,
            not how many; chunks after it leave no trace without the bag's metadata.yaml).
        after_ns: stamp of the last frame read (0 when none).
        until_ns: stamp until which frames were lost, when known.
    """

    detail: str
    frames_lost: int | None
    estimated: bool
    after_ns: int
    until_ns: int | None

    def describe(self, start_ns: int) -> str:
        """One line for the command line: count, time range (s from ``start_ns``, the first
        frame's stamp; without any frame read, from the start of the recording), cause."""
        count = ("an unknown number of frames" if self.frames_lost is None else
                 f"{'at least ' if self.estimated else ''}{self.frames_lost} frame"
                 f"{'' if self.frames_lost == 1 else 's'}")
        if self.frames_lost == 0 and not self.estimated:
            return f"DAMAGED, but every frame it lists was read ({self.detail})"
        if not (self.after_ns and start_ns):
            span = "from the start, before any frame could be read"
        else:
            t0 = (self.after_ns - start_ns) / 1e9
            span = (f"after {t0:.3f} s" if self.until_ns is None else
                    f"between {t0:.3f} s and {(self.until_ns - start_ns) / 1e9:.3f} s")
        return f"LOST {count} {span} ({self.detail})"

    def to_dict(self, start_ns: int) -> dict[str, Any]:
        return {
            "detail": self.detail,
            "frames_lost": self.frames_lost,
            "estimated": self.estimated,
            "after_ns": self.after_ns,
            "until_ns": self.until_ns,
            "after_s": (round((self.after_ns - start_ns) / 1e9, 6)
                        if self.after_ns and start_ns else 0.0),
            "until_s": (round((self.until_ns - start_ns) / 1e9, 6)
                        if self.until_ns is not None and start_ns else None),
        }


def decode_raw(raw: RawFrame) -> np.ndarray:
    """Decode a raw frame to a grey image (uint8, or uint16 for 16-bit sources).

    Raises:
        ImageError: the frame carries an error or its payload does not decode.
    """
    if raw.error:
        raise ImageError(raw.error)
    if raw.kind == "array":
        return raw.payload
    if raw.kind == "compressed":
        img = decode_compressed(raw.payload, raw.encoding)
    else:
        img = decode_image(raw.encoding, raw.height, raw.width, raw.step, raw.payload,
                           raw.is_bigendian)
    if raw.camera is not None and (img.shape[1], img.shape[0]) != (raw.camera.width_px,
                                                                   raw.camera.height_px):
        raise ImageError(
            f"image is {img.shape[1]}x{img.shape[0]} but its camera info says "
            f"{raw.camera.width_px}x{raw.camera.height_px}"
        )
    return img


def _bag_errors() -> tuple[type[BaseException], ...]:
    import struct

    import apsw
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError

    # What rosbags' parsers raise on hostile bytes, besides their own errors: TypeError for an
    # MCAP file that ends after its magic, MemoryError for a flipped length field that asks for
    # gigabytes, apsw's errors for a damaged page of a sqlite3 bag (rosbags reads them by apsw).
    return (AnyReaderError, ReaderError, SerdeError, sqlite3.Error, apsw.Error, OSError,
            ValueError, KeyError, IndexError, EOFError, AssertionError, TypeError, struct.error,
            OverflowError, AttributeError, NotImplementedError, RuntimeError, MemoryError)


def open_bag_reader(path: Path, salvage: bool = True) -> Any:
    """An open reader on a rosbag2 folder or a single ``.mcap``/``.db3`` file.

    Normally rosbags' ``AnyReader``. When it refuses a damaged bag (an MCAP without footer, a
    sqlite3 database cut short, a folder whose recorder died before writing metadata.yaml) and
    ``salvage`` is set, a ``salvage.SalvageReader`` over the complete messages; its
    ``damage`` says what could not be read (``AnyReader`` has none).

    Raises:
        BagError: missing, not a bag, or nothing readable.
    """
    from rosbags.highlevel import AnyReader

    from ficap_ros.io.salvage import (
        NothingSalvaged,
        SalvageReader,
        index_damage,
        storage_files,
    )

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path} does not exist")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        if salvage and storage_files(path):
            return SalvageReader(path, jazzy_typestore())
        raise BagError(f"{path} is a folder without metadata.yaml, not a rosbag2 bag")
    try:
        storage = [f for f in storage_files(path) if f.suffix.lower() == ".mcap" and f.is_file()]
    except OSError:
        storage = []
    if salvage and any(index_damage(f) for f in storage):
        # A chunk index that does not fit its file: read the file front to back instead.
        return SalvageReader(path, jazzy_typestore())
    try:
        reader = AnyReader([path], default_typestore=jazzy_typestore())
        reader.open()
    except _bag_errors() as err:
        if salvage and (path.is_dir() or path.suffix.lower() in (".mcap", ".db3")):
            try:
                return SalvageReader(path, jazzy_typestore())
            except NothingSalvaged as lost:
                # rosbags' reason ("File end magic is invalid.") names no file and does not say
                # the file was cut short; the salvage walked it and knows where it ends.
                if path.is_file() and path.suffix.lower() == ".mcap":
                    raise BagError(
                        f"{path} is truncated or damaged, not a complete MCAP file: "
                        f"{lost.detail}; no complete message before the damage to salvage "
                        f"(docs/bag_tools.md)") from err
            except BagError:
                pass  # not even a damaged bag: report rosbags' reason
        raise BagError(f"cannot read bag {path}: {one_line(err)}") from err
    return reader


def _pick_camera_info(topics: dict[str, str], image_topic: str) -> str | None:
    """The CameraInfo topic of ``image_topic``: the one beside it (image_transport's rule, the
    node's: ``camera_info.camera_info_beside`` of the base topic, a CompressedImage topic without
    its ``/compressed``), else the only one, else the nearest in an enclosing namespace."""
    infos = sorted(t for t, typ in topics.items() if typ == CAMERA_INFO_TYPE)
    base = image_topic
    if topics.get(image_topic) == COMPRESSED_TYPE and image_topic.endswith("/compressed"):
        base = image_topic[:-len("/compressed")]
    if camera_info_beside(base) in infos:
        return camera_info_beside(base)
    if len(infos) <= 1:
        return infos[0] if infos else None
    parts = image_topic.rstrip("/").split("/")
    for n in range(len(parts) - 1, 0, -1):
        candidate = "/".join(parts[:n]) + "/camera_info"
        if candidate in infos:
            return candidate
    return None


class RecordingKind(str, Enum):
    """What a ``FrameSource`` reads (a ``str``: prints and compares as its value)."""

    BAG = "bag"
    VIDEO = "video"

    def __str__(self) -> str:
        return self.value


class FrameSource:
    """Frames of one recording with their intrinsics: ``BagSource`` or ``VideoSource``, each
    opened completely by its constructor (``open_frames`` picks one by the path).

    Attributes:
        path: the input.
        kind: ``RecordingKind.BAG`` or ``RecordingKind.VIDEO``.
        image_topic: the topic read ("" for a video).
        camera_info_topic: the CameraInfo topic used ("" when intrinsics come from a file).
        count: number of images (exact for bags, the container's estimate for videos).
        start_ns: stamp of the first image (0 when empty).
        end_ns: when the recording ends as its container says (a bag's last message, a video's
            frame count over its rate), 0 when it does not say.
        timing: the camera's timing as the inputs say (the intrinsics file's ``camera_timing``,
            else a bag folder's metadata ``ficap.camera_timing``), or None: not known.
        timing_source: where ``timing`` comes from: ``intrinsics``, ``bag metadata`` or ''.
    """

    kind: RecordingKind

    def __init__(self, path: str | Path, intrinsics: str | Path | CameraModel | None) -> None:
        self.path = Path(path)
        self.image_topic = ""
        self.camera_info_topic = ""
        self.count = 0
        self.start_ns = 0
        self.end_ns = 0
        self._intrinsics: CameraModel | None = (
            intrinsics if isinstance(intrinsics, CameraModel) or intrinsics is None
            else load_camera_yaml(intrinsics))
        self.timing: CameraTiming | None = None
        self.timing_source = ""
        if not (isinstance(intrinsics, CameraModel) or intrinsics is None):
            self.timing = load_camera_timing(intrinsics)
            self.timing_source = "intrinsics" if self.timing is not None else ""
        if not self.path.exists():
            raise BagError(f"{self.path} does not exist")
        self._damage: Any = None  # salvage.Damage of the container, if damaged
        self._read = 0  # images the last full iteration yielded
        self._last_ns = 0  # log time (video: stamp) of the last image read
        self._midway: str = ""  # an error that stopped an iteration early
        self._expected: int | None = None  # images the container says it holds
        self._until_ns: int | None = None
        self._dt_ns = 0.0

    @property
    def loss(self) -> Loss | None:
        """What a damaged container could not give (after a full iteration); None when intact."""
        detail = self._midway or (self._damage.detail if self._damage is not None else "")
        if not detail:
            return None
        lost: int | None = None
        estimated = False
        if self._expected is not None and self._expected >= self._read:
            lost = self._expected - self._read
        elif self._until_ns is not None and self._read >= 2 and self._dt_ns > 0:
            lost = max(int(round((self._until_ns - self._last_ns) / self._dt_ns)), 0)
            estimated = True
        return Loss(detail, lost, estimated, self._last_ns, self._until_ns)

    # -- iteration ------------------------------------------------------------------------------
    def raw_frames(self) -> Iterator[RawFrame]:
        """Undecoded frames in recording order (raises ``BagError`` on a corrupt container)."""
        raise NotImplementedError

    def frames(self) -> Iterator[Frame]:
        """Decoded frames in recording order; an undecodable one carries its ``ImageError``."""
        for raw in self.raw_frames():
            try:
                yield Frame(raw.index, raw.stamp_ns, decode_raw(raw), None, raw.camera, raw.frame_id)
            except ImageError as err:
                yield Frame(raw.index, raw.stamp_ns, None, err, raw.camera, raw.frame_id)

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()


class BagSource(FrameSource):
    """The images of one topic of a rosbag2 bag (folder, ``.mcap`` or ``.db3``), with the
    CameraInfo of its namespace (or ``intrinsics``; ``rectified``: P, no distortion). Each image
    takes the CameraInfo ``camera_info.pick_camera_info`` chooses, as the node does."""

    kind = RecordingKind.BAG

    def __init__(self, path: str | Path, image_topic: str | None = None,
                 camera_info_topic: str | None = None,
                 intrinsics: str | Path | CameraModel | None = None, rectified: bool = False,
                 camera_info_max_stamp_diff_ns: int = CAMERA_INFO_MAX_STAMP_DIFF_NS) -> None:
        super().__init__(path, intrinsics)
        self._info: list[tuple[int, CameraModel]] = []
        self._msgtype = ""
        self._rectified = bool(rectified)
        self._max_stamp_diff_ns = int(camera_info_max_stamp_diff_ns)
        self._load_bag(image_topic, camera_info_topic)
        if self.timing is None:
            self.timing = _bag_timing(self.path)
            self.timing_source = "bag metadata" if self.timing is not None else ""
        self._info_ns = [s for s, _ in self._info]

    def raw_frames(self) -> Iterator[RawFrame]:
        yield from self._bag_frames()

    def _camera_at(self, stamp_ns: int) -> CameraModel | None:
        if self._intrinsics is not None:
            return self._intrinsics
        if not self._info:
            return None
        return self._info[pick_camera_info(self._info_ns, stamp_ns, self._max_stamp_diff_ns)][1]

    def _bag_frames(self) -> Iterator[RawFrame]:
        reader = open_bag_reader(self.path)
        try:
            conns = [c for c in reader.connections if c.topic == self.image_topic]
            index = 0
            first_ns = last_ns = 0
            self._midway = ""
            it = reader.messages(connections=conns)
            while True:
                try:
                    conn, log_ns, raw = next(it)
                except StopIteration:
                    break
                except _bag_errors() as err:
                    # Damage the index did not show: keep what was read, say what stopped it.
                    self._midway = f"unreadable after {index} images: {one_line(err)}"
                    break
                first_ns = first_ns or int(log_ns)
                last_ns = int(log_ns)
                yield self._raw_from_message(reader, conn, log_ns, raw, index)
                index += 1
            self._read, self._last_ns = index, last_ns
            self._dt_ns = (last_ns - first_ns) / (index - 1) if index > 1 else 0.0
        finally:
            reader.close()

    def _raw_from_message(self, reader: Any, conn: Any, log_ns: int, raw: bytes,
                          index: int) -> RawFrame:
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except _bag_errors() as err:
            return RawFrame(index, int(log_ns), self._camera_at(int(log_ns)), "image", b"",
                            error=f"undecodable {conn.msgtype} message: {one_line(err)}")
        stamp = stamp_to_ns(msg.header.stamp) or int(log_ns)
        camera = self._camera_at(stamp)
        frame_id = str(msg.header.frame_id)
        error = "" if camera is not None else "no camera info before this image"
        if conn.msgtype == COMPRESSED_TYPE:
            return RawFrame(index, stamp, camera, "compressed", bytes(msg.data), str(msg.format),
                            frame_id=frame_id, error=error)
        return RawFrame(index, stamp, camera, "image", bytes(msg.data), str(msg.encoding),
                        int(msg.height), int(msg.width), int(msg.step), bool(msg.is_bigendian),
                        frame_id, error)

    def _load_bag(self, image_topic: str | None, camera_info_topic: str | None) -> None:
        reader = open_bag_reader(self.path)
        try:
            topics = {c.topic: c.msgtype for c in reader.connections}
            images = sorted(t for t, typ in topics.items() if typ in (IMAGE_TYPE, COMPRESSED_TYPE))
            if image_topic:
                if image_topic not in topics:
                    raise BagError(f"bag {self.path} has no topic {image_topic} "
                                   f"(image topics: {', '.join(images) or 'none'})")
                if topics[image_topic] not in (IMAGE_TYPE, COMPRESSED_TYPE):
                    raise BagError(f"topic {image_topic} is {topics[image_topic]}, "
                                   "not an Image or CompressedImage")
            elif len(images) == 1:
                image_topic = images[0]
            elif not images:
                raise BagError(f"bag {self.path} has no Image or CompressedImage topic")
            else:
                raise BagError(f"bag {self.path} has {len(images)} image topics "
                               f"({', '.join(images)}); choose one with --image-topic")
            self.image_topic = image_topic
            self._msgtype = topics[image_topic]
            self.count = sum(c.msgcount for c in reader.connections if c.topic == image_topic)
            self.end_ns = int(getattr(reader, "end_time", 0) or 0)
            self._damage = getattr(reader, "damage", None)
            if self._damage is not None:
                expected = self._damage.expected_counts
                self._expected = expected.get(image_topic) if expected else None
                self._until_ns = self._damage.lost_until_ns
            else:
                self._expected = self.count
            if self._intrinsics is None:
                if camera_info_topic:
                    if camera_info_topic not in topics:
                        raise BagError(f"bag {self.path} has no topic {camera_info_topic}")
                    if topics[camera_info_topic] != CAMERA_INFO_TYPE:
                        raise BagError(f"topic {camera_info_topic} is "
                                       f"{topics[camera_info_topic]}, not a CameraInfo")
                else:
                    camera_info_topic = _pick_camera_info(topics, image_topic)
                if camera_info_topic is None:
                    raise BagError(f"bag {self.path} has no CameraInfo for {image_topic}; "
                                   "pass --camera-info-topic or --intrinsics camera.yaml")
                self.camera_info_topic = camera_info_topic
                self._info = self._read_camera_infos(reader, camera_info_topic)
            self.start_ns = self._first_image_stamp(reader)
        finally:
            reader.close()

    def _first_image_stamp(self, reader: Any) -> int:
        """The first image's stamp as ``raw_frames`` gives it (its header's, else its log time),
        ns, read by the reader the bag is already open in; 0 when no image can be read."""
        conns = [c for c in reader.connections if c.topic == self.image_topic]
        try:
            for conn, log_ns, raw in reader.messages(connections=conns):
                try:
                    return stamp_to_ns(reader.deserialize(raw, conn.msgtype).header.stamp) or int(log_ns)
                except _bag_errors():
                    return int(log_ns)
        except _bag_errors():
            pass
        return 0

    def _read_camera_infos(self, reader: Any, topic: str) -> list[tuple[int, CameraModel]]:
        out: list[tuple[int, CameraModel]] = []
        last_key: tuple | None = None
        last: CameraModel | None = None
        seen, rejected = 0, ""  # CameraInfo messages read; why the first one was refused
        conns = [c for c in reader.connections if c.topic == topic]
        try:
            for conn, log_ns, raw in reader.messages(connections=conns):
                seen += 1
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    key = camera_info_key(msg)
                    if key != last_key:  # cameras rarely change: keep one model per change
                        last = camera_from_info(msg, self._rectified)
                        last_key = key
                except FicapError as err:
                    # An invalid CameraInfo (all zeros before calibration): skip it.
                    rejected = rejected or str(err)
                    continue
                except _bag_errors() as err:
                    rejected = rejected or f"undecodable message: {one_line(err)}"
                    continue
                assert last is not None
                out.append((stamp_to_ns(msg.header.stamp) or int(log_ns), last))
        except _bag_errors() as err:
            if not out:  # damage past some CameraInfo only costs the frames after it
                raise BagError(f"bag {self.path} is corrupt: {one_line(err)}") from err
        if not out:
            why = ("holds no CameraInfo message" if not seen else
                   f"holds no valid CameraInfo ({seen} refused, the first: {rejected})")
            raise BagError(f"topic {topic} of {self.path} {why}; pass --intrinsics camera.yaml")
        out.sort(key=lambda item: item[0])
        return out



def _bag_timing(path: Path) -> CameraTiming | None:
    """The camera timing a bag folder's metadata.yaml holds under ``TIMING_METADATA_KEY``
    (None: none, or not a folder with a metadata.yaml the guarded loader reads).

    Raises:
        BagError: the key is there but does not hold a valid timing.
    """
    import json

    from ficap_ros.files import load_yaml

    meta_path = path / "metadata.yaml"
    if not meta_path.is_file():
        return None
    try:
        meta = load_yaml(meta_path, "bag metadata", BagError)
        text = meta["rosbag2_bagfile_information"]["custom_data"][TIMING_METADATA_KEY]
    except (BagError, KeyError, TypeError):
        return None
    try:
        return CameraTiming.from_mapping(json.loads(text), f"metadata {TIMING_METADATA_KEY}")
    except (ValueError, TypeError, RecursionError, IntrinsicsError) as err:
        raise BagError(f"bag {path}: {one_line(err)}") from None


class VideoSource(FrameSource):
    """The frames of a video file, stamped from the frame rate (``fps``, default the
    container's), with ``intrinsics`` (rescaled to a video of another size, same aspect ratio)."""

    kind = RecordingKind.VIDEO

    def __init__(self, path: str | Path, intrinsics: str | Path | CameraModel | None,
                 fps: float | None = None) -> None:
        super().__init__(path, intrinsics)
        import cv2

        # Opened before asking for intrinsics: a file that is no video at all (notes.txt) must not
        # be called a video that lacks --intrinsics.
        cap = self._open_video()
        try:
            if self._intrinsics is None:
                raise BagError(f"video {self.path} needs --intrinsics camera.yaml")
            container_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            self.count = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)
        finally:
            cap.release()
        rate = fps if fps else container_fps
        if not (rate and math.isfinite(rate) and 0.01 <= rate <= 1000.0):
            raise BagError(f"video {self.path} does not say a usable frame rate "
                           f"({rate:g}); pass --fps")
        self._fps = float(rate)
        self.end_ns = int(round(self.count * 1e9 / self._fps)) if self.count else 0

    def raw_frames(self) -> Iterator[RawFrame]:
        yield from self._video_frames()

    def _open_video(self) -> Any:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise BagError(f"{self.path} is neither a bag (rosbag2 folder, .mcap, .db3) nor a "
                           f"video OpenCV can open")
        return cap

    def _video_frames(self) -> Iterator[RawFrame]:
        import cv2

        cap = self._open_video()
        camera = self._intrinsics
        assert camera is not None
        try:
            index = 0
            self._midway = ""
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                stamp = int(round(index * 1e9 / self._fps))
                gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
                if index == 0:
                    try:
                        check_pixel_budget(gray.shape[1], gray.shape[0], what=f"video {self.path}")
                    except ImageError as err:
                        raise BagError(str(err)) from None
                if index == 0 and (gray.shape[1], gray.shape[0]) != (camera.width_px,
                                                                     camera.height_px):
                    camera = _camera_for_size(camera, gray.shape[1], gray.shape[0], self.path)
                yield RawFrame(index, stamp, camera, "array", gray)
                index += 1
            # The container's frame count (AVI/MKV headers) says how many a cut file lost.
            self._read, self._last_ns = index, (int(round((index - 1) * 1e9 / self._fps))
                                                if index else 0)
            self._dt_ns = 1e9 / self._fps
            if self.count > index:
                self._midway = f"video ends after {index} of the {self.count} frames its header lists"
                self._expected = self.count
                self._until_ns = int(round((self.count - 1) * 1e9 / self._fps))
        finally:
            cap.release()


def _camera_for_size(camera: CameraModel, width: int, height: int, path: Path) -> CameraModel:
    """The intrinsics rescaled to a video of another size with the same aspect ratio."""
    factor = width / camera.width_px
    if abs(height - camera.height_px * factor) > 1.0:
        raise BagError(
            f"video {path} is {width}x{height} but the intrinsics are for "
            f"{camera.width_px}x{camera.height_px}"
        )
    return camera.scaled(factor)


def open_frames(
    path: str | Path,
    image_topic: str | None = None,
    camera_info_topic: str | None = None,
    intrinsics: str | Path | CameraModel | None = None,
    fps: float | None = None,
    rectified: bool = False,
) -> FrameSource:
    """Open a recording for reading frames.

    Args:
        path: rosbag2 folder, ``.mcap``/``.db3`` file, or video file.
        image_topic: Image or CompressedImage topic (auto when the bag has exactly one).
        camera_info_topic: CameraInfo topic (auto: the only one, or the image's namespace's).
        intrinsics: camera YAML (or a CameraModel) overriding the bag's CameraInfo; required for
            a video.
        fps: video frame rate (default: the container's).
        rectified: the images are rectified: CameraInfo P is the camera matrix, no distortion
            (the node's ``image_is_rectified`` parameter; never guessed from the topic name).

    Raises:
        BagError: unreadable input, missing topic, no intrinsics.
        IntrinsicsError: an unreadable intrinsics file.
    """
    path = Path(path)
    if path.is_dir() or path.suffix.lower() in (".mcap", ".db3", ".bag"):
        return BagSource(path, image_topic, camera_info_topic, intrinsics, rectified)
    return VideoSource(path, intrinsics, fps)
