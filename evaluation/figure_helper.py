"""A second process that renders part of a report's figures while this one renders the rest
(``report_figures``): matplotlib draws one panel at a time in one thread, so on a machine with
two or more CPUs the figures take about half the wall time.

The helper is a fresh interpreter (``spawn``: never a fork of a process holding gtsam's or
numba's threads). It reads the run from its output directory itself, works out the same split
of the figures as this process from the same files (``report_figures.split``), writes its
figures' PNGs to OUTDIR/plots/ and sends back their bytes and captions. Whatever it does not
deliver (it failed, was killed, or could not start) this process renders itself, so a bug in a
figure surfaces here as without the helper.

This module imports only the standard library: ``start`` is called before the report's own
imports (matplotlib), so that the helper's imports run alongside them."""

from __future__ import annotations

import multiprocessing as mp
import os
from pathlib import Path

# Seconds by which the helper starts behind this process's figures when it is started after
# this process has imported matplotlib (its own interpreter start and imports): its share of
# the figures is that much smaller (``report_figures.split``).
LATE_START_S = 0.7


def cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def wanted() -> bool:
    """Whether a helper is worth starting: two or more CPUs, and this process is not already
    one of a pool's workers (``ddfuse fleet`` on processes, ``ddfuse bench``), whose siblings
    use the other CPUs."""
    return cpus() >= 2 and mp.parent_process() is None


class Helper:
    """The helper process for the run in ``outdir``; ``lead_s``: how many seconds of figures
    this process will have drawn before the helper is ready (``LATE_START_S`` when started
    after the imports, else 0)."""

    def __init__(self, outdir: Path, lead_s: float = 0.0) -> None:
        ctx = mp.get_context("spawn")
        # A pipe, not a Queue: it tells this process when the helper dies without a result.
        self._recv, send = ctx.Pipe(duplex=False)
        self.lead_s = lead_s
        self._proc = ctx.Process(target=_main, args=(str(outdir), lead_s, send), daemon=True,
                                 name="ddfuse-report-figures")
        self._proc.start()
        send.close()  # the helper's copy is the only one left: its death ends recv()

    def results(self) -> dict[str, tuple[bytes | None, str]] | None:
        """{figure name: (PNG bytes or None, caption)} of the helper's share, once it is done;
        None when it failed or died (the caller renders that share itself)."""
        try:
            return self._recv.recv()
        except (EOFError, OSError):
            return None
        finally:
            self.close()

    def close(self) -> None:
        """End the helper (at once if still working) and wait for it."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join()
        self._recv.close()


def start(outdir: Path, lead_s: float = 0.0) -> Helper | None:
    """A helper for ``outdir``'s figures (``Helper``), or None where none is ``wanted`` or
    none can be started (the figures are then all drawn in this process)."""
    if not wanted():
        return None
    try:
        return Helper(Path(outdir), lead_s)
    except (OSError, ValueError, AssertionError):  # no pipes or processes here: draw alone
        return None


def _main(outdir: str, lead_s: float, send) -> None:
    """The helper process: its share of the figures, sent to the parent (None on failure)."""
    try:
        from ddfuse.evaluation import report_figures

        out = report_figures.render_helper_share(Path(outdir), lead_s)
    except BaseException:  # noqa: BLE001 - the parent draws this share and raises, if it must
        out = None
    try:
        send.send(out)
    except (OSError, ValueError):  # the parent is gone or stopped listening
        pass
    finally:
        send.close()
