"""Decode ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` payloads to grey arrays.

Pure numpy/OpenCV: no ROS import, so the bag tools, the node (through ``io.messages``) and tests share
one decoder. Encodings are the ``sensor_msgs/image_encodings`` names.

JPEGs go through ``simplejpeg`` (libjpeg-turbo, an optional dependency) where it is installed and
the stream is a plain 8-bit Huffman-coded frame (``_fast_decodable``): it gives the very pixels
``cv2.imdecode`` gives, at less cost. Anything else (PNG, other JPEG codings, an Exif orientation,
any libjpeg warning or error, ``simplejpeg`` absent) is decoded by OpenCV as below, so the pixels
and the verdict on a damaged image do not depend on which decoder is installed.

Memory is checked before it is spent: an image's size comes from its message fields or from its
compressed header (``compressed_size``: a JPEG's frame header, a PNG's IHDR) and is held against
the pixel budget (``check_pixel_budget``) before anything is decoded.

A damaged JPEG is not an image. libjpeg decodes corrupt entropy-coded data anyway (it only warns,
"Corrupt JPEG data: ..."), and what it makes of it is wrong by whole 8x8 blocks from the damage
on: a tag there can be found, decoded and fitted with small residuals at the wrong place, and no
covariance built from the residuals can tell (the frame's bounds would claim a tenth of a degree
for a pose degrees off). No widening of the bounds is honest either: how far the corners moved is
not knowable from the frame. So the decoder's own warnings are read for every frame
(``native_log.call_capturing_stderr`` around the decode: a few system calls) and a JPEG libjpeg
warns about is refused as damaged (``DamagedImageError``): the frame is labelled with the reason
and without a pose, and the node publishes no pose for it.
"""

from __future__ import annotations

import functools
import os
import re
import struct
from collections.abc import Iterator
from types import ModuleType

import cv2
import numpy as np

from ficap_ros.errors import ConfigError, ImageError
from ficap_ros.io.native_log import call_capturing_stderr

__all__ = ["ENCODINGS", "encoding_layout", "decode_image", "decode_compressed", "jpeg_decoder", "compressed_size",
           "check_compressed",
           "check_pixel_budget", "max_pixels", "DEFAULT_MAX_PIXELS", "DamagedImageError"]


class DamagedImageError(ImageError):
    """A compressed image whose decoder reported corrupt data (it decodes, but wrongly)."""

#: Largest image accepted, in pixels (``FICAP_MAX_PIXELS`` overrides it). 40 MP holds every
#: camera a cap is filmed with (1080p is 2.1 MP, 4K 8.3 MP, a 12 MP phone photo); detection's
#: working memory grows with the pixel count, so a larger photo is refused before it costs
#: gigabytes.
DEFAULT_MAX_PIXELS = 40_000_000


def max_pixels() -> int:
    """The pixel budget: ``FICAP_MAX_PIXELS`` (a number of pixels, ``40000000`` or ``4e7``) when
    set, else the default.

    Raises:
        ConfigError: ``FICAP_MAX_PIXELS`` is set but not a finite number >= 1.
    """
    text = os.environ.get("FICAP_MAX_PIXELS", "").strip()
    if not text:
        return DEFAULT_MAX_PIXELS
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 1 and value < float("inf")):
        raise ConfigError(f"FICAP_MAX_PIXELS={text!r} is not a number of pixels (e.g. 40000000)")
    return int(value)


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


#: JPEG markers that start a frame header (SOF0-3, 5-7, 9-11, 13-15) and carry no length.
_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
_STANDALONE = frozenset({0x01, *range(0xD0, 0xD9)})
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _jpeg_segments(head: memoryview) -> Iterator[tuple[int, int, int]]:
    """(marker, byte position, segment length) of each marker segment of a JPEG from its start
    of image up to its first scan: the start of scan (``0xDA``) or an end of image (``0xD9``)
    comes last, with length 0. Stops early where the data is cut short.

    Raises:
        ImageError: a byte where a marker belongs is not one.
    """
    pos = 2
    while pos + 4 <= len(head):
        if head[pos] != 0xFF:
            raise ImageError(f"JPEG header is damaged (no marker at byte {pos})")
        marker = head[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _STANDALONE:
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, or the scan data
            yield marker, pos, 0
            return
        (length,) = struct.unpack(">H", head[pos + 2: pos + 4])
        yield marker, pos, length
        pos += 2 + length


def compressed_size(data: bytes | np.ndarray) -> tuple[str, int, int]:
    """(format, width, height) of a compressed image from its header, without decoding it: a
    JPEG's frame header (SOFn), a PNG's IHDR chunk.

    Raises:
        ImageError: neither JPEG nor PNG, or a header cut short or without a size.
    """
    head = memoryview(data).cast("B") if not isinstance(data, np.ndarray) else \
        memoryview(np.ascontiguousarray(data).view(np.uint8).reshape(-1))
    if bytes(head[:8]) == _PNG_SIGNATURE:
        if len(head) < 24 or bytes(head[12:16]) != b"IHDR":
            raise ImageError("PNG image without its header (IHDR)")
        width, height = struct.unpack(">II", head[16:24])
        return "png", width, height
    if bytes(head[:2]) != b"\xff\xd8":
        raise ImageError("compressed image is neither JPEG nor PNG")
    for marker, pos, length in _jpeg_segments(head):
        if marker in _SOF:
            if pos + 9 > len(head) or length < 7:
                break
            height, width = struct.unpack(">HH", head[pos + 5: pos + 9])
            if not (width and height):
                raise ImageError(f"JPEG frame header gives no size ({width}x{height})")
            return "jpeg", width, height
    raise ImageError("JPEG image without a frame header (cut short or damaged)")


def check_compressed(data: bytes | np.ndarray) -> tuple[str, int, int]:
    """``compressed_size`` held against the pixel budget: what ``decode_compressed`` checks
    before decoding (and the node before it queues a frame).

    Raises:
        ImageError: no usable header, or a size above the budget.
    """
    try:
        kind, width, height = compressed_size(data)
    except ImageError as err:
        raise ImageError(f"cannot decode compressed image ({len(data)} bytes): {err}") from None
    check_pixel_budget(width, height, what=f"{kind.upper()} image")
    return kind, width, height


#: libjpeg's warnings that the data it decodes is corrupt (the decoded pixels are not the
#: image's); its other warnings (an unknown JFIF revision, a bad ICC profile) leave them intact.
_DAMAGE = re.compile(rb"^(Corrupt JPEG data(?!: bad ICC marker)|Premature end of JPEG file|"
                     rb"Invalid SOS parameters|Inconsistent progression|"
                     rb"Application transferred too many scanlines).*$", re.M)


def _damage(messages: bytes) -> str:
    """The first damage warning among a decode's stderr bytes, without its counts ('' when
    none); every other line is passed on to fd 2 as it came."""
    found = _DAMAGE.search(messages)
    rest = _DAMAGE.sub(b"", messages).strip(b"\n")
    if rest:
        try:
            os.write(2, rest + b"\n")
        except OSError:
            pass
    if found is None:
        return ""
    text = found.group(0).decode(errors="replace").strip()
    return re.sub(r"\s*\b(0x[0-9a-fA-F]+|\d+)\b", "", text)


#: Frame headers the fast decoder takes: Huffman-coded baseline, extended sequential and
#: progressive JPEG (the encodings cameras and ``cv2.imencode`` write).
_FAST_SOF = frozenset({0xC0, 0xC1, 0xC2})


@functools.cache
def _simplejpeg() -> ModuleType | None:
    """The ``simplejpeg`` module, or None where it is not installed (the cv2 decoder then)."""
    try:
        import simplejpeg
    except ImportError:
        return None
    return simplejpeg


def _fast_decodable(head: np.ndarray) -> bool:
    """Whether a JPEG is one ``simplejpeg`` decodes to the same grey pixels as ``cv2.imdecode``:
    a ``_FAST_SOF`` frame of 8-bit samples in one or three components (``simplejpeg`` greys a
    four-component CMYK/YCCK image by a formula of its own), whose headers reach its first scan,
    without an Exif segment (``cv2.imdecode`` turns an image by its Exif orientation,
    ``simplejpeg`` does not)."""
    view = memoryview(head)
    frame = False
    try:
        for marker, pos, length in _jpeg_segments(view):
            if marker == 0xDA:
                return frame
            if marker in _SOF:
                if marker not in _FAST_SOF or pos + 10 > len(view) or length < 8:
                    return False
                frame = view[pos + 4] == 8 and view[pos + 9] in (1, 3)
            elif marker == 0xE1 and bytes(view[pos + 4: pos + 8]) == b"Exif":
                return False
    except ImageError:
        pass  # a damaged header: the cv2 decoder says what is wrong with it
    return False


def jpeg_decoder(buf: np.ndarray) -> str:
    """Which decoder ``decode_compressed`` gives the JPEG ``buf`` (uint8): ``"simplejpeg"`` where
    it is installed and the stream is ``_fast_decodable``, else ``"cv2.imdecode"``."""
    return "simplejpeg" if _simplejpeg() is not None and _fast_decodable(buf) else "cv2.imdecode"


def _decode_jpeg_fast(buf: np.ndarray) -> np.ndarray | None:
    """``buf`` (a JPEG) decoded to grey by ``simplejpeg``'s libjpeg-turbo, pixel for pixel what
    ``cv2.imdecode(buf, IMREAD_GRAYSCALE)`` gives, at less cost (no stderr capture: it stops on
    libjpeg's first warning instead of printing it). None where ``simplejpeg`` is absent, the
    stream is not ``_fast_decodable``, or libjpeg reported anything (an error or any warning):
    the cv2 decoder then decodes it and gives its verdict on damage.
    """
    if jpeg_decoder(buf) != "simplejpeg":
        return None
    codec = _simplejpeg()
    try:
        img = codec.decode_jpeg(buf, colorspace="GRAY", fastdct=False, fastupsample=False,
                                strict=True)
    except (ValueError, RuntimeError):  # libjpeg's error or warning; no decoder instance
        return None
    return img.reshape(img.shape[0], img.shape[1])


def decode_compressed(data: bytes | np.ndarray, fmt: str = "") -> np.ndarray:
    """Decode a ``sensor_msgs/CompressedImage`` payload (JPEG or PNG) to a uint8 grey image.

    The size in its header is held against the pixel budget first; a JPEG is decoded by
    ``simplejpeg`` where it decodes it as OpenCV does, else by OpenCV, whose warnings are read
    (see the module docstring): a damaged JPEG is refused.

    Args:
        data: the compressed bytes.
        fmt: the message's ``format`` field (informational; the header says the codec).

    Raises:
        DamagedImageError: libjpeg reported corrupt data. ImageError: empty, neither JPEG nor
            PNG, above the pixel budget, or undecodable data.
    """
    try:
        buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    except (TypeError, ValueError) as err:
        raise ImageError(f"compressed image data is not a byte buffer: {err}") from None
    if buf.size == 0:
        raise ImageError("compressed image is empty")
    buf = np.ascontiguousarray(buf.reshape(-1).view(np.uint8))
    kind, _, _ = check_compressed(buf)
    img = _decode_jpeg_fast(buf) if kind == "jpeg" else None
    if img is not None:
        return img
    try:
        img, messages = call_capturing_stderr(cv2.imdecode, buf, cv2.IMREAD_GRAYSCALE)
    except cv2.error as err:  # e.g. a header claiming more pixels than OpenCV allows
        raise ImageError(f"cannot decode compressed image ({buf.size} bytes): "
                         f"{str(err).strip().splitlines()[-1]}") from None
    damage = _damage(messages)
    if img is None:
        what = f" {fmt}" if fmt else ""
        raise ImageError(f"cannot decode compressed{what} image ({buf.size} bytes)"
                         + (f": {damage}" if damage else ""))
    if damage:
        raise DamagedImageError(f"damaged JPEG ({damage})")
    check_pixel_budget(img.shape[1], img.shape[0])
    return img
