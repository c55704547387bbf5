"""Chunks of stars on a thread pool (the ``threads`` knob of the ``stars`` stage).

The fast engine (:func:`~mavispm.measure.stars.batched_fit.fit_stars`), the neighbour
marginalisation of its errors and the ePSF error model work in chunks of ``chunk``
stars. The chunks that are independent (one colour of a sweep, the uncertainties at
the solution) run on :class:`ChunkPool`; its :meth:`ChunkPool.map` returns their
results in chunk order, and every sum that reaches a result (the model image's
deposits, the neighbours' Fisher terms) is taken by the caller in that order, on one
thread. The chunking is the ``chunk`` knob's, whatever the thread count: the results
are the same bit for bit on any number of threads. Most of a chunk's time is in
compiled kernels and numpy calls that release the GIL (the ePSF stamps and the
normal equations, the batched inverses, the gathers).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from mavispm.core.cores import usable_cores

__all__ = ["ChunkPool", "resolve_threads"]

T = TypeVar("T")
R = TypeVar("R")


def resolve_threads(requested: int) -> int:
    """Threads for the chunk pools: ``requested``, or every core this process may use.

    Parameters
    ----------
    requested : int
        The ``threads`` knob: a count (>= 1) as it is; 0: automatic, the cores this
        process may run on (:func:`~mavispm.core.cores.usable_cores`).

    Returns
    -------
    int
        At least 1.
    """
    requested = int(requested)
    if requested < 0:
        raise ValueError(f"threads must be >= 0 (0: automatic), got {requested}")
    if requested:
        return requested
    return usable_cores()


class ChunkPool:
    """A lazily started thread pool that maps a function over chunks, in order.

    Parameters
    ----------
    threads : int
        Worker threads (after :func:`resolve_threads`); 1: everything on the caller's
        thread, no pool.
    """

    def __init__(self, threads: int = 1):
        self.threads = max(int(threads), 1)
        self._pool: ThreadPoolExecutor | None = None

    def map(self, fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
        """``[fn(item) for item in items]``, the items spread over the threads.

        With one thread, or one item, on the caller's thread. An exception in ``fn``
        is raised here (after the items already started have finished).
        """
        items = list(items)
        if self.threads == 1 or len(items) < 2:
            return [fn(item) for item in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(
                max_workers=self.threads, thread_name_prefix="mavispm-chunks"
            )
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        """Stop the worker threads (a later :meth:`map` starts new ones)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> ChunkPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
