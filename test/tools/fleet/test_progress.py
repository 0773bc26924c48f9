"""ficap_ros.tools.fleet.progress: the fleet's bar, plain lines in a log and a redrawn bar on a
terminal."""

from __future__ import annotations

import io

from ficap_ros.tools.fleet.progress import FleetProgress


def test_fleet_progress_off_a_terminal_is_plain_lines() -> None:
    """A fleet's progress in a log: whole lines (a first one, then at most one per 30 s, and the
    last), never a line redrawn with carriage returns; on a terminal the bar redraws."""
    log = io.StringIO()
    bar = FleetProgress(60, 2, 0, 0, enabled=True, stream=log)
    for recording in range(2):
        list(bar.counted([None] * 30))
        bar.recording_done("done")
    bar.close()
    text = log.getvalue()
    assert "\r" not in text and text.endswith("\n"), repr(text)
    lines = text.splitlines()
    assert 2 <= len(lines) <= 3, lines  # the first, the last, and one more if a 30 s tick fell
    assert "60/60" in lines[-1] and "2/2 recordings" in lines[-1]

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    bar = FleetProgress(60, 2, 0, 0, enabled=True, stream=tty)
    list(bar.counted([None] * 60))
    bar.close()
    assert "\r" in tty.getvalue() and "60/60" in tty.getvalue()
