"""Decode ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` payloads to grey arrays.

Pure numpy/OpenCV: no ROS import, so the bag tools, the node (through ``ros_msgs``) and tests share
one decoder. Encodings are the ``sensor_msgs/image_encodings`` names.
"""

from __future__ import annotations

import cv2
import numpy as np

from ficap_ros.errors import ImageError

__all__ = ["ENCODINGS", "encoding_layout", "decode_image", "decode_compressed",
           "check_pixel_budget", "max_pixels", "DEFAULT_MAX_PIXELS"]

#: Largest image accepted, in pixels (``FICAP_MAX_PIXELS`` overrides it). 40 MP holds every
#: camera a cap is filmed with (1080p is 2.1 MP, 4K 8.3 MP, a 12 MP phone photo); detection's
#: working memory grows with the pixel count, so a larger photo is refused before it costs
#: gigabytes.
DEFAULT_MAX_PIXELS = 40_000_000


def max_pixels() -> int:
    """The pixel budget: ``FICAP_MAX_PIXELS`` when set to a positive integer, else the default."""
    import os

    text = os.environ.get("FICAP_MAX_PIXELS", "").strip()
    try:
        value = int(text) if text else DEFAULT_MAX_PIXELS
    except ValueError:
        return DEFAULT_MAX_PIXELS
    return value if value > 0 else DEFAULT_MAX_PIXELS


def check_pixel_budget(width: int, height: int, what: str = "image",
                       budget: int | None = None) -> None:
    """Refuse an image above the pixel budget before it costs memory.

    Raises:
        ImageError: ``width * height`` exceeds ``budget`` (default ``max_pixels()``).
    """
    limit = max_pixels() if budget is None else int(budget)
    if int(width) * int(height) > limit:
        raise ImageError(
            f"{what} is {int(width)}x{int(height)} ({int(width) * int(height) / 1e6:.1f} MP), "
            f"above the {limit / 1e6:.1f} MP budget (FICAP_MAX_PIXELS)")

# encoding -> (channels, bytes per channel); Bayer patterns are one channel.
_LAYOUT: dict[str, tuple[int, int]] = {
    "mono8": (1, 1), "8uc1": (1, 1),
    "mono16": (1, 2), "16uc1": (1, 2),
    "bgr8": (3, 1), "rgb8": (3, 1), "8uc3": (3, 1),
    "bgra8": (4, 1), "rgba8": (4, 1), "8uc4": (4, 1),
    "bgr16": (3, 2), "rgb16": (3, 2), "bgra16": (4, 2), "rgba16": (4, 2),
    "yuv422": (2, 1), "uyvy": (2, 1), "yuv422_yuy2": (2, 1), "yuyv": (2, 1),
}
# ROS Bayer names -> OpenCV codes. OpenCV names the pattern by the 2x2 block starting at pixel
# (1, 1), ROS by the block at (0, 0), so ROS rggb is OpenCV's BG (the mapping cv_bridge uses).
_BAYER: dict[str, int] = {
    "rggb": cv2.COLOR_BayerBG2GRAY,
    "bggr": cv2.COLOR_BayerRG2GRAY,
    "gbrg": cv2.COLOR_BayerGR2GRAY,
    "grbg": cv2.COLOR_BayerGB2GRAY,
}
for _pattern in _BAYER:
    _LAYOUT[f"bayer_{_pattern}8"] = (1, 1)
    _LAYOUT[f"bayer_{_pattern}16"] = (1, 2)

#: Every raw encoding ``decode_image`` accepts.
ENCODINGS: tuple[str, ...] = tuple(sorted(_LAYOUT))


def encoding_layout(encoding: str) -> tuple[int, int]:
    """(channels, bytes per channel) of a raw image encoding (case-insensitive; Bayer mosaics are
    one channel).

    Raises:
        ImageError: not one of ``ENCODINGS``.
    """
    enc = str(encoding).strip().lower()
    if enc not in _LAYOUT:
        raise ImageError(f"unsupported image encoding {encoding!r}")
    return _LAYOUT[enc]


def decode_image(
    encoding: str, height: int, width: int, step: int, data: bytes | np.ndarray,
    is_bigendian: bool | int = False,
) -> np.ndarray:
    """Decode the fields of a ``sensor_msgs/Image`` to a grey image.

    Args:
        encoding: image encoding name (case-insensitive), one of ``ENCODINGS``.
        height, width: image size, px.
        step: bytes per row (may include padding).
        data: the pixel bytes.
        is_bigendian: whether 16-bit samples are big-endian.

    Returns:
        (height, width) uint8 array, or uint16 for 16-bit mono/Bayer (``as_gray`` scales those).

    Raises:
        ImageError: unknown encoding, or a size/step that does not match the data.
    """
    enc = str(encoding).strip().lower()
    channels, depth = encoding_layout(enc)
    try:
        height, width, step = int(height), int(width), int(step)
    except (TypeError, ValueError, OverflowError) as err:
        raise ImageError(f"image size fields are not integers: {err}") from None
    if height <= 0 or width <= 0:
        raise ImageError(f"image has no pixels ({width}x{height})")
    check_pixel_budget(width, height)
    row_bytes = width * channels * depth
    if step < row_bytes:
        raise ImageError(f"image step {step} is smaller than a {encoding} row of {row_bytes} bytes")
    try:
        buf = np.frombuffer(memoryview(data).cast("B") if not isinstance(data, np.ndarray) else
                            np.ascontiguousarray(data).view(np.uint8).reshape(-1), dtype=np.uint8)
    except (TypeError, ValueError) as err:
        raise ImageError(f"image data is not a byte buffer: {err}") from None
    if buf.size < step * (height - 1) + row_bytes:
        raise ImageError(
            f"image data holds {buf.size} bytes, {width}x{height} {encoding} with step {step} "
            f"needs {step * (height - 1) + row_bytes}"
        )
    if buf.size > step * height:
        raise ImageError(
            f"image data holds {buf.size} bytes, more than {width}x{height} {encoding} with step "
            f"{step} ({step * height})"
        )
    if buf.size < step * height:  # last row without its padding: pad so the reshape works
        buf = np.concatenate([buf, np.zeros(step * height - buf.size, np.uint8)])
    rows = buf[: step * height].reshape(height, step)[:, :row_bytes]
    if depth == 2:
        dtype = np.dtype(">u2" if is_bigendian else "<u2")
        img = np.ascontiguousarray(rows).view(dtype).astype(np.uint16)
    else:
        img = rows
    img = img.reshape(height, width, channels) if channels > 1 else img.reshape(height, width)
    img = np.ascontiguousarray(img)
    if enc.startswith("bayer_"):
        return cv2.cvtColor(img, _BAYER[enc[6:10]])
    if channels == 1:
        return img
    if enc in ("yuv422", "uyvy"):
        return cv2.cvtColor(img, cv2.COLOR_YUV2GRAY_UYVY)
    if enc in ("yuv422_yuy2", "yuyv"):
        return cv2.cvtColor(img, cv2.COLOR_YUV2GRAY_YUY2)
    code = {
        (3, True): cv2.COLOR_RGB2GRAY, (3, False): cv2.COLOR_BGR2GRAY,
        (4, True): cv2.COLOR_RGBA2GRAY, (4, False): cv2.COLOR_BGRA2GRAY,
    }[(channels, enc.startswith("rgb"))]
    return cv2.cvtColor(img, code)


def decode_compressed(data: bytes | np.ndarray, fmt: str = "") -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` payload (JPEG, PNG, ...) to a uint8 grey image.

    Args:
        data: the compressed bytes.
        fmt: the message's ``format`` field (informational; OpenCV sniffs the codec).

    Raises:
        ImageError: empty or undecodable data.
    """
    try:
        buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    except (TypeError, ValueError) as err:
        raise ImageError(f"compressed image data is not a byte buffer: {err}") from None
    if buf.size == 0:
        raise ImageError("compressed image is empty")
    try:
        img = cv2.imdecode(np.ascontiguousarray(buf.reshape(-1).view(np.uint8)),
                           cv2.IMREAD_GRAYSCALE)
    except cv2.error as err:  # e.g. a header claiming more pixels than OpenCV allows
        raise ImageError(f"cannot decode compressed image ({buf.size} bytes): "
                         f"{str(err).strip().splitlines()[-1]}") from None
    if img is None:
        kind = f" {fmt}" if fmt else ""
        raise ImageError(f"cannot decode compressed{kind} image ({buf.size} bytes)")
    check_pixel_budget(img.shape[1], img.shape[0])
    return img
