"""A fleet's progress: one tqdm bar over every recording's frames (frames/s, ETA), recordings
done in its postfix; off a terminal (a log) a plain line every 30 s instead of redraws.
"""

from __future__ import annotations

import threading
from typing import Any, Iterable, Iterator

__all__ = ["FleetProgress"]


class _LogLines:
    """A stream for tqdm off a terminal: each redraw (``\\r`` + the bar) becomes a line of its own,
    so a log holds one line per update instead of one endless line of carriage returns."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> None:
        for piece in text.replace("\r", "\n").split("\n"):
            if piece.strip():
                self._stream.write(piece.rstrip() + "\n")

    def flush(self) -> None:
        self._stream.flush()


class FleetProgress:
    """tqdm over the fleet's frames (frames/s, ETA), recordings done in the postfix."""

    def __init__(self, total_frames: int, recordings: int, done: int, failed: int,
                 enabled: bool, stream: Any = None) -> None:
        self._lock = threading.Lock()
        self._recordings, self._done, self._failed = recordings, done, failed
        self._bar = None
        if enabled:
            import sys

            from tqdm import tqdm

            # A fleet runs for hours, often into a log: there a plain line every 30 s (and one
            # at the end), not silence and not a line redrawn with carriage returns.
            stream = sys.stderr if stream is None else stream
            self._tty = stream.isatty()
            self._bar = tqdm(total=total_frames, unit="frame", desc="fleet", dynamic_ncols=True,
                             file=stream if self._tty else _LogLines(stream),
                             ascii=not self._tty, mininterval=0.5 if self._tty else 30.0,
                             smoothing=0.05)
            self._postfix()

    def _postfix(self) -> None:
        if self._bar is not None:
            text = f"{self._done}/{self._recordings} recordings"
            # Off a terminal a recording done waits for the next 30 s line.
            self._bar.set_postfix_str(text + (f", {self._failed} failed" if self._failed else ""),
                                      refresh=self._tty)

    def counted(self, frames: Iterable[Any]) -> Iterator[Any]:
        for item in frames:
            if self._bar is not None:
                with self._lock:
                    self._bar.update(1)
            yield item

    def recording_done(self, status: str) -> None:
        with self._lock:
            self._done += 1
            self._failed += status == "failed"
            self._postfix()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
