"""Where tasks run: in this process, in local threads or processes, or on dask.

All executors offer the same small interface (:class:`Executor`): ``submit`` a
picklable function call, ``wait`` for the first of several futures to finish,
and ``close``. The runner never depends on which one it has; since every task
is a pure function of its inputs, settings and seed, products are bitwise
identical whatever the executor.

``make_executor(spec)`` understands

* ``None`` or ``"threads"``: a thread pool on this machine (the default);
* ``"processes"``: a process pool (forkserver/spawn start, no server);
* ``"serial"``: run each task in the calling thread when submitted;
* ``"tcp://host:port"`` (or any dask address): an existing
  dask.distributed scheduler. Workers must see the work directory at the same
  path (a shared file system) and have mavispm installed;
* a ``distributed.Client`` instance.
"""

from __future__ import annotations

import abc
import concurrent.futures as cf
import multiprocessing
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from mavispm.core.cores import usable_cores
from mavispm.core.errors import ConfigError

if TYPE_CHECKING:
    import distributed

__all__ = [
    "DaskExecutor",
    "Executor",
    "PoolExecutor",
    "SerialExecutor",
    "default_workers",
    "make_executor",
]

LOCAL_KINDS = ("threads", "processes", "serial")


class Executor(abc.ABC):
    """Interface of the runner's executors."""

    name = "executor"

    @abc.abstractmethod
    def submit(self, fn: Callable, *args):
        """Start ``fn(*args)``; return a future.

        Parameters
        ----------
        fn : callable
            A picklable function (a process pool or dask pickles it).
        *args
            Its arguments.

        Returns
        -------
        concurrent.futures.Future or distributed.Future
            The running call.
        """

    def wait(self, futures: Iterable) -> tuple[set, set]:
        """Block until at least one future is done.

        Parameters
        ----------
        futures : iterable of futures
            Futures returned by :meth:`submit`.

        Returns
        -------
        done, not_done : set
            The finished futures and the others.
        """
        return cf.wait(list(futures), return_when=cf.FIRST_COMPLETED)

    @staticmethod
    def outcome(future: cf.Future):
        """The future's result (re-raising the task's exception).

        Parameters
        ----------
        future : future
            A finished future of this executor.

        Returns
        -------
        object
            What the task returned.
        """
        return future.result()

    def close(self) -> None:  # noqa: B027 - nothing to release by default
        """Release workers and connections."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class SerialExecutor(Executor):
    """Runs each task immediately in the calling thread."""

    name = "serial"

    def submit(self, fn: Callable, *args):
        """Run ``fn(*args)`` now, in the calling thread.

        Parameters
        ----------
        fn : callable
            The function.
        *args
            Its arguments.

        Returns
        -------
        concurrent.futures.Future
            A finished future holding the result or the exception (KeyboardInterrupt and
            SystemExit propagate at once).
        """
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:  # delivered through the future like a pool would
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            fut.set_exception(exc)
        return fut


class PoolExecutor(Executor):
    """A ``concurrent.futures`` thread or process pool on this machine.

    Parameters
    ----------
    kind : {"threads", "processes"}
        Pool type; processes start by forkserver where available, else spawn.
    workers : int
        Pool size (>= 1).
    """

    def __init__(self, kind: str, workers: int):
        self.name = f"{kind}({workers})"
        if kind == "threads":
            self._pool = cf.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mavispm")
        else:
            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
            self._pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx)

    def submit(self, fn: Callable, *args):
        """Start ``fn(*args)`` in the pool.

        Parameters
        ----------
        fn : callable
            The function (picklable for a process pool).
        *args
            Its arguments.

        Returns
        -------
        concurrent.futures.Future
            The running call.
        """
        return self._pool.submit(fn, *args)

    def close(self):
        """Shut the pool down, cancelling tasks not yet started and waiting for running ones."""
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(Executor):
    """Tasks on a dask.distributed cluster.

    Parameters
    ----------
    client_or_address : distributed.Client or str
        A connected client, or a scheduler address such as ``tcp://host:8786``.
    timeout : float
        Seconds to wait for the scheduler before giving up with a clear error.
    """

    def __init__(self, client_or_address, timeout: float = 20.0):
        import distributed

        self._own = not isinstance(client_or_address, distributed.Client)
        if self._own:
            try:
                self.client = distributed.Client(client_or_address, timeout=timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ConfigError(
                    f"cannot connect to the dask scheduler {client_or_address!r} ({exc}); "
                    "expected the address of a running scheduler, e.g. tcp://host:8786",
                    key="--scheduler",
                ) from None
        else:
            self.client = client_or_address
        self.name = f"dask({self.client.scheduler.address})"

    def submit(self, fn: Callable, *args):
        # pure=False: each call is a task of its own even with equal arguments.
        """Start ``fn(*args)`` on the cluster (each call its own task, even with equal arguments).

        Parameters
        ----------
        fn : callable
            A picklable function.
        *args
            Its arguments.

        Returns
        -------
        distributed.Future
            The running call.
        """
        return self.client.submit(fn, *args, pure=False)

    def wait(self, futures: Iterable):
        """Block until at least one future is done.

        Parameters
        ----------
        futures : iterable of distributed.Future
            Futures returned by :meth:`submit`.

        Returns
        -------
        done, not_done : set
            The finished futures and the others.
        """
        import distributed

        done, not_done = distributed.wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done), set(not_done)

    def close(self):
        """Close the client when this executor opened it (a client passed in stays open)."""
        if self._own:
            self.client.close()


def default_workers() -> int:
    """Number of CPUs available to this process (:func:`~mavispm.core.cores.usable_cores`)."""
    return usable_cores()


def make_executor(
    spec: str | distributed.Client | None = None, workers: int = 0, timeout: float = 20.0
) -> Executor:
    """Build an executor from a ``--scheduler`` value (see module docstring).

    Parameters
    ----------
    spec : str, distributed.Client or None
    workers : int
        Pool size for local pools (0 = number of CPUs).
    timeout : float
        Seconds to wait for a dask scheduler [s].

    Raises
    ------
    ConfigError
        For an unknown specification or an unreachable scheduler.
    """
    if spec is None:
        spec = "threads"
    if not isinstance(spec, str):
        return DaskExecutor(spec)
    if spec == "serial":
        return SerialExecutor()
    if spec in ("threads", "processes"):
        return PoolExecutor(spec, workers or default_workers())
    if "://" in spec or ":" in spec:
        return DaskExecutor(spec, timeout=timeout)
    raise ConfigError(
        f"unknown scheduler {spec!r}; expected one of {list(LOCAL_KINDS)} or a dask "
        "scheduler address such as tcp://host:8786",
        key="--scheduler",
    )
