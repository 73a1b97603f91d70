"""What a bag stream drops, per topic, and the warnings and errors that say so.

``TopicDrops`` holds the counts a ``ddfuse.estimation.bags.BagStream`` keeps while it reads:
messages rejected per (topic, reason) (``Stream.rejected``), measurements that came too late to
reorder, messages seen and measurements offered per topic, and the sightings' landmark ids not
in the map. At the end of the bag it turns them into ``warnings`` (a topic that lost more than
``WARN_SHARE`` of its messages to one reason or as late, with the setting that keeps them; a
topic without messages) and into the BagErrors that leave nothing to estimate from (every
message of a topic rejected, a topic whose stamps jump, no sensor message at all).
"""

from __future__ import annotations

import logging
import math
from collections import Counter, defaultdict
from pathlib import Path

from ddfuse.estimation.bag_reader import Source
from ddfuse.estimation.config import LANDMARK_NOT_IN_MAP, Config
from ddfuse.estimation.converters import unknown_landmarks_note
from ddfuse.estimation.duplicates import DUPLICATE
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.stamp_check import StampCheck

__all__ = ["DAMAGED", "LATE_PREFIX", "WARN_SHARE", "TopicDrops"]

log = logging.getLogger(__name__)

# A topic that loses more than this share of its messages (or of its measurements as late: the
# reorder window too short for it), wholly or in part, gets a warning beside the count in
# ``rejected``: a run's terminal shows no log.
WARN_SHARE = 0.1
LATE_PREFIX = "arrived after messages stamped up to more than"
# the reason under which messages lost to a damaged record of the bag are counted
DAMAGED = "lost to a damaged record of the bag (see the warning naming its byte)"
# reasons with a warning of their own, whatever their share
QUIET = (DAMAGED, DUPLICATE)


class TopicDrops:
    """The drop counts of one bag stream (see the module docstring); ``depth``: its reorder
    window, s; ``landmarks``: the merged landmark map, id -> (x, y) m, or None."""

    def __init__(self, bag: Path, cfg: Config, landmarks: dict | None, depth: float) -> None:
        self.bag = bag
        self.cfg = cfg
        self.landmarks = landmarks
        self.depth = depth
        # topic -> ids of its sightings not in the map (dropped as LANDMARK_NOT_IN_MAP)
        self.unknown_landmarks: defaultdict[str, Counter] = defaultdict(Counter)
        self.rejected: Counter = Counter()
        self.late: Counter = Counter()  # topic -> measurements that came too late to reorder
        self.passed_late: Counter = Counter()  # topic -> of them, passed on out of order
        self.lateness: dict[str, float] = {}  # topic -> the most a late one lagged the newest
        self.offered: Counter = Counter()  # topic -> measurements offered to the buffer
        self.seen: Counter = Counter()  # topic -> messages read (per source reading it)
        # what the run should tell its user (a topic mostly late, a topic without messages):
        # whole sentences naming the bag and topic, also logged
        self.warnings: list[str] = []

    def count_late(self, topic: str, t: float, released: float, newest: float) -> None:
        """Count a measurement stamped ``t`` that came after ``released`` was passed on, when
        the newest stamp was ``newest``: a reorder window of ``newest - t`` would have kept
        it (releases happen at the same messages whatever the window)."""
        self.late[topic] += 1
        if newest - t > self.lateness.get(topic, 0.0):
            self.lateness[topic] = newest - t
        self.rejected[(topic, f"{LATE_PREFIX} "
                              f"reorder_window ({self.depth:g} s) later had been passed on; "
                              "raise reorder_window to keep it")] += 1
        if self.late[topic] == 1:
            log.warning("%s: %s: a message stamped %.3f s before the last one passed on came "
                        "too late to reorder (reorder_window %g s); dropped and counted",
                        self.bag, topic, released - t, self.depth)

    def count_passed_late(self, topic: str, t: float, newest: float) -> None:
        """Count a measurement stamped ``t`` that came too late to reorder and is passed on out
        of order (``BagStream(pass_late=True)``: each estimator decides whether it can use it
        that late), when the newest stamp was ``newest``."""
        self.passed_late[topic] += 1
        if newest - t > self.lateness.get(topic, 0.0):
            self.lateness[topic] = newest - t

    def count_damage(self, lines: list[str], lost: Counter) -> None:
        """The damaged records of the bag (``BagMessages.damage``): each line a warning, the
        messages lost per topic counted in ``rejected`` under DAMAGED."""
        self.warnings.extend(lines)
        for topic, n in sorted(lost.items()):
            if n:
                self.rejected[(topic, DAMAGED)] += n

    def warn_rejected(self) -> None:
        """The warnings of WARN_SHARE: per topic, each reason that cost more than that share of
        its messages (a compass without orientation that only a count said was unused), and
        the measurements dropped as late, with the reorder window that keeps them."""
        for (topic, reason), n in sorted(self.rejected.items()):
            total = self.seen[topic]
            if reason.startswith(LATE_PREFIX) or reason in QUIET or not n > WARN_SHARE * total:
                continue
            self.warnings.append(f"{self.bag}: topic {topic}: {n} of {total} messages "
                                 f"({100.0 * n / total:.0f} %) rejected, in whole or in part: "
                                 f"{reason}{self.reason_note(topic, reason)}")
        # what happened to the late ones, and what a wider reorder window would do
        fates = ((self.late, "dropped as late: they came up to", "to keep them"),
                 (self.passed_late, "came late: up to", "to give every estimator them in order"))
        for counts, what, gain in fates:
            for topic, n in sorted(counts.items()):
                total = self.offered[topic]
                if not n > WARN_SHARE * total:
                    continue
                lag = self.lateness[topic]
                passed = (" passed on to each estimator that can use them that late, dropped "
                          "by the others (counted per estimator);" if counts is self.passed_late
                          else "")
                self.warnings.append(
                    f"{self.bag}: topic {topic}: {n} of {total} measurements "
                    f"({100.0 * n / total:.0f} %) {what} {lag:.2f} s behind the newest stamp, "
                    f"beyond reorder_window ({self.depth:g} s);{passed} set reorder_window to "
                    f"at least {math.ceil(lag * 10.0) / 10.0:g} s (or --reorder-window) {gain}")

    def reason_note(self, topic: str, reason: str) -> str:
        """More on a rejection ``reason`` of ``topic`` for its warning or error: for sightings
        not in the map, the map and the ids (``unknown_landmarks_note``); else nothing."""
        if reason != LANDMARK_NOT_IN_MAP:
            return ""
        return "; " + unknown_landmarks_note(self.cfg, self.landmarks,
                                             self.unknown_landmarks[topic])

    def check_sources(self, sources: list[Source], checks: dict[int, StampCheck],
                      tolerance: float) -> None:
        """At the end of the bag: BagError for a topic whose every message was rejected, for
        one whose stamps jump too often, for no sensor message at all; the stamp check's drops
        counted; a warning for each topic without messages."""
        bag, rejected = self.bag, self.rejected
        empty = []
        for src in sorted(sources, key=lambda s: s.index):
            chk = checks.get(src.index)
            if chk is None:
                bad = {r: n for (tp, r), n in rejected.items() if tp == src.topic}
                if bad:
                    reason = max(bad.items(), key=lambda x: x[1])[0]
                    raise BagError(f"{bag}: topic {src.topic} ({src.key}): all "
                                   f"{sum(bad.values())} messages rejected: {reason}"
                                   f"{self.reason_note(src.topic, reason)}")
                empty.append(src)  # a message either converts (a check) or is counted
                continue
            if chk.bad:
                rejected[(src.topic, f"header stamp more than {tolerance:g} s off its "
                                     "topic's clock (time went backwards or jumped)")] += chk.bad
                if chk.n >= 3 and chk.bad > 0.1 * chk.n:
                    raise BagError(
                        f"{bag}: topic {src.topic} ({src.key}): {chk.bad} of {chk.n} stamps "
                        f"jump by more than {tolerance:g} s against the bag's record "
                        "time; the bag mixes clocks or time goes backwards beyond "
                        "reorder_window")
        sensors = [s for s in sources if s.key != "ground_truth"]
        if sensors and {s.index for s in sensors} <= {s.index for s in empty}:
            raise BagError(f"{bag}: no configured sensor topic has a message "
                           f"({', '.join(f'{s.topic} ({s.key})' for s in sensors)}): nothing "
                           "to estimate from")
        for src in empty:
            self.warnings.append(f"{bag}: topic {src.topic} ({src.key}) has no messages; "
                                 "the run goes on without it")
