"""A one-slot mailbox between a subscription callback and a worker thread: the newest item wins,
replaced items are counted as dropped, and the callback never waits for the worker."""

from __future__ import annotations

import threading
from typing import Any, Callable

__all__ = ["Mailbox"]


class Mailbox:
    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._item: Any = None
        self._open = True
        self.received = 0  # items put
        self.dropped = 0  # items replaced before the worker took them

    def put(self, item: Any) -> None:
        with self._cv:
            self.received += 1
            if self._item is not None:  # an unprocessed older item: newest wins
                self.dropped += 1
            self._item = item
            self._cv.notify()

    def take(self, timeout_s: float = 0.5) -> tuple[bool, Any]:
        """(open, item): waits up to ``timeout_s`` for an item (None: none came)."""
        with self._cv:
            self._cv.wait_for(lambda: self._item is not None or not self._open, timeout=timeout_s)
            item, self._item = self._item, None
            return self._open, item

    def serve(self, handle: Callable[[Any], None],
              on_error: Callable[[Any, Exception], None]) -> None:
        """The worker's loop: hand each item taken to ``handle`` until the mailbox is closed; an
        exception goes to ``on_error`` with its item and the loop goes on (one bad frame must not
        stop a live node)."""
        while True:
            running, item = self.take()
            if not running:
                return
            if item is None:
                continue
            try:
                handle(item)
            except Exception as err:  # noqa: BLE001 - reported by on_error, the loop goes on
                on_error(item, err)

    def counts(self) -> tuple[int, int]:
        """(received, dropped) so far, read together."""
        with self._cv:
            return self.received, self.dropped

    def close(self) -> None:
        with self._cv:
            self._open = False
            self._cv.notify_all()
