"""Per-topic check of header stamps against the bag's record (receive) time.

A message whose header stamp disagrees with its topic's usual stamp-to-record-time offset by more
than a tolerance (``STAMP_TOLERANCE`` s, or the reorder window if larger) has a broken stamp (a
clock jump) and is dropped; ``StampCheck`` keeps that offset per topic. A stamp of zero or below
is a driver's clock not yet set, never a time: it is rejected before this check
(``UNSET_STAMP``). Used by the bag reader (``ddfuse.estimation.bags``) and the live converter
(``ddfuse.estimation.live``).
"""

from __future__ import annotations

import math
import statistics

__all__ = ["STAMP_TOLERANCE", "UNSET_STAMP", "StampCheck"]

# A message whose header stamp disagrees with its topic's usual stamp-to-record-time offset by
# more than this (or the reorder window, if larger) has a broken stamp and is dropped.
STAMP_TOLERANCE = 1.0  # s
# A stamp of zero or below is a driver's clock not yet set, never a time: rejected before the
# stamp check, whose warm-up median and drift tracking it would otherwise join.
UNSET_STAMP = "header stamp zero or negative (the sensor's clock was not set)"


class StampCheck:
    """Drops records of one source whose header stamp disagrees with the source's usual
    stamp-to-record-time offset by more than ``tolerance`` (a clock jump): such a message would
    otherwise land minutes away from its neighbours. A stamp of zero or below never reaches it
    (``UNSET_STAMP``): it would drag the warm-up's median and the drift's.

    The usual offset is the median over the source's first ``WARMUP`` records (or those within
    ``WARMUP_S`` seconds of record time of its first, or all it has at the end of the bag), held
    back until then; afterwards it follows the median of the last ``WARMUP`` accepted ones, so
    a slow drift is followed. A source with fewer than 3 records is not checked."""

    WARMUP = 15
    WARMUP_S = 5.0

    __slots__ = ("pending", "first_rt", "ref", "recent", "n", "bad")

    def __init__(self) -> None:
        self.pending: list | None = []  # (stamp, record time, payload) during the warm-up
        self.first_rt = math.nan
        self.ref = 0.0
        self.recent: list[float] = []
        self.n = 0  # records seen
        self.bad = 0  # records dropped

    def end_warmup(self, tolerance: float) -> list:
        """The warm-up's records that pass, in their order; the check is armed from now on."""
        recs, self.pending = self.pending or [], None
        if not recs:
            return []
        offsets = [t - rt for t, rt, _ in recs]
        self.ref = statistics.median(offsets)
        if len(recs) < 3:
            return recs
        keep = [r for r, off in zip(recs, offsets, strict=True)
                if abs(off - self.ref) <= tolerance]
        self.bad += len(recs) - len(keep)
        self.recent = [r[0] - r[1] for r in keep][-self.WARMUP:]
        return keep

    def ok(self, t: float, rt: float, tolerance: float) -> bool:
        off = t - rt
        if abs(off - self.ref) > tolerance:
            self.bad += 1
            return False
        recent = self.recent
        recent.append(off)
        if len(recent) >= 2 * self.WARMUP:
            del recent[:self.WARMUP]
            self.ref = statistics.median(recent)
        return True
