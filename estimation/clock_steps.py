"""The recording clock stepping back (NTP, a manual ``date``), seen in write or arrival order.

A recorder writes messages in the order they arrive, stamped with its system clock (the record
time); drivers on the same machine stamp headers with the same clock. When that clock steps
back by S seconds mid-recording, every message after the step has its record time and (on
those topics) its header stamp S seconds early, so that, ordered by stamp, the next S seconds
of data interleave with the S seconds before the step: a track that jumps back and forth.

The write order is the evidence: real time never runs backwards, so a record time that goes
back by more than ``tolerance`` (s) against the newest one written before it, on its own topic
too, is a step (a bag written topic by topic, as merging scripts do, goes back only across
topics). Each
message read after a step is re-timed by the sum of the steps before it: its record time
always, its header stamp when that stamp stepped too, i.e. when the re-timed stamp lies nearer
its topic's previous stamp than the stamp as written (a topic whose stamps come from another
clock, a GPS receiver's, keeps them). With the step measured as the jump of the record time
(exact to one message interval of the busiest topic, a few ms), the re-timed stream is the
one that would have been recorded without the step: nothing is dropped. Figures:
docs/design/bag_faults.md.

Used by the bag reader on the bags it reads in write order: ROS1 (file order: ``ros1_scan``),
ROS2 sqlite3 (row order) and MCAP (file order: ``ros2_write_order``); and by the live converter
(arrival order). A ROS2 bag compressed per file or per message, or of another storage plugin,
is read through rosbags sorted by record time, which hides the write order: not covered.
"""

from __future__ import annotations

from collections import Counter

__all__ = ["ClockSteps"]


class ClockSteps:
    """Detects backward steps of the record (receive) clock in write order and re-times what
    follows (module docstring). ``tolerance``: s of backward record time taken as jitter.
    ``steps``: (record time s where it stepped, as written; step s) of each;
    ``retimed``: topic -> messages whose stamp was re-timed."""

    OUTLIER_RUN = 10  # garbled records in a row that are still taken as one outlier

    __slots__ = ("tolerance", "shift", "newest", "last", "steps", "retimed", "first_stamp",
                 "jumped_from", "since_jump", "topic_rt")

    def __init__(self, tolerance: float) -> None:
        self.tolerance = tolerance
        self.shift = 0.0  # s added to the record times (and stepped stamps) read from now on
        self.newest = float("-inf")  # the newest re-timed record time, s
        self.last: dict[str, float] = {}  # topic -> its last (re-timed) header stamp, s
        self.steps: list[tuple[float, float]] = []
        self.retimed: Counter = Counter()
        self.first_stamp: float | None = None  # of the first step, re-timed, for the warning
        # the newest record time before the last forward jump beyond the tolerance, while the
        # records after it follow it: one garbled record time (a damaged chunk) that the next
        # record comes back from is an outlier, not a step back
        self.jumped_from: float | None = None
        self.since_jump = 0  # records since that jump; past OUTLIER_RUN it was a real one
        self.topic_rt: dict[str, float] = {}  # topic -> its newest (re-timed) record time, s

    def retime(self, topic: str, t: float, rt: float) -> tuple[float, float]:
        """(stamp, record time) of a message on ``topic`` with header stamp ``t`` and record
        time ``rt`` (s), read next in write order, re-timed for the steps so far."""
        rt += self.shift
        tol = self.tolerance
        prev = self.topic_rt.get(topic)
        back = rt < self.newest - tol
        if back and (prev is None or rt >= prev - tol):
            # this topic's own record times run on: the bag was written out of time order
            # (merged topic by topic), not recorded across a step
            back = False
        if back:
            if self.jumped_from is not None and rt >= self.jumped_from - tol:
                self.newest = self.jumped_from  # the jump was an outlier
            else:
                step = self.newest - rt
                self.steps.append((rt - self.shift, step))
                self.shift += step
                rt += step
            self.jumped_from = None
        elif rt > self.newest + tol and self.newest > float("-inf"):
            self.jumped_from, self.since_jump = self.newest, 0
        elif self.jumped_from is not None:
            self.since_jump += 1
            if self.since_jump > self.OUTLIER_RUN:
                self.jumped_from = None
        if rt > self.newest:
            self.newest = rt
        if prev is None or rt > prev:
            self.topic_rt[topic] = rt
        if self.shift:
            moved = t + self.shift
            last = self.last.get(topic)
            if last is None or abs(moved - last) < abs(t - last):
                if self.first_stamp is None:
                    self.first_stamp = moved
                t = moved
                self.retimed[topic] += 1
        if t - t == 0.0:  # finite: a NaN stamp (rejected later) must not become the last
            self.last[topic] = t
        return t, rt

    def warning(self, source: str, t0: float | None) -> str | None:
        """One line naming ``source`` (the bag or 'live input'): when, by how much, which
        topics and how many of their messages were re-timed; None without a step.
        ``t0``: the stream's first stamp, s, to say when."""
        if not self.steps:
            return None
        total = sum(s for _, s in self.steps)
        when = ("" if self.first_stamp is None or t0 is None
                else f" at t={self.first_stamp - t0:.2f} s")
        steps = ("" if len(self.steps) == 1
                 else f" in {len(self.steps)} steps (" +
                 ", ".join(f"{s:.2f} s" for _, s in self.steps) + ")")
        topics = ", ".join(f"{tp} ({n})" for tp, n in sorted(self.retimed.items()))
        return (f"{source}: the recording clock stepped back by {total:.2f} s{when}{steps} "
                f"(record times go back in write order); the messages after it were re-timed "
                f"by that much, stamps included on {topics or 'no topic'}")
