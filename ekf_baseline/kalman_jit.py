"""Compiled (numba) hot path of the unicycle EKF and the 11-state IGVC EKF: prediction, the
measurement models, the gate with its lock-out bookkeeping, the Joseph-form update and the
innovation log, on preallocated arrays updated in place.

Why: in Python every filter step costs ~20-40 us of interpreter and numpy call overhead for a
few hundred floating-point operations (docs/results/ekf_speed.md). Here one ``process(m)``
is one call of an entry point below (~0.5 us of call overhead, ~0.3-1 us of arithmetic).

The maths is that of the Python filters, which stay the reference (``reference=True``, the
dense numpy ``KalmanCore.update_blocks``) and the fallback for what this module does not do.
Functions not written here but compiled into these kernels (``numba.extending.register_jitable``,
so they stay plain Python for their other callers): ``ddfuse.factors.kinematics.se2_step_jac``,
``twist_coeffs``, ``ddfuse.ekf_baseline.unicycle.euler_step_jac``, ``unicycle_process_noise_terms``,
``scaled_step_terms`` (prediction with odometry scale states), ``delayed_gps_terms``,
``ddfuse.ekf_baseline.igvc.igvc_q_values`` and the sympy-generated ``*_step_sparse`` of
``ekf_baseline/igvc_jacobians.py``.

Every kernel returns a bit set: ``DEFER`` -- a gated block needs what only Python does (a gate
lock-out candidate that may be a recovery or a corroboration verdict, a non-positive-definite S,
a non-finite NIS, a block of more than two rows); the kernel has then predicted (if asked to)
and changed nothing else, and the caller runs the measurement update in Python on the same
arrays; ``REJECTED`` -- some block was gate-rejected: its count is pending in the sensor table
(``SI_REJ``) for the caller's ``log.rejected`` Counter; ``GROW`` -- the innovation log has no
room: nothing was done, grow it and call again.

Arrays (all float64 or int64, C order; layout constants below; ``ddfuse.ekf_baseline.compiled``
builds them):

* ``fp`` (float, 1-D): header (FP_*), then the state x (n,) at ``FP_X``, the F and Q values and
  random-walk variances at offsets given in ``ip``, and scratch.
* ``ip`` (int, 1-D): header (IP_*), the angle states, F's nonzero (row, col) pairs, Q's (row,
  col) pairs, the random-walk states.
* ``W`` (float, 2-D, (4 n + 8 MAXR, n)): rows 0:n the covariance P, then scratch.
* ``sf``, ``si`` (float / int, (sensors, SF_COLS / SI_COLS)): per sensor its gate thresholds,
  biases, offsets, lever arm, delay, and per (sensor, kind) slot the gate streak, the last
  acceptance and the recovery hold-off (``KalmanCore._streak``, ``_last_ok``, ``_holdoff``).
* ``lg`` (float, (capacity, LG_COLS)): innovation log rows (t, nis, y0, y1, S00, S01, S10, S11,
  sensor row, kind, m, accepted), ``ip[IP_LOGN]`` of them used.
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline.compiled import (  # noqa: F401 - re-exported: the kernels' codes
    DEFER,
    GROW,
    IGVC_KINDS,
    REJECTED,
    T_ACCEL,
    T_GPS,
    T_GYRO,
    T_HEAD,
    T_HEAD_POSE,
    T_NONE,
    T_ODOM,
    T_WHEELS,
    UNI_KINDS,
)
from ddfuse.ekf_baseline.igvc import igvc_q_values
from ddfuse.ekf_baseline.unicycle import (
    delayed_gps_terms,
    euler_step_jac,
    pose_correct,
    scaled_step_terms,
    se2_error_terms,
    unicycle_process_noise_terms,
)
from ddfuse.factors.kinematics import se2_step_jac, twist_coeffs
from numba import njit
from numba.extending import register_jitable

for _f in (twist_coeffs, se2_step_jac, euler_step_jac, unicycle_process_noise_terms,
           scaled_step_terms, delayed_gps_terms, se2_error_terms, pose_correct, igvc_q_values,
           gen.euler_step_sparse, gen.icc_step_sparse):
    register_jitable(_f)


MAXR = 2  # rows per measurement (GPS, wheel speeds, odometry); scratch of the event kernels
MAXB = 2  # blocks per measurement (odometry: v and yaw rate)

# ip header
IP_N = 0  # state size n
IP_MOTION = 1  # unicycle: 0 exact SE(2), 1 Euler; igvc: 0 euler, 1 icc
IP_NANG = 2  # number of angle states
IP_LOCKN = 3  # lockout_count
IP_LOGN = 4  # innovation log rows used
IP_LOGCAP = 5  # rows of lg
IP_KS = 6  # index of k_v (k_w follows), -1 without the scale states
IP_NF = 7  # nonzeros of F
IP_NQ = 8  # entries of Q set from the model's process noise
IP_NWALK = 9  # random-walk (calibration) states
IP_OFF_F = 10  # offset of F's (row, col) pairs in ip; their values at ip[IP_OFF_FVAL] in fp
IP_OFF_Q = 11  # offset of Q's (row, col) pairs in ip
IP_OFF_WALK = 12  # offset of the random-walk state indices in ip
IP_OFF_FVAR = 13  # offset in ip: for each entry of the model's F values, its F entry number
IP_NFVAR = 14  # number of those
IP_OFF_FVAL = 16  # offset in fp of F's values (IP_NF of them)
IP_OFF_QVAL = 17  # offset in fp of Q's values
IP_OFF_WALKV = 18  # offset in fp of the random-walk variances per second
IP_LIE = 19  # unicycle: 1 when the pose error is in SE(2) exponential coordinates (body-frame
# rho, theta; UnicycleEkf(pose_error='se2')): se2_error_terms' F and Q, the GPS rows' R(psi),
# the position correction by pose_correct
IP_WTRUE = 20  # unicycle with scale states: 1 when state 4 is the true yaw rate (a gyro is
# fused), 0 when it is the odometry's (UnicycleEkf._w_true)
IP_ANG = 24  # angle state indices (up to 8)
MAXANG = 8
IP_OFF_ZI = 15  # offset in ip of the event kernels' block table (MAXB, 4), then int scratch
IP_HEADER = 40

# fp header
FP_LOCKT = 0  # lockout_time, s
FP_LASTNIS = 1  # NIS of the last gated block (KalmanCore.last_nis)
FP_WHEEL_R = 2  # m, wheel radius (NaN: not configured)
FP_TRACK = 3  # m, track width (NaN: not configured)
FP_RADIUS = 4  # m, igvc: the Earth sphere's radius
FP_MAXSTEP = 5  # s, igvc: longest prediction step
FP_NOISE = 8  # process noise densities (8 slots), the filter's order (unicycle: set by
# UnicycleEkf whenever the acceleration-limit densities change)
FP_SCR = 16  # scratch: y (MAXR), zf (2 MAXB), fs (MAXB)
FP_X = 48  # the state x (n,)

# sensor table columns; slot (per kind k) columns at SF_K + SF_KW k, SI_K + SI_KW k
SF_THR1, SF_THR2, SF_BIAS, SF_HOFF, SF_LX, SF_LY, SF_DELAY = range(7)
SF_K = 8
SF_KW = 4
SK_T0, SK_OKT, SK_HOLD_UNTIL, SK_HOLD_WAIT = range(4)
SI_BIAS, SI_HOFF, SI_REJ = range(3)
SI_K = 4
SI_KW = 5
SK_CNT, SK_ACC, SK_EXISTS, SK_OKMASK, SK_HOLD = range(5)
NKIND = 6
SF_COLS = SF_K + SF_KW * NKIND
SI_COLS = SI_K + SI_KW * NKIND
LG_COLS = 12

# kinds (slots, UNI_KINDS / IGVC_KINDS) of the unicycle filter, and of the igvc filter
K_GYRO, K_HEAD, K_V, K_YAWRATE, K_WHEELS, K_GPS = range(6)
KI_GYRO, KI_HEAD, KI_ACCEL, KI_ODOM, KI_WHEELS, KI_GPS = range(6)

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi
# the entries of unicycle_process_noise_terms' upper triangle that are off the diagonal
_UNI_Q_OFFDIAG = (1, 2, 3, 4, 6, 7, 8, 10, 11, 13)
# igvc state indices
_LAT, _LON, _THETA, _X, _Y, _PSI, _V, _W, _VL, _VR, _A = range(11)


@njit(cache=True)
def _wrap(a):
    return (a + _PI) % _TWO_PI - _PI


@njit(cache=True)
def _wrap_states(x, ip):
    for k in range(ip[IP_NANG]):
        i = ip[IP_ANG + k]
        x[i] = (x[i] + _PI) % _TWO_PI - _PI


# ----------------------------------------------------------------------------- prediction
@njit(cache=True)
def _propagate_cov(fp, ip, W, n, dt):
    """P <- F P F^T + Q, symmetrised (KalmanCore.predict), F and Q sparse: F's (row, col) pairs
    in ip, values in fp (filled by the caller); Q's model entries likewise plus dt times the
    random-walk variances on their diagonal."""
    P = W[0:n]
    A = W[n:2 * n]
    B = W[2 * n:3 * n]
    nf = ip[IP_NF]
    of = ip[IP_OFF_F]
    ofv = ip[IP_OFF_FVAL]
    for i in range(n):
        for j in range(n):
            A[i, j] = 0.0
            B[i, j] = 0.0
    for e in range(nf):  # A = F P
        r = ip[of + 2 * e]
        c = ip[of + 2 * e + 1]
        v = fp[ofv + e]
        for j in range(n):
            A[r, j] += v * P[c, j]
    for e in range(nf):  # B = A F^T
        r = ip[of + 2 * e]
        c = ip[of + 2 * e + 1]
        v = fp[ofv + e]
        for i in range(n):
            B[i, r] += A[i, c] * v
    oq = ip[IP_OFF_Q]
    oqv = ip[IP_OFF_QVAL]
    for e in range(ip[IP_NQ]):
        B[ip[oq + 2 * e], ip[oq + 2 * e + 1]] += fp[oqv + e]
    ow = ip[IP_OFF_WALK]
    owv = ip[IP_OFF_WALKV]
    for e in range(ip[IP_NWALK]):
        i = ip[ow + e]
        B[i, i] += fp[owv + e] * dt
    for i in range(n):
        for j in range(n):
            P[i, j] = 0.5 * (B[i, j] + B[j, i])


@njit(cache=True)
def _uni_predict(fp, ip, W, n, dt):
    """UnicycleEkf._predict_to for dt > 0 s: the constant-twist (or Euler) step of (x, y, psi),
    F (its Jacobian, identity elsewhere), Q (unicycle_process_noise_terms + walks); with the
    odometry scale states (IP_KS >= 0) scaled_step_terms."""
    x = fp[FP_X:FP_X + n]
    ofv = ip[IP_OFF_FVAL]
    ks = ip[IP_KS]
    # F's entries in the order UnicycleEkf._compiled_core lays them out: rows 0..2 first
    if ip[IP_LIE] != 0:  # UnicycleEkf._predict_to's se2 branch
        kv = 1.0 if ks < 0 else x[ks]
        kw = 1.0 if ks < 0 else x[ks + 1]
        x1, y1, p1, F0, q0 = scaled_step_terms(
            x[0], x[1], x[2], x[3], x[4], kv, kw, dt, ip[IP_MOTION] != 0,
            fp[FP_NOISE], fp[FP_NOISE + 1], fp[FP_NOISE + 2], fp[FP_NOISE + 3],
            fp[FP_NOISE + 4], ip[IP_WTRUE] != 0)
        F, q = se2_error_terms(x[2], p1, F0, q0)
        fp[ofv + 0] = F[12]
        fp[ofv + 1] = F[0]
        fp[ofv + 2] = F[1]
        fp[ofv + 3] = F[2]
        fp[ofv + 4] = F[15]
        fp[ofv + 5] = F[3]
        fp[ofv + 6] = F[4]
        fp[ofv + 7] = F[5]
        fp[ofv + 9] = F[6]
        o2 = ofv + 10
        if ks >= 0:
            for k in range(5):
                fp[ofv + 10 + k] = F[7 + k]
            o2 = ofv + 15
        fp[o2] = F[13]  # the pose block's (0, 1), (1, 0)
        fp[o2 + 1] = F[14]
    elif ks < 0:
        if ip[IP_MOTION] == 0:
            x1, y1, p1, J = se2_step_jac(x[0], x[1], x[2], x[3], x[4], dt)
        else:
            x1, y1, p1, J = euler_step_jac(x[0], x[1], x[2], x[3], x[4], dt)
        fp[ofv + 1] = J[0][2]
        fp[ofv + 2] = J[0][3]
        fp[ofv + 3] = J[0][4]
        fp[ofv + 5] = J[1][2]
        fp[ofv + 6] = J[1][3]
        fp[ofv + 7] = J[1][4]
        fp[ofv + 9] = dt
        q = unicycle_process_noise_terms(x[2], x[3], dt, fp[FP_NOISE], fp[FP_NOISE + 1],
                                         fp[FP_NOISE + 2], fp[FP_NOISE + 3], fp[FP_NOISE + 4])
    else:  # then the scale columns of x, y, psi
        x1, y1, p1, F, q = scaled_step_terms(
            x[0], x[1], x[2], x[3], x[4], x[ks], x[ks + 1], dt, ip[IP_MOTION] != 0,
            fp[FP_NOISE], fp[FP_NOISE + 1], fp[FP_NOISE + 2], fp[FP_NOISE + 3],
            fp[FP_NOISE + 4], ip[IP_WTRUE] != 0)
        fp[ofv + 1] = F[0]
        fp[ofv + 2] = F[1]
        fp[ofv + 3] = F[2]
        fp[ofv + 5] = F[3]
        fp[ofv + 6] = F[4]
        fp[ofv + 7] = F[5]
        fp[ofv + 9] = F[6]
        for k in range(5):
            fp[ofv + 10 + k] = F[7 + k]
    oqv = ip[IP_OFF_QVAL]
    for k in range(15):  # the upper triangle, then its off-diagonal entries again (lower)
        fp[oqv + k] = q[k]
    for j in range(10):
        fp[oqv + 15 + j] = q[_UNI_Q_OFFDIAG[j]]
    x[0] = x1
    x[1] = y1
    x[2] = p1
    _wrap_states(x, ip)
    _propagate_cov(fp, ip, W, n, dt)


@njit(cache=True)
def _igvc_predict(fp, ip, W, n, dt_total):
    """IgvcEkf.predict_to for dt_total > 0 s: steps of at most FP_MAXSTEP, each the generated
    model step (its sparse Jacobian) and igvc_q_values."""
    x = fp[FP_X:FP_X + n]
    nsteps = max(1, math.ceil(dt_total / fp[FP_MAXSTEP] - 1e-9))
    dt = dt_total / nsteps
    track = fp[FP_TRACK]
    radius = fp[FP_RADIUS]
    ofv = ip[IP_OFF_FVAL]
    ovar = ip[IP_OFF_FVAR]
    oqv = ip[IP_OFF_QVAL]
    for _ in range(nsteps):
        s = (x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8], x[9], x[10])
        # the two models' Jacobians have different sparsity (tuples of different lengths)
        if ip[IP_MOTION] == 0:
            f, fv = gen.euler_step_sparse(s, dt, track, radius)
            for k in range(len(fv)):
                fp[ofv + ip[ovar + k]] = fv[k]
        else:
            f, fv = gen.icc_step_sparse(s, dt, track, radius)
            for k in range(len(fv)):
                fp[ofv + ip[ovar + k]] = fv[k]
        q = igvc_q_values(x[_LAT], dt, radius, fp[FP_NOISE], fp[FP_NOISE + 1], fp[FP_NOISE + 2],
                          fp[FP_NOISE + 3], fp[FP_NOISE + 4], fp[FP_NOISE + 5],
                          fp[FP_NOISE + 6])
        for k in range(16):
            fp[oqv + k] = q[k]
        for k in range(11):
            x[k] = f[k]
        _wrap_states(x, ip)
        _propagate_cov(fp, ip, W, n, dt)


# ----------------------------------------------------------------------------- update
@njit(cache=True)
def _inverse(S, m, Si):
    """Si <- the inverse of the m x m matrix S: the adjugate for m <= 3 (as KalmanCore), else
    Gauss-Jordan with partial pivoting."""
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
        M = S.copy()
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


@njit(cache=True)
def _update(fp, ip, W, sf, si, lg, t, H, y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs):
    """KalmanCore.update_blocks (dense reference semantics) of ``nb`` blocks stacked in rows
    0:nr of H (nr, n), y (nr,), R (nr, nr) (block diagonal); ``blk`` (nb, 4) = (row start, row
    stop, sensor row, kind); ``fs`` (nb,) each block's factor on its R in the fusion
    (KalmanCore's ``fuse``: 1.0, or a time-correlated GPS fix's inflation). Scratch (no
    allocation per call): Ut (>= nr, n) for (P H^T)^T, S (>= nr, >= nr), Z (4 nr + n,
    >= max(n, nr)), zf (>= 2 nb), zi (>= 4 nb + nr + 2 n); ``blk`` is flat: block b's fields at
    4 b .. 4 b + 3. On return (without DEFER) zi[0:nb] holds the verdicts (0 fused).

    Each block is gated on its own against the common prior (its diagonal block of
    S = H P H^T + R), the per-(sensor, kind) streaks are those of KalmanCore._judge, rejected
    blocks are logged first and accepted ones after the update (the reference's order), then
    one Joseph-form update applies the accepted rows, with R scaled by ``fs`` (S, the NIS and
    the log keep R). Returns the module's bits."""
    n = ip[IP_N]
    P = W[0:n]
    x = fp[FP_X:FP_X + n]
    # U = P H^T (stored transposed), S = H U + R
    for r in range(nr):
        for i in range(n):
            acc = 0.0
            for c in range(n):
                h = H[r, c]
                if h != 0.0:
                    acc += P[i, c] * h
            Ut[r, i] = acc
    for r in range(nr):
        for q in range(nr):
            acc = 0.0
            for c in range(n):
                h = H[r, c]
                if h != 0.0:
                    acc += h * Ut[q, c]
            S[r, q] = acc + R[r, q]
    # gate every block against the prior; streaks simulated on copies (a DEFER must leave them)
    lockn = ip[IP_LOCKN]
    lockt = fp[FP_LOCKT]
    verdict = zi[0:nb]  # 0 accepted, 1 rejected
    cnt = zi[nb:2 * nb]
    acc_n = zi[2 * nb:3 * nb]
    ex = zi[3 * nb:4 * nb]
    nis_b = zf[0:nb]
    t0 = zf[nb:2 * nb]
    for b in range(nb):
        r0 = blk[4 * b + 0]
        r1 = blk[4 * b + 1]
        s = blk[4 * b + 2]
        k = blk[4 * b + 3]
        m = r1 - r0
        if m == 1:
            s00 = S[r0, r0]
            if not s00 > 0.0:
                return DEFER
            nis = y[r0] * y[r0] / s00
            thr = sf[s, SF_THR1]
        elif m == 2:
            a = S[r0, r0]
            bb = S[r0, r0 + 1]
            d = S[r0 + 1, r0 + 1]
            det = a * d - bb * bb
            if not (a > 0.0 and det > 0.0):
                return DEFER
            y0 = y[r0]
            y1 = y[r0 + 1]
            nis = (d * y0 * y0 - 2.0 * bb * y0 * y1 + a * y1 * y1) / det
            thr = sf[s, SF_THR2]
        else:
            return DEFER
        if not math.isfinite(nis):
            return DEFER
        nis_b[b] = nis
        # this slot's streak: after an earlier block of the same slot in this call, else stored
        prev = -1
        for j in range(b):
            if blk[4 * j + 2] == s and blk[4 * j + 3] == k:
                prev = j
        cb = SI_K + SI_KW * k
        fb = SF_K + SF_KW * k
        if prev >= 0:
            c_, a_, e_, t_ = cnt[prev], acc_n[prev], ex[prev], t0[prev]
        else:
            c_, a_, e_, t_ = si[s, cb + SK_CNT], si[s, cb + SK_ACC], si[s, cb + SK_EXISTS], \
                sf[s, fb + SK_T0]
        if nis > thr:
            if e_ == 0:
                e_, c_, t_, a_ = 1, 0, t, 0
            if c_ == 0:
                t_ = t
            c_ += 1
            # a lock-out candidate. KalmanCore._holdoff_over is False only while a hold-off
            # runs (no side effects then); otherwise the recovery or corroboration decision
            # is Python's
            if c_ >= lockn and t - t_ >= lockt and not (
                    si[s, cb + SK_HOLD] != 0 and a_ < lockn and t < sf[s, fb + SK_HOLD_UNTIL]):
                return DEFER
            verdict[b] = 1
        else:
            if e_ != 0:
                c_ = 0
                a_ += 1
            verdict[b] = 0
        cnt[b], acc_n[b], ex[b], t0[b] = c_, a_, e_, t_
    # commit: streaks, last NIS, rejected blocks logged and counted
    code = 0
    ln = ip[IP_LOGN]
    n_acc_rows = 0
    for b in range(nb):
        s = blk[4 * b + 2]
        k = blk[4 * b + 3]
        cb = SI_K + SI_KW * k
        si[s, cb + SK_CNT] = cnt[b]
        si[s, cb + SK_ACC] = acc_n[b]
        si[s, cb + SK_EXISTS] = ex[b]
        sf[s, SF_K + SF_KW * k + SK_T0] = t0[b]
        if verdict[b] == 1:
            _log_row(lg, ln, t, nis_b[b], y, S, blk, b, 0.0)
            ln += 1
            si[s, SI_REJ] += 1
            code |= REJECTED
        else:
            n_acc_rows += blk[4 * b + 1] - blk[4 * b + 0]
    fp[FP_LASTNIS] = nis_b[nb - 1]
    ip[IP_LOGN] = ln
    if n_acc_rows == 0:
        return code
    # the accepted rows
    o = 4 * nb
    rows = zi[o:o + n_acc_rows]
    cols = zi[o + nr:o + nr + n]
    inC = zi[o + nr + n:o + nr + 2 * n]
    q = 0
    for b in range(nb):
        if verdict[b] == 0:
            for r in range(blk[4 * b + 0], blk[4 * b + 1]):
                rows[q] = r
                q += 1
    ma = n_acc_rows
    # the fusion's R: an accepted block's R times its factor (R is scratch; the log keeps S)
    scaled = False
    for b in range(nb):
        f = fs[b]
        if verdict[b] == 0 and f != 1.0:
            scaled = True
            for r in range(blk[4 * b + 0], blk[4 * b + 1]):
                for q in range(blk[4 * b + 0], blk[4 * b + 1]):
                    R[r, q] *= f
    # S of the accepted rows and its inverse: in U^T's rows (U is not needed after K)
    Sa = Z[2 * nr + n:2 * nr + n + ma, 0:ma]
    Si = Z[3 * nr + n:3 * nr + n + ma, 0:ma]
    if scaled:  # H P H^T + f R, as S above
        for i in range(ma):
            for j in range(ma):
                acc = 0.0
                for c in range(n):
                    h = H[rows[i], c]
                    if h != 0.0:
                        acc += h * Ut[rows[j], c]
                Sa[i, j] = acc + R[rows[i], rows[j]]
    else:
        for i in range(ma):
            for j in range(ma):
                Sa[i, j] = S[rows[i], rows[j]]
    _inverse(Sa, ma, Si)
    # K = U S^-1 (n, ma), stored transposed
    Kt = Z[0:ma]
    KRt = Z[nr:nr + ma]
    Mt = Z[2 * nr:2 * nr + n]
    for i in range(n):
        for j in range(ma):
            acc = 0.0
            for l in range(ma):
                acc += Ut[rows[l], i] * Si[l, j]
            Kt[j, i] = acc
    px = x[0]
    py = x[1]
    psi0 = x[2]
    d0 = 0.0
    d1 = 0.0
    for i in range(n):
        acc = 0.0
        for j in range(ma):
            acc += Kt[j, i] * y[rows[j]]
        if i == 0:
            d0 = acc
        elif i == 1:
            d1 = acc
        x[i] += acc
    if ip[IP_LIE] != 0:  # the body-frame position correction (UnicycleEkf._apply)
        x[0], x[1] = pose_correct(px, py, psi0, d0, d1)
    # Joseph form, factored: P <- M P M^T + K R K^T, M = I - K H. M differs from I only in the
    # columns H observes (support C): A = M P and M A^T are sums over C only
    nc = 0
    for c in range(n):
        for j in range(ma):
            if H[rows[j], c] != 0.0:
                cols[nc] = c
                nc += 1
                break
    for i in range(n):  # Mt[q, i] = M[i, C[q]]
        inC[i] = 0
        for q2 in range(nc):
            c = cols[q2]
            acc = 0.0
            for j in range(ma):
                acc += Kt[j, i] * H[rows[j], c]
            Mt[q2, i] = (1.0 if i == c else 0.0) - acc
    for q2 in range(nc):
        inC[cols[q2]] = 1
    A = W[n:2 * n]
    B = W[2 * n:3 * n]
    for i in range(n):
        keep = inC[i] == 0
        for jj in range(n):
            acc = P[i, jj] if keep else 0.0
            for q2 in range(nc):
                acc += Mt[q2, i] * P[cols[q2], jj]
            A[i, jj] = acc
    # K R K^T
    for i in range(n):
        for j in range(ma):
            acc = 0.0
            for l in range(ma):
                acc += Kt[l, i] * R[rows[l], rows[j]]
            KRt[j, i] = acc
    for i in range(n):
        for jj in range(n):
            acc = 0.0 if inC[jj] else A[i, jj]
            for q2 in range(nc):
                acc += A[i, cols[q2]] * Mt[q2, jj]
            kk = 0.0
            for l in range(ma):
                kk += KRt[l, i] * Kt[l, jj]
            B[i, jj] = acc + kk
    for i in range(n):
        for jj in range(n):
            P[i, jj] = 0.5 * (B[i, jj] + B[jj, i])
    _wrap_states(x, ip)
    # accepted blocks: logged in order, their last acceptance (time, observed columns) kept
    for b in range(nb):
        if verdict[b] == 0:
            s = blk[4 * b + 2]
            k = blk[4 * b + 3]
            _log_row(lg, ln, t, nis_b[b], y, S, blk, b, 1.0)
            ln += 1
            mask = 0
            for c in range(n):
                for r in range(blk[4 * b + 0], blk[4 * b + 1]):
                    if H[r, c] != 0.0:
                        mask |= 1 << c
                        break
            sf[s, SF_K + SF_KW * k + SK_OKT] = t
            si[s, SI_K + SI_KW * k + SK_OKMASK] = mask
    ip[IP_LOGN] = ln
    return code


@njit(cache=True)
def _log_row(lg, ln, t, nis, y, S, blk, b, accepted):
    r0 = blk[4 * b + 0]
    m = blk[4 * b + 1] - r0
    lg[ln, 0] = t
    lg[ln, 1] = nis
    lg[ln, 2] = y[r0]
    lg[ln, 4] = S[r0, r0]
    if m == 2:
        lg[ln, 3] = y[r0 + 1]
        lg[ln, 5] = S[r0, r0 + 1]
        lg[ln, 6] = S[r0 + 1, r0]
        lg[ln, 7] = S[r0 + 1, r0 + 1]
    lg[ln, 8] = blk[4 * b + 2]
    lg[ln, 9] = blk[4 * b + 3]
    lg[ln, 10] = m
    lg[ln, 11] = accepted


# ----------------------------------------------------------------------------- models
@njit(cache=True)
def _uni_model(fp, ip, sf, si, H, y, R, blk, nr, nb, typ, s, z0, z1, r0, r1, r01, r10, flags):
    """Rows of one message for the unicycle EKF (UnicycleEkf._apply / _gps_model), appended at
    row ``nr`` and block ``nb``; returns the new (nr, nb). The caller has checked what decides
    whether the message is used at all (``uses``, initialisation, offsets initialised)."""
    n = ip[IP_N]
    x = fp[FP_X:FP_X + n]
    ks = ip[IP_KS]
    if typ == T_NONE:
        return nr, nb
    if typ == T_GYRO:
        _zero_rows(H, R, nr, 1)
        bi = si[s, SI_BIAS]
        b = sf[s, SF_BIAS] if bi < 0 else x[bi]
        if ks < 0 or ip[IP_WTRUE] != 0:
            y[nr] = z0 - (x[4] + b)
            H[nr, 4] = 1.0
        else:  # the gyro sees the true yaw rate k_w om (+ bias)
            kw = x[ks + 1]
            om = x[4]
            y[nr] = z0 - (kw * om + b)
            H[nr, 4] = kw
            H[nr, ks + 1] = om
        if bi >= 0:
            H[nr, bi] = 1.0
        R[nr, nr] = r0
        return _block(blk, nr, 1, nb, s, K_GYRO)
    if typ == T_HEAD:
        _zero_rows(H, R, nr, 1)
        hi = si[s, SI_HOFF]
        if hi < 0:
            hpred = x[2] + sf[s, SF_HOFF]
        else:
            hpred = x[2] + x[hi]
            H[nr, hi] = 1.0
        H[nr, 2] = 1.0
        y[nr] = (z0 - hpred + _PI) % _TWO_PI - _PI
        R[nr, nr] = r0
        return _block(blk, nr, 1, nb, s, K_HEAD)
    if typ == T_ODOM:
        # the odometry's twist is the state's (with scale states, the odometry-frame twist)
        if flags & 1:
            _zero_rows(H, R, nr, 1)
            y[nr] = z0 - x[3]
            H[nr, 3] = 1.0
            R[nr, nr] = r0
            nr, nb = _block(blk, nr, 1, nb, s, K_V)
        if flags & 2:
            _zero_rows(H, R, nr, 1)
            if ks >= 0 and ip[IP_WTRUE] != 0:  # the true yaw rate / k_w
                kw = x[ks + 1]
                y[nr] = z1 - x[4] / kw
                H[nr, 4] = 1.0 / kw
                H[nr, ks + 1] = -x[4] / (kw * kw)
            else:
                y[nr] = z1 - x[4]
                H[nr, 4] = 1.0
            R[nr, nr] = r1
            nr, nb = _block(blk, nr, 1, nb, s, K_YAWRATE)
        return nr, nb
    if typ == T_GPS:
        _zero_rows(H, R, nr, 2)
        lx = sf[s, SF_LX]
        ly = sf[s, SF_LY]
        d = sf[s, SF_DELAY]
        c = math.cos(x[2])
        sn = math.sin(x[2])
        if d == 0.0:
            y[nr] = z0 - (x[0] + c * lx - sn * ly)
            y[nr + 1] = z1 - (x[1] + sn * lx + c * ly)
            H[nr, 0] = 1.0
            H[nr + 1, 1] = 1.0
            if not (lx == 0.0 and ly == 0.0):
                H[nr, 2] = -sn * lx - c * ly
                H[nr + 1, 2] = c * lx - sn * ly
        else:  # the antenna d s before the state's time: the exact step backwards
            kv = 1.0 if ks < 0 else x[ks]
            kw = 1.0 if ks < 0 else x[ks + 1]
            g = delayed_gps_terms(x[0], x[1], x[2], x[3], x[4], kv, kw, lx, ly, d,
                                  ip[IP_WTRUE] != 0)
            y[nr] = z0 - g[0]
            y[nr + 1] = z1 - g[1]
            H[nr, 0] = 1.0
            H[nr, 2] = g[2]
            H[nr, 3] = g[3]
            H[nr, 4] = g[4]
            H[nr + 1, 1] = 1.0
            H[nr + 1, 2] = g[7]
            H[nr + 1, 3] = g[8]
            H[nr + 1, 4] = g[9]
            if ks >= 0:
                H[nr, ks] = g[5]
                H[nr, ks + 1] = g[6]
                H[nr + 1, ks] = g[10]
                H[nr + 1, ks + 1] = g[11]
        if ip[IP_LIE] != 0:  # d(east, north) / d(rho_x, rho_y) = R(psi)
            H[nr, 0] = c
            H[nr, 1] = -sn
            H[nr + 1, 0] = sn
            H[nr + 1, 1] = c
        R[nr, nr] = r0
        R[nr, nr + 1] = r01
        R[nr + 1, nr] = r10
        R[nr + 1, nr + 1] = r1
        return _block(blk, nr, 2, nb, s, K_GPS)
    if typ == T_WHEELS:
        _zero_rows(H, R, nr, 2)
        rw = fp[FP_WHEEL_R]
        k = 0.5 * fp[FP_TRACK] / rw
        # the nominal geometry turns the state's (odometry-frame) twist into wheel speeds
        if ks >= 0 and ip[IP_WTRUE] != 0:  # (the odometry-frame yaw rate is w / k_w)
            kw = x[ks + 1]
            k /= kw
            dk = x[4] * k / kw
            H[nr, ks + 1] = dk
            H[nr + 1, ks + 1] = -dk
        vr = x[3] / rw
        wr = x[4] * k
        H[nr, 3] = 1.0 / rw
        H[nr, 4] = -k
        H[nr + 1, 3] = 1.0 / rw
        H[nr + 1, 4] = k
        y[nr] = z0 - (vr - wr)
        y[nr + 1] = z1 - (vr + wr)
        R[nr, nr] = r0
        R[nr + 1, nr + 1] = r1
        return _block(blk, nr, 2, nb, s, K_WHEELS)
    return nr, nb


@njit(cache=True)
def _igvc_model(fp, ip, sf, si, H, y, R, blk, nr, nb, typ, s, z0, z1, r0, r1, r01, r10, flags):
    """Rows of one message for the IGVC EKF (IgvcEkf._measurement, _odometry_model,
    _gps_metres with gps_model); as _uni_model. For a GpsFix z0, z1 are its latitude and
    longitude in degrees; for odometry ``flags`` bit 0 = v present, bit 1 = yaw rate present."""
    n = ip[IP_N]
    x = fp[FP_X:FP_X + n]
    ks = ip[IP_KS]
    if typ == T_NONE:
        return nr, nb
    if typ == T_GYRO:
        _zero_rows(H, R, nr, 1)
        bi = si[s, SI_BIAS]
        if bi < 0:
            y[nr] = z0 - (x[_W] + sf[s, SF_BIAS])
        else:
            y[nr] = z0 - (x[_W] + x[bi])
            H[nr, bi] = 1.0
        H[nr, _W] = 1.0
        R[nr, nr] = r0
        return _block(blk, nr, 1, nb, s, KI_GYRO)
    if typ == T_HEAD or typ == T_HEAD_POSE:  # noqa: SIM109 - plain compares for numba
        _zero_rows(H, R, nr, 1)
        if typ == T_HEAD_POSE:
            g = x[_PSI]
            H[nr, _PSI] = 1.0
        else:
            g = _HALF_PI - x[_THETA]
            H[nr, _THETA] = -1.0
        hi = si[s, SI_HOFF]
        if hi >= 0:
            offset = x[hi]
            H[nr, hi] = 1.0
        else:
            offset = sf[s, SF_HOFF]
        h = (g + offset + _PI) % _TWO_PI - _PI
        y[nr] = (z0 - h + _PI) % _TWO_PI - _PI
        R[nr, nr] = r0
        return _block(blk, nr, 1, nb, s, KI_HEAD)
    if typ == T_ACCEL:
        _zero_rows(H, R, nr, 1)
        y[nr] = z0 - x[_A]
        H[nr, _A] = 1.0
        R[nr, nr] = r0
        return _block(blk, nr, 1, nb, s, KI_ACCEL)
    if typ == T_ODOM:
        L = fp[FP_TRACK]
        if ks >= 0:
            kv = x[ks]
            kw = x[ks + 1]
        else:
            kv = 1.0
            kw = 1.0
        m = 0
        if flags & 1:
            _zero_rows(H, R, nr, 1)
            v = 0.5 * (x[_VL] + x[_VR])
            y[nr] = z0 - v / kv
            H[nr, _VL] = 0.5 / kv
            H[nr, _VR] = 0.5 / kv
            if ks >= 0:
                H[nr, ks] = -v / (kv * kv)
            R[nr, nr] = r0
            m += 1
        if flags & 2:
            r = nr + m
            _zero_rows(H, R, r, 1)
            w = (x[_VR] - x[_VL]) / L
            y[r] = z1 - w / kw
            H[r, _VR] = 1.0 / (L * kw)
            H[r, _VL] = -1.0 / (L * kw)
            if ks >= 0:
                H[r, ks + 1] = -w / (kw * kw)
            R[r, r] = r1
            if m == 1:
                R[nr, r] = 0.0
                R[r, nr] = 0.0
            m += 1
        if m == 0:
            return nr, nb
        return _block(blk, nr, m, nb, s, KI_ODOM)
    if typ == T_WHEELS:
        _zero_rows(H, R, nr, 2)
        rw = fp[FP_WHEEL_R]
        vl = x[_VL]
        vr = x[_VR]
        if ks < 0:
            y[nr] = z0 - vl / rw
            y[nr + 1] = z1 - vr / rw
            H[nr, _VL] = 1.0 / rw
            H[nr + 1, _VR] = 1.0 / rw
        else:  # rim speeds -> (v / k_v, w / k_w) -> wheel speeds through the nominal geometry
            kv = x[ks]
            kw = x[ks + 1]
            a = 0.5 / (kv * rw)
            b = 0.5 / (kw * rw)
            s_ = vl + vr
            d_ = vr - vl
            dkv = -a * s_ / kv
            dkw = b * d_ / kw
            y[nr] = z0 - (a * s_ - b * d_)
            y[nr + 1] = z1 - (a * s_ + b * d_)
            H[nr, _VL] = a + b
            H[nr, _VR] = a - b
            H[nr, ks] = dkv
            H[nr, ks + 1] = dkw
            H[nr + 1, _VL] = a - b
            H[nr + 1, _VR] = a + b
            H[nr + 1, ks] = dkv
            H[nr + 1, ks + 1] = -dkw
        R[nr, nr] = r0
        R[nr + 1, nr + 1] = r1
        return _block(blk, nr, 2, nb, s, KI_WHEELS)
    if typ == T_GPS:
        _zero_rows(H, R, nr, 2)
        radius = fp[FP_RADIUS]
        lx = sf[s, SF_LX]
        ly = sf[s, SF_LY]
        delay = sf[s, SF_DELAY]
        lat0 = x[_LAT]
        lon0 = x[_LON]
        lat = lat0
        lon = lon0
        psi = x[_PSI]
        # d(moved-back state)/d(state) - I: only these entries (IgvcEkf._gps_metres)
        j_lat_theta = j_lat_v = j_lon_lat = j_lon_theta = j_lon_v = j_psi_w = 0.0
        if delay != 0.0:
            theta = x[_THETA]
            v = x[_V]
            w = x[_W]
            ct = math.cos(theta)
            st_ = math.sin(theta)
            cl0 = math.cos(lat0)
            lat = lat0 - delay * v * ct / radius
            lon = lon0 - delay * v * st_ / (radius * cl0)
            psi = psi - delay * w
            j_lat_theta = delay * v * st_ / radius
            j_lat_v = -delay * ct / radius
            j_lon_lat = -delay * v * st_ * math.sin(lat0) / (radius * cl0 * cl0)
            j_lon_theta = -delay * v * ct / (radius * cl0)
            j_lon_v = -delay * st_ / (radius * cl0)
            j_psi_w = -delay
        # gps_model at the moved-back state: rows (lat, lon) of H, nonzero at LAT, LON, PSI
        c = math.cos(psi)
        sn = math.sin(psi)
        e_off = c * lx - sn * ly
        n_off = sn * lx + c * ly
        cl = math.cos(lat)
        h_lat = lat + n_off / radius
        h_lon = lon + e_off / (radius * cl)
        a_lat_psi = e_off / radius
        b_lon_lat = e_off * math.sin(lat) / (radius * cl * cl)
        b_lon_psi = -n_off / (radius * cl)
        te = radius * math.cos(lat0)
        tn = radius
        # east row: te * (lon row of H J); north row: tn * (lat row of H J)
        re = nr
        rn = nr + 1
        H[re, _LON] = te * 1.0
        H[re, _LAT] = te * (b_lon_lat + j_lon_lat)
        H[re, _PSI] = te * b_lon_psi
        H[re, _THETA] = te * (b_lon_lat * j_lat_theta + j_lon_theta)
        H[re, _V] = te * (b_lon_lat * j_lat_v + j_lon_v)
        H[re, _W] = te * (b_lon_psi * j_psi_w)
        H[rn, _LAT] = tn * 1.0
        H[rn, _PSI] = tn * a_lat_psi
        H[rn, _THETA] = tn * j_lat_theta
        H[rn, _V] = tn * j_lat_v
        H[rn, _W] = tn * (a_lat_psi * j_psi_w)
        zlat = math.radians(z0)
        zlon = math.radians(z1)
        dlon_z = (zlon - lon0 + _PI) % _TWO_PI - _PI
        y[re] = te * dlon_z - te * (h_lon - lon0)
        y[rn] = tn * (zlat - lat0) - tn * (h_lat - lat0)
        R[re, re] = r0
        R[re, rn] = r01
        R[rn, re] = r10
        R[rn, rn] = r1
        return _block(blk, nr, 2, nb, s, KI_GPS)
    return nr, nb


@njit(cache=True)
def _zero_rows(H, R, r0, m):
    for r in range(r0, r0 + m):
        for c in range(H.shape[1]):
            H[r, c] = 0.0
        for c in range(R.shape[0]):  # R is square in its first R.shape[0] columns
            R[r, c] = 0.0
            R[c, r] = 0.0


@njit(cache=True)
def _block(blk, r0, m, nb, s, k):
    blk[4 * nb + 0] = r0
    blk[4 * nb + 1] = r0 + m
    blk[4 * nb + 2] = s
    blk[4 * nb + 3] = k
    return r0 + m, nb + 1


# ----------------------------------------------------------------------------- entry points
# explicit signatures: arguments are converted to these types (an int reading, a bool flag),
# never compiled again for another combination of argument types
_ARRAYS = ("float64[::1], int64[::1], float64[:, ::1], float64[:, ::1], int64[:, ::1], "
           "float64[:, ::1], float64, float64")
_EVENT_SIG = (f"int64({_ARRAYS}, int64, int64, float64, float64, float64, float64, float64, "
              "float64, int64, float64)")
_STACKED_SIG = f"int64({_ARRAYS}, float64[:, ::1], int64)"


@njit(cache=True)
def _event_scratch(fp, ip, W, n):
    """The event kernels' scratch: in W after P and its two n x n work blocks H, U^T and Z;
    y, R, S, zf, fs in fp's header; the block table and zi at ip[IP_OFF_ZI]."""
    H = W[3 * n:3 * n + MAXR]
    Ut = W[3 * n + MAXR:3 * n + 2 * MAXR]
    Z = W[3 * n + 2 * MAXR:4 * n + 6 * MAXR]  # Kt, KRt, Mt, Sa, Si
    # (no reshape: numba's run-time reshape costs ~50 ns a call)
    R = W[4 * n + 6 * MAXR:4 * n + 7 * MAXR]
    S = W[4 * n + 7 * MAXR:4 * n + 8 * MAXR]
    y = fp[FP_SCR:FP_SCR + MAXR]
    zf = fp[FP_SCR + MAXR:FP_SCR + MAXR + 2 * MAXB]
    fs = fp[FP_SCR + MAXR + 2 * MAXB:FP_SCR + MAXR + 3 * MAXB]
    oi = ip[IP_OFF_ZI]
    blk = ip[oi:oi + 4 * MAXB]
    zi = ip[oi + 4 * MAXB:oi + 8 * MAXB + MAXR + 2 * n]
    return H, Ut, y, R, S, blk, Z, zf, zi, fs


@njit(_EVENT_SIG, cache=True)
def uni_event(fp, ip, W, sf, si, lg, dt, t, typ, s, z0, z1, r0, r1, r01, r10, flags, rf):
    """One message of the event-driven unicycle EKF: predict by ``dt`` s (if > 0) to the
    message time ``t`` (s), then its update. ``typ`` (T_*), ``s`` the sensor's row; z0, z1 the
    reading(s), r0, r1 their variances, r01, r10 their covariance (GPS); ``flags`` which
    odometry components are present; ``rf`` the factor on R in the fusion (1.0; a
    time-correlated GPS fix: its inflation; the gate and the log keep R). Returns the module's
    bits (a single-block message was fused unless REJECTED or DEFER)."""
    if ip[IP_LOGN] + MAXB > ip[IP_LOGCAP]:
        return GROW
    n = ip[IP_N]
    if dt > 0.0:
        _uni_predict(fp, ip, W, n, dt)
    H, Ut, y, R, S, blk, Z, zf, zi, fs = _event_scratch(fp, ip, W, n)
    nr, nb = _uni_model(fp, ip, sf, si, H, y, R, blk, 0, 0, typ, s, z0, z1, r0, r1, r01, r10,
                        flags)
    if nb == 0:
        return 0
    for b in range(nb):
        fs[b] = rf
    return _update(fp, ip, W, sf, si, lg, t, H, y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs)


@njit(_EVENT_SIG, cache=True)
def igvc_event(fp, ip, W, sf, si, lg, dt, t, typ, s, z0, z1, r0, r1, r01, r10, flags, rf):
    """uni_event for the IGVC EKF (its prediction in steps of at most FP_MAXSTEP)."""
    if ip[IP_LOGN] + MAXB > ip[IP_LOGCAP]:
        return GROW
    n = ip[IP_N]
    if dt > 0.0:
        _igvc_predict(fp, ip, W, n, dt)
    H, Ut, y, R, S, blk, Z, zf, zi, fs = _event_scratch(fp, ip, W, n)
    nr, nb = _igvc_model(fp, ip, sf, si, H, y, R, blk, 0, 0, typ, s, z0, z1, r0, r1, r01, r10,
                         flags)
    if nb == 0:
        return 0
    for b in range(nb):
        fs[b] = rf
    return _update(fp, ip, W, sf, si, lg, t, H, y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs)


@njit(_STACKED_SIG, cache=True)
def uni_stacked(fp, ip, W, sf, si, lg, dt, t, mb, k):
    """One fixed-rate step of the unicycle EKF: predict by ``dt`` s to ``t``, then one stacked
    update from the ``k`` messages in ``mb`` (rows: typ, sensor row, z0, z1, r0, r1, r01, r10,
    flags, rf: uni_event's arguments), each gated on its own (KalmanCore.update_blocks). On
    return without DEFER, a GPS row's flags column says whether its fix was fused (1.0) or
    not (0.0)."""
    if ip[IP_LOGN] + MAXB * k > ip[IP_LOGCAP]:
        return GROW
    n = ip[IP_N]
    if dt > 0.0:
        _uni_predict(fp, ip, W, n, dt)
    mr = MAXR * k
    H = np.empty((mr, n))
    Ut = np.empty((mr, n))
    y = np.empty(mr)
    R = np.zeros((mr, mr))
    S = np.empty((mr, mr))
    blk = np.empty(4 * MAXB * k, np.int64)
    Z = np.empty((4 * mr + n, max(n, mr)))
    # (fs and each message's first block in the same allocations: ~0.1 us each per step)
    zf = np.empty(3 * MAXB * k)
    zi = np.empty(4 * MAXB * k + mr + 2 * n + k, np.int64)
    fs = zf[2 * MAXB * k:]
    first = zi[4 * MAXB * k + mr + 2 * n:]  # each message's first block (-1: none)
    nr = 0
    nb = 0
    for i in range(k):
        nb0 = nb
        nr, nb = _uni_model(fp, ip, sf, si, H, y, R, blk, nr, nb, int(mb[i, 0]), int(mb[i, 1]),
                            mb[i, 2], mb[i, 3], mb[i, 4], mb[i, 5], mb[i, 6], mb[i, 7],
                            int(mb[i, 8]))
        first[i] = nb0 if nb > nb0 else -1
        for b in range(nb0, nb):
            fs[b] = mb[i, 9]
    if nb == 0:
        return 0
    code = _update(fp, ip, W, sf, si, lg, t, H[:nr], y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs)
    if not code & DEFER:
        for i in range(k):
            if int(mb[i, 0]) == T_GPS and first[i] >= 0:  # its one block's verdict
                mb[i, 8] = 1.0 if zi[first[i]] == 0 else 0.0
    return code


@njit("float64[:, ::1](float64[:, ::1], int64, float64)", cache=True)
def world_cov(W, n, psi):
    """UnicycleEkf.estimate's covariance for the se2 pose error: A P A^T (P = W[0:n]),
    A = I with R(psi) in its (x, y) block, the first-order world-frame image of the body-frame
    pose error; exactly symmetric. A new (n, n) array."""
    c = math.cos(psi)
    s = math.sin(psi)
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = W[i, j]
    for j in range(n):
        a = out[0, j]
        b = out[1, j]
        out[0, j] = c * a - s * b
        out[1, j] = s * a + c * b
    for i in range(n):
        a = out[i, 0]
        b = out[i, 1]
        out[i, 0] = c * a - s * b
        out[i, 1] = s * a + c * b
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = v
            out[j, i] = v
    return out
