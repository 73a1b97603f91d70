"""``Reject``: a single message that cannot be used (the converters', ``converters.Reject``)."""

from __future__ import annotations


class Reject(Exception):
    """A single message that cannot be used; its text is the counted reason. ``kept``: the
    measurements of the message's other fields, used all the same (a part rejected)."""

    def __init__(self, reason: str, kept: list | None = None):
        super().__init__(reason)
        self.kept = kept or []
