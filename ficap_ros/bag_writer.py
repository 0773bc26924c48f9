"""Writing rosbag2 bags (MCAP or sqlite3) atomically, and the rosbags message builders the bag
tools and tests write with (no ROS install needed).

A bag is written into a hidden temporary folder beside its destination and renamed into place when
complete, so an error or Ctrl-C never leaves a partial bag.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ficap_ros.bag_io import jazzy_typestore
from ficap_ros.camera import CameraModel
from ficap_ros.errors import BagError, OutputError

__all__ = ["BagWriter", "header", "pose_msg", "pose_stamped_msg", "pose_with_covariance_stamped_msg", "camera_info_msg", "compressed_image_msg", "image_msg"]


# -- writing -------------------------------------------------------------------------------------
class BagWriter:
    """Write a rosbag2 bag atomically: into a hidden temporary folder, renamed when complete.

    Use as a context manager. ``layout``:
        ``folder``: ``path`` becomes a rosbag2 folder (``metadata.yaml`` + ``<name>.mcap``/``.db3``).
        ``file``: ``path`` is a single ``.mcap`` file (rosbag2 MCAP profile, with the rosbag2
            metadata record inside) and ``metadata.yaml`` is put next to it, so the file's folder
            is also a rosbag2 bag (``ros2 bag info DIR`` and ``ros2 bag info DIR/x.mcap`` both
            work). An existing ``metadata.yaml`` there is replaced.

    An exception (Ctrl-C included) inside the ``with`` block removes the temporary folder and
    leaves ``path`` untouched.

    Raises:
        BagError: the destination folder is not writable.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", layout: str = "folder") -> None:
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"unknown bag storage {storage!r}; expected mcap or sqlite3")
        if layout not in ("folder", "file"):
            raise BagError(f"unknown bag layout {layout!r}")
        if layout == "file" and storage != "mcap":
            raise BagError("a single-file bag must use MCAP storage")
        self.path = Path(path)
        self.storage = storage
        self.layout = layout
        self.typestore = jazzy_typestore()
        self._writer: Any = None
        self._tmpdir: Path | None = None
        self._conns: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        import shutil
        import tempfile

        from rosbags.rosbag2 import StoragePlugin, Writer

        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=parent))
        except OSError as err:
            raise OutputError(f"cannot write to {parent}: {err.strerror or err}") from err
        name = self.path.stem if self.layout == "file" else self.path.name
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._tmpdir / name, version=9, storage_plugin=plugin)
        try:
            self._writer.open()
        except OSError as err:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
        return self

    def set_custom_data(self, key: str, value: str) -> None:
        """A string in metadata.yaml's ``custom_data`` (before the bag is closed)."""
        self._writer.set_custom_data(key, value)

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic (once) before writing to it."""
        self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialize ``msg`` (a rosbags message object) and write it with receive time ``stamp_ns``."""
        conn = self._conns[topic]
        try:
            self._writer.write(conn, int(stamp_ns),
                               self.typestore.serialize_cdr(msg, conn.msgtype))
        except OSError as err:  # a full disk: one line, and __exit__ removes the temporary
            raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        import shutil

        assert self._tmpdir is not None
        try:
            if exc_type is not None:
                try:
                    self._writer.abort() if hasattr(self._writer, "abort") else None
                except Exception:  # noqa: BLE001 - the original error matters, not this one
                    pass
                return
            try:
                self._writer.close()
            except OSError as err:
                raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
            inner = self._tmpdir / (self.path.stem if self.layout == "file" else self.path.name)
            try:
                if self.layout == "file":
                    os.replace(inner / self.path.name, self.path)
                    os.replace(inner / "metadata.yaml", self.path.parent / "metadata.yaml")
                else:
                    if self.path.exists():
                        shutil.rmtree(self.path)
                    os.replace(inner, self.path)
            except OSError as err:
                raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)


# -- message builders (rosbags message objects; no ROS needed) ------------------------------------
def _types() -> Any:
    return jazzy_typestore().types


def header(stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/Header``."""
    t = _types()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                    frame_id=frame_id)


def pose_msg(T: Any) -> Any:
    """``geometry_msgs/Pose`` of a ``Transform`` (translation in m)."""
    t = _types()
    x, y, z = (float(v) for v in T.translation_m)
    qx, qy, qz, qw = (float(v) for v in T.q_xyzw)
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )


def pose_stamped_msg(stamp_ns: int, frame_id: str, T: Any) -> Any:
    """``geometry_msgs/PoseStamped``."""
    return _types()["geometry_msgs/msg/PoseStamped"](header=header(stamp_ns, frame_id),
                                                     pose=pose_msg(T))


def pose_with_covariance_stamped_msg(stamp_ns: int, frame_id: str, T: Any,
                                     covariance: np.ndarray) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` (covariance 6x6, ROS order)."""
    t = _types()
    cov = np.asarray(covariance, dtype=np.float64).reshape(36)
    return t["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=header(stamp_ns, frame_id),
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg(T), covariance=cov.copy()),
    )


def camera_info_msg(stamp_ns: int, frame_id: str, camera: CameraModel) -> Any:
    """``sensor_msgs/CameraInfo`` of a camera model (P = [K | 0], R = I)."""
    t = _types()
    p = np.hstack([camera.K, np.zeros((3, 1))]).reshape(12)
    model = "plumb_bob" if camera.distortion_model == "none" else camera.distortion_model
    d = camera.D if camera.D.size else np.zeros(5)
    return t["sensor_msgs/msg/CameraInfo"](
        header=header(stamp_ns, frame_id), height=camera.height_px, width=camera.width_px,
        distortion_model=model, d=np.asarray(d, dtype=np.float64).copy(),
        k=camera.K.reshape(9).copy(), r=np.eye(3).reshape(9), p=p, binning_x=0, binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False),
    )


def compressed_image_msg(stamp_ns: int, frame_id: str, data: bytes, fmt: str = "jpeg") -> Any:
    """``sensor_msgs/CompressedImage``."""
    return _types()["sensor_msgs/msg/CompressedImage"](
        header=header(stamp_ns, frame_id), format=fmt, data=np.frombuffer(data, np.uint8).copy())


def image_msg(stamp_ns: int, frame_id: str, image: np.ndarray, encoding: str) -> Any:
    """``sensor_msgs/Image`` of an array already laid out for ``encoding`` (little-endian)."""
    arr = np.ascontiguousarray(image)
    height, width = arr.shape[:2]
    step = arr.strides[0]
    return _types()["sensor_msgs/msg/Image"](
        header=header(stamp_ns, frame_id), height=height, width=width, encoding=encoding,
        is_bigendian=0, step=step, data=arr.view(np.uint8).reshape(-1).copy())


