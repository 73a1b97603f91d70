"""Where fan-out work runs: a picklable function mapped over tasks, results as they complete.

``Engine(scheduler, jobs)`` picks the backend once: a running Dask scheduler
(``Client(address)``, ``scheduler`` given), a Dask ``LocalCluster`` of ``jobs`` worker
processes (Dask installed, the ``scale`` extra), the standard library's ProcessPoolExecutor
(Dask not installed), or this process alone (``jobs`` 1, no scheduler). ``Engine.backend`` says
which in one line. ``Engine.map(fn, tasks)`` yields one ``Outcome`` per task in the order the
tasks complete, so a caller keeps what it needs of each result and drops the rest.
``Engine.shared(fn, obj)`` is for many rounds of small tasks over one large object (tuning's
runs over one stream): ``obj`` goes to each worker once (forked into local processes, scattered
to Dask workers) and ``fn(obj, task)`` runs there, the results in the tasks' order.

Every backend runs the same ``fn`` on the same task, so a deterministic ``fn`` gives the same
result on any of them (tests/test_fleet_cluster.py checks it to the last digit). A task whose
worker dies is run once more (Dask: ``retries=1`` and, on the local cluster, the scheduler's
``allowed-failures`` 1; the process pool: a new pool), then its Outcome carries the error.
docs/design/fleet.md says why and what a cluster needs.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ddfuse.estimation.errors import DdfuseError

__all__ = ["CONNECT_TIMEOUT_S", "SCALE_HINT", "Engine", "Outcome", "SharedMap", "TaskFailed",
           "dask_available"]

CONNECT_TIMEOUT_S = 10.0  # waiting for a --scheduler to answer before giving up
SCALE_HINT = "pip install 'ddfuse[scale]'"
RETRIES = 1  # a task whose worker died (or that raised) runs this many more times


@dataclass(frozen=True)
class Outcome:
    """One task's end: its position ``index`` in the tasks given, ``fn``'s return ``value``
    (None on error) and ``error``, one line (None on success)."""

    index: int
    value: Any = None
    error: str | None = None


class TaskFailed(DdfuseError):
    """A task of ``SharedMap.map`` failed on every try (one line: which and why)."""


def dask_available() -> bool:
    """Whether ``distributed`` (the ``scale`` extra) can be imported."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


class Engine:
    """A context manager over the chosen backend: ``with Engine(address, jobs) as eng:
    for o in eng.map(fn, tasks): ...``.

    ``scheduler``: a Dask scheduler address (``tcp://host:8786``) or None; ``jobs``: worker
    processes when no scheduler is given (default: the CPU count); ``timeout``: s to wait for
    the scheduler; ``fork``: without a scheduler, the local processes are the standard
    library's, forked from this one, even with Dask installed (for ``shared`` work over an
    object this process holds: a fork hands it over as it is, where a LocalCluster would start
    in seconds and be sent it). DdfuseError, one line, for an unreachable scheduler or
    ``scheduler`` without Dask installed."""

    def __init__(self, scheduler: str | None = None, jobs: int | None = None,
                 timeout: float = CONNECT_TIMEOUT_S, fork: bool = False) -> None:
        self.scheduler = scheduler
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self.timeout = timeout
        self.client = None
        self.cluster = None
        self._quiet = None
        self.fork = fork
        self.kind = ("dask" if scheduler else "serial" if self.jobs == 1
                     else "dask-local" if dask_available() and not fork else "processes")
        if scheduler and not dask_available():
            raise DdfuseError(f"--scheduler {scheduler}: needs Dask; {SCALE_HINT}")

    @property
    def backend(self) -> str:
        """What runs the tasks, in one line (for the terminal)."""
        if self.kind == "dask":
            n = len(self.client.scheduler_info().get("workers", {})) if self.client else 0
            return f"Dask scheduler {self.scheduler} ({n} workers)"
        if self.kind == "dask-local":
            return f"Dask LocalCluster, {self.jobs} worker processes"
        if self.kind == "processes" and self.fork:
            return f"local processes (standard library, {self.jobs}, forked from this one)"
        if self.kind == "processes":
            return (f"local processes (standard library, {self.jobs}; Dask not installed: "
                    f"{SCALE_HINT})")
        return "this process (--jobs 1)"

    def __enter__(self) -> Engine:
        if self.kind == "dask":
            self._connect()
        elif self.kind == "dask-local":
            import dask
            from distributed import Client, LocalCluster

            # Dask's INFO lines (scheduler start, workers joining, closing) reach the root
            # logger's handler: not ours to show; a task's failure is its Outcome
            dlog = logging.getLogger("distributed")
            self._quiet = (dlog, dlog.level)
            dlog.setLevel(logging.ERROR)

            # a worker that dies mid-task: its task is tried once more, then reported failed
            with dask.config.set({"distributed.scheduler.allowed-failures": RETRIES}):
                # no dashboard; its HTTP server (there without one) on a free port, not
                # 8787, which another cluster on the machine may hold
                self.cluster = LocalCluster(
                    n_workers=self.jobs, threads_per_worker=1, processes=True,
                    dashboard_address=None, host="127.0.0.1", silence_logs=logging.ERROR,
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
            self.client = Client(self.cluster)
        return self

    def _connect(self) -> None:
        from distributed import Client

        try:
            self.client = Client(self.scheduler, timeout=self.timeout)
        except (OSError, TimeoutError, ValueError) as e:
            raise DdfuseError(f"--scheduler {self.scheduler}: no Dask scheduler answered within "
                              f"{self.timeout:g} s ({_one_line(e)})") from None

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        if self._quiet is not None:
            self._quiet[0].setLevel(self._quiet[1])
        self.client = self.cluster = self._quiet = None

    def map(self, fn: Callable[[Any], Any], tasks: Iterable[Any]) -> Iterator[Outcome]:
        """``fn(task)`` for every task, an Outcome each as it completes (any order). ``fn``
        and the tasks must pickle (a module-level function, plain data)."""
        tasks = list(tasks)
        if self.kind == "serial":
            yield from self._serial(fn, tasks)
        elif self.kind == "processes":
            yield from self._pool(fn, tasks)
        else:
            yield from self._dask(fn, tasks)

    @staticmethod
    def _serial(fn, tasks) -> Iterator[Outcome]:
        for i, t in enumerate(tasks):
            try:
                yield Outcome(i, fn(t))
            except Exception as e:  # noqa: BLE001 - one task's failure is its row
                yield Outcome(i, error=_one_line(e))

    def _dask(self, fn, tasks) -> Iterator[Outcome]:
        from distributed import as_completed

        futures = [self.client.submit(fn, t, pure=False, retries=RETRIES) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in as_completed(futures):
            i = index[fut.key]
            if fut.status == "finished":
                yield Outcome(i, fut.result())
            elif fut.status == "cancelled":
                yield Outcome(i, error="cancelled (the scheduler or the client went away)")
            else:  # 'error': fn raised, or its workers died more than allowed (KilledWorker)
                yield Outcome(i, error=_one_line(fut.exception()))
            fut.release()  # the driver keeps what it took from the result, not the result

    def _pool(self, fn, tasks) -> Iterator[Outcome]:
        from concurrent.futures import ProcessPoolExecutor, as_completed
        from concurrent.futures.process import BrokenProcessPool

        pending = dict(enumerate(tasks))
        tries = dict.fromkeys(pending, 0)
        while pending:
            # A worker that dies breaks the whole pool: every task still in it is charged one
            # try and the survivors go to a new pool.
            with ProcessPoolExecutor(max_workers=min(self.jobs, len(pending))) as pool:
                futs = {pool.submit(fn, t): i for i, t in pending.items()}
                for fut in as_completed(futs):
                    i = futs[fut]
                    try:
                        value = fut.result()
                    except BrokenProcessPool as e:
                        tries[i] += 1
                        if tries[i] > RETRIES:
                            del pending[i]
                            yield Outcome(i, error=f"worker process died ({_one_line(e)})")
                        continue
                    except Exception as e:  # noqa: BLE001 - one task's failure is its row
                        del pending[i]
                        yield Outcome(i, error=_one_line(e))
                        continue
                    del pending[i]
                    yield Outcome(i, value)

    def shared(self, fn: Callable[[Any, Any], Any], obj: Any) -> SharedMap:
        """A :class:`SharedMap` running ``fn(obj, task)`` on this engine's workers, ``obj``
        sent to each once; close it (or use it as a context manager) when done."""
        return SharedMap(self, fn, obj)


# On a worker: one task over a shared object at a time, as a worker thread of a user's
# multi-threaded Dask worker would otherwise change the object under another's feet
_SHARED_LOCK = threading.Lock()
_SHARED: tuple[Callable, Any] | None = None  # a forked pool worker's (fn, obj)


def _with_shared(fn, obj, task):
    with _SHARED_LOCK:
        return fn(obj, task)


def _set_forked(fn, obj) -> None:
    global _SHARED
    _SHARED = (fn, obj)


def _call_forked(task):
    return _with_shared(*_SHARED, task)


class SharedMap:
    """``fn(obj, task)`` for batches of tasks on an engine's workers, ``obj`` handed to each
    worker once: in this process (serial), forked into the standard library's pool (the pool
    kept for every batch), or scattered to every Dask worker (a LocalCluster's or a
    scheduler's). ``fn`` and the tasks must pickle on a Dask engine, ``obj`` too. ``obj``
    may be changed by ``fn``: each worker has its own copy, one task at a time."""

    def __init__(self, engine: Engine, fn: Callable[[Any, Any], Any], obj: Any) -> None:
        self.engine, self.fn, self.obj = engine, fn, obj
        self._pool = self._scattered = None
        if engine.kind == "processes":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            ctx = multiprocessing.get_context("fork" if engine.fork else None)
            self._pool = ProcessPoolExecutor(engine.jobs, mp_context=ctx,
                                             initializer=_set_forked, initargs=(fn, obj))
        elif engine.kind != "serial":
            self._scattered = engine.client.scatter(obj, broadcast=True, hash=False)

    def map(self, tasks: Iterable[Any]) -> list[Any]:
        """``fn(obj, task)`` for each task, in the tasks' order. On workers, TaskFailed (one
        line) for a task that raised or whose worker died (on Dask: on both tries); in this
        process (serial), ``fn``'s own exception."""
        tasks = list(tasks)
        if self._pool is not None:  # not retried: a worker that dies breaks the pool
            try:
                return list(self._pool.map(_call_forked, tasks))
            except Exception as e:  # noqa: BLE001 - one line, as on Dask
                raise TaskFailed(f"a task of {len(tasks)} failed on {self.engine.backend}: "
                                 f"{_one_line(e)}") from None
        if self._scattered is None:
            return [self.fn(self.obj, t) for t in tasks]
        client = self.engine.client
        futures = [client.submit(_with_shared, self.fn, self._scattered, t, pure=False,
                                 retries=RETRIES) for t in tasks]
        try:
            out = []
            for i, f in enumerate(futures):
                try:
                    out.append(f.result())
                except Exception as e:  # noqa: BLE001 - named with its task, one line
                    raise TaskFailed(f"task {i + 1} of {len(tasks)} failed on "
                                     f"{self.engine.backend}: {_one_line(e)}") from None
            return out
        finally:
            for f in futures:
                f.release()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
        if self._scattered is not None:
            self._scattered.release()
        self._pool = self._scattered = None

    def __enter__(self) -> SharedMap:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
