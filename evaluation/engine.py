"""Where fan-out work runs: a picklable function mapped over tasks, results as they complete.

``Engine(scheduler, jobs)`` picks the backend once: a running Dask scheduler
(``Client(address)``, ``scheduler`` given), a Dask ``LocalCluster`` of ``jobs`` worker
processes (Dask installed, the ``scale`` extra), the standard library's ProcessPoolExecutor
(Dask not installed), or this process alone (``jobs`` 1, no scheduler). ``Engine.backend`` says
which in one line. ``Engine.map(fn, tasks)`` yields one ``Outcome`` per task in the order the
tasks complete, so a caller keeps what it needs of each result and drops the rest.

Every backend runs the same ``fn`` on the same task, so a deterministic ``fn`` gives the same
result on any of them (tests/test_fleet_cluster.py checks it to the last digit). A task whose
worker dies is run once more (Dask: ``retries=1`` and, on the local cluster, the scheduler's
``allowed-failures`` 1; the process pool: a new pool), then its Outcome carries the error.
docs/design/fleet.md says why and what a cluster needs.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ddfuse.estimation.errors import DdfuseError

__all__ = ["CONNECT_TIMEOUT_S", "SCALE_HINT", "Engine", "Outcome", "dask_available"]

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
    the scheduler. DdfuseError, one line, for an unreachable scheduler or ``scheduler`` without
    Dask installed."""

    def __init__(self, scheduler: str | None = None, jobs: int | None = None,
                 timeout: float = CONNECT_TIMEOUT_S) -> None:
        self.scheduler = scheduler
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self.timeout = timeout
        self.client = None
        self.cluster = None
        self._quiet = None
        self.kind = ("dask" if scheduler else "serial" if self.jobs == 1
                     else "dask-local" if dask_available() else "processes")
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
