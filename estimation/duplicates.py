"""Exact duplicate messages: the same message recorded twice (two recorders merged, a bridge
republishing, a replay recorded over its source). Fused twice, each duplicate counts double
in the filter (NEES 2.7 -> 4.2 on the sample with every sensor message doubled).

A duplicate is a message on the same source (configured topic) whose serialised bytes equal
those of one read within ``WINDOW`` messages before it on that source, the ROS1 header's
``seq`` left out (a republisher renumbers it): same header stamp, same content. Same stamp
with different content is not a duplicate and is left alone. A live subscriber has message
objects, not bytes: there the key is the extracted record (``ddfuse.estimation.rosmsg``: the
header stamp and every field a converter reads), which leaves ``seq`` out as well.
"""

from __future__ import annotations

from collections import Counter, deque

__all__ = ["DUPLICATE", "Duplicates"]

DUPLICATE = "duplicate message (same topic, header stamp and content as one read before)"


class Duplicates:
    """Per source, the last ``WINDOW`` messages' bytes; ``seen_before`` says whether a message
    repeats one of them. ``ros1``: raw bytes are ROS1 serialisations (their first 4 bytes are
    the header's seq). ``count``: topic -> duplicates found."""

    WINDOW = 64  # messages per source: a repeat is recorded within a few of its original

    __slots__ = ("skip", "recent", "count")

    def __init__(self, ros1: bool) -> None:
        self.skip = 4 if ros1 else 0
        self.recent: dict[int, tuple[deque, set]] = {}  # source index -> (keys in order, set)
        self.count: Counter = Counter()

    def seen_before(self, index: int, topic: str, raw) -> bool:
        """Whether ``raw`` (the serialised bytes) on source ``index`` repeats one of its last
        WINDOW messages; counted under ``topic`` if so. A message already decoded (not bytes)
        never does."""
        if not isinstance(raw, (bytes, memoryview)):
            return False
        return self._repeats(index, topic, bytes(raw[self.skip:]))

    def record_seen_before(self, index, topic: str, rec: tuple) -> bool:
        """Whether the extracted record ``rec`` (a plain tuple of the message's stamp and
        fields) on source ``index`` repeats one of its last WINDOW records; counted under
        ``topic`` if so. A field that is not hashable (an array) is compared by its repr."""
        try:
            hash(rec)
            key = rec
        except TypeError:
            key = repr(rec)
        return self._repeats(index, topic, key)

    def _repeats(self, index, topic: str, key) -> bool:
        entry = self.recent.get(index)
        if entry is None:
            entry = self.recent[index] = (deque(), set())
        order, keys = entry
        if key in keys:
            self.count[topic] += 1
            return True
        order.append(key)
        keys.add(key)
        if len(order) > self.WINDOW:
            keys.discard(order.popleft())
        return False

    def warnings(self, source: str, seen: Counter) -> list[str]:
        """One line per topic with duplicates: how many of its messages, dropped."""
        return [f"{source}: topic {topic}: {n} of {seen[topic]} messages are exact duplicates "
                f"of one read just before (same header stamp and content); dropped, each "
                "fused once" for topic, n in sorted(self.count.items())]
