"""``ddfuse bench``: decode time, and per estimator its wall time excluding decoding, real-time
factor, update latency percentiles and peak resident memory.

Each estimator runs in its own child process (spawned, so nothing is shared with the parent),
which makes its peak RSS its own: ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of that child.
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import time
from pathlib import Path

import numpy as np

from estimation.bags import read_stream
from estimation.config import load_config
from estimation.runner import initial_pose, run


def _one(bag: str, cfg_path: str, name: str, lag: float | None, queue) -> None:
    from evaluation import estimators as registry

    cfg = load_config(cfg_path)
    t0 = time.perf_counter()
    stream = read_stream(bag, cfg)
    decode_s = time.perf_counter() - t0
    # Linux reports ru_maxrss in KiB.
    decoded_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    pose = initial_pose(cfg.initial_pose, stream)
    est = registry.SPECS[name].build(cfg, stream, pose, lag if lag else cfg.smoother.lag)
    t1 = time.perf_counter()
    result = run(stream, {name: est})
    wall = time.perf_counter() - t1
    upd = result.runs[name].update_s * 1e3
    queue.put({
        "estimator": name, "duration_s": stream.duration, "decode_s": decode_s,
        "messages": len(stream.measurements), "wall_s": wall,
        "rtf": stream.duration / wall if wall > 0 else None,
        "update_ms": {"p50": float(np.percentile(upd, 50)), "p99": float(np.percentile(upd, 99)),
                      "max": float(upd.max())} if len(upd) else None,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "decoded_rss_mb": decoded_mb,  # peak up to the end of decoding: libraries + the stream
        "error": result.runs[name].error,
    })


def bench_bag(bag: Path, cfg_path: Path, names: list[str] | None = None,
              lag: float | None = None) -> dict:
    """Benchmark every selected estimator on one bag, each in a fresh process."""
    from evaluation import estimators as registry

    cfg = load_config(cfg_path)
    chosen = registry.select(cfg, names)
    ctx = mp.get_context("spawn")
    rows = []
    for name in chosen:
        q = ctx.Queue()
        p = ctx.Process(target=_one, args=(str(bag), str(cfg_path), name, lag, q))
        p.start()
        try:
            rows.append(q.get(timeout=3600))
        finally:
            p.join()
    decode = min(r["decode_s"] for r in rows) if rows else None
    duration = rows[0]["duration_s"] if rows else None
    return {"bag": str(bag), "config": str(cfg_path), "duration_s": duration,
            "decode_s": decode, "decode_rtf": duration / decode if decode else None,
            "messages": rows[0]["messages"] if rows else None, "estimators": rows}
