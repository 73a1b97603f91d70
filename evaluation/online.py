"""Online use: feed measurements one at a time, ask for the current estimate at any moment.

``OnlineSession`` is what a live robot uses from Python: call ``push(measurement)`` from each
sensor callback (measurements in time order, as ``estimation.measurements`` dataclasses) and
``estimate(name)`` whenever a pose is needed; ``latency_ms()`` gives per-update latency
percentiles. ``replay`` drives a session from a bag, optionally paced by the header stamps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from estimation.bags import read_stream
from estimation.config import Config
from estimation.estimator import Estimate, Estimator
from estimation.measurements import Stream
from estimation.runner import initial_pose
from evaluation import estimators as registry


class OnlineSession:
    """Estimators updated message by message, with the wall time of every update recorded."""

    def __init__(self, estimators: dict[str, Estimator]) -> None:
        self.estimators = estimators
        self.update_s: dict[str, list[float]] = {n: [] for n in estimators}

    @classmethod
    def from_config(cls, cfg: Config, names: list[str] | None = None, *,
                    stream: Stream | None = None, lag: float | None = None) -> OnlineSession:
        """Build the named estimators (default: all the config allows, except the offline
        batch). ``stream`` supplies the datum, landmark map and truth-based initial pose."""
        stream = stream or Stream(measurements=[])
        chosen = [n for n in registry.select(cfg, names) if names or n != "batch"]
        pose = initial_pose(cfg.initial_pose, stream)
        lag = lag if lag is not None else cfg.smoother.lag
        return cls({n: registry.SPECS[n].build(cfg, stream, pose, lag) for n in chosen})

    def push(self, m) -> None:
        """Fuse one measurement into every estimator."""
        clock = time.perf_counter
        for name, est in self.estimators.items():
            t0 = clock()
            est.process(m)
            self.update_s[name].append(clock() - t0)

    def estimate(self, name: str) -> Estimate | None:
        return self.estimators[name].estimate()

    def latency_ms(self) -> dict[str, dict[str, float]]:
        """Per-estimator update latency p50 / p99 / max, ms."""
        out = {}
        for name, s in self.update_s.items():
            a = np.array(s) * 1e3 if s else np.zeros(1)
            out[name] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                         "max": float(a.max()), "updates": len(s)}
        return out


def replay(bag: str | Path, cfg: Config, *, names: list[str] | None = None,
           realtime: bool = False, print_every: float = 1.0,
           on_print: Callable[[float, dict[str, Estimate | None]], None] | None = None
           ) -> OnlineSession:
    """Replay a bag into an OnlineSession, one message at a time. With ``realtime`` the messages
    are paced by their header stamps; ``on_print`` is called with (t, estimates) every
    ``print_every`` seconds of data time."""
    stream = read_stream(bag, cfg)
    session = OnlineSession.from_config(cfg, names, stream=stream)
    wall0, next_print = time.perf_counter(), stream.t0
    for m in stream.measurements:
        if realtime:
            lead = (m.t - stream.t0) - (time.perf_counter() - wall0)
            if lead > 0:
                time.sleep(lead)
        session.push(m)
        if on_print is not None and m.t >= next_print:
            on_print(m.t - stream.t0, {n: session.estimate(n) for n in session.estimators})
            next_print = m.t + print_every
    for est in session.estimators.values():
        est.finish()
    return session
