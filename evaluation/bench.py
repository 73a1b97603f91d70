"""``ddfuse bench``: decode time, and per estimator its wall time excluding decoding, real-time
factor, update latency percentiles and peak resident memory.

The latencies (``update_ms``, ms) are of the per-message ``process()`` calls. An offline
estimator (``offline``: the batch, whose track comes from ``final_estimates``) solves the whole
run once in ``finish()``; that time (``finish_s``, s) is in its ``runtime_s`` and in no
latency percentile.

Each estimator runs in its own child process (spawned, so nothing is shared with the parent),
which makes its peak RSS its own: the high-water mark ``VmHWM`` of the child's own address space
(/proc/self/status). Not ``ru_maxrss``: Linux carries that across the fork and exec that start
the child, so it would never be below the parent's RSS at that moment.
The bag is decoded as a stream while the estimator runs (``estimation.bags.BagStream``, ground
truth not kept), as ``ddfuse run`` does, so the peak is what the estimator itself holds on top
of the libraries; ``start_rss_mb`` is the peak once the stream is open and the estimator built
(libraries, the first seconds of data), before any measurement is fed.
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import time
from pathlib import Path

import numpy as np
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.runner import run


def peak_rss_mb() -> float:
    """This process's peak resident set size, MB: VmHWM from /proc/self/status on Linux, else
    ``ru_maxrss`` (see the module docstring)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    # Linux and most BSDs report ru_maxrss in KiB (macOS in bytes: rough there)
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _one(bag: str, cfg_path: str, name: str, lag: float | None, tracks: list[str] | None,
         conn) -> None:
    try:
        conn.send(_measure(bag, cfg_path, name, lag, tracks))
    except BagError as e:
        conn.send({"estimator": name, "fatal": str(e)})
    except Exception as e:  # reported by the parent, never a hang on the pipe
        conn.send({"estimator": name, "fatal": f"{type(e).__name__}: {e}"})
    finally:
        conn.close()


def _measure(bag: str, cfg_path: str, name: str, lag: float | None,
             tracks: list[str] | None) -> dict:
    from ddfuse.evaluation import estimators as registry

    cfg = load_config(cfg_path)
    stream = BagStream(bag, cfg, keep_truth=False).prime()
    est = registry.build(cfg, stream, [name], lag=lag or None, tracks=tracks)[name]
    lagged = getattr(est, "lagged_estimates", None)
    outputs = [name] + ([f"{name}_lagged"] if callable(lagged) and lagged() is not None else [])
    # An offline estimator (the batch) does its real work once, in finish(), which no update
    # latency covers: timed on its own here so that the report can say how much of est s it is.
    finish_s = [0.0]
    finish = est.finish

    def timed_finish() -> None:
        t = time.perf_counter()
        try:
            finish()
        finally:
            finish_s[0] += time.perf_counter() - t

    est.finish = timed_finish
    start_mb = peak_rss_mb()
    t1 = time.perf_counter()
    result = run(stream, {name: est})
    wall = time.perf_counter() - t1
    peak_mb = peak_rss_mb()  # before the statistics below make their own copies
    if stream.error is not None and not result.messages:
        raise BagError(stream.error)
    upd = result.runs[name].update_s
    runtime = result.runs[name].runtime_s
    return {
        "estimator": name, "outputs": outputs,
        "duration_s": stream.duration, "decode_s": stream.decode_s,
        "messages": result.messages,
        "wall_s": wall,  # decoding included: the stream is decoded as it is fed
        "runtime_s": runtime,  # in the estimator's calls alone, finish() included
        "finish_s": finish_s[0],  # in finish() alone: the batch's whole-run solve
        # its track is produced at the end (final_estimates), so update_ms is not its latency
        "offline": callable(getattr(est, "final_estimates", None)),
        "rtf": stream.duration / runtime if runtime > 0 else None,
        "update_ms": {"p50": 1e3 * float(np.percentile(upd, 50)),
                      "p99": 1e3 * float(np.percentile(upd, 99)),
                      "max": 1e3 * float(upd.max())} if len(upd) else None,
        "peak_rss_mb": peak_mb,
        "start_rss_mb": start_mb,
        "error": result.runs[name].error,
        "input_error": stream.error,
        "input_warnings": list(stream.warnings),  # the reader's (a topic mostly dropped)
    }


def bench_bag(bag: Path, cfg_path: Path, names: list[str] | None = None,
              lag: float | None = None) -> dict:
    """Benchmark every selected estimator on one bag, each in a fresh process. An estimator
    computes the output tracks named in ``names`` (default: all it gives; each row's
    ``outputs``): ``smoother`` alone is the filtered output, without the lagged one's
    covariances.

    A truncated or damaged bag is benchmarked on what can be read (as ``ddfuse run`` does);
    ``input_error`` then says why it stops early. A bag that cannot be used raises BagError."""
    from ddfuse.evaluation import estimators as registry

    cfg = load_config(cfg_path)
    chosen = registry.select(cfg, names)
    BagStream(bag, cfg).close()  # a bag that cannot be opened fails here, once, in one line
    ctx = mp.get_context("spawn")
    rows = []
    for name in chosen:
        # A pipe, not a Queue: a Queue's semaphores outlive an early exit (a resource_tracker
        # warning), and a pipe tells the parent when the child dies without a result.
        recv, send = ctx.Pipe(duplex=False)
        p = ctx.Process(target=_one, args=(str(bag), str(cfg_path), name, lag, names or None,
                                           send))
        p.start()
        send.close()  # the child's copy is the only one: its death ends recv() with EOFError
        try:
            rows.append(recv.recv())
        except EOFError:
            p.join()
            rows.append({"estimator": name, "fatal": f"{bag}: the benchmark process of "
                         f"{name} ended without a result (exit code {p.exitcode})"})
        finally:
            recv.close()
            p.join()
        if "fatal" in rows[-1]:
            raise BagError(rows[-1]["fatal"])
    decode = min(r["decode_s"] for r in rows) if rows else None
    duration = rows[0]["duration_s"] if rows else None
    return {"bag": str(bag), "config": str(cfg_path), "duration_s": duration,
            "decode_s": decode, "decode_rtf": duration / decode if decode else None,
            "messages": rows[0]["messages"] if rows else None,
            "input_error": rows[0]["input_error"] if rows else None,
            "input_warnings": rows[0]["input_warnings"] if rows else [], "estimators": rows}
