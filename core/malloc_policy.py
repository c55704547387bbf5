"""glibc's allocator keeps the memory a ``mavispm`` process frees, for its next arrays.

A ``simulate frames`` process allocates and frees full-frame and batch arrays of 5-60 MB
(halo transforms, stamp buffers, noise output). By default glibc serves blocks above a
moving threshold (128 KB rising to the largest block freed, at most 32 MB) by ``mmap``
and returns them with ``munmap``, trims the top of its heap once more than twice that
threshold is free, and gives each worker thread an arena of its own. Every block the
process gets again from the kernel is faulted in and zeroed afresh: on the benchmark's
machine (a VM whose freed memory the host reclaims) that zeroing is most of the
process's system time, and it scatters from 0.3 to 1 s between identical runs.

:func:`keep_freed_memory` fixes the ``mmap`` threshold at glibc's largest (32 MB: the
frame and other larger arrays are still mapped, and unmapped when freed), keeps freed
memory in the heap (no trimming below 1 GiB free) and serves the worker threads from
the main arena, so the buffers of one stage are reused by the next.

Only the ``mavispm`` program calls it (``workflows/cli.py``: ``main()`` reading
``sys.argv``), for the commands it was measured on (``KEEP_FREED_MEMORY``: ``simulate
frames``; ``measure stars`` ran at the same CPU with a 7 % higher peak RSS, so it is left
out); library callers keep their allocator as it is. Without glibc's ``mallopt``
(another C library) it does nothing.
"""

from __future__ import annotations

__all__ = ["ARENA_MAX", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

#: ``mallopt`` parameters (glibc's ``malloc.h``).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8

#: Blocks at least this large are still ``mmap``-ed (glibc's largest allowed threshold).
MMAP_THRESHOLD = 32 << 20

#: Free memory at the top of the heap kept before glibc trims it.
TRIM_THRESHOLD = 1 << 30

#: Arenas: the worker threads share the main thread's heap (and its freed blocks).
ARENA_MAX = 1

_applied = False


def keep_freed_memory() -> bool:
    """Set glibc's allocator to keep and reuse freed memory (see the module docstring).

    Call it early (before threads allocate); once per process.

    Returns
    -------
    bool
        Whether the settings were applied now (False: already applied, or no glibc
        ``mallopt``).
    """
    global _applied
    if _applied:
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc: nothing to set
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success; an out-of-range value leaves that setting alone
    done = [
        mallopt(_M_ARENA_MAX, ARENA_MAX),
        mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
    ]
    _applied = all(done)
    return _applied
