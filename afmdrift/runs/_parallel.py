"""Independent tasks of one command on this machine's cores, or on its Dask cluster.

``afmdrift diagnose`` re-runs the model online once per candidate effect; the
re-runs share nothing, so they run side by side. :class:`TaskPool` maps a
module-level function over a list of arguments:

* inside a Dask worker (``afmdrift batch --task diagnose``), as tasks of the
  cluster the worker belongs to (:func:`distributed.worker_client`; the
  calling task leaves the worker's thread pool while it waits, so the cluster
  runs the tasks on whichever workers are free);
* otherwise in the calling process and ``workers − 1`` more processes of
  this machine, started with the ``spawn`` method (a fresh interpreter: no
  fork of a process that holds BLAS, FFTW or Numba threads). The processes
  start when the pool is entered and import the package while the caller
  does its first, serial part. They take the tasks from the front of the
  list, the caller from the back, until none is left;
* with ``workers=1``, or where no process can be started (a daemonic
  process), in the calling process, one task after the other.

Results come back in the order of the arguments and are the same on every
path (the same functions on the same data). A task that raises raises in the
caller; a worker process that dies (killed, out of memory) is logged and its
tasks are done in the calling process, so nothing is lost.

**Spawned processes and scripts.** ``spawn`` starts each process by importing
the caller's ``__main__`` script under another name. The ``afmdrift`` command
and ``python -m afmdrift`` are safe; a script of your own that uses
``workers > 1`` must keep its work under ``if __name__ == "__main__":``, as
for any Python multiprocessing. The library's own default is ``workers=1``.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import logging
import multiprocessing
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from afmdrift._cores import available_cores

__all__ = ["TaskPool", "available_cores", "dask_worker"]

log = logging.getLogger(__name__)

_A = TypeVar("_A")
_R = TypeVar("_R")

#: Thread counts a spawned worker starts with: the workers are the
#: parallelism, so a BLAS or OpenMP pool per worker would only oversubscribe.
_ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def dask_worker() -> Any | None:
    """The Dask worker running the calling task, or None outside a Dask task."""
    if "distributed" not in sys.modules:
        return None  # a Dask worker has imported it; importing it here costs 0.5 s
    try:
        from distributed import get_worker
    except ImportError:  # pragma: no cover - distributed is a dependency
        return None
    try:
        return get_worker()
    except ValueError:
        return None


def _ready(*_: object) -> int:
    """A worker process's first task: it has imported the package."""
    return os.getpid()


@contextlib.contextmanager
def _thread_limits() -> Iterator[None]:
    """The environment spawned processes inherit, one BLAS/OpenMP thread each."""
    saved = {k: os.environ.get(k) for k in _ONE_THREAD}
    os.environ.update(_ONE_THREAD)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class TaskPool:
    """Map a module-level function over arguments, in parallel where it can.

    Parameters
    ----------
    workers : int
        Processes on this machine, the caller included (``1``: in the calling
        process only). Ignored in a Dask worker, where the cluster's workers
        run the tasks.
    warm : callable, optional
        Run once in each process when it starts (compile kernels, import
        modules), so that the first real task does not pay for it.

    Use it as a context manager: entering starts the processes, leaving
    stops them.

    Raises
    ------
    ValueError
        ``workers`` < 1.
    """

    def __init__(self, workers: int = 1, *, warm: Callable[[], object] | None = None) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self._warm = warm
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._ready: list[concurrent.futures.Future[int]] = []
        self.where = "serial"
        """``"dask"``, ``"processes"`` or ``"serial"``: where :meth:`map` runs tasks."""

    def __enter__(self) -> TaskPool:
        if dask_worker() is not None:
            self.where = "dask"
        elif self.workers > 1 and not multiprocessing.current_process().daemon:
            ctx = multiprocessing.get_context("spawn")
            with _thread_limits():
                self._executor = concurrent.futures.ProcessPoolExecutor(
                    self.workers - 1, mp_context=ctx, initializer=self._warm
                )
                # Start every process now: they import while the caller works.
                self._ready = [self._executor.submit(_ready) for _ in range(self.workers - 1)]
            self.where = "processes"
        return self

    def wait_started(self, timeout_s: float = 60.0) -> None:
        """Block until every worker process has started (a no-op without them):
        before, :meth:`map` leaves the tasks to the caller."""
        concurrent.futures.wait(self._ready, timeout=timeout_s)

    def __exit__(self, *exc: object) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def map(self, fn: Callable[[_A], _R], items: Sequence[_A]) -> list[_R]:
        """``[fn(a) for a in items]``, the tasks side by side where the pool can.

        ``fn`` must be a module-level function and ``items`` picklable.
        """
        items = list(items)
        if len(items) <= 1 or self.where == "serial":
            return [fn(a) for a in items]
        if self.where == "dask":
            return self._map_dask(fn, items)
        return self._map_processes(fn, items)

    @staticmethod
    def _map_dask(fn: Callable[[_A], _R], items: list[_A]) -> list[_R]:
        from distributed import worker_client

        with worker_client() as client:
            futures = client.map(fn, items, pure=False)
            out: list[_R] = client.gather(futures)
        return out

    def _map_processes(self, fn: Callable[[_A], _R], items: list[_A]) -> list[_R]:
        """The processes take tasks from the front (one feeder thread each,
        waiting on its process), the caller from the back, until none is left.

        A feeder takes its first task only once its process has started
        (imported the package and run ``warm``): until then the caller takes
        the tasks, so a pool whose processes are still starting is never
        slower than the caller alone (a short record's two re-runs are done
        before a process on a busy machine has imported numpy)."""
        assert self._executor is not None
        executor = self._executor
        todo = collections.deque(range(len(items)))
        lock = threading.Lock()
        out: list[Any] = [None] * len(items)
        errors: dict[int, BaseException] = {}
        broken: list[BaseException] = []

        def take(front: bool) -> int | None:
            with lock:
                if not todo or errors:
                    return None
                return todo.popleft() if front else todo.pop()

        def feed(ready: concurrent.futures.Future[int] | None) -> None:
            while ready is not None and not ready.done():
                with lock:
                    if not todo or errors:
                        return
                concurrent.futures.wait([ready], timeout=0.02)
            while (i := take(front=True)) is not None:
                try:
                    out[i] = executor.submit(fn, items[i]).result()
                except concurrent.futures.process.BrokenProcessPool as err:
                    with lock:  # the caller does it
                        todo.appendleft(i)
                        broken.append(err)
                    return
                except BaseException as err:  # raised in the caller below
                    with lock:
                        errors[i] = err
                    return

        ready: list[concurrent.futures.Future[int] | None] = list(self._ready)
        ready += [None] * (self.workers - 1 - len(ready))
        feeders = [threading.Thread(target=feed, args=(r,), daemon=True) for r in ready]
        for t in feeders:
            t.start()
        while (i := take(front=False)) is not None:
            try:
                out[i] = fn(items[i])
            except BaseException as err:  # the feeders stop after their task
                with lock:
                    errors[i] = err
        for t in feeders:
            t.join()
        if errors:
            raise errors[min(errors)]
        if broken:
            self._stopped(broken[0])
        while todo:  # left by feeders that stopped after the caller's last task
            i = todo.popleft()
            out[i] = fn(items[i])
        return out

    def _stopped(self, err: BaseException) -> None:
        """Worker processes died: log it, and run every later task in the caller."""
        log.warning("worker processes stopped (%s); their tasks are done here", err)
        self.where = "serial"
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
