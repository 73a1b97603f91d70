"""The batch smoother's cost on a long bag: what it will cost, said before it starts.

The batch (``estimation.smoother.batch``) keeps every keyframe of the run while it is fed (its
online part) and solves them all at once in its ``finish`` (Levenberg-Marquardt, then a
marginal covariance per keyframe), after the other estimators have had every message. Measured
on simulated Husky bags (2.5 keyframes a second; CPU seconds, docs/design/outputs.md "Long
bags"): the whole batch costs ``BATCH_S_PER_1000 * (keyframes / 1000) ** BATCH_EXPONENT`` s, of
which the final solve ``SOLVE_S_PER_1000 * (keyframes / 1000) ** SOLVE_EXPONENT`` s.
``announce_solve`` makes the batch say, before its solve, that it is solving and about how long
that takes, when it is ``NOTICE_ABOVE_S`` or more; the default estimator set leaves the batch
out of a bag whose whole batch would take more than ``DEFAULT_MAX_BATCH_S``
(``DEFAULT_MAX_SPAN_S`` of bag).
"""

from __future__ import annotations

from collections.abc import Callable

# measured (docs/design/outputs.md, "Long bags"): CPU s of the final solve and of the whole batch
# on 1500, 4500, 9000 and 18000 keyframes (10, 30, 60 and 120 min of simulated Husky bag)
SOLVE_S_PER_1000 = 0.395
SOLVE_EXPONENT = 1.057
BATCH_S_PER_1000 = 2.75  # linear: a power law's fit (exponent 0.97) would extrapolate lower
BATCH_EXPONENT = 1.0
NOTICE_ABOVE_S = 60.0
KEYFRAMES_PER_S = 2.5  # a GPS-keyed window at a 2.5 Hz receiver, for the estimate before reading
# s: the longest whole batch the default estimator set waits for; the bag span (s) whose
# estimated batch it is (about 12 h of bag, an extrapolation beyond the 2 h measured) is where
# the default set leaves the batch out
DEFAULT_MAX_BATCH_S = 300.0
DEFAULT_MAX_SPAN_S = (1000.0 * (DEFAULT_MAX_BATCH_S / BATCH_S_PER_1000) ** (1.0 / BATCH_EXPONENT)
                      / KEYFRAMES_PER_S)


def solve_seconds(keyframes: int) -> float:
    """The batch's estimated final solve (s) for ``keyframes`` keyframes (module docstring)."""
    return SOLVE_S_PER_1000 * (max(keyframes, 0) / 1000.0) ** SOLVE_EXPONENT


def batch_seconds(keyframes: int) -> float:
    """The batch's estimated whole cost (s: its online part and the final solve) for
    ``keyframes`` keyframes (module docstring)."""
    return BATCH_S_PER_1000 * (max(keyframes, 0) / 1000.0) ** BATCH_EXPONENT


def _duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 5400 else f"{s / 60:.0f} min" if s >= 90 else f"{s:.0f} s"


def solve_notice(keyframes: int) -> str | None:
    """What to tell the user before a solve of ``keyframes`` keyframes; None when it is
    expected to take less than ``NOTICE_ABOVE_S``."""
    s = solve_seconds(keyframes)
    if s < NOTICE_ABOVE_S:
        return None
    return (f"batch: now solving the whole run at once ({keyframes} keyframes): about "
            f"{_duration(s)} (a model measured on simulated bags; docs/design/outputs.md); "
            "Ctrl-C skips it and keeps the other estimators' results, and --estimators "
            "without batch leaves it out")


def leave_out_notice(span_s: float, others: list[str]) -> str:
    """What to tell the user when the default set leaves the batch out of a bag spanning
    ``span_s`` s (more than ``DEFAULT_MAX_SPAN_S``); ``others``: the estimators that run."""
    s = batch_seconds(int(span_s * KEYFRAMES_PER_S))
    return (f"batch: left out of the default estimators: this bag spans {_duration(span_s)} and "
            f"the batch, which holds and solves the whole run at once, would take about "
            f"{_duration(s)} here (a model measured on simulated bags; docs/design/outputs.md); "
            f"ask for it with --estimators {','.join([*others, 'batch'])}")


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
