"""Camera intrinsics and lens models.

Pixel convention: OpenCV's, pixel centres at integer coordinates, (0, 0) the centre of the top-left
pixel. (AprilTag's C library puts (0, 0) at the outer corner of that pixel: subtract 0.5 px from its
coordinates to compare.) Camera optical frame: x right, y down, z forward (REP-103 ``_optical``).

Lens models, named as in ``sensor_msgs/CameraInfo``:
    ``plumb_bob`` (k1 k2 p1 p2 k3), ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6),
    ``equidistant`` (fisheye k1 k2 k3 k4, OpenCV's ``cv2.fisheye``), and ``none`` (rectified or ideal
    pinhole; what a rectified image with projection matrix P uses).

``CameraModel`` is the door every intrinsics pass (CameraInfo, a camera YAML, a video's scaling):
its construction validates them once (finite numbers; K of the form [fx s cx; 0 fy cy; 0 0 1]
with focal lengths and principal point sane for the image size; as many distortion coefficients
as the lens model takes, none beyond a real lens's magnitude), so no OpenCV call downstream meets
values it refuses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from ficap_ros.errors import IntrinsicsError
from ficap_ros.files import load_yaml

__all__ = ["CameraModel", "CameraTiming", "DISTORTION_MODELS", "ROW_ORDERS", "TIMING_KEY",
           "load_camera_yaml", "load_camera_timing"]

#: Largest image side accepted in intrinsics: beyond any camera, so a larger value is a typo or a
#: hostile file (the pixel budget of ``image_codec`` bounds the images themselves).
MAX_SIDE_PX = 100_000

#: Focal lengths accepted, as a multiple of the image's larger side: from a fisheye seeing far
#: behind itself to a telephoto of a fraction of a degree.
FOCAL_RANGE_SIDES = (0.01, 100.0)
#: Largest magnitude of a distortion coefficient: real lenses stay within tens (a rational
#: model's paired coefficients within hundreds).
MAX_DISTORTION_COEFFICIENT = 1e3

#: Number of distortion coefficients each lens model takes (fewer are padded with zeros; more
#: only when the extra ones are zeros, which are dropped).
DISTORTION_MODELS: dict[str, int] = {
    "none": 0,
    "plumb_bob": 5,
    "rational_polynomial": 8,
    "equidistant": 4,
}


#: Orders in which a rolling shutter reads its rows (``CameraTiming.row_order``).
ROW_ORDERS = ("top_to_bottom", "bottom_to_top")
#: The camera YAML's optional mapping of ``CameraTiming`` fields (camera_calibration's parsers
#: ignore keys they do not know, so such a file still loads in ``camera_info_manager``).
TIMING_KEY = "camera_timing"
_TIMING_FIELDS = ("exposure_ms", "readout_ms", "row_order", "stamp_offset_ms")


@dataclass(frozen=True)
class CameraTiming:
    """When a camera's pixels see the scene, relative to the image's stamp.

    Convention: ``stamp + stamp_offset_ms`` is the middle of the middle row's exposure (the
    instant a global-shutter image shows, and the instant poses are reported at). A rolling
    shutter exposes row ``y`` (pixel-centre coordinate, OpenCV's convention) centred on that
    instant plus ``row_time_s(y)``: ``(y + 0.5 - H / 2) / H * readout_ms``, rows read in
    ``row_order``; every row integrates light for ``exposure_ms`` around its centre.

    Attributes:
        exposure_ms: each row's exposure time, ms; 0 = not known (no motion blur modelled).
        readout_ms: time between the first and the last row's exposure centres, ms; 0 = a
            global shutter.
        row_order: ``top_to_bottom`` or ``bottom_to_top`` (``ROW_ORDERS``).
        stamp_offset_ms: added to a stamp to reach the middle row's mid-exposure: 0 for drivers
            that stamp it; ``(exposure_ms + readout_ms) / 2`` for a stamp at the start of the
            first row's exposure; negative for a stamp at the end of the frame.
    """

    exposure_ms: float = 0.0
    readout_ms: float = 0.0
    row_order: str = "top_to_bottom"
    stamp_offset_ms: float = 0.0

    def __post_init__(self) -> None:
        if self.row_order not in ROW_ORDERS:
            raise IntrinsicsError(f"row_order must be one of {', '.join(ROW_ORDERS)}, "
                                  f"got {self.row_order!r}")
        for name in ("exposure_ms", "readout_ms"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1000.0):
                raise IntrinsicsError(f"{name} must be in [0, 1000] ms, got {value}")
        if not (math.isfinite(self.stamp_offset_ms) and abs(self.stamp_offset_ms) <= 1000.0):
            raise IntrinsicsError(f"stamp_offset_ms must be in [-1000, 1000] ms, "
                                  f"got {self.stamp_offset_ms}")

    @classmethod
    def from_mapping(cls, values: Any, what: str = "camera timing") -> CameraTiming:
        """From a mapping of field names (``to_dict``'s; missing ones take their defaults).

        Raises:
            IntrinsicsError: not a mapping, an unknown key, a value of the wrong type or out of
                range (the message names ``what``).
        """
        if not isinstance(values, dict):
            raise IntrinsicsError(f"{what} must be a mapping of {', '.join(_TIMING_FIELDS)}")
        unknown = sorted(set(map(str, values)) - set(_TIMING_FIELDS))
        if unknown:
            raise IntrinsicsError(f"{what}: unknown key {unknown[0]!r} (expected "
                                  f"{', '.join(_TIMING_FIELDS)})")
        kw: dict[str, Any] = {}
        for name, value in values.items():
            if name == "row_order":
                if not isinstance(value, str):
                    raise IntrinsicsError(f"{what}: row_order must be a string, got {value!r}")
                kw[name] = value
            elif isinstance(value, (int, float)) and not isinstance(value, bool) and \
                    not abs(value) >= 1e300:  # NaN goes on to the range check
                kw[name] = float(value)
            else:
                raise IntrinsicsError(f"{what}: {name} must be a number of ms, got {value!r}")
        try:
            return cls(**kw)
        except IntrinsicsError as err:
            raise IntrinsicsError(f"{what}: {err}") from None

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain values (the camera YAML's ``camera_timing``, summary.json's,
        a synth bag's metadata): ``from_mapping`` reads it back to an equal timing."""
        return {"exposure_ms": float(self.exposure_ms), "readout_ms": float(self.readout_ms),
                "row_order": self.row_order, "stamp_offset_ms": float(self.stamp_offset_ms)}

    @property
    def stated(self) -> bool:
        """Whether the timing states an exposure or a readout: only then is the cap's velocity
        reported (``CapPose.velocity``, the head twist) and a frame solved with its next one. With
        neither the outputs are the timing-agnostic estimator's, identical whatever the frames
        before say of the motion; the velocity then serves only the readout's evidence."""
        return self.exposure_ms > 0.0 or self.readout_ms > 0.0

    @property
    def rolling(self) -> bool:
        """Whether rows are exposed at different times (a rolling shutter)."""
        return self.readout_ms > 0.0

    def row_time_s(self, y_px: np.ndarray, height_px: int) -> np.ndarray:
        """Time of row ``y_px`` (pixel-centre coordinates, any shape) relative to the middle
        row's mid-exposure, s: negative for rows exposed earlier."""
        y = np.asarray(y_px, dtype=np.float64)
        frac = (y + 0.5 - 0.5 * height_px) / float(height_px)
        if self.row_order == "bottom_to_top":
            frac = -frac
        return frac * (self.readout_ms * 1e-3)


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
        _check_size(self.width_px, self.height_px)
        _check_matrix(k, int(self.width_px), int(self.height_px))
        d = _distortion(d, self.distortion_model)
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
        if not self.is_distorted:
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
        """The lens maps points elsewhere than the ideal pinhole with the same K: any non-zero
        coefficient, or a fisheye (``equidistant`` with zero coefficients is the f-theta lens,
        r = f * atan(x / z), not a pinhole)."""
        return self.distortion_model == "equidistant" or (
            self.distortion_model != "none" and bool(np.any(self.D)))

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

    def to_camera_yaml(self, name: str = "camera",
                       timing: CameraTiming | None = None) -> dict[str, Any]:
        """The camera_calibration (ROS ``camera_info_manager``) YAML form; with ``timing``, also
        its ``camera_timing`` mapping (``load_camera_timing`` reads it back)."""
        d = self.D.tolist()
        p = np.hstack([self.K, np.zeros((3, 1))])
        extra = {} if timing is None else {TIMING_KEY: timing.to_dict()}
        return {
            "image_width": self.width_px,
            "image_height": self.height_px,
            "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": self.K.reshape(-1).tolist()},
            "distortion_model": "plumb_bob" if self.distortion_model == "none" else self.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": len(d) or 5, "data": d or [0.0] * 5},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).reshape(-1).tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": p.reshape(-1).tolist()},
            **extra,
        }


def _check_size(width_px: Any, height_px: Any) -> None:
    if int(width_px) <= 0 or int(height_px) <= 0:
        raise IntrinsicsError(f"camera image size must be positive, got {width_px}x{height_px}")
    if max(int(width_px), int(height_px)) > MAX_SIDE_PX:
        raise IntrinsicsError(f"camera image size {width_px}x{height_px} is beyond any camera "
                              f"(largest side {MAX_SIDE_PX} px)")


def _check_matrix(k: np.ndarray, width_px: int, height_px: int) -> None:
    """K is [fx s cx; 0 fy cy; 0 0 1], focal lengths within ``FOCAL_RANGE_SIDES`` of the larger
    side, principal point inside the image, skew smaller than the focal length."""
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if k[1, 0] != 0.0 or not np.allclose(k[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise IntrinsicsError(f"camera matrix K must be [fx s cx; 0 fy cy; 0 0 1], got rows "
                              f"{np.round(k[1:], 6).tolist()}")
    side = max(width_px, height_px)
    lo, hi = FOCAL_RANGE_SIDES[0] * side, FOCAL_RANGE_SIDES[1] * side
    if not (lo <= fx <= hi and lo <= fy <= hi):
        raise IntrinsicsError(f"camera focal lengths fx={fx:.6g} fy={fy:.6g} px are not sane for "
                              f"a {width_px}x{height_px} image ({lo:g} to {hi:g} px)")
    if not (0.0 < cx < width_px and 0.0 < cy < height_px):
        raise IntrinsicsError(f"principal point ({cx:.1f}, {cy:.1f}) lies outside the "
                              f"{width_px}x{height_px} image")
    if abs(k[0, 1]) >= fx:
        raise IntrinsicsError(f"camera skew {k[0, 1]:.6g} is not smaller than fx {fx:.6g}")


def _distortion(d: np.ndarray, model: str) -> np.ndarray:
    """The coefficients of ``model``: padded with zeros to its count, extra zeros dropped."""
    need = DISTORTION_MODELS[model]
    if d.size > need:
        if np.any(d[need:]):
            names = {"plumb_bob": " (k1 k2 p1 p2 k3)", "rational_polynomial": " (k1 k2 p1 p2 k3 "
                     "k4 k5 k6)", "equidistant": " (k1 k2 k3 k4)"}.get(model, "")
            raise IntrinsicsError(f"distortion model {model} takes {need} coefficients"
                                  f"{names}, got {d.size}")
        d = d[:need]
    if np.any(np.abs(d) > MAX_DISTORTION_COEFFICIENT):
        raise IntrinsicsError(f"distortion coefficients {d.tolist()} exceed "
                              f"{MAX_DISTORTION_COEFFICIENT:g} in magnitude (no real lens)")
    return np.concatenate([d, np.zeros(need - d.size)]) if d.size < need else d


def _read_camera_yaml(path: str | Path) -> dict[str, Any]:
    """A camera_calibration YAML file as its mapping, read through the guarded loader
    (``files.load_yaml``); raises ``IntrinsicsError`` naming the file."""
    data = load_yaml(path, "intrinsics", IntrinsicsError)
    if not isinstance(data, dict):
        raise IntrinsicsError(f"intrinsics {path} is not a camera_calibration YAML mapping")
    return data


def load_camera_yaml(path: str | Path) -> CameraModel:
    """Read intrinsics in the camera_calibration YAML format; raises ``IntrinsicsError``."""
    data = _read_camera_yaml(path)
    try:
        k = data["camera_matrix"]["data"]
        d = data.get("distortion_coefficients", {}).get("data", []) or []
        model = data.get("distortion_model", "plumb_bob") or "plumb_bob"
        return CameraModel.from_camera_info(
            int(data["image_width"]), int(data["image_height"]), k, d, model
        )
    except IntrinsicsError as err:
        raise IntrinsicsError(f"intrinsics {path}: {err}") from None
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
        raise IntrinsicsError(f"intrinsics {path}: missing or malformed field {err}") from err


def load_camera_timing(path: str | Path) -> CameraTiming | None:
    """The ``camera_timing`` mapping of a camera YAML (``CameraModel.to_camera_yaml``), or None
    when the file has none (its timing is not known).

    Raises:
        IntrinsicsError: an unreadable file or a malformed ``camera_timing``.
    """
    data = _read_camera_yaml(path)
    if data.get(TIMING_KEY) is None:
        return None
    return CameraTiming.from_mapping(data[TIMING_KEY], f"intrinsics {path}: {TIMING_KEY}")
