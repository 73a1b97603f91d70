"""numpy twins of ``ddfuse.ekf_baseline.joseph``'s two entry points, for a process whose
numba cache does not hold them yet (the first ``ddfuse run`` after installing:
``kalman.update_functions``).

Same contract, shapes and in-place effects as ``joseph.innovation_cov`` / ``joseph.apply_update``
(P (n, n), H (m, n), y (m,), R (m, m), ``Ut`` (m, n); ``blk`` the flat block table, block b's rows
``blk[4 b]:blk[4 b + 1]``; ``verdict`` 0 for an accepted block; ``fs`` each block's factor on its
R in the fusion, applied to R in place). The same algebra in dense matrix products: the sums run
in another order, so the results agree with the compiled functions to rounding (relative ~1e-15
per update), not bit for bit. The inverse of the accepted rows' S is ``joseph.inverse`` itself
(plain Python on at most a few rows), so an update that the compiled path applies is applied here.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from ddfuse.ekf_baseline.joseph import inverse

__all__ = ["apply_update", "innovation_cov"]


@lru_cache(maxsize=16)
def _eye(n: int) -> np.ndarray:
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def innovation_cov(P, H, R):
    """(Ut, S): U = P H^T transposed (m, n) and S = H P H^T + R (m, m) of H (m, n)."""
    Ut = H @ P  # (P H^T)^T = H P^T = H P for the symmetric P
    return Ut, H @ Ut.T + R


def _fuse_noise(R, blk, verdict, fs) -> None:
    """``joseph.fuse_noise``: R_ij of accepted blocks a, b times sqrt(f_a f_b), in place."""
    acc = [b for b in range(verdict.shape[0]) if verdict[b] == 0]
    for a in acc:
        for b in acc:
            f = math.sqrt(fs[a] * fs[b])
            if f != 1.0:
                R[blk[4 * a]:blk[4 * a + 1], blk[4 * b]:blk[4 * b + 1]] *= f


def apply_update(P, H, y, R, Ut, blk, verdict, fs):
    """(P, dx): the covariance after the update from the accepted blocks and the state
    correction dx = K y (n,); ``joseph.apply_update``'s contract (R is fused in place)."""
    # the block table as Python ints: a few numpy reductions here cost more than the update
    vl, bl = verdict.tolist(), blk.tolist()
    if any(vl) or sum(bl[1::4]) - sum(bl[0::4]) != H.shape[0]:
        _fuse_noise(R, blk, verdict, fs)
        rows = np.concatenate([np.arange(blk[4 * b], blk[4 * b + 1])
                               for b in range(verdict.shape[0]) if verdict[b] == 0])
        Ha, Ua, Raa, ya = H[rows], Ut[rows], R[np.ix_(rows, rows)], y[rows]
    else:  # every row in an accepted block (most updates): no copies
        if any(f != 1.0 for f in fs.tolist()):
            _fuse_noise(R, blk, verdict, fs)
        Ha, Ua, Raa, ya = H, Ut, R, y
    Sa = Ha @ Ua.T + Raa
    ma = Ha.shape[0]
    Si = np.empty((ma, ma))
    inverse(Sa, ma, Si)
    K = Ua.T @ Si  # (n, ma)
    dx = K @ ya
    M = _eye(P.shape[0]) - K @ Ha
    B = (M @ P) @ M.T + (K @ Raa) @ K.T
    return 0.5 * (B + B.T), dx
