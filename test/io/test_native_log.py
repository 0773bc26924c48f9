"""ficap_ros.io.native_log: C libraries' lines on file descriptor 2 throttled to one per kind and
interval (with the count held back), every other line passed on unchanged."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_libjpeg_messages_are_throttled() -> None:
    """libjpeg's line per damaged frame (printed by OpenCV calls outside the decoder's capture)
    reaches the terminal once per interval, with the count held back; through
    ``decode_compressed`` each is its frame's own reason instead and never printed."""
    code = (
        "import numpy as np, cv2\n"
        "from ficap_ros.errors import ImageError\n"
        "from ficap_ros.io.native_log import ThrottledStderr\n"
        "from ficap_ros.io.image_codec import decode_compressed\n"
        "img = np.random.default_rng(0).integers(0, 255, (120, 160), dtype=np.uint8)\n"
        "jpg = cv2.imencode('.jpg', img)[1].tobytes()\n"
        "bad = jpg[: len(jpg) // 2] + bytes(50) + jpg[-2:]\n"
        "with ThrottledStderr():\n"
        "    for _ in range(500):\n"
        "        cv2.imdecode(np.frombuffer(bad, np.uint8), cv2.IMREAD_GRAYSCALE)\n"
        "    reasons = set()\n"
        "    for _ in range(50):\n"
        "        try:\n"
        "            decode_compressed(bad)\n"
        "        except ImageError as err:\n"
        "            reasons.add(str(err))\n"
        "    print(sorted(reasons))\n"
        "    import sys; print('other text passes', file=sys.stderr)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120, cwd=ROOT)
    lines = res.stderr.decode().splitlines()
    assert res.returncode == 0, lines
    assert "other text passes" in lines
    jpeg = [ln for ln in lines if "Corrupt JPEG data" in ln]
    assert 1 <= len(jpeg) <= 3, lines
    assert all(ln.startswith("ficap: warning:") for ln in jpeg)
    assert "held back" in jpeg[-1] or "more like it" in jpeg[-1]
    held = int(jpeg[-1].split("(")[-1].split()[0])
    assert held <= 499  # only the OpenCV calls' lines: the decoder's own were captured
    assert res.stdout.decode().strip() == \
        "['damaged JPEG (Corrupt JPEG data: premature end of data segment)']"


def test_a_calls_messages_are_captured_and_the_rest_passes(capfd: pytest.CaptureFixture[str]
                                                           ) -> None:
    """``call_capturing_stderr``: what fd 2 gets during the call is returned (C libraries write
    there directly), and fd 2 is itself again afterwards."""
    import os

    from ficap_ros.io.native_log import call_capturing_stderr

    result, captured = call_capturing_stderr(lambda: os.write(2, b"from the call\n") and 7)
    assert result == 7 and captured == b"from the call\n"
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"


def _write_fd2(text: str) -> None:
    import os

    os.write(2, text.encode())


def test_each_kind_once_then_held_and_counted_at_exit(capfd: pytest.CaptureFixture[str]) -> None:
    """In this process: the first line of each kind goes to ``emit``; the rest of that kind are
    held and counted once at exit; every other piece (a progress bar's \\r-ended redraws
    included) reaches fd 2 unchanged."""
    from ficap_ros.io.native_log import ThrottledStderr

    got: list[str] = []
    with ThrottledStderr(emit=got.append, throttle_s=3600.0):
        _write_fd2("".join(f"Corrupt JPEG data: {i} extraneous bytes before marker 0xd{i}\n"
                           for i in range(5)))
        _write_fd2("plain text\n[mjpeg @ 0x55d1c0] overread 8\nframes: 1/3\rframes: 2/3\r")
        _write_fd2("Corrupt JPEG data mid-line is text when the piece ends with a carriage\r")
        _write_fd2("libpng warning: iCCP: known incorrect sRGB profile\nno newline at the end")
    err = capfd.readouterr().err
    assert got == ["Corrupt JPEG data: 0 extraneous bytes before marker 0xd0",
                   "[mjpeg @ 0x55d1c0] overread 8",
                   "libpng warning: iCCP: known incorrect sRGB profile"]
    assert err.startswith("plain text\nframes: 1/3\rframes: 2/3\rCorrupt JPEG data mid-line")
    assert "no newline at the end\n" in err
    held = [ln for ln in err.splitlines() if ln.startswith("ficap: warning:")]
    assert held == ["ficap: warning: Corrupt JPEG data: # extraneous bytes be... (4 more held back)"]


def test_a_kind_speaks_again_after_its_interval_with_the_count(
        capfd: pytest.CaptureFixture[str]) -> None:
    import time

    from ficap_ros.io.native_log import ThrottledStderr

    got: list[str] = []
    with ThrottledStderr(emit=got.append, throttle_s=0.2):
        _write_fd2("Premature end of JPEG file\n" * 4)  # one piece: handled together
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.4)
        _write_fd2("Premature end of JPEG file\n")
    assert got == ["Premature end of JPEG file",
                   "Premature end of JPEG file (3 more like it in the last 0.2 s)"]
    assert capfd.readouterr().err == ""  # nothing held at exit
    with ThrottledStderr(emit=got.append, throttle_s=0.0):
        _write_fd2("Invalid SOS parameters for sequential JPEG\n" * 3)
    assert got[2:] == ["Invalid SOS parameters for sequential JPEG"] * 3
