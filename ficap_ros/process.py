"""Settings of this process for long runs of the pipeline: the allocator keeps freed large
blocks (``keep_freed_memory``), and the start-up's objects leave the garbage collector's full
collections (``freeze_start_up``). The replay's processes and the node use them; no result depends
on them.
"""

from __future__ import annotations

import sys

__all__ = ["keep_freed_memory", "freeze_start_up"]


def keep_freed_memory() -> bool:
    """Let this process's allocator keep freed large blocks for reuse (glibc ``mallopt``; a
    no-op returning False elsewhere). For processes of our own that run the pipeline over many
    frames: the command's, its workers.

    Every frame allocates and frees the same few MB of large buffers (the JPEG payload, the
    decoded image, the refinement's sample grids). glibc's defaults hand large freed blocks back
    to the system (blocks above its mmap threshold unmapped, the heap's top trimmed), and the next
    frame faults the pages in again. Here blocks up to 8 MB are served from the heap, its top is
    trimmed only past 64 MB free and grown 16 MB at a time: far fewer page faults for the same
    peak memory (docs/benchmarks.md). The labels do not depend on it.
    """
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    m_trim_threshold, m_top_pad, m_mmap_threshold = -1, -2, -3  # <malloc.h>
    # Each call returns 1 on success (musl's stub: 0).
    return all([mallopt(m_mmap_threshold, 8 << 20) == 1, mallopt(m_trim_threshold, 64 << 20) == 1,
                mallopt(m_top_pad, 16 << 20) == 1])


def freeze_start_up() -> None:
    """Collect the garbage, then move every object this process still holds into the cyclic
    garbage collector's permanent generation (``gc.freeze``), out of its later collections. For
    processes of our own that run the pipeline over many frames (the replay's, its workers, the
    node), once their start-up (the imports, the recording opened, the kernels warmed) is done.

    The start-up's objects (modules, classes, functions, the message types' tables) live as long
    as the process; every full collection would walk them all
    again, the frames' allocations trigger such collections, and the interpreter makes one more
    when it exits. Only live objects are frozen (the collection first); they are still freed when
    their last reference goes, only a reference cycle among them stays. The labels do not depend
    on it.
    """
    import gc

    gc.collect()
    gc.freeze()
