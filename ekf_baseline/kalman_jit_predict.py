"""The compiled EKF kernels' prediction (numba): the sparse covariance propagation and the
unicycle, IGVC and landmark EKFs' steps, on the arrays of ``ddfuse.ekf_baseline.kalman_jit``
(its module docstring), called by its entry points. The models are the Python filters' own
functions (``unicycle_motion``, ``igvc_jacobians``, ``igvc_model``, ``landmark_model``),
compiled as they are."""

from __future__ import annotations

import math

from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline import kalman_jit_layout as lay
from ddfuse.ekf_baseline import landmark_model as lmm
from ddfuse.ekf_baseline.igvc_model import igvc_q_values
from ddfuse.ekf_baseline.unicycle_motion import (
    euler_step_jac,
    scaled_step_terms,
    se2_error_terms,
    unicycle_process_noise_terms,
)
from ddfuse.factors.kinematics import se2_step_jac
from numba import njit

_PI = math.pi
_TWO_PI = 2.0 * math.pi
# the entries of unicycle_process_noise_terms' upper triangle that are off the diagonal
_UNI_Q_OFFDIAG = (1, 2, 3, 4, 6, 7, 8, 10, 11, 13)
# igvc state indices
_LAT, _LON, _THETA, _X, _Y, _PSI, _V, _W, _VL, _VR, _A = range(11)


@njit(cache=True)
def _wrap(a):
    return (a + _PI) % _TWO_PI - _PI


@njit(cache=True)
def _wrap_states(x, ip):
    for k in range(ip[lay.IP_NANG]):
        i = ip[lay.IP_ANG + k]
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
    nf = ip[lay.IP_NF]
    of = ip[lay.IP_OFF_F]
    ofv = ip[lay.IP_OFF_FVAL]
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
    oq = ip[lay.IP_OFF_Q]
    oqv = ip[lay.IP_OFF_QVAL]
    for e in range(ip[lay.IP_NQ]):
        B[ip[oq + 2 * e], ip[oq + 2 * e + 1]] += fp[oqv + e]
    ow = ip[lay.IP_OFF_WALK]
    owv = ip[lay.IP_OFF_WALKV]
    for e in range(ip[lay.IP_NWALK]):
        i = ip[ow + e]
        B[i, i] += fp[owv + e] * dt
    for i in range(n):
        for j in range(n):
            P[i, j] = 0.5 * (B[i, j] + B[j, i])


@njit(cache=True)
def _integrated_walks(fp, ip, W, n, dt):
    """After F P F^T + Q: the states driven by a rate state (ip's rate pairs (i, j): x_i' = x_j,
    x_j a random walk of variance q2 per second): x_i += dt x_j and P <- G P G^T + Q_r, with
    G = I + dt e_i e_j^T (the rest of F leaves x_j alone, so G F is the whole step's F) and
    Q_r = q2 [[dt^3 / 3, dt^2 / 2], [dt^2 / 2, dt]] on (i, j); UnicycleEkf._predict_step's."""
    P = W[0:n]
    x = fp[lay.FP_X:lay.FP_X + n]
    o = ip[lay.IP_OFF_RATE]
    ov = ip[lay.IP_OFF_RATEV]
    for e in range(ip[lay.IP_NRATE]):
        i = ip[o + 2 * e]
        j = ip[o + 2 * e + 1]
        q2 = fp[ov + e]
        x[i] += dt * x[j]
        for k in range(n):
            P[i, k] += dt * P[j, k]
        for k in range(n):
            P[k, i] += dt * P[k, j]
        P[i, i] += q2 * dt * dt * dt / 3.0
        P[i, j] += 0.5 * q2 * dt * dt
        P[j, i] += 0.5 * q2 * dt * dt
        P[j, j] += q2 * dt


@njit(cache=True)
def _put_step_f(fp, ofv, F, ks):
    """F's pose-row entries from ``scaled_step_terms``' layout (or se2_error_terms' first 12)
    into fp at ``ofv`` (UnicycleEkf._compiled_core's order), with the scale columns when
    ``ks`` >= 0; returns the offset after them."""
    fp[ofv + 1] = F[0]
    fp[ofv + 2] = F[1]
    fp[ofv + 3] = F[2]
    fp[ofv + 5] = F[3]
    fp[ofv + 6] = F[4]
    fp[ofv + 7] = F[5]
    fp[ofv + 9] = F[6]
    if ks < 0:
        return ofv + 10
    for k in range(5):
        fp[ofv + 10 + k] = F[7 + k]
    return ofv + 15


@njit(cache=True)
def _uni_predict(fp, ip, W, n, dt):
    """UnicycleEkf._predict_to for dt > 0 s: the constant-twist (or Euler) step of (x, y, psi),
    F (its Jacobian, identity elsewhere), Q (unicycle_process_noise_terms + walks); with the
    odometry scale states (IP_KS >= 0) scaled_step_terms."""
    x = fp[lay.FP_X:lay.FP_X + n]
    ofv = ip[lay.IP_OFF_FVAL]
    ks = ip[lay.IP_KS]
    # F's entries in the order UnicycleEkf._compiled_core lays them out: rows 0..2 first
    lie = ip[lay.IP_LIE] != 0
    nz = lay.FP_NOISE
    if lie or ks >= 0:  # UnicycleEkf._predict_step's se2 and scale-state branches
        kv = 1.0 if ks < 0 else x[ks]
        kw = 1.0 if ks < 0 else x[ks + 1]
        x1, y1, p1, F0, q0 = scaled_step_terms(
            x[0], x[1], x[2], x[3], x[4], kv, kw, dt, ip[lay.IP_MOTION] != 0, fp[nz],
            fp[nz + 1], fp[nz + 2], fp[nz + 3], fp[nz + 4], ip[lay.IP_WTRUE] != 0)
        if lie:
            F, q = se2_error_terms(x[2], p1, F0, q0)
            fp[ofv + 0] = F[12]
            fp[ofv + 4] = F[15]
            o2 = _put_step_f(fp, ofv, F, ks)
            fp[o2] = F[13]  # the pose block's (0, 1), (1, 0)
            fp[o2 + 1] = F[14]
        else:
            q = q0
            _put_step_f(fp, ofv, F0, ks)
    else:
        if ip[lay.IP_MOTION] == 0:
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
        q = unicycle_process_noise_terms(x[2], x[3], dt, fp[nz], fp[nz + 1], fp[nz + 2],
                                         fp[nz + 3], fp[nz + 4])
    oqv = ip[lay.IP_OFF_QVAL]
    for k in range(15):  # the upper triangle, then its off-diagonal entries again (lower)
        fp[oqv + k] = q[k]
    for j in range(10):
        fp[oqv + 15 + j] = q[_UNI_Q_OFFDIAG[j]]
    x[0] = x1
    x[1] = y1
    x[2] = p1
    _wrap_states(x, ip)
    _propagate_cov(fp, ip, W, n, dt)
    if ip[lay.IP_NRATE] > 0:
        _integrated_walks(fp, ip, W, n, dt)
        _wrap_states(x, ip)


@njit(cache=True)
def _igvc_predict(fp, ip, W, n, dt_total):
    """IgvcEkf.predict_to for dt_total > 0 s: steps of at most FP_MAXSTEP, each the generated
    model step (its sparse Jacobian) and igvc_q_values."""
    x = fp[lay.FP_X:lay.FP_X + n]
    nsteps = max(1, math.ceil(dt_total / fp[lay.FP_MAXSTEP] - 1e-9))
    dt = dt_total / nsteps
    track = fp[lay.FP_TRACK]
    radius = fp[lay.FP_RADIUS]
    ofv = ip[lay.IP_OFF_FVAL]
    ovar = ip[lay.IP_OFF_FVAR]
    oqv = ip[lay.IP_OFF_QVAL]
    for _ in range(nsteps):
        s = (x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8], x[9], x[10])
        # the two models' Jacobians have different sparsity (tuples of different lengths)
        if ip[lay.IP_MOTION] == 0:
            f, fv = gen.euler_step_sparse(s, dt, track, radius)
            for k in range(len(fv)):
                fp[ofv + ip[ovar + k]] = fv[k]
        else:
            f, fv = gen.icc_step_sparse(s, dt, track, radius)
            for k in range(len(fv)):
                fp[ofv + ip[ovar + k]] = fv[k]
        nz = lay.FP_NOISE
        q = igvc_q_values(x[_LAT], dt, radius, fp[nz], fp[nz + 1], fp[nz + 2], fp[nz + 3],
                          fp[nz + 4], fp[nz + 5], fp[nz + 6])
        for k in range(16):
            fp[oqv + k] = q[k]
        for k in range(11):
            x[k] = f[k]
        _wrap_states(x, ip)
        _propagate_cov(fp, ip, W, n, dt)


@njit(cache=True)
def _lm_predict(fp, ip, W, n, dt, v, w, v_var, w_var, tau):
    """The landmark EKF's predict_to for dt > 0 s (``ekf_baseline.landmark``): the pose moved
    by the odometry's twist (v m/s, w rad/s) times the scale states (IP_KS >= 0) or 1
    (``landmark_model.odometry_step``; IP_MOTION 1: Euler), F its Jacobian (with the scale
    states' columns) and Q ``landmark_model.odometry_noise_terms`` of the odometry's variances
    (v_var, w_var) held for its period ``tau`` s and the slip (IP_SLIP, FP_NOISE). F's and Q's
    entries in LandmarkKernels._compiled_core's order."""
    x = fp[lay.FP_X:lay.FP_X + n]
    ks = ip[lay.IP_KS]
    kv = 1.0
    kw = 1.0
    if ks >= 0:
        kv = x[ks]
        kw = x[ks + 1]
    psi = x[2]
    x1, y1, p1, J = lmm.odometry_step(x[0], x[1], psi, kv * v, kw * w, dt,
                                      ip[lay.IP_MOTION] != 0)
    nz = lay.FP_NOISE
    q = lmm.odometry_noise_terms(J, kv, kw, v_var, w_var, tau, dt, psi, fp[nz], fp[nz + 1],
                                 fp[nz + 2], ip[lay.IP_SLIP] != 0)
    ofv = ip[lay.IP_OFF_FVAL]
    fp[ofv + 1] = J[0][2]
    fp[ofv + 3] = J[1][2]
    if ks >= 0:  # d pose1 / d (k_v, k_w)
        fp[ofv + 5] = J[0][3] * v
        fp[ofv + 6] = J[0][4] * w
        fp[ofv + 7] = J[1][3] * v
        fp[ofv + 8] = J[1][4] * w
        fp[ofv + 9] = J[2][4] * w
    oqv = ip[lay.IP_OFF_QVAL]
    for k in range(6):  # the upper triangle, then (1, 0), (2, 0), (2, 1)
        fp[oqv + k] = q[k]
    fp[oqv + 6] = q[1]
    fp[oqv + 7] = q[2]
    fp[oqv + 8] = q[4]
    x[0] = x1
    x[1] = y1
    x[2] = _wrap(p1)  # (landmark.motion_step's wrap, then KalmanCore.predict's)
    _wrap_states(x, ip)
    _propagate_cov(fp, ip, W, n, dt)
