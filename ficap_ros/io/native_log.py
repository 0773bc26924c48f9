"""Messages that C libraries print straight to stderr (libjpeg, libpng, FFmpeg): per call, or
throttled.

OpenCV's decoders let libjpeg print "Corrupt JPEG data: ..." on file descriptor 2 for a damaged
frame, libpng its warnings, and FFmpeg "[mjpeg @ 0x...] ..." lines; ``cv2.setLogLevel`` does not
reach them, and no OpenCV call returns them. ``call_capturing_stderr`` gives one call's lines to
its caller (the image decoder reads libjpeg's verdict on each frame that way).
``ThrottledStderr`` puts a pipe on file descriptor 2 for its lifetime: a thread forwards every
line to the real stderr unchanged, except those libraries' lines, which go to ``emit`` at most
once per ``throttle_s`` per kind, with the number held back. The CLI emits them as
``ficap: warning: ...``; the node through its logger.
"""

from __future__ import annotations

import os
import re
import sys
import threading
import time
from typing import Any, Callable

__all__ = ["ThrottledStderr", "LIBRARY_LINE", "call_capturing_stderr"]

#: Lines of the C libraries under OpenCV (libjpeg, libpng, FFmpeg): at the start of a line.
LIBRARY_LINE = re.compile(
    rb"^(Corrupt JPEG data|Premature end of JPEG|Invalid SOS|Bogus |Unsupported marker|"
    rb"JPEG datastream|Not a JPEG|Warning: unknown JFIF|libpng (warning|error)|"
    rb"\[[\w ,./-]+ @ 0x[0-9a-fA-F]+\])")


_PIECE = re.compile(rb"(\r|\n)")

#: The capture pipe of this process: (pid, read end, write end); a forked child makes its own.
_CAPTURE: tuple[int, int, int] | None = None
_CAPTURE_LOCK = threading.Lock()


def _capture_pipe() -> tuple[int, int]:
    """This process's capture pipe: non-blocking at both ends (a writer that fills it loses its
    text rather than waiting on a reader that waits on the call), 1 MiB deep."""
    global _CAPTURE
    if _CAPTURE is None or _CAPTURE[0] != os.getpid():
        import fcntl

        read_fd, write_fd = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        try:
            fcntl.fcntl(write_fd, fcntl.F_SETPIPE_SZ, 1 << 20)
        except OSError:
            pass  # the default depth (64 KiB) then
        _CAPTURE = (os.getpid(), read_fd, write_fd)
    return _CAPTURE[1], _CAPTURE[2]


def call_capturing_stderr(fn: Callable[..., Any], *args: Any) -> tuple[Any, bytes]:
    """``fn(*args)`` with file descriptor 2 on a pipe for its duration: (its result, what was
    written to fd 2 meanwhile).

    What the C libraries under OpenCV print about one call (libjpeg's "Corrupt JPEG data" for
    the image it decodes) is then known per call, not only on the terminal. The swap is process
    wide, so calls are serialised (a lock) and anything another thread printed meanwhile is in
    the bytes returned: the caller passes on what is not its own (``os.write(2, ...)``). Costs a
    few system calls. Without a file descriptor 2 the call runs as it is.
    """
    with _CAPTURE_LOCK:
        read_fd, write_fd = _capture_pipe()
        try:
            saved = os.dup(2)
        except OSError:
            return fn(*args), b""
        try:
            os.dup2(write_fd, 2)
            try:
                result = fn(*args)
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
        chunks = []
        while True:
            try:
                chunk = os.read(read_fd, 1 << 16)
            except BlockingIOError:
                break
            if not chunk:
                break
            chunks.append(chunk)
    return result, b"".join(chunks)


class ThrottledStderr:
    """Context manager: C-library lines on fd 2 through ``emit``, throttled; the rest unchanged.

    Args:
        emit: receives one line (without newline) per kind and ``throttle_s``.
        throttle_s: least interval between two lines of one kind.
    """

    def __init__(self, emit: Callable[[str], None] | None = None, throttle_s: float = 5.0) -> None:
        self.throttle_s = float(throttle_s)
        self._emit = emit
        self._saved = self._saved_fd = -1
        self._read_fd = -1
        self._thread: threading.Thread | None = None
        self._last: dict[bytes, float] = {}
        self._held: dict[bytes, int] = {}

    def _default_emit(self, text: str) -> None:
        self._write(f"ficap: warning: {text}\n".encode(errors="replace"))

    def _write(self, data: bytes) -> None:
        try:
            os.write(self._saved_fd, data)
        except OSError:
            pass  # the real stderr is gone (closed pipe): nothing left to tell

    def __enter__(self) -> ThrottledStderr:
        try:
            sys.stderr.flush()
            self._saved = self._saved_fd = os.dup(2)
            if os.isatty(2):
                # A terminal stays a terminal (progress bars draw only on one): a pseudo-terminal
                # of the same size, raw so that bytes pass unchanged.
                import fcntl
                import termios
                import tty

                self._read_fd, write_fd = os.openpty()
                tty.setraw(write_fd)
                size = fcntl.ioctl(self._saved, termios.TIOCGWINSZ, b"\0" * 8)
                fcntl.ioctl(write_fd, termios.TIOCSWINSZ, size)
            else:
                self._read_fd, write_fd = os.pipe()
            os.dup2(write_fd, 2)
            os.close(write_fd)
        except OSError:
            self._saved = -1  # no usable fd 2 (a daemon): leave stderr alone
            return self
        self._thread = threading.Thread(target=self._pump, name="ficap-stderr", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved < 0:
            return
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os.dup2(self._saved, 2)  # closes the pipe's last write end held here: the pump ends
        if self._thread is not None:
            self._thread.join(timeout=2.0)  # worker processes may still hold a write end
        self._flush_held()
        if self._thread is None or not self._thread.is_alive():
            os.close(self._saved)  # else the pump still forwards a child's last lines to it
        self._saved = -1

    def _pump(self) -> None:
        buffer = b""
        while True:
            try:
                chunk = os.read(self._read_fd, 65536)
            except OSError:  # EIO: the pseudo-terminal's last writer closed it
                chunk = b""
            if not chunk:
                break
            buffer += chunk
            # Pieces end at \n or \r (a progress bar redraws its line after \r): each is
            # passed on, or throttled when it is a library's line, as soon as it is complete.
            parts = _PIECE.split(buffer)
            buffer = parts.pop()
            for text, end in zip(parts[0::2], parts[1::2]):
                self._line(text, end)
        if buffer:
            self._line(buffer, b"\n")
        os.close(self._read_fd)

    def _line(self, line: bytes, end: bytes = b"\n") -> None:
        match = LIBRARY_LINE.match(line) if end == b"\n" else None
        if match is None:
            self._write(line + end)
            return
        kind = re.sub(rb"0x[0-9a-fA-F]+|\d+", b"#", line)[:40]
        now = time.monotonic()
        if now - self._last.get(kind, -1e9) < self.throttle_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            return
        self._last[kind] = now
        held = self._held.pop(kind, 0)
        text = line.decode(errors="replace").strip()
        if held:
            text += f" ({held} more like it in the last {self.throttle_s:g} s)"
        (self._emit or self._default_emit)(text)

    def _flush_held(self) -> None:
        # At exit the caller's logger may be gone (the node's context is shut down): plain stderr.
        for kind, held in sorted(self._held.items()):
            if held:
                self._default_emit(
                    f"{kind.decode(errors='replace').strip()}... ({held} more held back)")
        self._held.clear()
