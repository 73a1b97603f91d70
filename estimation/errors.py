"""Errors that ddfuse reports to its user as one line (the CLI exits with code 2, no traceback)."""

import re


class DdfuseError(Exception):
    """Base class: the message names the file, topic, field or key and what was wrong."""


class ConfigError(DdfuseError):
    """A config file that does not validate."""


class BagError(DdfuseError):
    """A bag that cannot be read as configured (missing, unreadable, topic absent, wrong type).

    ``partial``, when set, holds the measurement stream decoded before the bag became unreadable
    (a truncated or damaged bag), so that callers can still use what was read."""

    def __init__(self, message: str, partial=None):
        super().__init__(message)
        self.partial = partial


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C ended a run after its results so far were written (``results_written``); the
    message says where the run stopped and where the results are. A KeyboardInterrupt, so that
    whatever does not know it still stops as on Ctrl-C."""

    results_written = True


_SYMBOL = re.compile(r"\(Symbol: ([^)]+)\)")


def error_line(text: str) -> str:
    """An exception's message as one line: its first non-blank line, with the variable it
    names where gtsam's paragraph names one on a later line (``(Symbol: x61)``), e.g.
    "Indeterminate linear system detected while working near variable x61"; "error" for an
    empty message."""
    first = next((line.strip() for line in str(text).splitlines() if line.strip()), "error")
    sym = _SYMBOL.search(str(text))
    if sym and sym.group(1) not in first:
        first += f" {sym.group(1)}"
    return first
