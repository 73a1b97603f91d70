"""Online use: feed measurements one at a time, ask for the current estimate at any moment.

``OnlineSession`` is what a live robot uses from Python: call ``push(measurement)`` from each
sensor callback (measurements in time order, as ``estimation.measurements`` dataclasses;
``estimation.live.LiveConverter`` makes them from the ROS messages) and
``estimate(name)`` whenever a pose is needed; ``latency_ms()`` gives per-update latency
percentiles. ``replay`` drives a session from a bag, optionally paced by the header stamps.
"""

from __future__ import annotations

import time
from array import array
from collections.abc import Callable
from pathlib import Path

import numpy as np

from estimation.bags import BagStream
from estimation.config import Config
from estimation.errors import BagError
from estimation.estimator import Estimate, Estimator
from estimation.measurements import Stream
from estimation.runner import initial_pose
from evaluation import estimators as registry


class OnlineSession:
    """Estimators updated message by message, with the wall time of every update recorded."""

    def __init__(self, estimators: dict[str, Estimator]) -> None:
        self.estimators = estimators
        self.update_s: dict[str, array] = {n: array("f") for n in estimators}  # s, float32
        self.input_error: str | None = None  # set by replay when the bag breaks off
        self.replayed_s = 0.0  # data seconds replayed
        self.last_t: float | None = None  # set by replay: the last message's s since the first
        self.interrupted: str | None = None  # set by replay(interruptible=True) on Ctrl-C

    @classmethod
    def from_config(cls, cfg: Config, names: list[str] | None = None, *,
                    stream: Stream | None = None, lag: float | None = None) -> OnlineSession:
        """Build the named estimators (default: all the config allows, except the offline
        batch). ``stream`` supplies the datum, landmark map and truth-based initial pose."""
        stream = stream if stream is not None else Stream(measurements=[])
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
            if len(self.update_s[name]) % 1000 == 0:
                est.log.innovations.compact()

    def estimate(self, name: str) -> Estimate | None:
        return self.estimators[name].estimate()

    def latency_ms(self) -> dict[str, dict[str, float]]:
        """Per-estimator update latency p50 / p99 / max, ms."""
        out = {}
        for name, s in self.update_s.items():
            a = np.array(s, float) * 1e3 if s else np.zeros(1)
            out[name] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                         "max": float(a.max()), "updates": len(s)}
        return out


def replay(bag: str | Path, cfg: Config, *, names: list[str] | None = None,
           realtime: bool = False, print_every: float = 1.0,
           on_print: Callable[[float, dict[str, Estimate | None]], None] | None = None,
           reorder_window: float | None = None, interruptible: bool = False) -> OnlineSession:
    """Replay a bag into an OnlineSession, one message at a time, decoding it as it goes
    (``estimation.bags.BagStream``). With ``realtime`` the messages are paced by their header
    stamps; ``on_print`` is called with (t, estimates) every ``print_every`` seconds of data
    time (> 0; ValueError otherwise), from the first message on; the session's ``last_t`` is the
    last message's time (s since the first), at which the estimates after ``finish`` are
    final. A truncated or damaged bag is replayed up to where it breaks off; the session's
    ``input_error`` then says why (BagError if nothing could be read). With ``interruptible``,
    Ctrl-C ends the replay there as the bag's end would, and the session's ``interrupted`` says
    where (the latency figures so far are kept); otherwise it propagates."""
    if not (print_every > 0.0 and np.isfinite(print_every)):
        raise ValueError(f"print_every: expected seconds > 0, got {print_every!r}")
    stream = BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=False).prime()
    session = OnlineSession.from_config(cfg, names, stream=stream)
    t0 = stream.t0 if stream.t0 is not None else 0.0
    wall0, next_print = time.perf_counter(), t0
    n = 0
    t_last = None
    try:
        for m in stream:
            n += 1
            t_last = m.t
            if realtime:
                lead = (m.t - t0) - (time.perf_counter() - wall0)
                if lead > 0:
                    time.sleep(lead)
            session.push(m)
            if on_print is not None and m.t >= next_print:
                on_print(m.t - t0, {k: session.estimate(k) for k in session.estimators})
                next_print = m.t + print_every
    except KeyboardInterrupt:
        if not interruptible:
            raise
        at = "before the first message" if t_last is None else \
            f"{t_last - t0:.3f} s after the first message"
        session.interrupted = f"interrupted (Ctrl-C) after {n} messages, {at}"
    if stream.error is not None and not n:
        raise BagError(stream.error)
    for est in session.estimators.values():
        est.finish()
    session.input_error = stream.error
    session.replayed_s = stream.duration
    session.last_t = None if t_last is None else t_last - t0
    return session
