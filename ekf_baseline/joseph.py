"""The Kalman update's arithmetic, written once: the cross-covariance U = P H^T, the innovation
covariance S = H U + R, the fused measurement noise, the gain K = U S^-1 with the state
correction K y, and the factored Joseph update P <- (I - K H) P (I - K H)^T + K R K^T.

Plain-float loops over index arrays (``numba.extending.register_jitable``): the compiled
kernels (``ddfuse.ekf_baseline.kalman_jit._update``) compile these functions into their update,
and :class:`ddfuse.ekf_baseline.kalman.KalmanCore` calls them through the two compiled entry
points at the bottom (``innovation_cov``, ``apply_update``). Every sum over state columns
skips H's zeros, so an update costs O(n^2 |C|) for the |C| states H observes, not O(n^3)
(docs/design/ekf_kernels.md).

Shapes (n = state size, nr = stacked measurement rows, ma = accepted rows, nb = blocks): P (n, n),
H (>= nr, n), y (>= nr,), R (>= nr, >= nr); ``Ut`` (>= nr, n) holds U transposed; ``blk`` is the
flat block table of the kernels (block b's row start and stop at ``blk[4 b]``, ``blk[4 b + 1]``),
``verdict`` (nb,) 0 for an accepted block, ``fs`` (nb,) each block's factor on its R in the
fusion; ``rows`` (>= ma,) the accepted rows in order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba.extending import register_jitable

__all__ = ["SIGNATURES", "apply_update", "innovation_cov", "load_cached", "ready"]


@register_jitable
def h_dot(H, r, X, q, n):
    """sum_c H[r, c] X[q, c] over the c where H[r, c] != 0."""
    acc = 0.0
    for c in range(n):
        h = H[r, c]
        if h != 0.0:
            acc += h * X[q, c]
    return acc


@register_jitable
def cross_and_innovation_cov(P, H, R, nr, n, Ut, S):
    """Ut[r, i] <- (P H^T)[i, r] and S[r, q] <- (H P H^T + R)[r, q] for rows 0:nr of H."""
    for r in range(nr):
        for i in range(n):
            Ut[r, i] = h_dot(H, r, P, i, n)
    for r in range(nr):
        for q in range(nr):
            S[r, q] = h_dot(H, r, Ut, q, n) + R[r, q]


@register_jitable
def fuse_noise(R, blk, verdict, fs, nb):
    """Scale R for the fusion: R_ij of accepted blocks a, b (rows i of a, j of b) times
    sqrt(f_a f_b), which within a block is exactly f_a (sqrt(f * f) == f in binary floating
    point): the covariance of each block's noise scaled by sqrt(f). Rejected blocks are left."""
    for a in range(nb):
        if verdict[a] != 0:
            continue
        for b in range(nb):
            if verdict[b] != 0:
                continue
            f = math.sqrt(fs[a] * fs[b])
            if f != 1.0:
                for r in range(blk[4 * a], blk[4 * a + 1]):
                    for q in range(blk[4 * b], blk[4 * b + 1]):
                        R[r, q] *= f


@register_jitable
def accepted_rows(blk, verdict, nb, rows):
    """rows[0:ma] <- the rows of the accepted blocks, in order; returns ma."""
    q = 0
    for b in range(nb):
        if verdict[b] == 0:
            for r in range(blk[4 * b], blk[4 * b + 1]):
                rows[q] = r
                q += 1
    return q


@register_jitable
def inverse(S, m, Si):
    """Si <- the inverse of the m x m matrix S: the adjugate for m <= 3, else Gauss-Jordan with
    partial pivoting (S is a small symmetric positive-definite innovation covariance)."""
    if m == 1:
        Si[0, 0] = 1.0 / S[0, 0]
    elif m == 2:
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        det = a * d - b * c
        Si[0, 0] = d / det
        Si[0, 1] = -b / det
        Si[1, 0] = -c / det
        Si[1, 1] = a / det
    elif m == 3:
        a, b, c = S[0, 0], S[0, 1], S[0, 2]
        d, e, f = S[1, 0], S[1, 1], S[1, 2]
        g, h, i = S[2, 0], S[2, 1], S[2, 2]
        A_ = e * i - f * h
        B_ = f * g - d * i
        C_ = d * h - e * g
        r = 1.0 / (a * A_ + b * B_ + c * C_)
        Si[0, 0] = A_ * r
        Si[0, 1] = (c * h - b * i) * r
        Si[0, 2] = (b * f - c * e) * r
        Si[1, 0] = B_ * r
        Si[1, 1] = (a * i - c * g) * r
        Si[1, 2] = (c * d - a * f) * r
        Si[2, 0] = C_ * r
        Si[2, 1] = (b * g - a * h) * r
        Si[2, 2] = (a * e - b * d) * r
    else:
        M = S[0:m, 0:m].copy()
        for i in range(m):
            for j in range(m):
                Si[i, j] = 1.0 if i == j else 0.0
        for col in range(m):
            piv = col
            for r in range(col + 1, m):
                if abs(M[r, col]) > abs(M[piv, col]):
                    piv = r
            if piv != col:
                for j in range(m):
                    M[col, j], M[piv, j] = M[piv, j], M[col, j]
                    Si[col, j], Si[piv, j] = Si[piv, j], Si[col, j]
            inv = 1.0 / M[col, col]
            for j in range(m):
                M[col, j] *= inv
                Si[col, j] *= inv
            for r in range(m):
                if r != col:
                    fct = M[r, col]
                    if fct != 0.0:
                        for j in range(m):
                            M[r, j] -= fct * M[col, j]
                            Si[r, j] -= fct * Si[col, j]


@register_jitable
def gain(H, y, R, Ut, rows, ma, n, Sa, Si, Kt, dx):
    """The gain of the accepted rows and the state correction: Sa <- H_a U_a + R_aa (with R as
    fused), Si <- Sa^-1, Kt <- (U_a Si)^T (ma, n), dx <- K y_a (n,)."""
    for i in range(ma):
        for j in range(ma):
            Sa[i, j] = h_dot(H, rows[i], Ut, rows[j], n) + R[rows[i], rows[j]]
    inverse(Sa, ma, Si)
    for i in range(n):
        for j in range(ma):
            acc = 0.0
            for l in range(ma):
                acc += Ut[rows[l], i] * Si[l, j]
            Kt[j, i] = acc
    for i in range(n):
        acc = 0.0
        for j in range(ma):
            acc += Kt[j, i] * y[rows[j]]
        dx[i] = acc


@register_jitable
def joseph(P, H, R, rows, ma, n, Kt, KRt, Mt, A, B, cols, inC):
    """P <- M P M^T + K R_aa K^T, M = I - K H_a, exactly symmetrised (the Joseph form in its
    factored form: the expanded P - K U^T - U K^T + K S K^T cancels catastrophically for a
    precise measurement of an uncertain state). M differs from I only in the columns H_a observes
    (support C): M P and (M P) M^T are sums over C only. Scratch: KRt (>= ma, n), Mt (>= n, n),
    A, B (n, n), cols, inC (n,) ints."""
    nc = 0
    for c in range(n):
        for j in range(ma):
            if H[rows[j], c] != 0.0:
                cols[nc] = c
                nc += 1
                break
    for i in range(n):  # Mt[q, i] = M[i, C[q]]
        inC[i] = 0
        for q in range(nc):
            c = cols[q]
            acc = 0.0
            for j in range(ma):
                acc += Kt[j, i] * H[rows[j], c]
            Mt[q, i] = (1.0 if i == c else 0.0) - acc
    for q in range(nc):
        inC[cols[q]] = 1
    for i in range(n):
        keep = inC[i] == 0
        for jj in range(n):
            acc = P[i, jj] if keep else 0.0
            for q in range(nc):
                acc += Mt[q, i] * P[cols[q], jj]
            A[i, jj] = acc
    for i in range(n):
        for j in range(ma):
            acc = 0.0
            for l in range(ma):
                acc += Kt[l, i] * R[rows[l], rows[j]]
            KRt[j, i] = acc
    for i in range(n):
        for jj in range(n):
            acc = 0.0 if inC[jj] else A[i, jj]
            for q in range(nc):
                acc += A[i, cols[q]] * Mt[q, jj]
            kk = 0.0
            for l in range(ma):
                kk += KRt[l, i] * Kt[l, jj]
            B[i, jj] = acc + kk
    for i in range(n):
        for jj in range(n):
            P[i, jj] = 0.5 * (B[i, jj] + B[jj, i])


# ----------------------------------------------------------------------------- entry points
# (KalmanCore's; C-contiguous float64 arrays, int64 block tables). Typed at the first call
# (numba's cache, or a compile); ``ready`` compiles them for SIGNATURES ahead of it (the
# background build of ``ekf_baseline.kernel_build``), ``load_cached`` loads them, never compiling.
@njit(cache=True)
def innovation_cov(P, H, R):
    """(Ut, S): U = P H^T transposed (m, n) and S = H P H^T + R (m, m) of H (m, n)."""
    nr, n = H.shape
    Ut = np.empty((nr, n))
    S = np.empty((nr, nr))
    cross_and_innovation_cov(P, H, R, nr, n, Ut, S)
    return Ut, S


@njit(cache=True)
def apply_update(P, H, y, R, Ut, blk, verdict, fs):
    """(P, dx): the covariance after the update from the accepted blocks (``verdict`` 0) of the
    stacked rows H (m, n), y (m,), R (m, m), with ``Ut`` from ``innovation_cov`` at this P, and
    the state correction dx = K y (n,). R is scaled for the fusion in place (``fuse_noise``)."""
    nr, n = H.shape
    nb = verdict.shape[0]
    fuse_noise(R, blk, verdict, fs, nb)
    rows = np.empty(nr, np.int64)
    ma = accepted_rows(blk, verdict, nb, rows)
    Sa = np.empty((ma, ma))
    Si = np.empty((ma, ma))
    Kt = np.empty((ma, n))
    dx = np.empty(n)
    gain(H, y, R, Ut, rows, ma, n, Sa, Si, Kt, dx)
    out = P.copy()
    KRt = np.empty((ma, n))
    Mt = np.empty((n, n))
    A = np.empty((n, n))
    B = np.empty((n, n))
    cols = np.empty(n, np.int64)
    inC = np.empty(n, np.int64)
    joseph(out, H, R, rows, ma, n, Kt, KRt, Mt, A, B, cols, inC)
    return out, dx


_M = "float64[:, ::1]"
SIGNATURES = {"innovation_cov": f"({_M}, {_M}, {_M})",
              "apply_update": f"({_M}, {_M}, float64[::1], {_M}, {_M}, int64[::1], int64[::1], "
                              "float64[::1])"}


def ready() -> None:
    """Compile the two entry points for SIGNATURES, or load them from numba's cache."""
    from ddfuse.factors.jitcache import arg_types, compiling, one_compiler

    with compiling("the Kalman update's entry points innovation_cov, apply_update"):
        for name, sig in SIGNATURES.items():
            with one_compiler(name):
                globals()[name].compile(arg_types(sig))  # the key a first call caches under


def load_cached() -> bool:
    """Whether both entry points are ready for SIGNATURES: loaded from numba's cache where it
    holds them (never compiling)."""
    from ddfuse.factors.jitcache import arg_types
    from ddfuse.factors.jitcache import load_cached as load

    return all(load(globals()[name], arg_types(sig)) for name, sig in SIGNATURES.items())
