"""Health of a live session as diagnostic statuses (the fields of ``diagnostic_msgs``'
``DiagnosticStatus``, transport-free): one per configured topic, one per estimator, one for the
node.

* Topic: messages received, their rate over the last ``RATE_WINDOW_S`` s of the receive clock
  (Hz), what the converter and the session dropped (by reason, counted); STALE when nothing
  came for more than ``node.topic_timeout`` s (also before its first message, counted from the
  session's start).
* Estimator: updates, update latency p50 / p99 / max (ms, ``OnlineSession.latency_ms``); per
  'sensor kind' the gate's rejections and the NIS verdict over the innovations stamped in the
  last ``node.nis_window`` s (``evaluation.consistency.nis_by_sensor``, the offline scoring's
  own band and thresholds: Pass / Warn / Fail, none below ``consistency.MIN_SAMPLES``). ERROR
  once stopped (its error in the message), WARN on a Fail verdict.
* Node: resets (clock jumps back), callback errors, measurements held in the reorder buffer.

Levels are ``diagnostic_msgs/DiagnosticStatus``'s: OK 0, WARN 1, ERROR 2, STALE 3.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass

from ddfuse.evaluation.consistency import InnovationTable, nis_by_sensor

OK, WARN, ERROR, STALE = 0, 1, 2, 3
RATE_WINDOW_S = 5.0  # s of receive times a topic's rate is measured over


@dataclass(frozen=True, slots=True)
class Status:
    """One ``DiagnosticStatus``: ``level`` (OK..STALE), ``name`` ('ddfuse: topic /fix'),
    ``message`` one line, ``hardware_id``, ``values`` (key, value) strings."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...]


class TopicClock:
    """Receive times of the configured topics: the last one and those of the last
    ``RATE_WINDOW_S`` s (s on the receive clock)."""

    def __init__(self, topics: list[str], timeout: float, start: float | None = None) -> None:
        self.timeout = timeout
        self.start = start  # set by the first ``at`` when None
        self.last: dict[str, float | None] = {t: None for t in topics}
        self.recent: dict[str, deque] = {t: deque() for t in topics}
        self.received: Counter = Counter()

    def at(self, now: float) -> None:
        """Start the clocks at ``now`` unless started."""
        if self.start is None:
            self.start = now

    def seen(self, topic: str, rt: float) -> None:
        self.at(rt)
        if topic not in self.last:
            return
        self.last[topic] = rt
        self.received[topic] += 1
        q = self.recent[topic]
        q.append(rt)
        while q and q[0] < rt - RATE_WINDOW_S:
            q.popleft()

    def silent_for(self, topic: str, now: float) -> float:
        """Seconds since ``topic``'s last message (since the start before its first)."""
        last = self.last[topic]
        return now - (self.start if last is None else last)

    def stale(self, now: float) -> set[str]:
        """The topics silent for more than the timeout at ``now``."""
        return {t for t in self.last if self.silent_for(t, now) > self.timeout}

    def rate(self, topic: str, now: float) -> float:
        """Messages per second over the last ``RATE_WINDOW_S`` s up to ``now`` (or since the
        start, when that is shorter)."""
        span = min(RATE_WINDOW_S, now - self.start)
        n = sum(1 for r in self.recent[topic] if r >= now - RATE_WINDOW_S)
        return n / span if span > 0 else math.nan


def topic_statuses(clock: TopicClock, now: float, rejected: Counter,
                   hardware_id: str) -> list[Status]:
    """One status per topic at ``now`` (module docstring); ``rejected``: (topic or sensor,
    reason) -> count, the converter's and the session's."""
    out = []
    for topic in clock.last:
        silent = clock.silent_for(topic, now)
        drops = {reason: n for (where, reason), n in rejected.items() if where == topic}
        values = [("received", str(clock.received[topic])),
                  ("rate_hz", f"{clock.rate(topic, now):.2f}"),
                  ("silent_s", f"{silent:.2f}"),
                  ("dropped", str(sum(drops.values())))]
        values += [(f"dropped: {reason}", str(n)) for reason, n in sorted(drops.items())]
        if silent > clock.timeout:
            level = STALE
            msg = (f"no message for {silent:.1f} s (topic_timeout {clock.timeout:g} s)"
                   if clock.last[topic] is not None else
                   f"no message yet, {silent:.1f} s after the start (topic_timeout "
                   f"{clock.timeout:g} s)")
        else:
            level, msg = OK, f"{clock.rate(topic, now):.1f} Hz"
        out.append(Status(level, f"ddfuse: topic {topic}", msg, hardware_id, tuple(values)))
    return out


def windowed_nis(log, since: float) -> dict:
    """``nis_by_sensor`` of the innovations of ``log`` (an InnovationLog) stamped at or after
    ``since`` (s)."""
    c = log.columns()
    sel = c["t"] >= since
    if not sel.any():
        return {}
    return nis_by_sensor(InnovationTable(c["t"][sel], c["sensor"][sel], c["kind"][sel],
                                         c["nis"][sel], c["dim"][sel], c["accepted"][sel]))


def estimator_statuses(session, newest: float, window: float, hardware_id: str
                       ) -> list[Status]:
    """One status per estimator of ``session`` (an OnlineSession): its updates, latency and
    per-sensor NIS verdict over the ``window`` s of stamps up to ``newest`` (module
    docstring)."""
    out = []
    lat = session.latency_ms()
    for name, est in session.estimators.items():
        q = lat[name]
        values = [("updates", str(q["updates"]))]
        values += [(f"latency_{k}_ms", "nan" if math.isnan(q[k]) else f"{q[k]:.3f}")
                   for k in ("p50", "p99", "max")]
        fails = []
        if math.isfinite(newest):
            for label, st in windowed_nis(est.log.innovations, newest - window).items():
                c = st.nis
                values.append((f"nis {label}", f"{c.verdict or '-'} (n {c.n}, mean/expected "
                               f"{c.ratio:.2f}, outside band {c.outside:.2f})"))
                values.append((f"gate rejected {label}", str(st.rejected)))
                if c.verdict == "Fail":
                    fails.append(label)
        err = session.errors[name]
        if err is not None:
            level, msg = ERROR, f"stopped: {err}"
        elif fails:
            level, msg = WARN, f"NIS verdict Fail over the last {window:g} s: {', '.join(fails)}"
        else:
            level, msg = OK, f"{q['updates']} updates, latency p99 {q['p99']:.2f} ms"
        out.append(Status(level, f"ddfuse: estimator {name}", msg, hardware_id, tuple(values)))
    return out

