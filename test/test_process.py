"""ficap_ros.process: the settings of a process that runs the pipeline for long."""

from __future__ import annotations


def test_keep_freed_memory_takes_on_glibc() -> None:
    """The allocator setting (process.keep_freed_memory): glibc takes it (this project's
    platform); elsewhere it says it did nothing, and the labels never depend on it."""
    import platform
    import sys

    from ficap_ros.process import keep_freed_memory

    expected = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert keep_freed_memory() is expected


def test_freeze_start_up_collects_then_takes_live_objects_out_of_collections() -> None:
    """process.freeze_start_up: a reference cycle nothing holds is collected, not frozen; what is
    alive leaves the collector's generations (gc.get_objects lists none of it); the collector
    still runs on what comes after."""
    import gc
    import weakref

    from ficap_ros.process import freeze_start_up

    class Node:
        pass

    garbage = Node()
    garbage.self = garbage  # a cycle: only the collector frees it
    gone = weakref.ref(garbage)
    del garbage
    alive = [[]]  # a container the collector tracks
    try:
        freeze_start_up()
        assert gone() is None
        assert gc.get_freeze_count() > 0 and gc.isenabled()
        later = [[]]
        tracked = {id(o) for o in gc.get_objects()}
        assert id(alive) not in tracked and id(later) in tracked
    finally:
        gc.unfreeze()  # the test process's objects back in the collections
