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

:func:`release_pages` returns the pages of an array the caller is done with to the
kernel at once (``madvise(MADV_DONTNEED)``), e.g. behind the write of a large array to a
file (:func:`mavispm.core.products.write_product`'s ``release``): the file's page cache
then takes those just-freed pages instead of fresh ones.
"""

from __future__ import annotations

__all__ = [
    "ARENA_MAX",
    "MMAP_THRESHOLD",
    "TRIM_THRESHOLD",
    "keep_freed_memory",
    "owns_memory",
    "release_pages",
]

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


#: ``madvise`` advice: drop the pages; the range reads as zeros afterwards (Linux).
_MADV_DONTNEED = 4

_madvise = None


def _load_madvise():
    global _madvise
    if _madvise is None:
        import ctypes
        import sys

        fn = False
        if sys.platform.startswith("linux"):  # MADV_DONTNEED zero-fills only on Linux
            try:
                fn = ctypes.CDLL(None, use_errno=True).madvise
                fn.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
                fn.restype = ctypes.c_int
            except (OSError, AttributeError):
                fn = False
        _madvise = fn
    return _madvise


def owns_memory(arr) -> bool:
    """Whether ``arr``'s memory is a writeable, C-contiguous block of a numpy array.

    Its ``base`` chain ends in an ndarray that owns its data (not a ``bytes`` object, a
    file map or another buffer), so dropping its pages (:func:`release_pages`) can only
    change numpy arrays.
    """
    import numpy as np

    if not isinstance(arr, np.ndarray) or not arr.flags.c_contiguous or not arr.flags.writeable:
        return False
    a = arr
    while isinstance(a, np.ndarray) and not a.flags.owndata:
        a = a.base
    return isinstance(a, np.ndarray) and a.flags.owndata and not isinstance(a, np.memmap)


def release_pages(arr, start: int, stop: int) -> int:
    """Return the memory pages lying wholly inside bytes ``[start, stop)`` of ``arr`` to the kernel.

    ``madvise(MADV_DONTNEED)``: the pages go back to the kernel's free lists at once
    (glibc would keep a freed heap block, and the rest of ``arr`` still holds the
    mapping); those bytes of ``arr`` (and of every array sharing its memory) read as
    zeros afterwards. The caller must be done with them; ``arr`` must pass
    :func:`owns_memory`. Partial pages at either end are left alone.

    Parameters
    ----------
    arr : ndarray
        C-contiguous, see :func:`owns_memory`.
    start, stop : int
        Byte offsets into ``arr``'s data.

    Returns
    -------
    int
        Bytes released (0: none, or no ``madvise``).
    """
    import mmap

    fn = _load_madvise()
    if not fn:
        return 0
    if not owns_memory(arr):
        raise ValueError("release_pages needs a writeable C-contiguous array owning its memory")
    start, stop = max(int(start), 0), min(int(stop), arr.nbytes)
    page = mmap.PAGESIZE
    base = arr.ctypes.data
    lo = -(-(base + start) // page) * page
    hi = (base + stop) // page * page
    if hi <= lo:
        return 0
    return hi - lo if fn(lo, hi - lo, _MADV_DONTNEED) == 0 else 0
