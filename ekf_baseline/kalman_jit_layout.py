"""What the compiled EKF kernels (``ddfuse.ekf_baseline.kalman_jit``,
``kalman_jit_predict``) are built from: the plain-float functions they compile
(``numba.extending.register_jitable``, so that they stay plain Python for the reference path
and their other callers) and the layout of the arrays they work on (``kalman_jit``'s module
docstring; ``ddfuse.ekf_baseline.compiled`` builds the arrays)."""

from __future__ import annotations

from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline import igvc_measurements as im
from ddfuse.ekf_baseline import landmark_model as lmm
from ddfuse.ekf_baseline import unicycle_measurements as um
from ddfuse.ekf_baseline.igvc_model import igvc_q_values
from ddfuse.ekf_baseline.kalman import block_nis
from ddfuse.ekf_baseline.unicycle_motion import (
    euler_step_jac,
    pose_correct,
    scaled_step_terms,
    se2_error_terms,
    unicycle_process_noise_terms,
)
from ddfuse.estimation.lockout import gate_streak, holdoff_over, lockout_due
from ddfuse.factors.kinematics import antenna_position, se2_step_jac, twist_coeffs
from numba.extending import register_jitable

for _f in (twist_coeffs, se2_step_jac, antenna_position, euler_step_jac,
           unicycle_process_noise_terms, scaled_step_terms, se2_error_terms, pose_correct,
           igvc_q_values, gen.euler_step_sparse, gen.icc_step_sparse, um.delayed_gps_terms,
           um.gyro_rows, um.heading_rows, um.speed_rows, um.yaw_rate_rows, um.gps_rows,
           um.wheel_rows, im.gyro_rows, im.heading_rows, im.accel_rows, im.odometry_rows,
           im.wheel_rows, im.gps_rows, block_nis, gate_streak, lockout_due, holdoff_over,
           lmm.range_bearing_terms, lmm.landmark_rows, lmm.odometry_step,
           lmm.odometry_noise_terms):
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
IP_SLIP = 21  # landmark EKF: 1 when the robot's slip (FP_NOISE: longitudinal, lateral m^2/s,
# heading rad^2/s) is stated
IP_NRATE = 22  # unicycle: states driven by a rate state (integrated walks: x_i' = x_j)
IP_OFF_RATE = 23  # offset in ip of their (i, j) pairs
IP_OFF_RATEV = 32  # offset in fp of their rate's walk, variance per second
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
# the landmark EKF's one kind (LANDMARK_KINDS)
KL_LANDMARK = 0
