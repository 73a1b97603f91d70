"""What the commands share in printing: number cells, one-line messages, progress bars."""

from __future__ import annotations

import math
import sys


def fmt(v: float | None, spec: str = ".2f") -> str:
    """``v`` formatted by ``spec``; '-' for None or a non-finite float."""
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines too) made one space."""
    return " ".join(str(text).split())


class Bars:
    """Rich progress bars on stderr, one per stage, shown only once a stage has run for
    ``delay`` seconds (short runs stay quiet); ``progress()`` makes them only when both stdout
    and stderr are terminals."""

    def __init__(self, delay: float = 2.0, clock=None) -> None:
        import time

        self.delay = delay
        self.clock = clock or time.monotonic
        self.bar = None
        self.tasks: dict[str, int] = {}
        self.started = self.clock()

    def update(self, stage: str, fraction: float) -> None:
        if self.bar is None:
            if self.clock() - self.started < self.delay or fraction >= 1.0:
                return
            from rich.console import Console
            from rich.progress import Progress

            self.bar = Progress(console=Console(stderr=True), transient=True)
            self.bar.start()
        if stage not in self.tasks:
            self.tasks[stage] = self.bar.add_task(stage, total=1.0)
        self.bar.update(self.tasks[stage], completed=fraction)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


def progress() -> Bars | None:
    """Progress bars on a terminal; None (no output at all) when output is redirected."""
    return Bars() if sys.stdout.isatty() and sys.stderr.isatty() else None


def headline_text(lines: list[str]) -> str:
    """A run's headline (``evaluation.headline.Headline.lines``) for the terminal: a rule,
    then the lines as the report shows them (unwrapped: a terminal wraps them itself)."""
    return "---- headline " + "-" * 46 + "\n" + "\n".join(lines) + "\n"


def table(header: list[str], rows: list[list[str]], left: int = 1) -> str:
    """Columns as wide as their widest cell, two spaces apart; the first ``left`` columns
    aligned left, the others right."""
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    return "".join("  ".join(c.ljust(w) if k < left else c.rjust(w)
                             for k, (c, w) in enumerate(zip(r, widths, strict=True))).rstrip()
                   + "\n" for r in [header, *rows])
