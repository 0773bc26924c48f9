"""ficap_ros.mailbox: the newest item wins; replaced items are counted."""

from __future__ import annotations

import threading

from ficap_ros.mailbox import Mailbox


def test_newest_wins_and_drops_are_counted() -> None:
    box = Mailbox()
    box.put(1)
    box.put(2)
    assert box.take(0.0) == (True, 2) and box.counts() == (2, 1)
    assert box.take(0.0) == (True, None)
    taken: list = []
    worker = threading.Thread(target=lambda: taken.append(box.take(5.0)))
    worker.start()
    box.put(3)
    worker.join(5.0)
    assert taken == [(True, 3)]
    box.close()
    assert box.take(0.0)[0] is False
