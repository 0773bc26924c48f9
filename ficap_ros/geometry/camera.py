"""Camera intrinsics and lens models.

Pixel convention: OpenCV's, pixel centres at integer coordinates, (0, 0) the centre of the top-left
pixel. (AprilTag's C library puts (0, 0) at the outer corner of that pixel: subtract 0.5 px from its
coordinates to compare.) Camera optical frame: x right, y down, z forward (REP-103 ``_optical``).

Lens models, named as in ``sensor_msgs/CameraInfo``:
    ``plumb_bob`` (k1 k2 p1 p2 k3), ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6),
    ``equidistant`` (fisheye k1 k2 k3 k4, OpenCV's ``cv2.fisheye``), and ``none`` (rectified or ideal
    pinhole; what a rectified image with projection matrix P uses).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import yaml

from ficap_ros.errors import IntrinsicsError
from ficap_ros.files import read_text

__all__ = ["CameraModel", "DISTORTION_MODELS", "load_camera_yaml", "camera_from_info", "camera_info_key",
           "CameraInfoCache", "pick_camera_info", "CAMERA_INFO_MAX_STAMP_DIFF_NS"]

#: How close a CameraInfo's stamp must be to an image's to count as that image's (the node's
#: ``camera_info_max_stamp_diff_ms`` default; bags use it as is).
CAMERA_INFO_MAX_STAMP_DIFF_NS = 1_000_000

#: Largest image side accepted in intrinsics: beyond any camera, so a larger value is a typo or a
#: hostile file (the pixel budget of ``image_codec`` bounds the images themselves).
MAX_SIDE_PX = 100_000

#: Number of distortion coefficients each lens model takes (at least; extra zeros are allowed).
DISTORTION_MODELS: dict[str, int] = {
    "none": 0,
    "plumb_bob": 5,
    "rational_polynomial": 8,
    "equidistant": 4,
}


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera.

    Attributes:
        width_px, height_px: image size.
        K: 3x3 camera matrix (fx, fy, cx, cy in px).
        D: distortion coefficients of ``distortion_model`` (empty for ``none``).
        distortion_model: one of ``DISTORTION_MODELS``.
    """

    width_px: int
    height_px: int
    K: np.ndarray
    D: np.ndarray
    distortion_model: str = "none"

    def __post_init__(self) -> None:
        if self.distortion_model not in DISTORTION_MODELS:
            raise IntrinsicsError(
                f"unknown distortion model {self.distortion_model!r}; "
                f"expected one of {', '.join(DISTORTION_MODELS)}"
            )
        k = np.asarray(self.K, dtype=np.float64)
        if k.size != 9:
            raise IntrinsicsError(f"camera matrix K must have 9 values, got {k.size}")
        k = k.reshape(3, 3).copy()
        d = np.asarray(self.D, dtype=np.float64).reshape(-1).copy()
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
            raise IntrinsicsError("camera intrinsics contain NaN or infinity")
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        if fx <= 0.0 or fy <= 0.0:
            raise IntrinsicsError(f"camera focal lengths must be positive, got fx={fx} fy={fy}")
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise IntrinsicsError(
                f"camera image size must be positive, got {self.width_px}x{self.height_px}"
            )
        if max(int(self.width_px), int(self.height_px)) > MAX_SIDE_PX:
            raise IntrinsicsError(
                f"camera image size {self.width_px}x{self.height_px} is beyond any camera "
                f"(largest side {MAX_SIDE_PX} px)")
        if not (0.0 < cx < self.width_px and 0.0 < cy < self.height_px):
            raise IntrinsicsError(
                f"principal point ({cx:.1f}, {cy:.1f}) lies outside the "
                f"{self.width_px}x{self.height_px} image"
            )
        need = DISTORTION_MODELS[self.distortion_model]
        if d.size < need:
            d = np.concatenate([d, np.zeros(need - d.size)])
        if self.distortion_model == "equidistant":
            d = d[:4]
        k.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "D", d)
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))

    # -- identity ---------------------------------------------------------------------------------
    @property
    def key(self) -> tuple:
        """What identifies the intrinsics (size, K, D and lens model; arrays by their bytes, so
        equal models compare and hash equal and a changed coefficient never does)."""
        return (self.width_px, self.height_px, self.K.tobytes(), self.D.tobytes(),
                self.distortion_model)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CameraModel) and self.key == other.key

    def __hash__(self) -> int:
        return hash(self.key)

    def check_image_size(self, width_px: int, height_px: int) -> None:
        """Raises ``IntrinsicsError`` unless an image of this size fits these intrinsics."""
        if (width_px, height_px) != (self.width_px, self.height_px):
            raise IntrinsicsError(f"image {width_px}x{height_px} does not match the intrinsics "
                                  f"{self.width_px}x{self.height_px}")

    # -- constructors ----------------------------------------------------------------------------
    @classmethod
    def pinhole(
        cls, width_px: int, height_px: int, hfov_deg: float | None = None, f_px: float | None = None
    ) -> CameraModel:
        """An ideal pinhole with the principal point at the image centre."""
        if f_px is None:
            if hfov_deg is None:
                raise IntrinsicsError("pinhole camera needs hfov_deg or f_px")
            f_px = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        k = np.array([[f_px, 0.0, (width_px - 1) / 2.0], [0.0, f_px, (height_px - 1) / 2.0],
                      [0.0, 0.0, 1.0]])
        return cls(width_px, height_px, k, np.zeros(0), "none")

    @classmethod
    def from_camera_info(
        cls,
        width: int,
        height: int,
        k: Sequence[float],
        d: Sequence[float],
        distortion_model: str,
        p: Sequence[float] | None = None,
        rectified: bool = False,
    ) -> CameraModel:
        """From the fields of ``sensor_msgs/CameraInfo``.

        Args:
            rectified: the image is already rectified: use P's left 3x3 and no distortion.
        """
        if rectified:
            if p is None or len(p) != 12:
                raise IntrinsicsError("a rectified image needs the 12 values of P")
            pm = np.asarray(p, dtype=np.float64).reshape(3, 4)
            return cls(width, height, pm[:, :3], np.zeros(0), "none")
        model = distortion_model or ("plumb_bob" if len(d) else "none")
        if not any(d) and model not in DISTORTION_MODELS:
            model = "none"
        return cls(width, height, np.asarray(k, dtype=np.float64), np.asarray(d), model)

    # -- geometry --------------------------------------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project points (N, 3) in the camera optical frame (any length unit) to pixels (N, 2)."""
        pts = np.ascontiguousarray(np.asarray(points_cam, dtype=np.float64).reshape(-1, 1, 3))
        zero = np.zeros(3)
        if self.distortion_model == "equidistant":
            px, _ = cv2.fisheye.projectPoints(pts, zero, zero, self.K, self.D)
        else:
            px, _ = cv2.projectPoints(pts, zero, zero, self.K, self.D)
        return px.reshape(-1, 2)

    def undistort_px(self, points_px: np.ndarray) -> np.ndarray:
        """Map distorted pixels (N, 2) to the pixels an ideal pinhole with the same K would see."""
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if self.distortion_model == "none" or not np.any(self.D):
            return pts.reshape(-1, 2).copy()
        if self.distortion_model == "equidistant":
            out = cv2.fisheye.undistortPoints(pts, self.K, self.D, P=self.K)
        else:
            out = cv2.undistortPointsIter(
                pts, self.K, self.D, None, self.K,
                (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
            )
        return out.reshape(-1, 2)

    @property
    def is_distorted(self) -> bool:
        return self.distortion_model != "none" and bool(np.any(self.D))

    def scaled(self, factor: float) -> CameraModel:
        """The same camera seen in an image resized by ``factor`` (pixel-centre convention)."""
        k = self.K.copy()
        k[0, 0] *= factor
        k[1, 1] *= factor
        k[0, 2] = (k[0, 2] + 0.5) * factor - 0.5
        k[1, 2] = (k[1, 2] + 0.5) * factor - 0.5
        return CameraModel(
            round(self.width_px * factor), round(self.height_px * factor), k, self.D,
            self.distortion_model,
        )

    def to_camera_yaml(self, name: str = "camera") -> dict[str, Any]:
        """The camera_calibration (ROS ``camera_info_manager``) YAML form."""
        d = self.D.tolist()
        p = np.hstack([self.K, np.zeros((3, 1))])
        return {
            "image_width": self.width_px,
            "image_height": self.height_px,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": self.K.reshape(-1).tolist()},
            "distortion_model": "plumb_bob" if self.distortion_model == "none" else self.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": len(d) or 5, "data": d or [0.0] * 5},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).reshape(-1).tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": p.reshape(-1).tolist()},
        }


def load_camera_yaml(path: str | Path) -> CameraModel:
    """Read intrinsics in the camera_calibration YAML format; raises ``IntrinsicsError``."""
    text = read_text(path, "intrinsics", IntrinsicsError)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise IntrinsicsError(f"intrinsics {path} is not valid YAML") from err
    if not isinstance(data, dict):
        raise IntrinsicsError(f"intrinsics {path} is not a camera_calibration YAML mapping")
    try:
        k = data["camera_matrix"]["data"]
        d = data.get("distortion_coefficients", {}).get("data", []) or []
        model = data.get("distortion_model", "plumb_bob") or "plumb_bob"
        return CameraModel.from_camera_info(
            int(data["image_width"]), int(data["image_height"]), k, d, model
        )
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
        raise IntrinsicsError(f"intrinsics {path}: missing or malformed field {err}") from err


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
