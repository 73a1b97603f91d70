"""Compiled (numba) hot path of the unicycle EKF, the 11-state IGVC EKF and the known-map
landmark EKF (``lm_predict``, ``lm_sighting``; ``ekf_baseline.landmark_compiled``):
prediction, the measurement models, the gate with its lock-out bookkeeping, the Joseph-form
update and the innovation log, on preallocated arrays updated in place.

Why: in Python every filter step costs ~20-40 us of interpreter and numpy call overhead for a
few hundred floating-point operations (docs/results/ekf_speed.md). Here one ``process(m)``
is one call of an entry point below (~0.5 us of call overhead, ~0.3-1 us of arithmetic).

The maths is the Python filters': the measurement models (``unicycle_measurements``,
``igvc_measurements``, ``landmark_model``), the motion models (``unicycle_motion``,
``igvc_model``, the generated ``igvc_jacobians``, ``landmark_model``), the NIS of a block
(``kalman.block_nis``) and the gate's lock-out streak
rule (``ddfuse.estimation.lockout``) are plain-float functions both the reference path and
these kernels call (compiled here through ``numba.extending.register_jitable``:
``kalman_jit_layout``), and so are the gain and the factored Joseph update
(``ddfuse.ekf_baseline.joseph``, which ``KalmanCore.update_blocks`` calls too). The prediction
kernels are in ``kalman_jit_predict``; docs/design/ekf_kernels.md.

Every kernel returns a bit set: ``DEFER`` -- a gated block needs what only Python does (a gate
lock-out candidate that may be a recovery or a corroboration verdict, a non-positive-definite S,
a non-finite NIS, a block of more than two rows); the kernel has then predicted (if asked to)
and changed nothing else, and the caller runs the measurement update in Python on the same
arrays; ``REJECTED`` -- some block was gate-rejected: its count is pending in the sensor table
(``SI_REJ``) for the caller's ``log.rejected`` Counter; ``GROW`` -- the innovation log has no
room: nothing was done, grow it and call again.

Arrays (all float64 or int64, C order; layout constants in ``kalman_jit_layout``;
``ddfuse.ekf_baseline.compiled`` builds them):

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
from ddfuse.ekf_baseline import igvc_measurements as im
from ddfuse.ekf_baseline import landmark_model as lmm
from ddfuse.ekf_baseline import unicycle_measurements as um
from ddfuse.ekf_baseline.joseph import (
    accepted_rows,
    cross_and_innovation_cov,
    fuse_noise,
    gain,
    joseph,
)
from ddfuse.ekf_baseline.kalman import block_nis
from ddfuse.ekf_baseline.kalman_jit_layout import (  # noqa: F401 - the layout
    FP_LASTNIS,
    FP_LOCKT,
    FP_MAXSTEP,
    FP_NOISE,
    FP_RADIUS,
    FP_SCR,
    FP_TRACK,
    FP_WHEEL_R,
    FP_X,
    IP_ANG,
    IP_HEADER,
    IP_KS,
    IP_LIE,
    IP_LOCKN,
    IP_LOGCAP,
    IP_LOGN,
    IP_MOTION,
    IP_N,
    IP_NANG,
    IP_NF,
    IP_NFVAR,
    IP_NQ,
    IP_NRATE,
    IP_NWALK,
    IP_OFF_F,
    IP_OFF_FVAL,
    IP_OFF_FVAR,
    IP_OFF_Q,
    IP_OFF_QVAL,
    IP_OFF_RATE,
    IP_OFF_RATEV,
    IP_OFF_WALK,
    IP_OFF_WALKV,
    IP_OFF_ZI,
    IP_SLIP,
    IP_WTRUE,
    K_GPS,
    K_GYRO,
    K_HEAD,
    K_V,
    K_WHEELS,
    K_YAWRATE,
    KI_ACCEL,
    KI_GPS,
    KI_GYRO,
    KI_HEAD,
    KI_ODOM,
    KI_WHEELS,
    KL_LANDMARK,
    LG_COLS,
    MAXANG,
    MAXB,
    MAXR,
    NKIND,
    SF_BIAS,
    SF_COLS,
    SF_DELAY,
    SF_HOFF,
    SF_K,
    SF_KW,
    SF_LX,
    SF_LY,
    SF_THR1,
    SF_THR2,
    SI_BIAS,
    SI_COLS,
    SI_HOFF,
    SI_K,
    SI_KW,
    SI_REJ,
    SK_ACC,
    SK_CNT,
    SK_EXISTS,
    SK_HOLD,
    SK_HOLD_UNTIL,
    SK_HOLD_WAIT,
    SK_OKMASK,
    SK_OKT,
    SK_T0,
)
from ddfuse.ekf_baseline.kalman_jit_predict import (
    _igvc_predict,
    _lm_predict,
    _uni_predict,
    _wrap_states,
)
from ddfuse.ekf_baseline.kernel_codes import (  # noqa: F401 - re-exported: the kernels' codes
    DEFER,
    GROW,
    IGVC_KINDS,
    LANDMARK_KINDS,
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
from ddfuse.ekf_baseline.unicycle_motion import pose_correct
from ddfuse.estimation.lockout import gate_streak, holdoff_over, lockout_due
from ddfuse.factors.jitcache import compiling, one_compiler
from ddfuse.factors.jitcache import load_cached as _load
from numba import njit


# ----------------------------------------------------------------------------- update
@njit(cache=True)
def _update(fp, ip, W, sf, si, lg, t, H, y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs):
    """KalmanCore.update_blocks of ``nb`` blocks stacked in rows 0:nr of H (nr, n), y (nr,),
    R (nr, nr) (block diagonal); ``blk`` (nb, 4) = (row start, row stop, sensor row, kind);
    ``fs`` (nb,) each block's factor on its R in the fusion (KalmanCore's ``fuse``: 1.0, or a
    time-correlated GPS fix's inflation). Scratch (no
    allocation per call): Ut (>= nr, n) for (P H^T)^T, S (>= nr, >= nr), Z (4 nr + n,
    >= max(n, nr)), zf (>= 2 nb), zi (>= 4 nb + nr + 2 n); ``blk`` is flat: block b's fields at
    4 b .. 4 b + 3. On return (without DEFER) zi[0:nb] holds the verdicts (0 fused).

    Each block is gated on its own against the common prior (its diagonal block of
    S = H P H^T + R), the per-(sensor, kind) streaks are those of KalmanCore._judge, rejected
    blocks are logged first and accepted ones after the update (the reference's order), then
    one Joseph-form update applies the accepted rows, with R fused by ``fs``
    (``joseph.fuse_noise``; S, the NIS and the log keep R). Returns the module's bits."""
    n = ip[IP_N]
    P = W[0:n]
    x = fp[FP_X:FP_X + n]
    cross_and_innovation_cov(P, H, R, nr, n, Ut, S)  # U = P H^T (transposed), S = H U + R
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
            nis = block_nis(1, y[r0], 0.0, S[r0, r0], 0.0, 0.0)
            thr = sf[s, SF_THR1]
        elif m == 2:
            nis = block_nis(2, y[r0], y[r0 + 1], S[r0, r0], S[r0, r0 + 1], S[r0 + 1, r0 + 1])
            thr = sf[s, SF_THR2]
        else:
            return DEFER
        if nis < 0.0 or not math.isfinite(nis):  # S not positive definite, or not finite
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
        rejected = nis > thr
        if rejected and e_ == 0:
            e_, c_, t_, a_ = 1, 0, t, 0
        if e_ != 0:
            c_, t_, a_ = gate_streak(rejected, t, c_, t_, a_)
        if rejected:
            # a lock-out candidate: the recovery or corroboration decision is Python's
            # (KalmanCore._holdoff_over drops a hold-off that is over: Python's too)
            if lockout_due(c_, t_, t, lockn, lockt) and holdoff_over(
                    si[s, cb + SK_HOLD] != 0, sf[s, fb + SK_HOLD_UNTIL], a_, lockn, t):
                return DEFER
            verdict[b] = 1
        else:
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
    # the accepted rows, the fusion's R, the gain and the correction (ekf_baseline.joseph)
    fuse_noise(R, blk, verdict, fs, nb)
    o = 4 * nb
    rows = zi[o:o + n_acc_rows]
    ma = accepted_rows(blk, verdict, nb, rows)
    Kt = Z[0:ma]
    dx = W[2 * n]  # B's first row: free until joseph
    gain(H, y, R, Ut, rows, ma, n, Z[2 * nr + n:2 * nr + n + ma, 0:ma],
         Z[3 * nr + n:3 * nr + n + ma, 0:ma], Kt, dx)
    px = x[0]
    py = x[1]
    psi0 = x[2]
    for i in range(n):
        x[i] += dx[i]
    if ip[IP_LIE] != 0:  # the body-frame position correction (UnicycleEkf._apply)
        x[0], x[1] = pose_correct(px, py, psi0, dx[0], dx[1])
    joseph(P, H, R, rows, ma, n, Kt, Z[nr:nr + ma], Z[2 * nr:2 * nr + n], W[n:2 * n],
           W[2 * n:3 * n], zi[o + nr:o + nr + n], zi[o + nr + n:o + nr + 2 * n])
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
    """Rows of one message for the unicycle EKF (``ddfuse.ekf_baseline.unicycle_measurements``,
    the models the reference path calls too), appended at row ``nr`` and block ``nb``; returns
    the new (nr, nb). The caller has checked what decides whether the message is used at all
    (``uses``, initialisation, offsets initialised)."""
    n = ip[IP_N]
    x = fp[FP_X:FP_X + n]
    ks = ip[IP_KS]
    wtrue = ip[IP_WTRUE] != 0
    if typ == T_GYRO:
        _zero_rows(H, R, nr, 1)
        m = um.gyro_rows(x, ks, wtrue, si[s, SI_BIAS], sf[s, SF_BIAS], z0, r0, H, y, R, nr)
        return _block(blk, nr, m, nb, s, K_GYRO)
    if typ == T_HEAD:
        _zero_rows(H, R, nr, 1)
        m = um.heading_rows(x, si[s, SI_HOFF], sf[s, SF_HOFF], z0, r0, H, y, R, nr)
        return _block(blk, nr, m, nb, s, K_HEAD)
    if typ == T_ODOM:
        if flags & 1:
            _zero_rows(H, R, nr, 1)
            m = um.speed_rows(x, z0, r0, H, y, R, nr)
            nr, nb = _block(blk, nr, m, nb, s, K_V)
        if flags & 2:
            _zero_rows(H, R, nr, 1)
            m = um.yaw_rate_rows(x, ks, wtrue, z1, r1, H, y, R, nr)
            nr, nb = _block(blk, nr, m, nb, s, K_YAWRATE)
        return nr, nb
    if typ == T_GPS:
        _zero_rows(H, R, nr, 2)
        m = um.gps_rows(x, ks, wtrue, ip[IP_LIE] != 0, sf[s, SF_LX], sf[s, SF_LY],
                        sf[s, SF_DELAY], z0, z1, r0, r1, r01, r10, H, y, R, nr)
        return _block(blk, nr, m, nb, s, K_GPS)
    if typ == T_WHEELS:
        _zero_rows(H, R, nr, 2)
        m = um.wheel_rows(x, ks, wtrue, fp[FP_WHEEL_R], fp[FP_TRACK], z0, z1, r0, r1, H, y, R,
                          nr)
        return _block(blk, nr, m, nb, s, K_WHEELS)
    return nr, nb


@njit(cache=True)
def _igvc_model(fp, ip, sf, si, H, y, R, blk, nr, nb, typ, s, z0, z1, r0, r1, r01, r10, flags):
    """Rows of one message for the IGVC EKF (``ddfuse.ekf_baseline.igvc_measurements``); as
    _uni_model. For a GpsFix z0, z1 are its latitude and longitude in degrees; for odometry
    ``flags`` bit 0 = v present, bit 1 = yaw rate present."""
    n = ip[IP_N]
    x = fp[FP_X:FP_X + n]
    ks = ip[IP_KS]
    if typ == T_GYRO:
        _zero_rows(H, R, nr, 1)
        m = im.gyro_rows(x, si[s, SI_BIAS], sf[s, SF_BIAS], z0, r0, H, y, R, nr)
        return _block(blk, nr, m, nb, s, KI_GYRO)
    if typ == T_HEAD or typ == T_HEAD_POSE:  # noqa: SIM109 - plain compares for numba
        _zero_rows(H, R, nr, 1)
        m = im.heading_rows(x, typ == T_HEAD_POSE, si[s, SI_HOFF], sf[s, SF_HOFF], z0, r0, H, y,
                            R, nr)
        return _block(blk, nr, m, nb, s, KI_HEAD)
    if typ == T_ACCEL:
        _zero_rows(H, R, nr, 1)
        m = im.accel_rows(x, z0, r0, H, y, R, nr)
        return _block(blk, nr, m, nb, s, KI_ACCEL)
    if typ == T_ODOM:
        _zero_rows(H, R, nr, 2)
        m = im.odometry_rows(x, ks, fp[FP_TRACK], flags & 1 != 0, flags & 2 != 0, z0, z1, r0, r1,
                             H, y, R, nr)
        if m == 0:
            return nr, nb
        return _block(blk, nr, m, nb, s, KI_ODOM)
    if typ == T_WHEELS:
        _zero_rows(H, R, nr, 2)
        m = im.wheel_rows(x, ks, fp[FP_WHEEL_R], z0, z1, r0, r1, H, y, R, nr)
        return _block(blk, nr, m, nb, s, KI_WHEELS)
    if typ == T_GPS:
        _zero_rows(H, R, nr, 2)
        m = im.gps_rows(x, fp[FP_RADIUS], sf[s, SF_LX], sf[s, SF_LY], sf[s, SF_DELAY], z0, z1,
                        r0, r1, r01, r10, H, y, R, nr)
        return _block(blk, nr, m, nb, s, KI_GPS)
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
# never compiled again for another combination of argument types. Each entry point is compiled
# (or loaded from numba's cache) by ``ready`` when a filter that calls it is built, not when this
# module is imported: a run compiles only its filters' kernels (a cold compile of all of them
# takes tens of seconds).
_SIGNATURES: dict[str, str] = {}


def _entry(sig: str):
    """``njit(sig, cache=True)``, compiled on ``ready(name)`` rather than here; called before
    that it raises numba's TypeError (no matching definition), never compiles for other types."""
    def deco(f):
        _SIGNATURES[f.__name__] = sig
        d = njit(cache=True)(f)
        d._can_compile = False  # disable_compile() refuses a dispatcher without a signature yet
        return d
    return deco


def ready(*names: str) -> None:
    """Compile, or load from numba's cache, the entry points ``names`` for their signatures
    (once per process; what ``njit(sig)`` does at import)."""
    todo = [name for name in names if not globals()[name].signatures]
    if not todo:
        return
    with compiling(f"the EKF kernels {', '.join(todo)}"):
        for name in todo:
            d = globals()[name]
            d._can_compile = True
            with one_compiler(name):
                d.compile(_SIGNATURES[name])
            d.disable_compile()


def load_cached(*names: str) -> bool:
    """Load the entry points ``names`` from numba's cache where it holds them, never compiling
    (``factors.jitcache.load_cached``); whether all of them are now ready."""
    return all(globals()[name].signatures or _load(globals()[name], _SIGNATURES[name])
               for name in names)


_TABLES = ("float64[::1], int64[::1], float64[:, ::1], float64[:, ::1], int64[:, ::1], "
           "float64[:, ::1]")  # fp, ip, W, sf, si, lg
_ARRAYS = f"{_TABLES}, float64, float64"
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


@_entry(_EVENT_SIG)
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


@_entry(_EVENT_SIG)
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


@_entry(_STACKED_SIG)
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


@_entry("void(float64[::1], int64[::1], float64[:, ::1], float64, float64, float64, float64, "
        "float64, float64)")
def lm_predict(fp, ip, W, dt, v, w, v_var, w_var, tau):
    """The landmark EKF's prediction by ``dt`` s (> 0) with the odometry's twist (v m/s,
    w rad/s), its variances and sample period ``tau`` s (``kalman_jit_predict._lm_predict``)."""
    _lm_predict(fp, ip, W, ip[IP_N], dt, v, w, v_var, w_var, tau)


@_entry(f"int64({_TABLES}, float64, int64, float64, float64, int64, float64, float64, "
        "float64, float64, float64)")
def lm_sighting(fp, ip, W, sf, si, lg, t, s, lx, ly, bearing, zr, zb, rr, rb, rf):
    """One sighting at ``t`` (s) by the sensor of row ``s`` of the known landmark (lx, ly) m:
    range ``zr`` (m, variance ``rr``) and, when ``bearing`` != 0, bearing ``zb`` (rad, variance
    ``rb``) (``landmark_model.landmark_rows``), gated and fused as the landmark EKF's
    KalmanCore.update (kind 'landmark'); ``rf`` the factor on R in the fusion (1.0; a
    time-correlated sighting: ``estimation.landmark_correlation``; the gate and the log keep
    R). No prediction. Returns the module's bits; DEFER also
    when the landmark is at the body origin (the Python path counts it as degenerate)."""
    if ip[IP_LOGN] + MAXB > ip[IP_LOGCAP]:
        return GROW
    n = ip[IP_N]
    H, Ut, y, R, S, blk, Z, zf, zi, fs = _event_scratch(fp, ip, W, n)
    _zero_rows(H, R, 0, MAXR)
    m = lmm.landmark_rows(fp[FP_X:FP_X + n], lx, ly, bearing != 0, zr, zb, rr, rb, H, y, R, 0)
    if m == 0:
        return DEFER
    nr, nb = _block(blk, 0, m, 0, s, KL_LANDMARK)
    fs[0] = rf
    return _update(fp, ip, W, sf, si, lg, t, H, y, R, blk, nb, nr, Ut, S, Z, zf, zi, fs)


@_entry("float64[:, ::1](float64[:, ::1], int64, float64)")
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
