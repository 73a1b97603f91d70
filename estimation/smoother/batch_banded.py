"""The batch's linear algebra as one banded matrix: the whole run's normal equations factorised
with LAPACK's banded Cholesky, the keyframes' marginal covariances by a backward recursion over
the Cholesky factor's blocks.

Every factor of the batch ties keyframes at most a few apart in time (an interval ties two
neighbours, a fix or a heading sample one keyframe or two neighbours), so with the keys in
keyframe order the information matrix ``H = J^T J`` (``J`` the whitened Jacobian) is banded: 17
off-diagonals for neighbours with 9-vector keys. ``BandedSystem`` builds ``H`` and ``J^T b``
from ``batch_factors.VectorisedGraph`` (the intervals' blocks with numpy, the other factors from
one ``sparseJacobian_`` of gtsam's linearisation) and is the system contract of
``batch_lm.levenberg_marquardt``: the same iteration, with each damped solve
``(H + lambda I) delta = J^T b`` one call of ``scipy.linalg``'s ``cholesky_banded``. The steps are
gtsam's multifrontal Cholesky ones up to rounding (both factorise the normal equations).
"""

from __future__ import annotations

import gtsam
import numpy as np
from ddfuse.estimation.smoother.batch_factors import VectorisedGraph
from ddfuse.factors.state import DIM

# A graph whose factors tie keyframes further apart than this (in keyframe order) goes to
# gtsam's sparse elimination instead: the band's cost grows with its width squared.
MAX_KEY_SPAN = 4


class IndefiniteSystem(RuntimeError):
    """The information matrix is not positive definite (a state no factor determines)."""


def _upper_band_index(rows: np.ndarray, cols: np.ndarray, u: int, n: int) -> np.ndarray:
    """Flat index into a (u + 1, n) LAPACK upper band array of entries (rows <= cols)."""
    return (u + rows - cols) * n + cols


class _Triplets:
    """The pattern of a sparse Jacobian ``J`` given as (row, column) pairs, with the index
    arrays that turn its values into ``J^T J``'s upper band entries: computed once, reused
    while the pattern holds. gtsam's sparse Jacobian leaves exact zeros out, of ``b`` (a prior
    at its own value) and of ``J``: ``b`` is kept apart, and a pattern that changes is rebuilt."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray) -> None:
        self.rows, self.cols = rows, cols
        order = np.lexsort((cols, rows))
        counts = np.bincount(rows) if len(rows) else np.zeros(0, dtype=int)
        starts = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(int)
        nonempty = counts > 0
        c = cols[order]
        at = starts[nonempty]
        # keyframes a row spans
        self.span = int(np.max(np.maximum.reduceat(c, at) // DIM
                               - np.minimum.reduceat(c, at) // DIM)) if len(at) else 0
        self.groups = []  # per row length L: positions of its rows' entries (m, L), upper pairs
        pairs = []
        for length in np.unique(counts[nonempty]).tolist():
            sel = order[starts[counts == length][:, None] + np.arange(length)]
            cc = cols[sel]
            ci = np.broadcast_to(cc[:, :, None], (len(cc), length, length))
            cj = np.broadcast_to(cc[:, None, :], (len(cc), length, length))
            upper = ci <= cj
            self.groups.append((sel, upper))
            pairs.append((ci[upper], cj[upper]))
        self._pairs = pairs

    def band_index(self, u: int, n: int) -> np.ndarray:
        """Where ``weights``' entries go in a flat (u + 1, n) upper band array."""
        if not self._pairs:
            return np.zeros(0, dtype=int)
        return np.concatenate([_upper_band_index(ci, cj, u, n) for ci, cj in self._pairs])

    def same(self, rows: np.ndarray, cols: np.ndarray) -> bool:
        return np.array_equal(rows, self.rows) and np.array_equal(cols, self.cols)

    def weights(self, vals: np.ndarray) -> np.ndarray:
        """``J^T J``'s upper band entries (at ``band_index``) for ``J``'s values ``vals``."""
        out = []
        for sel, upper in self.groups:
            v = vals[sel]
            out.append((v[:, :, None] * v[:, None, :])[upper])
        return np.concatenate(out) if out else np.zeros(0)


class BandedSystem:
    """``graph`` (a ``VectorisedGraph``) over the keys of ``values``, every key a 9-vector, in
    key order (the keyframe index), with ``u`` = 9 * (span + 1) - 1 off-diagonals for the
    widest span of keyframes a factor ties. Build with ``build``, which returns None where the
    banded form does not apply (a key not a 9-vector, a factor tying keyframes more than
    ``MAX_KEY_SPAN`` apart)."""

    def __init__(self, graph: VectorisedGraph, keys: list[int], span: int,
                 first: tuple[gtsam.Values, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                 pattern: _Triplets) -> None:
        """``first``: the rest's triplets (``_rest_triplets``) at the values ``build`` had,
        ``pattern`` their ``_Triplets``."""
        self.graph, self.keys = graph, keys
        self.n = len(keys) * DIM
        self._pos = pos = {k: i for i, k in enumerate(keys)}
        base = np.arange(DIM)
        # the intervals' 18 columns (keyframe i's 9, then j's)
        ii = np.array([pos[k] for k in graph.keys_i], dtype=int)
        ij = np.array([pos[k] for k in graph.keys_j], dtype=int)
        cols = np.concatenate([ii[:, None] * DIM + base, ij[:, None] * DIM + base], axis=1)
        self._int_upper = cols[:, :, None] <= cols[:, None, :]
        shape = self._int_upper.shape
        self._int_pairs = (np.broadcast_to(cols[:, :, None], shape)[self._int_upper],
                           np.broadcast_to(cols[:, None, :], shape)[self._int_upper])
        # the bias rows: one row on keyframe j's 9 columns
        ib = np.array([pos[graph.keys[i]] for i in graph.ib], dtype=int)
        bcols = ib[:, None] * DIM + base
        self._upper9 = base[:, None] <= base[None, :]
        shape = (len(ib), DIM, DIM)
        self._bias_pairs = (np.broadcast_to(bcols[:, :, None], shape)[:, self._upper9].ravel(),
                            np.broadcast_to(bcols[:, None, :], shape)[:, self._upper9].ravel())
        self._static_g = np.concatenate([cols.ravel(), bcols.ravel()])
        self._vg_pos = np.array([pos[k] for k in graph.keys], dtype=int)
        self._rest_cols = self._rest_columns(graph, pos)
        self._x: tuple[gtsam.Values, np.ndarray] | None = None
        self._first: tuple | None = first
        self._set_band(span, pattern)

    def _set_band(self, span: int, pattern: _Triplets) -> None:
        """``u`` for ``span`` and where every entry of ``H`` goes in the band."""
        self.u = u = DIM * (span + 1) - 1
        self._pattern = pattern
        self._band_idx = np.concatenate([_upper_band_index(*self._int_pairs, u, self.n),
                                         _upper_band_index(*self._bias_pairs, u, self.n),
                                         pattern.band_index(u, self.n)])

    @staticmethod
    def _rest_columns(graph: VectorisedGraph, pos: dict[int, int]) -> np.ndarray:
        """Global column of each of the rest's ``sparseJacobian_`` columns but b's: it numbers
        them by the rest's own keys in key order."""
        rest_keys = sorted(int(k) for k in graph.rest.keyVector())
        starts = np.array([pos[k] * DIM for k in rest_keys], dtype=int).reshape(-1, 1)
        return (starts + np.arange(DIM)).ravel()

    @staticmethod
    def _rest_triplets(graph: VectorisedGraph, values: gtsam.Values, col_of: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The rest's whitened system at ``values``: ``J`` as (rows, global columns, values)
        and ``b`` per row."""
        if not graph.rest.size():
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros(0), np.zeros(0)
        trip = graph.rest.linearize(values).sparseJacobian_()
        rows = trip[0].astype(int) - 1
        cols = trip[1].astype(int) - 1
        in_b = cols == len(col_of)
        b = np.zeros(int(rows.max()) + 1 if len(rows) else 0)
        b[rows[in_b]] = trip[2][in_b]
        j = ~in_b
        return rows[j], col_of[cols[j]], trip[2][j], b

    @classmethod
    def build(cls, graph: VectorisedGraph, values: gtsam.Values) -> BandedSystem | None:
        """The banded form of ``graph`` at the keys of ``values``, or None where it does not
        apply (then gtsam's sparse elimination solves it)."""
        keys = sorted(int(k) for k in values.keys())  # noqa: SIM118 (Values: no __iter__)
        try:
            x = [values.atVector(k) for k in keys]
        except RuntimeError:  # not a Vector value
            return None
        if any(xk.shape != (DIM,) for xk in x):
            return None
        pos = {k: i for i, k in enumerate(keys)}
        ii = np.array([pos[k] for k in graph.keys_i], dtype=int)
        ij = np.array([pos[k] for k in graph.keys_j], dtype=int)
        span = int(np.max(np.abs(ij - ii))) if len(ii) else 1
        rows, cols, vals, b = cls._rest_triplets(graph, values, cls._rest_columns(graph, pos))
        pattern = _Triplets(rows, cols)
        span = max(span, pattern.span, 1)
        if span > MAX_KEY_SPAN:
            return None
        system = cls(graph, keys, span, (values, rows, cols, vals, b), pattern)
        system._x = (values, np.array(x))
        return system

    # -- the system contract of batch_lm.levenberg_marquardt -----------------------------------

    def states(self, values: gtsam.Values) -> np.ndarray:
        """The keys' values, shape (n_keys, 9), in key order."""
        if self._x is not None and self._x[0] is values:
            return self._x[1]
        at = values.atVector
        x = np.array([at(k) for k in self.keys]).reshape(-1, DIM)
        self._x = (values, x)
        return x

    def error(self, values: gtsam.Values) -> float:
        """Half the sum of squared whitened residuals at ``values`` (robust losses as gtsam)."""
        return self.graph.error_at(self.states(values)[self._vg_pos], values)

    def retract(self, values: gtsam.Values, delta: np.ndarray) -> gtsam.Values:
        """``values + delta`` (delta shape (n,), in key order)."""
        x = self.states(values) + delta.reshape(-1, DIM)
        out = gtsam.Values()
        for k, xk in zip(self.keys, x, strict=True):
            out.insert(k, xk)
        self._x = (out, x)
        return out

    def linearize(self, values: gtsam.Values) -> BandedStep:
        """The normal equations at ``values``: upper band of ``H``, ``J^T b`` and ``|b|^2``."""
        n, u = self.n, self.u
        x = self.states(values)[self._vg_pos]
        ai, aj, b, hb, eb = self.graph.whitened(x)
        a = np.concatenate([ai, aj], axis=2)  # (intervals, 9, 18): keyframe i's, then j's
        at = np.swapaxes(a, 1, 2)
        hh = hb[:, :, None] * hb[:, None, :]
        if self._first is not None and self._first[0] is values:
            _, rows, cols, vals, rb = self._first
        else:
            rows, cols, vals, rb = self._rest_triplets(self.graph, values, self._rest_cols)
            if not self._pattern.same(rows, cols):  # a Jacobian entry of exactly 0, say
                pattern = _Triplets(rows, cols)
                self._set_band(max(pattern.span, (self.u + 1) // DIM - 1), pattern)
                u = self.u
        self._first = None
        band = np.bincount(self._band_idx, minlength=(u + 1) * n, weights=np.concatenate(
            [(at @ a)[self._int_upper], hh[:, self._upper9].ravel(),
             self._pattern.weights(vals)]))
        g = np.bincount(np.concatenate([self._static_g, cols]), minlength=n,
                        weights=np.concatenate([(at @ b[:, :, None]).ravel(),
                                                (hb * -eb[:, None]).ravel(), vals * rb[rows]]))
        bb = float(np.sum(b * b)) + float(np.sum(eb * eb)) + float(rb @ rb)
        return BandedStep(band.reshape(u + 1, n), g, 0.5 * bb, u)

    def marginals(self, values: gtsam.Values) -> np.ndarray:
        """Every key's marginal covariance, shape (n_keys, 9, 9), in key order: the diagonal
        blocks of ``H^-1`` at ``values`` (gtsam.Marginals' values, up to rounding).
        IndefiniteSystem where ``H`` is not positive definite."""
        step = self.linearize(values)
        return _block_diagonal_of_inverse(step.cholesky(0.0), self.u)


class BandedStep:
    """One linearisation: ``H`` in LAPACK upper band storage (u + 1, n), ``g = J^T b`` (n,) and
    the linear error at zero ``old_error = |b|^2 / 2``."""

    def __init__(self, band: np.ndarray, g: np.ndarray, old_error: float, u: int) -> None:
        self.band, self.g, self.old_error, self.u = band, g, old_error, u

    def cholesky(self, lam: float) -> np.ndarray:
        """The upper band of U with ``U^T U = H + lam I``; IndefiniteSystem if there is none."""
        from scipy.linalg import LinAlgError, cholesky_banded

        damped = self.band.copy()
        damped[self.u] += lam
        try:
            c = cholesky_banded(damped, overwrite_ab=True, lower=False, check_finite=False)
        except (LinAlgError, ValueError) as e:
            raise IndefiniteSystem("the information matrix is not positive definite") from e
        if not np.all(np.isfinite(c)):  # LAPACK passes a NaN pivot through
            raise IndefiniteSystem("the information matrix is not finite")
        return c

    def solve(self, lam: float) -> np.ndarray | None:
        """The damped step ``(H + lam I)^-1 g``, or None where ``H + lam I`` is not positive
        definite (gtsam's IndeterminateLinearSystemException)."""
        from scipy.linalg import cho_solve_banded

        try:
            c = self.cholesky(lam)
        except IndefiniteSystem:
            return None
        delta = cho_solve_banded((c, False), self.g, check_finite=False)
        return delta if np.all(np.isfinite(delta)) else None

    def change(self, delta: np.ndarray) -> float:
        """The linear model's decrease ``|b|^2/2 - |J delta - b|^2/2`` for ``delta``."""
        return float(self.g @ delta) - 0.5 * float(delta @ _band_matvec(self.band, delta, self.u))


def _band_matvec(band: np.ndarray, x: np.ndarray, u: int) -> np.ndarray:
    """``H x`` for symmetric ``H`` in upper band storage."""
    y = band[u] * x
    for d in range(1, u + 1):
        diag = band[u - d, d:]  # H[j - d, j]
        y[:-d] += diag * x[d:]
        y[d:] += diag * x[:-d]
    return y


def _block_diagonal_of_inverse(ub: np.ndarray, u: int) -> np.ndarray:
    """The 9x9 diagonal blocks of ``(U^T U)^-1`` for ``U`` upper banded (LAPACK upper band
    storage, ``u`` off-diagonals). Blocks of ``s`` keys (``9 s >= (u + 1) / 2``) make ``U``
    block upper bidiagonal: row block k of ``U^-1`` is ``D_k^-1`` then ``-D_k^-1 O_k`` times
    row block k + 1, so ``S_k = D_k^-1 D_k^-T + P_k S_{k+1} P_k^T`` with ``P_k = D_k^-1 O_k``."""
    n = ub.shape[1]
    keys_per_block = -(-(u + 1) // (2 * DIM))
    bs = keys_per_block * DIM
    blocks = -(-n // bs)
    padded = np.zeros((u + 1, blocks * bs))
    padded[:, :n] = ub
    padded[u, n:] = 1.0  # decoupled unit variables fill the last block
    p = np.arange(bs)[:, None]
    q = np.arange(bs)[None, :]
    r0 = (np.arange(blocks) * bs)[:, None, None]
    d_ok = (q >= p) & (q - p <= u)
    d = np.where(d_ok, padded[np.where(d_ok, u + p - q, 0), r0 + q], 0.0)
    o_ok = (bs + q - p <= u)
    o = np.where(o_ok, padded[np.where(o_ok, u + p - bs - q, 0), r0[:-1] + bs + q], 0.0)
    dinv = np.linalg.inv(d)
    a = dinv @ np.swapaxes(dinv, 1, 2)
    pk = dinv[:-1] @ o
    s = np.empty_like(a)
    s[-1] = a[-1]
    for k in range(blocks - 2, -1, -1):
        pkk = pk[k]
        s[k] = a[k] + pkk @ s[k + 1] @ pkk.T
    per_key = s.reshape(blocks, keys_per_block, DIM, keys_per_block, DIM)
    diag = per_key[:, np.arange(keys_per_block), :, np.arange(keys_per_block), :]
    out = np.swapaxes(diag, 0, 1).reshape(-1, DIM, DIM)[: n // DIM]
    return 0.5 * (out + np.swapaxes(out, 1, 2))
