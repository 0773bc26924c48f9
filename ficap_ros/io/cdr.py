"""Serialising the few label messages labels.mcap writes on every frame straight to CDR bytes.

rosbags' ``serialize_cdr`` takes a message object, so a frame's detections would need an object
per tag and per point, and its named numbers one per name, to be turned into bytes at once. The
writers here produce the same bytes (plain CDR, little endian, as rosbags writes them for
rosbag2) from arrays and strings. Each message serialiser is held equal to rosbags' output by the
tests, byte for byte.

CDR, as used here: a 4-byte encapsulation header, then each field aligned to its own size (4
for 32-bit numbers and lengths, 8 for float64) counted from the end of that header; strings as
their length with the NUL, the UTF-8 bytes, the NUL; sequences as their length, then the items.
"""

from __future__ import annotations

import struct
from typing import Iterable

import numpy as np

__all__ = ["CdrWriter", "header_cdr", "named_values_cdr"]

#: The encapsulation header: plain CDR, little endian.
_LITTLE_ENDIAN = b"\x00\x01\x00\x00"
_U32 = struct.Struct("<I")


class CdrWriter:
    """Bytes of one CDR message, appended field by field (see the module docstring)."""

    def __init__(self) -> None:
        self.buf = bytearray(_LITTLE_ENDIAN)

    def offset(self) -> int:
        """Bytes written after the encapsulation header (what alignment counts from)."""
        return len(self.buf) - len(_LITTLE_ENDIAN)

    def align(self, size: int) -> None:
        """Zero bytes up to the next multiple of ``size`` after the encapsulation header."""
        pad = -(len(self.buf) - len(_LITTLE_ENDIAN)) % size
        if pad:
            self.buf += bytes(pad)

    def u32(self, value: int) -> None:
        """A ``uint32`` (also a string's or a sequence's length)."""
        self.align(4)
        self.buf += _U32.pack(value)

    def string(self, text: str) -> None:
        """A ``string`` field."""
        data = text.encode()
        self.u32(len(data) + 1)
        self.buf += data
        self.buf += b"\0"

    def strings(self, texts: Iterable[str]) -> None:
        """A ``string[]`` field."""
        items = [text.encode() for text in texts]
        self.u32(len(items))
        buf = self.buf
        for data in items:  # each one 4-aligned after the one before (a hot loop: inlined)
            pad = -(len(buf) - len(_LITTLE_ENDIAN)) % 4
            if pad:
                buf += bytes(pad)
            buf += _U32.pack(len(data) + 1)
            buf += data
            buf += b"\0"

    def raw(self, data: bytes, align: int) -> None:
        """Bytes already laid out (a fixed block of fields), after aligning to ``align``."""
        self.align(align)
        self.buf += data

    def float64s(self, values: np.ndarray) -> None:
        """A ``float64[]`` field: its length, then the values (aligned to 8 when there are any)."""
        v = np.ascontiguousarray(values, dtype="<f8").reshape(-1)
        self.u32(len(v))
        if len(v):
            self.raw(v.tobytes(), 8)

    def data(self) -> bytes:
        """The message's bytes."""
        return bytes(self.buf)


def header_cdr(out: CdrWriter, stamp_ns: int, frame_id: str) -> None:
    """A ``std_msgs/Header``: stamp (seconds, nanoseconds) from integer nanoseconds, frame id."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    out.align(4)
    out.buf += struct.pack("<iI", sec, nanosec)
    out.string(frame_id)


def named_values_cdr(stamp_ns: int, frame_id: str, names: Iterable[str],
                     values: np.ndarray) -> bytes:
    """``messages.named_values``'s ``sensor_msgs/JointState`` serialised: ``name`` and ``position``
    from ``names`` and ``values`` (float64), ``velocity`` and ``effort`` empty."""
    out = CdrWriter()
    header_cdr(out, stamp_ns, frame_id)
    out.strings(names)
    out.float64s(values)
    out.float64s(np.zeros(0))
    out.float64s(np.zeros(0))
    return out.data()
