"""A second process that renders part of a report's figures while this one renders the rest
(``report_figures``): matplotlib draws one panel at a time in one thread, so on a machine with
two or more CPUs the figures take about half the wall time.

The helper is a fresh interpreter running ``python -m ddfuse.evaluation.figure_helper OUTDIR
LEAD_S`` (never a fork of a process holding gtsam's or numba's threads; not multiprocessing's
``spawn`` either, which would start its resource tracker, a third interpreter, and re-import
the ``ddfuse`` command's modules in the helper: ~0.2 s of CPU on its critical path). It reads
the run from its output directory itself, works out the same split of the figures as this
process from the same files (``report_figures.split``), writes its figures' PNGs to
OUTDIR/plots/ and sends back their bytes and captions, pickled, on its standard output.
Whatever it does not deliver (it failed, was killed, or could not start) this process renders
itself, so a bug in a figure surfaces here as without the helper.

This module imports only the standard library: ``start`` is called before the report's own
imports (matplotlib), so that the helper's imports run alongside them."""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import subprocess
import sys
from pathlib import Path

# Seconds by which the helper starts behind this process's figures (its share of the figures
# is that much smaller: ``report_figures.split``). Started before this process imports
# matplotlib (``ddfuse report``): this process's own start before it (interpreter, the
# command's modules) and the helper's interpreter start, less the page this process builds
# after the figures. Started after (``render_report`` from Python, ``ddfuse run``): also the
# helper's imports. Measured: docs/results/secondary_speed.md, session 23.
EARLY_START_S = 0.2
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
    this process will have drawn before the helper is ready (``EARLY_START_S`` or
    ``LATE_START_S``)."""

    def __init__(self, outdir: Path, lead_s: float = EARLY_START_S) -> None:
        self.lead_s = lead_s
        # stdin closed: the helper reads nothing; stderr shared, as a figure's warnings are
        self._proc = subprocess.Popen(
            [sys.executable, "-m", __name__, str(outdir), repr(lead_s)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)

    def results(self) -> dict[str, tuple[bytes | None, str]] | None:
        """{figure name: (PNG bytes or None, caption)} of the helper's share, once it is done;
        None when it failed or died (the caller renders that share itself)."""
        try:
            out = pickle.load(self._proc.stdout)
        except (EOFError, OSError, pickle.UnpicklingError):  # it died before sending
            out = None
        finally:
            self.close()
        return out if isinstance(out, dict) else None

    def close(self) -> None:
        """End the helper (at once if still working) and wait for it."""
        if self._proc.poll() is None:
            self._proc.terminate()
        self._proc.wait()
        self._proc.stdout.close()


def start(outdir: Path, lead_s: float = EARLY_START_S) -> Helper | None:
    """A helper for ``outdir``'s figures (``Helper``), or None where none is ``wanted`` or
    none can be started (the figures are then all drawn in this process)."""
    if not wanted():
        return None
    try:
        return Helper(Path(outdir), lead_s)
    except (OSError, ValueError):  # no pipes or processes here: draw alone
        return None


def main(argv: list[str]) -> None:
    """The helper process (``argv``: OUTDIR LEAD_S): its share of the figures, pickled on
    standard output (None on failure)."""
    # the result owns the standard output: anything else printed goes to stderr
    send = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    try:
        from ddfuse.evaluation import report_figures

        out = report_figures.render_helper_share(Path(argv[0]), float(argv[1]))
    except BaseException:  # noqa: BLE001 - the parent draws this share and raises, if it must
        out = None
    try:
        pickle.dump(out, send, protocol=pickle.HIGHEST_PROTOCOL)
        send.close()
    except OSError:  # the parent is gone or stopped listening
        pass


if __name__ == "__main__":
    main(sys.argv[1:])
