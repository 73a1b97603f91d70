"""A track's scores against the truth over their associated pairs, a block of pairs at a time.

Pure math, no I/O. ``metrics.ape``, ``metrics.association_error`` and
``metrics.nees_series`` build per-pair arrays of the whole track, several (M, 3) at once;
a 2 h track at 10 Hz has M = 72 000 pairs, so those temporaries were the largest memory of a
long run's scoring. Here the pairs ``(i, j)`` (``metrics.associate``: indices into the
estimate and the reference) are computed once by the caller and walked ``block`` at a time:
what is held besides the tracks is one block's temporaries, the per-pair scalar series whose
statistics need every value (median), and for the SE(2) alignment the matched positions.

Every per-pair value is computed by the same elementwise expressions as the whole-array
functions, so the statistics are theirs (``tests/test_pair_scores.py``: block sizes 1, 7 and
larger than the track).
"""

from __future__ import annotations

import numpy as np
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation.metrics import Stats, _apply_se2, alignment, wrap

BLOCK = 8192  # pairs per block


def _blocks(m: int, block: int):
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    return range(0, m, block)


def ape_stats(est: Trajectory, ref: Trajectory, i: np.ndarray, j: np.ndarray,
              align: str = "none", block: int = BLOCK) -> tuple[Stats, Stats]:
    """``metrics.ape(est, ref, max_diff, align)``'s position (m) and heading (rad) statistics
    over the associated pairs ``i`` (into ``est``), ``j`` (into ``ref``), both (M,) int.
    ``align`` 'se2' reads the matched positions whole (two (M, 2) arrays, the alignment's
    sums as numpy forms them); 'origin' the first pair. ValueError where ``metrics.alignment``
    raises it."""
    m = len(i)
    r, t = np.eye(2), np.zeros(2)
    if align == "se2":
        r, t = alignment(est.pose[i], ref.pose[j], align)
    elif align != "none":  # the first pair's (or ValueError for an unknown method)
        r, t = alignment(est.pose[i[:1]], ref.pose[j[:1]], align)
    pos, yaw = np.empty(m), np.empty(m)
    for a in _blocks(m, block):
        pe, pr = est.pose[i[a:a + block]], ref.pose[j[a:a + block]]
        if align != "none":
            pe = _apply_se2(pe, r, t)
        d = pe[:, :2] - pr[:, :2]
        pos[a:a + block] = np.hypot(d[:, 0], d[:, 1])
        yaw[a:a + block] = np.abs(wrap(pe[:, 2] - pr[:, 2]))
    return Stats.of(pos), Stats.of(yaw[np.isfinite(yaw)])


def association_stats(est: Trajectory, ref: Trajectory, i: np.ndarray, j: np.ndarray,
                      block: int = BLOCK) -> Stats:
    """``metrics.association_error`` (m) over the associated pairs ``i``, ``j`` (M,)."""
    m = len(i)
    if m == 0 or len(ref) < 2:
        return Stats.of(np.zeros(0))
    out = np.empty(m)
    for a in _blocks(m, block):
        t = est.t[i[a:a + block]]
        jb = j[a:a + block]
        dx = np.interp(t, ref.t, ref.pose[:, 0]) - ref.pose[jb, 0]
        dy = np.interp(t, ref.t, ref.pose[:, 1]) - ref.pose[jb, 1]
        out[a:a + block] = np.hypot(dx, dy)
    return Stats.of(out)
