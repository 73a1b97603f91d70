"""Estimators fed in a forked second process beside the run.

On a cold kernel cache (the first ``ddfuse run`` after installing) the EKFs run their Python
reference path (``ddfuse.ekf_baseline.compiled.usable``), several times the compiled cost, while
the machine's second CPU is idle until the background build starts after the run. ``ddfuse run``
then feeds those filters in a child process, forked once they are built, from the child's own
decoding of the bag, while the main process feeds the others: the same measurements in the same
order reach every estimator (``ddfuse.estimation.runner.run`` in both), so the tracks are those
of one process.

Contract: the child returns its ``EstimatorRun``s (pickled through a pipe) and exits with
``os._exit`` (no atexit work of the parent's: the background build is the parent's alone). A
child that fails, dies or cannot be forked loses nothing: the parent's copies of those
estimators were never fed, and :meth:`SideRun.join` says so; the caller then feeds them itself.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import select
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass

from ddfuse.estimation.interrupts import held_signals, interrupt_name
from ddfuse.estimation.runner import EstimatorRun, RunResult, run

__all__ = ["SideResult", "SideRun", "cpus", "in_order", "run_split", "side_names"]


def cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


# Relative cost of feeding an estimator, in units of the smoother's (measured on
# rl_husky_gps.bag: an EKF on its Python reference path 2.5-2.7 s, the smoother 1.3 s, a batch
# that shares the smoother's run 0.1-0.5 s, the side process's own decoding of the bag 0.9 s)
REFERENCE_COST = 2.0
SHARED_COST = 0.3
SIDE_OVERHEAD = 0.7


def _cost(e) -> float:
    if getattr(e, "reference", False):
        return REFERENCE_COST
    return SHARED_COST if getattr(e, "source", None) is not None else 1.0


def side_names(ests: dict) -> list[str]:
    """The estimators of ``ests`` to feed in a side process: of those on their Python reference
    path (``reference`` true: their kernels are not in numba's cache), the last ones for as long
    as moving one shortens the longer of the two processes (by ``_cost``; the side process also
    decodes the bag); none without a second CPU or ``os.fork``."""
    if cpus() < 2 or not hasattr(os, "fork"):
        return []
    main = sum(_cost(e) for e in ests.values())
    side_cost, side = SIDE_OVERHEAD, []
    for n in reversed([n for n, e in ests.items() if getattr(e, "reference", False)]):
        c = _cost(ests[n])
        if max(side_cost + c, main - c) >= max(side_cost if side else 0.0, main):
            break
        side_cost, main = side_cost + c, main - c
        side.append(n)
    return side[::-1]


def in_order(names, *runs: dict[str, EstimatorRun]) -> dict[str, EstimatorRun]:
    """The runs of ``runs`` (dicts by track name) in the order of the estimators ``names``,
    each one's lagged track after it."""
    got = {k: v for r in runs for k, v in r.items()}
    out = {k: got[k] for n in names for k in (n, f"{n}_lagged") if k in got}
    return out | {k: v for k, v in got.items() if k not in out}


@dataclass
class SideResult:
    """What the child fed: its runs (by track name, the lagged ones included) and its
    ``RunResult.interrupted``; ``error`` (one line) instead when it gave nothing back."""

    runs: dict[str, EstimatorRun]
    interrupted: str | None = None
    error: str | None = None


class SideRun:
    """Feed ``ests`` (built, never fed) with ``runner.run`` in a forked child, on the stream
    ``open_stream()`` makes there (its own file handles: a descriptor shared across a fork
    shares its offset), withholding ``holdout``'s fixes as the main run does. Ctrl-C reaches the
    child as it reaches the parent (one process group): it stops feeding and returns what it
    had, as ``run(interruptible=True)``."""

    def __init__(self, open_stream: Callable[[], object], ests: dict,
                 holdout: str | None = None) -> None:
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            os.close(r)
            _child(w, open_stream, ests, holdout)
        os.close(w)
        self.pid, self._r = pid, r

    def join(self) -> SideResult:
        """Wait for the child and read what it fed. A Ctrl-C (or a SIGTERM taken as one) while
        waiting is held, not raised, and passed on to the child, which then returns what it
        had; ``interrupted`` says so. The wait polls (``select``, 0.1 s) so that a signal the
        kernel hands to another thread of this process (a progress bar's) is seen by the main
        thread's handler, which runs only between Python steps: a blocking read would not be
        woken by it."""
        chunks: list[bytes] = []
        forwarded: int | None = None
        with held_signals() as held:
            while True:
                if held and forwarded is None:
                    forwarded = held[0]
                    _signal(self.pid, forwarded)
                ready, _, _ = select.select([self._r], [], [], 0.1)
                if not ready:
                    continue
                b = os.read(self._r, 1 << 20)
                if not b:
                    break
                chunks.append(b)
        os.close(self._r)
        status = _wait(self.pid)
        try:
            out = pickle.loads(b"".join(chunks)) if chunks else None
        except Exception as e:  # a child killed mid-write
            out = None
            status = f"{status}; its results unreadable ({type(e).__name__})"
        if not isinstance(out, SideResult):
            out = SideResult({}, error=f"the side process ended ({status}) with no results")
        if forwarded is not None and out.interrupted is None:
            out.interrupted = f"interrupted ({interrupt_name(forwarded)}) in the side process"
        return out


def run_split(open_stream: Callable[[], object], stream, ests: dict, side: list[str], *,
              holdout: str | None = None, spill_dir=None, observer=None, progress=None,
              notice: Callable[[str], None] | None = None
              ) -> tuple[RunResult, tuple[str, ...], float]:
    """``runner.run`` of ``ests`` on ``stream`` (interruptible, with ``observer``, ``progress``
    and ``spill_dir`` as ``run`` takes them), the estimators ``side`` fed meanwhile in a forked
    process on ``open_stream()``; those the side process could not feed are fed here after the
    others (``notice`` is told), unless the run was interrupted. Returns the result (its runs in
    ``ests``'s order), the estimators that were fed beside, and the time (s) spent waiting for
    them after this process's loop."""
    child = None
    if side:
        try:
            child = SideRun(open_stream, {n: ests[n] for n in side}, holdout)
        except OSError as e:
            if notice is not None:
                notice(f"{', '.join(side)} fed in this process: no side process ({e})")
    main = {n: e for n, e in ests.items() if child is None or n not in side}
    result = run(stream, main, holdout=holdout, progress=progress, interruptible=True,
                 observers=() if observer is None else (observer,), spill_dir=spill_dir)
    if child is None:
        return result, (), 0.0
    t_wait = time.perf_counter()
    got = child.join()
    wait = time.perf_counter() - t_wait
    if got.error is None:
        result.runs = in_order(ests, result.runs, got.runs)
        result.interrupted = result.interrupted or got.interrupted
        return result, tuple(side), wait
    if result.interrupted is not None:  # the run was stopped: not started again for them
        result.interrupted = (f"{result.interrupted}; {', '.join(side)} not run (their side "
                              f"process: {got.error})")
        return result, (), 0.0
    if notice is not None:
        notice(f"the side process feeding {', '.join(side)} failed ({got.error}): they are "
               "fed here now")
    again = run(open_stream(), {n: ests[n] for n in side}, holdout=holdout, interruptible=True)
    result.runs = in_order(ests, result.runs, again.runs)
    result.interrupted = result.interrupted or again.interrupted
    return result, (), 0.0


def _child(w: int, open_stream, ests: dict, holdout) -> None:
    code = 0
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            res = run(open_stream(), ests, holdout=holdout, interruptible=True)
            out = SideResult(res.runs, res.interrupted)
        except BaseException as e:
            out = SideResult({}, error=f"{type(e).__name__}: {e}")
        data = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
        with os.fdopen(w, "wb") as f:
            f.write(data)
    except BaseException:
        code = 1
    finally:
        os._exit(code)


def _signal(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


def _wait(pid: int) -> str:
    while True:
        try:
            _, st = os.waitpid(pid, 0)
            break
        except KeyboardInterrupt:
            _signal(pid, signal.SIGINT)
        except ChildProcessError:
            return "already reaped"
    if os.WIFSIGNALED(st):
        return f"killed by signal {os.WTERMSIG(st)}"
    return f"exit status {os.WEXITSTATUS(st)}"
