"""ficap_ros.ros.mailbox: the newest item wins; replaced items are counted."""

from __future__ import annotations

import threading

from ficap_ros.ros.mailbox import Mailbox


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


def test_serve_hands_items_on_and_survives_a_failing_one() -> None:
    box = Mailbox()
    handled: list = []
    errors: list = []

    def handle(item: int) -> None:
        if item == 2:
            raise ValueError("bad frame")
        handled.append(item)
        if item == 3:
            box.close()

    worker = threading.Thread(target=lambda: box.serve(handle, lambda i, e: errors.append((i, str(e)))))
    worker.start()
    for item in (1, 2, 3):
        box.put(item)
        while box.counts()[0] == item and box._item is not None:  # wait until taken
            threading.Event().wait(0.001)
    worker.join(5.0)
    assert not worker.is_alive()
    assert handled == [1, 3] and errors == [(2, "bad frame")]
