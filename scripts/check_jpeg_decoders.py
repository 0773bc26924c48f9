"""Whether the JPEG frames of recordings decode to the same grey pixels through simplejpeg as
through OpenCV.

    python scripts/check_jpeg_decoders.py RECORDING [RECORDING ...]

Every CompressedImage frame of each recording (a bag folder, ``.mcap`` or ``.db3``) is decoded by
``image_codec.decode_compressed`` and by ``cv2.imdecode(..., IMREAD_GRAYSCALE)``; one line per
recording gives the frames, how many took the simplejpeg path, and how many differ (with the
largest absolute difference). Exits 0 when every frame is identical, 1 when one differs, 2 when
simplejpeg is not installed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from ficap_ros.io.image_codec import _decode_jpeg_fast, _simplejpeg, decode_compressed
from ficap_ros.io.sources import open_frames


def check(path: Path) -> tuple[int, int, int, int]:
    """(frames, decoded by simplejpeg, frames that differ, largest |difference|) of one recording."""
    frames = fast = differ = worst = 0
    for raw in open_frames(path).raw_frames():
        if raw.kind != "compressed" or raw.error:
            continue
        buf = np.ascontiguousarray(np.frombuffer(raw.payload, np.uint8))
        frames += 1
        fast += _decode_jpeg_fast(buf) is not None
        ours = decode_compressed(raw.payload, raw.encoding)
        ref = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        if ours.shape != ref.shape:
            differ += 1
            worst = 255
            continue
        diff = int(np.abs(ours.astype(np.int16) - ref).max())
        differ += diff > 0
        worst = max(worst, diff)
    return frames, fast, differ, worst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recordings", nargs="+", type=Path)
    args = parser.parse_args(argv)
    if _simplejpeg() is None:
        print("simplejpeg is not installed: every frame decodes through OpenCV")
        return 2
    failed = False
    for path in args.recordings:
        frames, fast, differ, worst = check(path)
        failed |= differ > 0
        print(f"{path.name}: {frames} JPEG frames, {fast} through simplejpeg, "
              f"{differ} differ (max |diff| {worst})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
