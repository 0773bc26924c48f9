"""tag36h11 detection: OpenCV ArUco (default) or AprilTag 3 (pupil-apriltags), chosen by name.

Corners are in OpenCV's order (c0..c3 = top-left, top-right, bottom-right, bottom-left of the tag as
``cv2.aruco.generateImageMarker`` draws it, which is the official apriltag-imgs image turned by
180 deg, so c0..c3 = AprilTag's p1, p0, p3, p2) and OpenCV's pixel convention (pixel centres at
integer coordinates), in the image as given (distorted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ficap_ros.errors import ImageError

__all__ = ["TagDetection", "DetectorConfig", "TagDetector", "as_gray"]


@dataclass(frozen=True)
class TagDetection:
    """One detected tag.

    Attributes:
        tag_id: tag36h11 id.
        corners_px: (4, 2) float64, OpenCV order and pixel convention, distorted image.
        hamming: bit errors corrected while decoding (0 when the backend does not say).
        decision_margin: backend's decoding confidence (NaN when the backend does not say).
    """

    tag_id: int
    corners_px: np.ndarray
    hamming: int = 0
    decision_margin: float = float("nan")

    def __post_init__(self) -> None:
        c = np.asarray(self.corners_px, dtype=np.float64).reshape(4, 2).copy()
        c.setflags(write=False)
        object.__setattr__(self, "corners_px", c)
        object.__setattr__(self, "tag_id", int(self.tag_id))


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings (see ``TagDetector``).

    Attributes:
        backend: ``opencv`` (cv2.aruco ArucoDetector, DICT_APRILTAG_36h11) or ``apriltag``
            (pupil-apriltags, the AprilTag 3 C library).
        corner_refine: ``edge`` (our edge fit of the four border lines, sub-pixel),
            ``subpix`` (cv2.cornerSubPix, the naive peer), ``apriltag`` (OpenCV's
            CORNER_REFINE_APRILTAG) or ``none``.
    """

    backend: str = "opencv"
    corner_refine: str = "edge"


class TagDetector:
    """Finds every tag36h11 tag in a grey image (not filtered by a cap model)."""

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()

    def detect(self, image: np.ndarray) -> list[TagDetection]:
        raise NotImplementedError


def as_gray(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as a contiguous uint8 grey array (no copy when it is one).

    Accepts (H, W) or (H, W, 1) grey, (H, W, 3) BGR and (H, W, 4) BGRA, uint8 or uint16
    (scaled to 8 bits).

    Raises:
        ImageError: not an array, empty, of an unsupported dtype or shape.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"image must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise ImageError(f"image is empty (shape {image.shape})")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"image dtype must be uint8 or uint16, got {image.dtype}")
    import cv2  # local: keep module import light for type-only users

    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        gray = image
    elif image.ndim == 3 and image.shape[2] == 3:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    else:
        raise ImageError(f"image shape {image.shape} is neither grey (H, W) nor colour (H, W, 3|4)")
    if gray.shape[0] < 8 or gray.shape[1] < 8:
        raise ImageError(f"image {gray.shape[1]}x{gray.shape[0]} is too small to hold a tag")
    if gray.dtype == np.uint16:
        gray = (gray >> 8).astype(np.uint8)
    return np.ascontiguousarray(gray)
