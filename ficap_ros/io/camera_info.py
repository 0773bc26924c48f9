"""The CameraInfo rule, one for the node and the bag tools: which ``sensor_msgs/CameraInfo`` an
image uses (``pick_camera_info``), how it becomes a ``CameraModel`` (``camera_from_info``), and the
live stream's cache of both (``CameraInfoCache``).

Messages are duck-typed: an rclpy message, a rosbags message or anything with CameraInfo's fields
(ROS 1's upper-case ``K``/``D``/``P`` too). No rclpy here.
"""

from __future__ import annotations

from bisect import bisect_right
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ficap_ros.errors import IntrinsicsError
from ficap_ros.geometry.camera import CameraModel, load_camera_yaml

__all__ = ["camera_from_info", "camera_info_key", "pick_camera_info", "CameraInfoCache",
           "CAMERA_INFO_MAX_STAMP_DIFF_NS", "camera_info_beside"]

#: How close a CameraInfo's stamp must be to an image's to count as that image's (the node's
#: ``camera_info_max_stamp_diff_ms`` default; bags use it as is).
CAMERA_INFO_MAX_STAMP_DIFF_NS = 1_000_000


def camera_info_beside(image_topic: str) -> str:
    """The CameraInfo topic of an image topic, image_transport's rule (``getCameraInfoTopic``):
    ``camera_info`` in the image topic's namespace (``/rear_cam/image_raw`` ->
    ``/rear_cam/camera_info``). ``image_topic`` is the base topic, without a transport's suffix
    (``/compressed``); a relative one gives a relative answer."""
    head, _, _ = image_topic.rstrip("/").rpartition("/")
    return f"{head}/camera_info" if head or image_topic.startswith("/") else "camera_info"


def camera_from_info(msg: Any, rectified: bool = False) -> CameraModel:
    """A ``sensor_msgs/CameraInfo`` as a ``CameraModel``: the one rule of the node and the bag tools.

    ``msg`` is any object with CameraInfo's fields (an rclpy message, a rosbags message, ROS 1's
    upper-case ``K``/``D``/``P``). K + D are used, or P's left 3x3 and no distortion when the image
    is ``rectified``. Some drivers fill only P (K all zero): that image is taken as rectified.

    Raises:
        IntrinsicsError: K and P both all zero (camera not calibrated), a rectified image without
            P, zero size, NaN/inf, or an unknown lens model.
    """
    def field(name: str) -> Any:
        value = getattr(msg, name, None)
        return getattr(msg, name.upper(), None) if value is None else value

    try:
        k = np.asarray(field("k"), dtype=np.float64).reshape(-1)
        p = np.asarray(field("p"), dtype=np.float64).reshape(-1)
        d = np.asarray(field("d"), dtype=np.float64).reshape(-1)
        width, height = int(msg.width), int(msg.height)
    except (TypeError, ValueError, AttributeError, OverflowError) as err:
        raise IntrinsicsError(f"malformed CameraInfo: {err}") from err
    has_p = p.size == 12 and bool(np.any(p))
    if not np.any(k):
        if not has_p:
            raise IntrinsicsError("CameraInfo K and P are all zero (camera not calibrated)")
        rectified = True  # some drivers fill only P
    if rectified and not has_p:
        raise IntrinsicsError("CameraInfo P is all zero but the image is rectified")
    return CameraModel.from_camera_info(width, height, k, d, str(field("distortion_model") or ""),
                                        p, rectified=rectified)


def camera_info_key(msg: Any) -> tuple:
    """What identifies a CameraInfo's intrinsics (size, lens model, K, D, P): messages with equal
    keys give equal ``CameraModel``s, so the model is built once per change."""
    def values(name: str) -> tuple[float, ...]:
        value = getattr(msg, name, None)
        value = getattr(msg, name.upper(), None) if value is None else value
        return tuple(np.asarray(value, dtype=np.float64).reshape(-1).tolist())

    return (int(msg.width), int(msg.height), str(getattr(msg, "distortion_model", "") or ""),
            values("k"), values("d"), values("p"))


def pick_camera_info(stamps_ns: Sequence[int], stamp_ns: int,
                     max_stamp_diff_ns: int = CAMERA_INFO_MAX_STAMP_DIFF_NS) -> int:
    """Which CameraInfo an image stamped ``stamp_ns`` uses, live and offline (one rule): the
    nearest in stamp when within ``max_stamp_diff_ns`` (the earlier on a tie), else the last one
    at or before the image, else the first (an image older than every CameraInfo).

    Args:
        stamps_ns: the CameraInfo stamps, ascending (equal stamps in arrival order: the last of
            them counts).

    Returns:
        An index into ``stamps_ns`` (which must not be empty).
    """
    i = bisect_right(stamps_ns, stamp_ns)  # stamps_ns[:i] are at or before the image
    before = stamp_ns - stamps_ns[i - 1] if i > 0 else None
    after = stamps_ns[i] - stamp_ns if i < len(stamps_ns) else None
    if after is not None and after <= max_stamp_diff_ns and (before is None or after < before):
        return i
    return i - 1 if i > 0 else 0


class CameraInfoCache:
    """Intrinsics for a live stream's frames: the CameraInfo ``pick_camera_info`` chooses among
    the last ``keep`` received, else static intrinsics (thread-safe: CameraInfo arrives on
    another thread than the frames).

    Args:
        static: intrinsics from a file, used while no CameraInfo has been received.
        static_error: why the file could not be read ('' = no file), the error without one.
        keep: CameraInfo messages kept.
    """

    def __init__(self, static: CameraModel | None = None, static_error: str = "",
                 keep: int = 50) -> None:
        import threading
        from collections import deque

        self._lock = threading.Lock()
        self._infos: deque[tuple[int, Any]] = deque(maxlen=keep)
        self._static = static
        self.static_error = static_error
        self._cache: tuple[tuple, CameraModel] | None = None

    @classmethod
    def with_file(cls, path: str | Path) -> CameraInfoCache:
        """A cache with a camera_calibration YAML's intrinsics ('' = none); an unreadable file
        leaves ``static_error`` (reported for every frame until a CameraInfo comes)."""
        if not path:
            return cls()
        try:
            return cls(load_camera_yaml(path))
        except IntrinsicsError as err:
            return cls(None, str(err))

    def add(self, stamp_ns: int, msg: Any) -> None:
        with self._lock:
            self._infos.append((int(stamp_ns), msg))

    def has(self, stamp_ns: int) -> bool:
        with self._lock:
            return any(s == stamp_ns for s, _ in self._infos)

    def camera_for(self, stamp_ns: int, max_stamp_diff_ns: int, rectified: bool) -> CameraModel:
        """The intrinsics of a frame stamped ``stamp_ns`` (``pick_camera_info``'s choice,
        ``camera_from_info``'s rule).

        Raises:
            IntrinsicsError: none received and no static intrinsics, or an invalid CameraInfo.
        """
        with self._lock:
            infos = sorted(self._infos, key=lambda e: e[0])  # stable: arrival order kept
        if not infos:
            if self._static is not None:
                return self._static
            raise IntrinsicsError(self.static_error or "no CameraInfo received yet and no "
                                  "camera_info_file")
        msg = infos[pick_camera_info([s for s, _ in infos], stamp_ns, max_stamp_diff_ns)][1]
        key = (camera_info_key(msg), rectified)
        cache = self._cache
        if cache is not None and cache[0] == key:
            return cache[1]
        camera = camera_from_info(msg, rectified=rectified)
        self._cache = (key, camera)
        return camera
