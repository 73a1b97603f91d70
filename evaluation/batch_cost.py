"""The batch smoother's whole-run solve on a long bag: what it will cost, said before it starts.

The batch (``estimation.smoother.batch``) solves every keyframe of the run at once in its
``finish`` (Levenberg-Marquardt, then a marginal covariance per keyframe), after the other
estimators have had every message. Its cost grows faster than the bag: measured on simulated
Husky bags (2.5 keyframes a second), ``SOLVE_S_PER_1000 * (keyframes / 1000) **
SOLVE_EXPONENT`` seconds; on a 2 h bag it is almost all of the run's time. ``announce_solve``
makes the batch say so, with that estimate, before it starts, when it is ``NOTICE_ABOVE_S`` or
more. The measurements and the choice (announce, not leave it out): docs/design/outputs.md.
"""

from __future__ import annotations

from collections.abc import Callable

# measured on a quiet machine (docs/design/outputs.md, "Long bags"): the batch's whole cost,
# 1500 keyframes 16.5 s, 4500 keyframes 224 s
SOLVE_S_PER_1000 = 6.3
SOLVE_EXPONENT = 2.37
NOTICE_ABOVE_S = 60.0
KEYFRAMES_PER_S = 2.5  # a GPS-keyed window at a 2.5 Hz receiver, for the estimate before reading
# s: the longest whole-run solve the default estimator set waits for; the bag span (s) whose
# estimated solve it is (about 34 min of bag) is where the default set leaves the batch out (a
# 2 h bag would take over an hour; mrclam1's 25 min, about 2 min, keeps it)
DEFAULT_MAX_SOLVE_S = 300.0
DEFAULT_MAX_SPAN_S = (1000.0 * (DEFAULT_MAX_SOLVE_S / SOLVE_S_PER_1000) ** (1.0 / SOLVE_EXPONENT)
                      / KEYFRAMES_PER_S)


def solve_seconds(keyframes: int) -> float:
    """The batch's estimated solve time (s) for ``keyframes`` keyframes (module docstring)."""
    return SOLVE_S_PER_1000 * (max(keyframes, 0) / 1000.0) ** SOLVE_EXPONENT


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 5400 else f"{s / 60:.0f} min" if s >= 90 else f"{s:.0f} s"


def solve_notice(keyframes: int) -> str | None:
    """What to tell the user before a solve of ``keyframes`` keyframes; None when it is
    expected to take less than ``NOTICE_ABOVE_S``."""
    s = solve_seconds(keyframes)
    if s < NOTICE_ABOVE_S:
        return None
    return (f"batch: now solving the whole run at once ({keyframes} keyframes), the slow part "
            f"of this run: about {_duration(s)} (a model measured on simulated bags; "
            "docs/design/outputs.md); Ctrl-C skips it and keeps the other estimators' "
            "results, and --estimators without batch leaves it out")


def leave_out_notice(span_s: float, others: list[str]) -> str:
    """What to tell the user when the default set leaves the batch out of a bag spanning
    ``span_s`` s (more than ``DEFAULT_MAX_SPAN_S``); ``others``: the estimators that run."""
    s = solve_seconds(int(span_s * KEYFRAMES_PER_S))
    return (f"batch: left out of the default estimators: this bag spans {_duration(span_s)} and "
            f"the batch's whole-run solve grows faster than the bag (about {_duration(s)} here, "
            f"a model measured on simulated bags; docs/design/outputs.md); ask for it with "
            f"--estimators {','.join([*others, 'batch'])}")


def announce_solve(batch, notice: Callable[[str], None]) -> None:
    """Make the BatchSmoother ``batch`` call ``notice`` with ``solve_notice`` of its keyframes
    just before its ``finish`` solves them (nothing when the solve is expected to be short)."""
    finish = batch.finish

    def announced() -> None:
        window = getattr(batch, "window", None)
        text = solve_notice(len(getattr(window, "all_kf_t", ()) or ()))
        if text:
            notice(text)
        finish()

    batch.finish = announced
