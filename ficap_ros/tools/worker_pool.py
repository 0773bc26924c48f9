"""Worker processes for a recording's tracking segments (``replay.process_frames`` with ``jobs > 1``).

The main process reads the recording and hands whole segments, each with its look-ahead frame
(``replay.segments``), to spawned worker processes; the results come back in recording order. A
worker that dies is noticed and its segments run again once (``SegmentPool``).
"""

from __future__ import annotations

from typing import Any, Callable, Iterator

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.io.sources import RawFrame

__all__ = ["SegmentPool", "parallel_frames"]


class SegmentPool:
    """Worker processes for whole segments (``concurrent.futures.ProcessPoolExecutor``, spawned),
    which notice a worker that dies: its segments fail with ``BrokenProcessPool`` instead of never
    coming back. The pool is then replaced and every segment in flight submitted again, once: a
    segment whose worker dies a second time (a frame that kills its decoder, memory that runs
    out) fails the recording with one line (``WorkerError``). Results are the same whatever
    retries happened (tracking restarts at each segment's first frame).
    """

    def __init__(self, jobs: int, init: Callable[..., None], initargs: tuple,
                 segment_fn: Callable[..., list[Any]], counter: Any,
                 timing: CameraTiming | None = None) -> None:
        self.jobs, self.init, self.initargs, self.counter, self.timing = jobs, init, initargs, counter, timing
        self.segment_fn = segment_fn
        self.others: set[Any] = set()  # the children that are not the pool's workers
        self.pool = self._new()

    def _new(self) -> Any:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.others = set(multiprocessing.active_children())
        return ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=self.init, initargs=self.initargs)

    def submit(self, segment: tuple[list[RawFrame], RawFrame | None]) -> Any:
        """Run ``segment`` in a worker. Workers are started by the submits, with SIGINT ignored
        from their first instruction: Ctrl-C reaches the whole process group and only this
        process must handle it (stop the pool, print one line); a worker still importing numpy
        when it comes has not run its initializer yet (an ignored signal stays ignored across
        exec, and Python keeps it so)."""
        import signal
        import threading

        raws, lookahead = segment
        if threading.current_thread() is not threading.main_thread():
            return self.pool.submit(self.segment_fn, raws, self.timing, lookahead)
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            return self.pool.submit(self.segment_fn, raws, self.timing, lookahead)
        finally:
            signal.signal(signal.SIGINT, previous)

    def restart(self, pending: list[list[Any]], done: int) -> None:
        """A worker died: a new pool, every segment in flight submitted again (each
        ``[segment, future, attempts]``), the progress counter back to the frames delivered."""
        from ficap_ros.errors import WorkerError

        self.stop()
        for item in pending:
            if item[2] >= 1:
                first, last = item[0][0][0].index, item[0][0][-1].index
                raise WorkerError(f"a worker process died twice on frames {first}-{last} "
                                  "(killed, out of memory or crashed in a native library)")
        with self.counter.get_lock():
            self.counter.value = done
        self.pool = self._new()
        for item in pending:
            item[1], item[2] = self.submit(item[0]), item[2] + 1

    def stop(self) -> None:
        """Cancel what waits and end the workers now (a segment in progress is not waited for).
        ``ProcessPoolExecutor`` has no public way to end running workers before Python 3.14: its
        workers are this process's children that were not there when the pool was made
        (``multiprocessing.active_children``)."""
        import multiprocessing

        processes = [p for p in multiprocessing.active_children() if p not in self.others]
        self.pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(timeout=5.0)


def parallel_frames(it: Iterator[tuple[list[RawFrame], RawFrame | None]], jobs: int,
                    init: Callable[..., None], initargs: tuple, segment_fn: Callable[..., list[Any]],
                    counter: Any, on_progress: Callable[[int], None] | None,
                    timing: CameraTiming | None) -> Iterator[Any]:
    """The segments of ``it`` (each with its look-ahead frame) through ``segment_fn(raws, timing,
    lookahead)`` in ``jobs`` worker processes started with ``init(*initargs)``, their results in
    order (``SegmentPool``); ``counter``: the workers' shared count of frames done, passed to
    ``on_progress`` while waiting."""
    from concurrent.futures import BrokenExecutor
    from concurrent.futures import TimeoutError as FutureTimeout

    pool = SegmentPool(jobs, init, initargs, segment_fn, counter, timing)
    done = 0
    try:
        # Bounded look-ahead: one segment per worker in flight plus one, in order, so the bag is
        # never read into memory ahead of the workers.
        pending: list[list[Any]] = []
        while True:
            while len(pending) < jobs + 1:
                segment = next(it, None)
                if segment is None:
                    break
                pending.append([segment, pool.submit(segment), 0])
            if not pending:
                break
            try:
                while True:
                    try:
                        frames = pending[0][1].result(timeout=0.1)
                        break
                    except FutureTimeout:
                        if on_progress is not None:
                            on_progress(counter.value)
            except BrokenExecutor:
                pool.restart(pending, done)
                continue
            pending.pop(0)
            done += len(frames)
            if on_progress is not None:
                on_progress(counter.value)
            yield from frames
    finally:
        pool.stop()
