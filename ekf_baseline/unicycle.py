"""Seed 003's unicycle EKF (x, y, psi, v, psi_dot) with GPS, wheel speed and gyro, corrected and
extended for real data.

State (world = local ENU frame; the same names and conventions as ``ddfuse.factors.state``)::

    index  name  unit   meaning
    0      x     m      position east
    1      y     m      position north
    2      psi   rad    heading of body x, CCW from east, kept wrapped to [-pi, pi)
    3      v     m/s    forward speed along body x
    4      w     rad/s  yaw rate, CCW positive
    5..    bg    rad/s  gyro bias (gyro reading = w + bg), one per IMU with gyro_bias: estimate
    ..     hoff  rad    heading offset (heading reading = wrap(psi + hoff)), one per IMU with
                        heading_offset: estimate
    ..     k_v   1      odometry scales: the odometry reports (v / k_v, w / k_w), k_v = true /
    ..     k_w   1      nominal wheel radius, k_w = that times nominal / true track width; when
                        the config states the geometry's uncertainty (robot.*_std), with the
                        prior RobotConfig.scale_std; constants

Scale states. With them, state 3 is the ODOMETRY-FRAME speed (named v_odo) and the body moves
with k_v v_odo -- the landmark EKF's convention; the odometry's and the wheels' speed is linear
in the state and carries no information about k_v; GPS does. State 4 is the yaw rate in the
frame of the sensor that pins it down, the gyro where one is fused:

* without a fused gyro, the odometry's (w_odo; the body turns at k_w w_odo), so that the
  odometry and the wheel speeds are linear in the state. (With the true twist as the state and
  the odometry measured as v / k_v, w / k_w, the update's Jacobians at the changing estimates
  leaked spurious information into unobservable scales: with wheel speeds alone, k_w drifted by
  1.3 % in 120 s of seed 002 at the default noise, by 8 % at 0.3 rad/s^2/sqrt(Hz)
  yaw-acceleration noise.)
* with a gyro, the true yaw rate (w): the gyro is linear in it and the odometry and the wheels
  see w / k_w. With w_odo as the state here, each gyro update (z = k_w w_odo + bg) regressed
  on the filter's own noisy w_odo, and k_w shrank towards 0 -- the errors-in-variables bias of
  an EKF estimating a parameter (Ljung 1979): 1.00 -> 0.87 in 11 s of straight driving on the
  sample bag with no information at all, to 0.54 in 120 s of a synthetic straight line, and to
  0.952 +- 0.013 while turning with k_w = 1 exact. The prior correlation of the two scales
  (RobotConfig.scale_std) dragged k_v along, which put the dead-reckoned position 1.2 % short
  of the odometry's in 20 s. w / k_w regresses on a state the gyro pins down instead
  (tests/test_unicycle.py, test_gyro_and_odometry_yaw_rates_do_not_bias_k_w).

The calibration states' random-walk densities are the IMU's stated ones (noise.gyro_bias_walk,
heading_offset_walk) where the config gives them, else ProcessNoise's.

Motion model. Over a step of dt seconds the twist (v, w) is held constant and the pose moves by the
exact SE(2) constant-twist step ``ddfuse.factors.kinematics.se2_step`` -- the same equations as the
smoother's motion factor. ``motion="euler"`` selects the seed's first-order step
x += dt v cos(psi), y += dt v sin(psi), psi += dt w instead (its error is in docs/errata.md).
v, w, the gyro biases and heading offsets are random walks driven by continuous white noise
(:class:`ProcessNoise`, spectral densities, not per-bag tuning); the discrete Q is the exact
integral int_0^dt Phi(s) G Qc G^T Phi(s)^T ds of the model linearised at the start of the step
(closed form below), plus white body-frame velocity noise (slip) on the position and white
yaw-rate noise on the heading: the config's robot.slip densities where it states them. When the
config states the robot's largest accelerations (robot.max_accel, max_yaw_accel), the white
accelerations driving v and w have the densities a_max sqrt(T) (:func:`twist_densities`,
Bar-Shalom's rule for the continuous white-noise acceleration model), T the shortest sample
period among the sensors measuring v (odometry, wheel speeds), resp. w (also the gyro), as
observed in the data; until a sensor's second sample, the default densities.

Pose error (``pose_error='se2'``, the default). The state vector holds the pose estimate
X_hat = (x, y, psi) in the world frame, but the covariance's pose block is that of the
body-frame error in SE(2) exponential coordinates, X_true = X_hat Exp(xi),
xi = (rho_x m, rho_y m, theta rad) = Log(X_hat^-1 X_true) (the left-invariant error of Barrau &
Bonnabel 2017; the other states' errors stay differences). Dead reckoning under a large heading
uncertainty spreads the true pose along a curved "banana", which a Gaussian in x, y cannot
describe and one in xi does (Long, Wolfe, Mashner, Chirikjian, RSS 2012): the world-frame
filter's position NEES grew to 38.6 (2 dof) where its heading sigma exceeded 0.4 rad
(docs/results/ekf_monte_carlo.md). The prediction's F and Q are the world-frame ones mapped
through the chart, F_xi = A1^-1 F A0, Q_xi = A1^-1 Q A1^-T, A = blockdiag(R(psi), 1) at the
estimate before / after the step (:func:`se2_error_terms`; for the exact step F_xi's pose block
is the adjoint Ad(Exp(-tau dt)) and its twist columns the right Jacobian J_r(tau dt) dt). A GPS
fix's rows are d(east, north)/d(rho) = R(psi) (times the world-frame lever-arm and delay rows,
which act on theta, the twist and the scales as before); heading, gyro, odometry and wheel
speeds touch psi and the Euclidean states only, unchanged. An update's correction K y adds
theta to psi and R(psi) rho to the position (:func:`pose_correct`), the first-order chart the
measurement rows are linearised in; the exponential map X Exp(K y) agrees to first order but,
for a large correction with the heading unknown (a gate lock-out's recovery), moves the
position along an arc off the fix (13 m in the kidnap test). No reset Jacobian is applied to P
after the correction (its effect is second order in the correction). ``estimate()`` reports
``pose_cov`` and ``state_cov`` mapped to the world frame to first order (A P A^T) and
``pose_error='se2'``, so that a NEES is scored against the filter's own Gaussian:
xi = Log(X_hat^-1 X_true) with covariance A^-1 pose_cov A^-T (ddfuse.evaluation.metrics.nees_series,
navlie's ``state.minus(truth)``). ``pose_error='world'`` keeps the world-frame error
(x, y, psi)_true - estimate throughout (the filter before; the same to first order).

Measurements (seed 003's piecewise model: H, R and h are assembled from the measurements
present at a step; each measurement is gated on its own with its sensor's chi-square gate):

    GpsFix          z = enu[:2]          h = (x, y) + R(psi) lever_arm      R = fix.cov[:2, :2]
                    (with the sensor's delay d: the antenna at t - d, reached from the state by
                    the exact constant-twist step backwards with the true twist, heading
                    psi - w d)
    WheelOdometry   z = v                h = v (v_odo)                      R = v_var
                    z = yaw_rate         h = w (w_odo; w / k_w with a gyro) R = yaw_rate_var
    WheelSpeeds     z = (w_l, w_r)       h = ((v - w L/2)/r, (v + w L/2)/r) (v_odo, w_odo;
                                         w / k_w with a gyro)               R = diag(vars)
    GyroYawRate     z = yaw_rate         h = w + bg (estimated or configured bias; k_w w_odo
                                         from a gyro the config does not name)
    Heading         z = yaw              h = wrap(psi + hoff) (estimated or configured offset),
                                         innovation wrapped

ForwardAccel, landmarks and ground truth are not used (ground truth only for
``initial_pose: ground_truth``).

Time-correlated GPS errors. A GPS sensor with ``correlation_time`` tau > 0 has each fix fused
with R_f = f R, f = ``estimation.gps_correlation.inflation(t - t_last, tau)``, t_last the stamp
of the last fix of that sensor the filter fused (accepted by the gate or by a lock-out
recovery, or taken for the initial position; none: f = 1); the gate, the logged innovation
and NIS, and a recovery's widening keep R (``KalmanCore``'s ``fuse``). In a fixed-rate step
holding several fixes of one sensor (a rate below the GPS's), a fix's t_last is the previous
one's in the step, which is gated against the same prior; t_last is then the last fused one's.
Every path (reference, Python fast, compiled) applies the same factors; tau = 0 leaves the
arithmetic as without the key, bit for bit.

Stepping. ``cfg.ekf.rate == 'event'``: predict to each message's time and update with it.
A rate in Hz: messages are buffered and the filter steps at t0 + k / rate, predicting to the step
time and applying every buffered message in one stacked update (seed 003: "the filter sample time
should be the same as the fastest sensor"); a message is applied up to 1/rate after its stamp.

Initialisation (constructor ``initial_pose`` first, then the config's ``initial_pose``):

* a known pose: the filter starts there at the first measurement.
* ``initial_pose: ground_truth``: at the first GroundTruthPose.
* otherwise position from the first GPS fix (or the origin without GPS), heading from the first
  absolute Heading of a sensor whose offset is a configured number, else:
* with GPS: the filter dead-reckons in a provisional frame (heading 0) from the first
  measurement, and once the GPS fixes have spread over ``init_distance`` metres it rotates and
  translates its state onto the GPS track by the least-squares 2-D rotation (Kabsch) between the
  dead-reckoned positions and the fixes -- GPS course, but robust to turns during the first
  metres. Without odometry it uses the course between the first and the last fix. ``estimate()``
  is None until then.
* without GPS: heading 0 (the local frame is the start pose).
An estimated heading offset is initialised from the first Heading after the heading is known,
hoff = wrap(z - psi), with the covariance that implies (var psi + R, correlated with psi).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from ddfuse.ekf_baseline import GIVEN_POSE_STD
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline.calibration import ScaleStates
from ddfuse.ekf_baseline.kalman import DEFAULT_LOCKOUT_COUNT, DEFAULT_LOCKOUT_TIME, KalmanCore
from ddfuse.estimation.config import DEFAULT_GATE, Config
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.gps_correlation import inflation as gps_inflation
from ddfuse.estimation.heading_survey import rotation_fit
from ddfuse.estimation.measurements import (
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.factors.kinematics import se2_step_jac, twist_coeffs

__all__ = ["ProcessNoise", "UnicycleEkf", "unicycle_process_noise", "euler_step_jac",
           "twist_densities", "scaled_step_terms", "delayed_gps_terms", "se2_error_terms",
           "se2_retract", "se2_log_error", "pose_correct", "POSE_ERRORS"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_cos = math.cos
_sin = math.sin
_USED = (GpsFix, WheelOdometry, WheelSpeeds, GyroYawRate, Heading)
# sparse H rows (KalmanCore.update_sparse) of the measurements of fixed states
_ROWS_V = (((3, 1.0),),)
_ROWS_W = (((4, 1.0),),)
_ROWS_PSI = (((2, 1.0),),)
_ROWS_XY = (((0, 1.0),), ((1, 1.0),))
# the compiled kernels' message types and return bits (ddfuse.ekf_baseline.compiled)
_T_NONE, _T_GYRO, _T_HEAD, _T_ODOM, _T_GPS, _T_WHEELS = (
    jit.T_NONE, jit.T_GYRO, jit.T_HEAD, jit.T_ODOM, jit.T_GPS, jit.T_WHEELS)
_DEFER = jit.DEFER
_REJECTED = jit.REJECTED
POSE_ERRORS = ("se2", "world")  # UnicycleEkf(pose_error=...): module docstring, "Pose error"
# Longest prediction step (s): a gap between messages (a driver restart, a dropped link) is
# predicted in steps of at most this. One linearised step over a turn misplaces the noise the
# twist's walk puts in along the way: after a 2 s gap at 0.5 rad/s the position covariance was
# off by 0.3-2.7x in some direction, after 10 s by 0.035-80x (overconfident across the turn);
# 0.1 s steps are within 0.25 % of 1 ms ones. The messages' own 10-50 Hz steps are never split.
MAX_PREDICT_DT = 0.1


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time process noise, as sigma densities (square roots of spectral densities).

    A white-noise density q drives a random walk whose sigma after dt seconds is q sqrt(dt).

    acc: m/s^2/sqrt(Hz) -- white forward acceleration driving v. 1.0: a ground robot changes its
        speed by ~1 m/s within ~1 s.
    yaw_acc: rad/s^2/sqrt(Hz) -- white yaw acceleration driving w; same reasoning, ~1 rad/s in 1 s.
        When the config states the robot's acceleration limits (robot.max_accel,
        max_yaw_accel), UnicycleEkf replaces both by :func:`twist_densities` of them.
    pos_long, pos_lat: m/sqrt(s) -- white body-frame velocity error on the position (wheel slip,
        the twist not being constant within a step); lateral smaller for a non-holonomic base.
    heading: rad/sqrt(s) -- white yaw-rate error on the heading.
    gyro_bias: rad/s/sqrt(s) -- gyro-bias random walk (MEMS bias instability order).
    heading_offset: rad/sqrt(s) -- random walk of a heading sensor's offset: a magnetometer
        disturbed by the robot and its surroundings wanders by tens of degrees over minutes
        (0.02 rad/sqrt(s) is 20 degrees 1-sigma over 5 minutes).
    """

    acc: float = 1.0
    yaw_acc: float = 1.0
    pos_long: float = 0.05
    pos_lat: float = 0.02
    heading: float = 0.01
    gyro_bias: float = 1e-4
    heading_offset: float = 0.02


def unicycle_process_noise(
    psi: float, v: float, dt: float, noise: ProcessNoise
) -> tuple[float, ...]:
    """Upper triangle of the 5x5 discrete Q of (x, y, psi, v, w) for a ``dt``-second step.

    Exact integral of the continuous model linearised at (psi, v): x' = v cos psi,
    y' = v sin psi, psi' = w, v' = n_a, w' = n_alpha, giving Phi(s) columns for the noise inputs
    (s cos psi, s sin psi, 0, 1, 0) and (-v sin psi s^2/2, v cos psi s^2/2, s, 0, 1). Slip and
    heading white noise add R(psi) diag(pos_long^2, pos_lat^2) R(psi)^T dt and heading^2 dt.
    Returned in row-major order: Qxx, Qxy, Qxpsi, Qxv, Qxw, Qyy, Qypsi, Qyv, Qyw, Qpp, Qpv, Qpw,
    Qvv, Qvw, Qww (units: products of the state units)."""
    return unicycle_process_noise_terms(psi, v, dt, noise.acc, noise.yaw_acc, noise.pos_long,
                                        noise.pos_lat, noise.heading)


def unicycle_process_noise_terms(
    psi: float, v: float, dt: float, acc: float, yaw_acc: float, pos_long: float,
    pos_lat: float, heading: float
) -> tuple[float, ...]:
    """:func:`unicycle_process_noise` with the :class:`ProcessNoise` densities as floats (same
    units), so that the compiled filter (ddfuse.ekf_baseline.kalman_jit) runs this same code."""
    qa = acc * acc
    qal = yaw_acc * yaw_acc
    pl2 = pos_long * pos_long
    pt2 = pos_lat * pos_lat
    c = _cos(psi)
    s = _sin(psi)
    dt2 = dt * dt
    dt3 = dt2 * dt
    a3 = qa * dt3 / 3.0
    b5 = qal * v * v * dt3 * dt2 / 20.0
    cc, ss, cs = c * c, s * s, c * s
    b4 = qal * v * dt2 * dt2 / 8.0
    b3 = qal * v * dt3 / 6.0
    a2 = qa * dt2 / 2.0
    return (
        a3 * cc + b5 * ss + (pl2 * cc + pt2 * ss) * dt,  # xx
        (a3 - b5 + (pl2 - pt2) * dt) * cs,  # xy
        -b4 * s,  # x psi
        a2 * c,  # x v
        -b3 * s,  # x w
        a3 * ss + b5 * cc + (pl2 * ss + pt2 * cc) * dt,  # yy
        b4 * c,  # y psi
        a2 * s,  # y v
        b3 * c,  # y w
        qal * dt3 / 3.0 + heading * heading * dt,  # psi psi
        0.0,  # psi v
        qal * dt2 / 2.0,  # psi w
        qa * dt,  # v v
        0.0,  # v w
        qal * dt,  # w w
    )


def twist_densities(a_max: float | None, yaw_a_max: float | None, t_v: float | None,
                    t_w: float | None, noise: ProcessNoise) -> ProcessNoise:
    """``noise`` with the white acceleration densities of v and w derived from the robot's
    largest accelerations (m/s^2, rad/s^2) and the sample periods (s) of the measurements of v
    and w (None: that density unchanged).

    Bar-Shalom, Li, Kirubarajan 2001, sec. 6.2.2: in the continuous white-noise acceleration
    model the velocity changes over a sampling period T by the order of sqrt(q T); a twist that
    changes by at most a_max T within one period gives q = a_max^2 T, density a_max sqrt(T)."""
    acc = noise.acc if a_max is None or t_v is None else a_max * math.sqrt(t_v)
    yaw_acc = noise.yaw_acc if yaw_a_max is None or t_w is None else yaw_a_max * math.sqrt(t_w)
    return replace(noise, acc=acc, yaw_acc=yaw_acc)


def euler_step_jac(
    x: float, y: float, psi: float, v: float, w: float, dt: float
) -> tuple[float, float, float, tuple[tuple[float, ...], ...]]:
    """Seed 003's explicit Euler step and its Jacobian (rows x, y, psi; columns x, y, psi, v, w).

    Same return layout as ``ddfuse.factors.kinematics.se2_step_jac``. Position error per step is
    O(v w dt^2) (the chord is taken along the start heading instead of the mean heading)."""
    c = _cos(psi)
    s = _sin(psi)
    d = v * dt
    j = (
        (1.0, 0.0, -d * s, dt * c, 0.0),
        (0.0, 1.0, d * c, dt * s, 0.0),
        (0.0, 0.0, 1.0, 0.0, dt),
    )
    return x + d * c, y + d * s, psi + w * dt, j


def scaled_step_terms(
    x: float, y: float, psi: float, u: float, om: float, kv: float, kw: float, dt: float,
    euler: bool, acc: float, yaw_acc: float, pos_long: float, pos_lat: float, heading: float,
    w_true: bool = False
) -> tuple[float, float, float, tuple[float, ...], tuple[float, ...]]:
    """Prediction with odometry scale states: states 3, 4 are the odometry-frame twist (u, om)
    and the body moves with the true twist (v, w) = (k_v u, k_w om); with ``w_true`` state 4
    is the true yaw rate itself (w = om: k_w does not enter the motion, its F entries are 0 and
    Q's om rows are not divided; module docstring, "Scale states"). ``euler``: the seed's
    Euler step (:func:`euler_step_jac`) instead of the exact SE(2) step; the densities are
    :class:`ProcessNoise`'s as floats (the compiled filter, ekf_baseline.kalman_jit, runs this
    same code).

    Returns the new (x, y, psi), the F entries in the order (x, y, psi rows) d/d(psi, u, om) of
    x and y, d psi/d om, then d/d(k_v, k_w) of x and y and d psi/d k_w, and the 5x5 Q upper
    triangle (``unicycle_process_noise``'s order) of (x, y, psi, u, om): the continuous white
    accelerations act on the true twist, so Q_true's u and om rows and columns are divided by
    k_v and k_w."""
    gw = 1.0 if w_true else kw  # d w / d om
    ow = 0.0 if w_true else om  # d w / d k_w
    v = kv * u
    w = gw * om
    if euler:
        x1, y1, p1, J = euler_step_jac(x, y, psi, v, w, dt)
    else:
        x1, y1, p1, J = se2_step_jac(x, y, psi, v, w, dt)
    j0 = J[0]
    j1 = J[1]
    F = (j0[2], j0[3] * kv, j0[4] * gw, j1[2], j1[3] * kv, j1[4] * gw, dt * gw,
         j0[3] * u, j0[4] * ow, j1[3] * u, j1[4] * ow, dt * ow)
    q = unicycle_process_noise_terms(psi, v, dt, acc, yaw_acc, pos_long, pos_lat, heading)
    a = 1.0 / kv
    b = 1.0 / gw
    q = (q[0], q[1], q[2], q[3] * a, q[4] * b,
         q[5], q[6], q[7] * a, q[8] * b,
         q[9], q[10] * a, q[11] * b,
         q[12] * a * a, q[13] * a * b, q[14] * b * b)
    return x1, y1, p1, F, q


def delayed_gps_terms(
    x: float, y: float, psi: float, u: float, om: float, kv: float, kw: float, lx: float,
    ly: float, d: float, w_true: bool = False
) -> tuple[float, ...]:
    """The GPS antenna ``d`` s before the state's time (lever arm (lx, ly) m, body frame),
    reached by the exact constant-twist step backwards with the true twist (k_v u, k_w om)
    (k_v = k_w = 1 without scale states; with ``w_true`` the yaw rate is om itself, as in
    :func:`scaled_step_terms`), and its Jacobian.

    Returns (east, north, de/dpsi, de/du, de/dom, de/dk_v, de/dk_w, dn/dpsi, dn/du, dn/dom,
    dn/dk_v, dn/dk_w); d/dx of east and d/dy of north are 1, the rest 0. Shared by the Python
    filter and the compiled one (ddfuse.ekf_baseline.kalman_jit)."""
    gw = 1.0 if w_true else kw
    ow = 0.0 if w_true else om
    xb, yb, pb, J = se2_step_jac(x, y, psi, kv * u, gw * om, -d)
    c = _cos(pb)
    s = _sin(pb)
    ae = -s * lx - c * ly  # d antenna offset / d heading at t - d
    an = c * lx - s * ly
    je = J[0]
    jn = J[1]
    # d psi(t - d) / d (psi, w) = (1, -d); w.r.t. the true twist (v, w) = (k_v u, k_w om)
    de_v = je[3]
    de_w = je[4] - d * ae
    dn_v = jn[3]
    dn_w = jn[4] - d * an
    return (xb + c * lx - s * ly, yb + s * lx + c * ly,
            je[2] + ae, de_v * kv, de_w * gw, de_v * u, de_w * ow,
            jn[2] + an, dn_v * kv, dn_w * gw, dn_v * u, dn_w * ow)


def se2_error_terms(p0: float, p1: float, F: tuple[float, ...], q: tuple[float, ...]
                    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The prediction's F and Q for the SE(2) exponential-coordinate pose error (module
    docstring, "Pose error"): world-frame ones (``scaled_step_terms``' F layout, 12 entries,
    and Q's 15-entry upper triangle of (x, y, psi, u, om)) of a step from heading ``p0`` to
    ``p1`` (rad) mapped by the chart's Jacobians, F_xi = A1^-1 F A0, Q_xi = A1^-1 Q A1^-T,
    A = d(x, y, psi) / d(rho_x, rho_y, theta) at xi = 0 = blockdiag(R(psi), 1).

    For the exact step this is the Lie-group Jacobian: the pose block is the adjoint
    Ad(Exp(-tau dt)) (rotation R(p0 - p1), translation column R(p1)^T dF/dpsi), the twist
    columns the right Jacobian J_r(tau dt) dt times the scales. Returns (F' in F's layout, then
    the pose block's (0, 0), (0, 1), (1, 0), (1, 1) entries; Q' in Q's order)."""
    c = _cos(p1)
    s = _sin(p1)
    cd = _cos(p0 - p1)
    sd = _sin(p0 - p1)
    Fo = (c * F[0] + s * F[3], c * F[1] + s * F[4], c * F[2] + s * F[5],
          -s * F[0] + c * F[3], -s * F[1] + c * F[4], -s * F[2] + c * F[5], F[6],
          c * F[7] + s * F[9], c * F[8] + s * F[10], -s * F[7] + c * F[9],
          -s * F[8] + c * F[10], F[11], cd, -sd, sd, cd)
    a, b, d = q[0], q[1], q[5]
    cc, ss, cs = c * c, s * s, c * s
    qo = (cc * a + 2.0 * cs * b + ss * d,  # xx
          cs * (d - a) + (cc - ss) * b,  # xy
          c * q[2] + s * q[6], c * q[3] + s * q[7], c * q[4] + s * q[8],  # x psi, x u, x om
          ss * a - 2.0 * cs * b + cc * d,  # yy
          -s * q[2] + c * q[6], -s * q[3] + c * q[7], -s * q[4] + c * q[8],  # y psi, u, om
          q[9], q[10], q[11], q[12], q[13], q[14])
    return Fo, qo


def se2_retract(x: float, y: float, psi: float, d0: float, d1: float, d2: float
                ) -> tuple[float, float, float]:
    """The pose (x m, y m, psi rad, world) moved by the body-frame exponential coordinates
    (d0 m, d1 m, d2 rad): X Exp(d), Exp(rho, theta) = (R(theta), V(theta) rho),
    V = [[S, -C], [C, S]], S = sin(theta)/theta, C = (1 - cos theta)/theta. psi not wrapped."""
    sa, ca, _, _ = twist_coeffs(d2)
    tx = sa * d0 - ca * d1
    ty = ca * d0 + sa * d1
    c = _cos(psi)
    s = _sin(psi)
    return x + c * tx - s * ty, y + s * tx + c * ty, psi + d2


def pose_correct(x: float, y: float, psi: float, d0: float, d1: float) -> tuple[float, float]:
    """The position (m, world) after an update's correction (d0, d1) m of the body-frame
    position error rho at heading ``psi`` (rad, the prior's): (x, y) + R(psi) (d0, d1), the
    chart the measurement models are linearised in (the heading correction is added to psi).
    Not the exponential map's (x, y) + R(psi) V(d_theta) (d0, d1): a large correction (a gate
    lock-out's recovery, with the heading unknown) would then land off the measured position
    (module docstring, "Pose error"); the two agree to first order."""
    c = _cos(psi)
    s = _sin(psi)
    return x + c * d0 - s * d1, y + s * d0 + c * d1


def se2_log_error(dx: float, dy: float, dpsi: float, psi: float) -> tuple[float, float, float]:
    """xi = Log(X_hat^-1 X_true) of a true pose that differs from the estimate (heading ``psi``
    rad) by the world-frame (dx m, dy m) and the wrapped heading difference ``dpsi`` rad:
    rho = V(dpsi)^-1 R(psi)^T (dx, dy), theta = dpsi. The inverse of :func:`se2_retract`."""
    c = _cos(psi)
    s = _sin(psi)
    bx = c * dx + s * dy
    by = -s * dx + c * dy
    sa, ca, _, _ = twist_coeffs(dpsi)
    det = sa * sa + ca * ca
    return (sa * bx + ca * by) / det, (-ca * bx + sa * by) / det, dpsi


class _Sensor:
    """Per-sensor settings looked up once: gate, GPS lever arm, bias/offset handling."""

    __slots__ = ("gate", "lever", "bias_idx", "bias", "hoff_idx", "hoff", "uses", "rows",
                 "rows_h", "delay", "row", "use_w", "use_yaw", "tau")

    def __init__(self, gate=DEFAULT_GATE, lever=(0.0, 0.0), uses=None, delay=0.0, tau=0.0):
        self.gate = gate
        self.lever = lever
        self.delay = delay  # s, GPS: the fix is the position this long before its stamp
        self.tau = tau  # s, GPS: correlation time of its errors (0: white)
        self.bias_idx: int | None = None
        self.bias = 0.0  # rad/s, configured gyro bias when not estimated
        self.hoff_idx: int | None = None
        self.hoff = 0.0  # rad, configured heading offset when not estimated
        self.uses = uses  # None: everything the message carries
        self.rows = _ROWS_W  # sparse H of its gyro (with its bias state when estimated)
        self.rows_h = _ROWS_PSI  # sparse H of its heading (with its offset state)
        self.row: int | None = None  # its row in the compiled core's sensor table
        self.use_w = uses is None or "yaw_rate" in uses  # gyro and heading used
        self.use_yaw = uses is None or "yaw" in uses


class UnicycleEkf(Estimator):
    """Unicycle EKF (module docstring). Convention for every filter in this package:
    ``UnicycleEkf(cfg, *, initial_pose=None)``, then ``process(m)`` per measurement in time order,
    ``estimate()`` at any time, ``finish()`` after the last one.

    Options: ``noise`` (:class:`ProcessNoise`), ``motion`` ('exact' SE(2) step or the seed's
    'euler'), ``init_distance`` (m of GPS spread before the GPS heading alignment),
    ``initial_std`` (position m, heading rad) for a known initial pose, ``v_std0`` (m/s),
    ``w_std0`` (rad/s), ``bias_std0`` (rad/s) prior sigmas, ``lockout_count`` /
    ``lockout_time`` for the gate lock-out recovery of :class:`ekf_baseline.kalman.KalmanCore`.
    ``reference``: update through the dense numpy ``KalmanCore.update_blocks`` instead of the
    fast sparse path ``update_sparse`` (same results; the tests compare the two).
    ``compiled``: run each step in the numba kernels of ``ekf_baseline.kalman_jit`` (prediction,
    measurement models, gate, Joseph update, innovation log; what they defer -- a gate
    lock-out's recovery, the initialisations -- runs the Python code on the same arrays; the
    acceleration-limit densities' bookkeeping stays in Python and is copied into the kernels'
    arrays when it changes them).
    Default: when numba is installed and ``reference`` is not set; False runs the Python fast
    path. Same results (tests/test_ekf_fast_path.py).
    ``pose_error``: 'se2' (default) carries the pose error in SE(2) exponential coordinates,
    'world' as the world-frame difference (module docstring, "Pose error").
    """

    name = "ekf_unicycle"

    def __init__(
        self,
        cfg: Config,
        *,
        initial_pose: tuple[float, float, float] | None = None,
        noise: ProcessNoise | None = None,
        motion: str = "exact",
        init_distance: float = 5.0,
        initial_std: tuple[float, float] = GIVEN_POSE_STD,
        v_std0: float = 1.0,
        w_std0: float = 0.5,
        bias_std0: float = 0.02,
        lockout_count: int = DEFAULT_LOCKOUT_COUNT,
        lockout_time: float = DEFAULT_LOCKOUT_TIME,
        reference: bool = False,
        compiled: bool | None = None,
        pose_error: str = "se2",
    ) -> None:
        super().__init__()
        if pose_error not in POSE_ERRORS:
            raise ValueError(f"pose_error must be one of {POSE_ERRORS}, got {pose_error!r}")
        self.pose_error = pose_error
        self._lie = pose_error == "se2"
        self.reference = bool(reference)
        if compiled is None:
            compiled = not self.reference and jit.available()
        elif compiled and (self.reference or not jit.available()):
            raise ValueError("compiled=True needs numba and reference=False")
        self.compiled = bool(compiled)
        if self.compiled:
            jit.warm_up("unicycle")  # compile / load the kernels now, not in the first step
            self.log = jit.BufferedLog()
        if motion not in ("exact", "euler"):
            raise ValueError(f"motion must be 'exact' or 'euler', got {motion!r}")
        self.cfg = cfg
        self.noise = noise or ProcessNoise()
        slip = cfg.robot.slip
        if slip and noise is None:  # the robot's stated slip replaces the default densities
            self.noise = replace(self.noise, pos_long=slip.get("longitudinal", self.noise.pos_long),
                                 pos_lat=slip.get("lateral", self.noise.pos_lat),
                                 heading=slip.get("heading", self.noise.heading))
        # the robot's stated acceleration limits set the twist random walks (twist_densities)
        r = cfg.robot
        self._amax = (r.max_accel, r.max_yaw_accel) if noise is None else (None, None)
        self._tw_last: dict[tuple[str, int], float] = {}  # (sensor, 3 v / 4 w): last stamp
        self._tw_period: dict[int, dict[str, float]] = {3: {}, 4: {}}  # per sensor, s
        self._tw_on = self._amax != (None, None)
        self._step_jac = se2_step_jac if motion == "exact" else euler_step_jac
        self.motion = motion
        self.rate = None if cfg.ekf.rate == "event" else float(cfg.ekf.rate)
        self.init_distance = float(init_distance)
        self.initial_std = initial_std
        self.v_std0, self.w_std0, self.bias_std0 = v_std0, w_std0, bias_std0
        self._lockout = (lockout_count, lockout_time)

        names = ["x", "y", "psi", "v", "w"]
        self._sensors: dict[str, _Sensor] = {}
        imus_b = [s for s in cfg.of_kind("imu")
                  if s.gyro_bias == "estimate" and "yaw_rate" in s.use]
        imus_h = [s for s in cfg.of_kind("imu")
                  if s.heading_offset == "estimate" and "yaw" in s.use]
        for s in cfg.sensors:
            info = _Sensor(gate=s.gate, lever=tuple(s.lever_arm), uses=set(s.use),
                           delay=s.delay,
                           tau=float(s.correlation_time) if s.kind == "gps" else 0.0)
            if s.kind == "imu":
                if isinstance(s.gyro_bias, float):
                    info.bias = s.gyro_bias
                if isinstance(s.heading_offset, float):
                    info.hoff = s.heading_offset
            self._sensors[s.name] = info
        # random-walk densities (variance per second) of the calibration states, in state order:
        # the IMU's stated ones (noise.gyro_bias_walk, heading_offset_walk), else the defaults
        walks: list[float] = []
        for s in imus_b:
            info = self._sensors[s.name]
            info.bias_idx = len(names)
            info.rows = (((4, 1.0), (info.bias_idx, 1.0)),)
            names.append("bg" if len(imus_b) == 1 else f"bg:{s.name}")
            walks.append(s.noise.get("gyro_bias_walk", self.noise.gyro_bias) ** 2)
        for s in imus_h:
            info = self._sensors[s.name]
            info.hoff_idx = len(names)
            info.rows_h = (((2, 1.0), (info.hoff_idx, 1.0)),)
            names.append("hoff" if len(imus_h) == 1 else f"hoff:{s.name}")
            walks.append(s.noise.get("heading_offset_walk", self.noise.heading_offset) ** 2)
        self._walks = tuple(walks)
        # a GPS sensor with time-correlated errors (module docstring)
        self._gps_corr = any(s.correlation_time > 0.0 for s in cfg.of_kind("gps"))
        # odometry scale states (ddfuse.ekf_baseline.calibration) when the config states the
        # geometry's uncertainty and a sensor gives odometry
        self._scale = ScaleStates.append_to(cfg, names)
        self._ks = self._scale.index if self._scale else None
        # with a gyro, state 4 is the true yaw rate, else the odometry's (module docstring)
        self._w_true = bool(self._scale) and any(
            "yaw_rate" in s.use for s in cfg.of_kind("imu"))
        if self._scale:  # states 3, 4 are then the odometry-frame twist (module docstring)
            names[3:5] = ["v_odo", "w" if self._w_true else "w_odo"]
        self.state_names = tuple(names)
        self.n = len(names)
        self._hoff_states = tuple(i for i, nm in enumerate(names) if nm.startswith("hoff"))
        self._bias_states = tuple(i for i, nm in enumerate(names) if nm.startswith("bg"))
        self._hoff_ready: set[int] = set()

        # initialisation mode
        if initial_pose is None and isinstance(cfg.initial_pose, tuple):
            initial_pose = cfg.initial_pose
        self._initial_pose = initial_pose
        has_gps = bool(cfg.of_kind("gps"))
        known_heading = any(
            "yaw" in s.use and isinstance(s.heading_offset, float) for s in cfg.of_kind("imu")
        )
        if initial_pose is not None:
            self._mode = "pose"
        elif cfg.initial_pose == "ground_truth":
            self._mode = "ground_truth"
        elif known_heading:
            self._mode = "heading"  # position from the first fix (or origin), heading measured
        elif has_gps:
            self._mode = "align"  # dead-reckon, then align onto the GPS track
        else:
            self._mode = "origin"
        self._has_gps = has_gps
        self._pending_pos: tuple[float, float, np.ndarray] | None = None
        self._pending_fix: tuple[str, float] | None = None  # (sensor, stamp) of _pending_pos
        # GPS sensor -> stamp of its last fused fix (module docstring, "Time-correlated GPS
        # errors"); kept for the sensors with a correlation time only
        self._gps_fused: dict[str, float] = {}
        self._pair_fix: dict[str, float] = {}  # GPS sensor -> stamp of its last fix in _pairs
        self._pending_head: tuple[float, float] | None = None
        self._aligned = self._mode != "align"
        self._pairs: list[tuple[float, float, float, float, float]] = []  # dr x, y, gps e, n, var

        self.kf: KalmanCore | None = None
        self.t: float | None = None  # time of the state
        self._buf: list = []
        self._t0 = 0.0
        self._k = 0
        self._F = np.eye(self.n)
        self._T = np.eye(self.n)  # estimate(): the se2 error's covariance to the world frame
        self._Q = np.zeros((self.n, self.n))
        self._F_flat = self._F.reshape(-1)  # views: assigning into them fills F and Q
        self._Q_flat = self._Q.reshape(-1)
        fr, fc = [0, 0, 0, 1, 1, 1, 2], [2, 3, 4, 2, 3, 4, 4]
        if self._ks is not None:  # scaled_step_terms' order: the scale columns of x, y, psi
            kv, kw = self._ks, self._ks + 1
            fr, fc = fr + [0, 0, 1, 1, 2], fc + [kv, kw, kv, kw, kw]
        if self._lie:  # se2_error_terms: then the pose block's rotation
            fr, fc = fr + [0, 0, 1, 1], fc + [0, 1, 0, 1]
        self._if = np.ravel_multi_index((fr, fc), (self.n, self.n))
        # the upper and lower triangle of the 5x5 block (unicycle_process_noise's order), then
        # the diagonal of the bias and the offset states
        iu = np.triu_indices(5)
        diag = np.array(self._bias_states + self._hoff_states, dtype=int)
        self._iq = np.ravel_multi_index(
            (np.concatenate([iu[0], iu[1], diag]), np.concatenate([iu[1], iu[0], diag])),
            (self.n, self.n))
        r = cfg.robot
        self._wheel = (r.wheel_radius, r.track_width)

    # ------------------------------------------------------------------ public
    def process(self, m) -> None:
        """Consume one measurement (time order). Unused types are ignored."""
        if isinstance(m, GroundTruthPose):
            if self._mode == "ground_truth" and self.kf is None:
                self._start(m.t, m.x, m.y, m.yaw, np.diag(np.square(
                    (self.initial_std[0], self.initial_std[0]))), self.initial_std[1] ** 2)
            return
        if not isinstance(m, _USED):
            return
        if self.kf is None and not self._try_start(m):
            return
        if self.rate is None:
            if self.compiled:
                p = self._pack(m)
                if p is not None:
                    self._run_event(m, p)
                    return
            self._predict_to(m.t)
            self._apply((m,))
            return
        # fixed rate: step at t0 + k / rate, applying what arrived since the previous step
        step = self._t0 + self._k / self.rate
        if m.t > step:
            if self._buf:
                self._step(step)
            # the next step is the first grid time at or after m.t
            self._k = max(self._k + 1, math.ceil((m.t - self._t0) * self.rate - 1e-9))
        self._buf.append(m)

    def finish(self) -> None:
        """Apply what is still buffered (rate mode) at the time of the last message."""
        if self._buf:
            self._step(max(self._buf[-1].t, self.t if self.t is not None else -math.inf))

    def estimate(self) -> Estimate | None:
        """Current estimate (at the time of the last predict/update), None before the heading is
        known (see the module docstring)."""
        if self.kf is None or not self._aligned:
            return None
        kf = self.kf
        x = kf.x
        if not self._lie:
            P = kf.P.copy()
        elif self.compiled:  # (the runner asks at 10 Hz: ~1 us here, ~9 us in numpy)
            P = kf.kj.world_cov(kf.W, self.n, float(x[2]))
        else:  # to the world frame, to first order: A P A^T, A = blockdiag(R(psi), I)
            c, s = _cos(x[2]), _sin(x[2])
            T = self._T
            T[0, 0], T[0, 1], T[1, 0], T[1, 1] = c, -s, s, c
            P = T @ kf.P @ T.T
            P += P.T
            P *= 0.5
        return Estimate(
            t=self.t,
            pose=(float(x[0]), float(x[1]), float(x[2])),
            pose_cov=P[:3, :3].copy(),
            state=x.copy(),
            state_cov=P,
            state_names=self.state_names,
            pose_error=self.pose_error,
        )

    # ------------------------------------------------------------------ initialisation
    def _try_start(self, m) -> bool:
        """Handle a measurement before the filter exists; True if the filter now runs and ``m``
        should be processed normally."""
        mode = self._mode
        if mode == "pose":
            x, y, psi = self._initial_pose
            s0, s2 = self.initial_std
            self._start(m.t, x, y, psi, np.diag((s0 * s0, s0 * s0)), s2 * s2)
            return True
        if mode in ("origin", "align"):
            self._start(m.t, 0.0, 0.0, 0.0, np.diag((1e-6, 1e-6)), 1e-6)
            return True
        if mode == "heading":
            if isinstance(m, Heading):
                info = self._sensor(m.sensor)
                if info.hoff_idx is None and (info.uses is None or "yaw" in info.uses):
                    self._pending_head = (m.yaw - info.hoff, m.var)
            elif isinstance(m, GpsFix) and m.enu is not None and m.status >= 0:
                self._pending_pos = (m.enu[0], m.enu[1], np.asarray(m.cov)[:2, :2])
                self._pending_fix = (m.sensor, m.t)
            if self._pending_head is not None and (self._pending_pos or not self._has_gps):
                px, py, pc = self._pending_pos or (0.0, 0.0, np.diag((1e-6, 1e-6)))
                self._start(m.t, px, py, self._pending_head[0], pc, self._pending_head[1])
                if self._pending_pos is not None:  # the position is that fix's
                    self._fused_fix(*self._pending_fix)
                # the message that completed the initialisation is not fused a second time
                return False
            self.log.rejected[(m.sensor, "before_init")] += 1
            return False
        # ground_truth: wait for the first reference pose
        self.log.rejected[(m.sensor, "before_init")] += 1
        return False

    def _start(self, t: float, x: float, y: float, psi: float, pos_cov, psi_var: float) -> None:
        n = self.n
        x0 = np.zeros(n)
        x0[0], x0[1], x0[2] = x, y, psi
        P0 = np.zeros((n, n))
        if self._lie:  # the position error in the body frame: R(psi)^T C R(psi)
            c, s = _cos(psi), _sin(psi)
            Rt = np.array([[c, s], [-s, c]])
            pos_cov = Rt @ np.asarray(pos_cov, dtype=float) @ Rt.T
        P0[:2, :2] = pos_cov
        P0[2, 2] = psi_var
        P0[3, 3] = self.v_std0**2
        P0[4, 4] = self.w_std0**2
        for i in self._bias_states:
            P0[i, i] = self.bias_std0**2
        for i in self._hoff_states:
            P0[i, i] = _PI * _PI / 3.0  # uniform on the circle until initialised from a Heading
        if self._scale:
            self._scale.set_prior(x0, P0)
        if self.compiled:
            self.kf = self._compiled_core(x0, P0)
        else:
            self.kf = KalmanCore(x0, P0, self.log, state_angles=(2, *self._hoff_states),
                                 lockout_count=self._lockout[0], lockout_time=self._lockout[1])
        if self._ks is not None:
            self.kf.held_in_recovery = (self._ks, self._ks + 1)
        self.t = t
        self._t0 = t
        self._k = 0
        self.log.note(t, f"{self.name}: started ({self._mode}) at ({x:.2f}, {y:.2f}, {psi:.3f})")

    def _fused_fix(self, sensor: str, stamp: float) -> None:
        """Record that the fix of GPS ``sensor`` stamped ``stamp`` was fused (or gave the
        initial position): the next fix's inflation counts from it (correlated sensors only)."""
        if self._sensor(sensor).tau > 0.0:
            self._gps_fused[sensor] = stamp

    def _gps_factor(self, m: GpsFix, tau: float, prev: dict | None) -> float:
        """The factor on fix ``m``'s covariance in the fusion (module docstring, "Time-correlated
        GPS errors"): from its sensor's last fused fix or, with ``prev`` (a fixed-rate step's
        sensor -> stamp of its previous fix in the step, updated here), that one."""
        if prev is not None and m.sensor in prev:
            t_last = prev[m.sensor]
        else:
            t_last = self._gps_fused.get(m.sensor, -math.inf)
        if prev is not None:
            prev[m.sensor] = m.t
        return gps_inflation(m.t - t_last, tau)

    def _sensor(self, name: str) -> _Sensor:
        info = self._sensors.get(name)
        if info is None:  # a sensor not in the config (synthetic streams): defaults
            info = self._sensors[name] = _Sensor()
        return info

    def _align(self, t: float) -> None:
        """Rotate/translate the dead-reckoned state onto the GPS track (least squares)."""
        pairs = np.array(self._pairs)
        a = pairs[:, 0:2] - pairs[:, 0:2].mean(axis=0)
        b = pairs[:, 2:4] - pairs[:, 2:4].mean(axis=0)
        saa = float((a * a).sum())
        sbb = float((b * b).sum())
        kf = self.kf
        if saa > 0.25 * sbb:
            th, res = rotation_fit(a, b)
            c, s = _cos(th), _sin(th)
            r2 = float((res * res).sum(axis=1).mean())
            # var(theta) ~ sigma^2 / sum |a_i|^2 for independent position errors of sigma (floored:
            # GPS noise is at least decimetres), plus a floor for DR heading drift over the track
            th_var = max(r2, 0.25**2) / saa + 0.03**2
            dx = kf.x[0] - pairs[:, 0].mean()
            dy = kf.x[1] - pairs[:, 1].mean()
            ex = pairs[:, 2].mean() + c * dx - s * dy
            ny = pairs[:, 3].mean() + s * dx + c * dy
            psi = kf.x[2] + th
            how = f"Kabsch rotation {math.degrees(th):.1f} deg, residual {math.sqrt(r2):.2f} m"
        else:  # no usable dead reckoning: course from the first to the last fix
            th = math.atan2(pairs[-1, 3] - pairs[0, 3], pairs[-1, 2] - pairs[0, 2])
            c, s = _cos(th - kf.x[2]), _sin(th - kf.x[2])
            th_var = 2.0 * pairs[-1, 4] / max(sbb / len(pairs), 1e-9) + 0.03**2
            ex, ny, psi = pairs[-1, 2], pairs[-1, 3], th
            how = "GPS course (no dead reckoning)"
        # rotate the cross-covariances of the pose with the other states, reset the pose block
        n = self.n
        T = np.eye(n)
        T[0, 0], T[0, 1], T[1, 0], T[1, 1] = c, -s, s, c
        P = T @ kf.P @ T.T
        P[:3, :] = 0.0
        P[:, :3] = 0.0
        P[0, 0] = P[1, 1] = pairs[-1, 4]
        P[2, 2] = th_var
        x = kf.x.copy()
        x[0], x[1], x[2] = ex, ny, (psi + _PI) % _TWO_PI - _PI
        kf.x = x
        kf.P = P
        self._aligned = True
        self._pairs = []
        for sensor, stamp in self._pair_fix.items():  # the position is the fixes'
            self._fused_fix(sensor, stamp)
        self._pair_fix = {}
        self.log.note(t, f"{self.name}: heading initialised from GPS ({how}); "
                         f"sigma {math.degrees(math.sqrt(th_var)):.1f} deg")

    # ------------------------------------------------------------------ filter steps
    def _step(self, ts: float) -> None:
        buf = self._buf
        self._buf = []
        if self.compiled:
            prev: dict[str, float] = {}
            packs = [self._pack(m, prev) for m in buf]
            if None not in packs:
                self._run_stacked(ts, buf, packs)
                return
        self._predict_to(ts)
        self._apply(buf)

    # ------------------------------------------------------------------ compiled path
    def _compiled_core(self, x0, P0):
        """The JitKalmanCore of this filter (ekf_baseline.compiled): F's pattern (identity plus
        the pose rows of the motion Jacobian), Q's entries, the random walks, the sensors."""
        kj = jit.kernels()
        self._uni_event, self._uni_stacked = kj.uni_event, kj.uni_stacked
        n = self.n
        # F: rows 0..2 in the order uni_predict fills them (with scale states their columns of
        # x, y, psi next), then the identity of the rest
        f_pairs = [(0, 0), (0, 2), (0, 3), (0, 4), (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (2, 4)]
        ks = self._ks
        if ks is not None:
            f_pairs += [(0, ks), (0, ks + 1), (1, ks), (1, ks + 1), (2, ks + 1)]
        if self._lie:  # the rotation block of the pose error's F (se2_error_terms)
            f_pairs += [(0, 1), (1, 0)]
        f_pairs += [(i, i) for i in range(3, n)]
        upper = [(i, j) for i in range(5) for j in range(i, 5)]  # unicycle_process_noise order
        q_pairs = upper + [(j, i) for i, j in upper if i != j]
        walks = list(zip(self._bias_states + self._hoff_states, self._walks, strict=True))
        r, L = self._wheel
        kf = jit.JitKalmanCore(
            x0, P0, self.log, state_angles=(2, *self._hoff_states),
            lockout_count=self._lockout[0], lockout_time=self._lockout[1], kinds=jit.UNI_KINDS,
            f_pairs=f_pairs, q_pairs=q_pairs, walks=walks,
            motion=0 if self.motion == "exact" else 1, ks=self._ks,
            noise=self._noise_floats(),
            params={kj.FP_WHEEL_R: r, kj.FP_TRACK: L})
        kf.ip[kj.IP_LIE] = 1 if self._lie else 0
        kf.ip[kj.IP_WTRUE] = 1 if self._w_true else 0
        for info in self._sensors.values():
            info.row = None  # (re)registered with this core on first use
        return kf

    def _noise_floats(self) -> tuple[float, ...]:
        """The process noise densities in the kernels' order (unicycle_process_noise_terms)."""
        nz = self.noise
        return (nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading)

    def _pack(self, m, prev: dict | None = None):
        """The kernels' arguments (typ, sensor row, z0, z1, r0, r1, r01, r10, flags, rf) for
        message ``m``, or None when it needs the Python path: a heading before the heading is
        known or before its offset is initialised, a GPS fix while aligning or without a
        position, wheel speeds without the geometry, another message type. ``rf``: the factor
        on R in the fusion (a correlated GPS sensor's fix: ``_gps_factor`` with ``prev``)."""
        info = self._sensors.get(m.sensor) or self._sensor(m.sensor)
        row = info.row
        if row is None:
            row = info.row = self.kf.sensor_row(
                m.sensor, gate=info.gate, bias=info.bias, hoff=info.hoff, lever=info.lever,
                delay=info.delay, bias_idx=info.bias_idx, hoff_idx=info.hoff_idx)
        cls = m.__class__
        if cls is GyroYawRate:
            if not info.use_w:
                return (_T_NONE, row, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1.0)
            return (_T_GYRO, row, m.yaw_rate, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is Heading:
            if not info.use_yaw:
                return (_T_NONE, row, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1.0)
            if not self._aligned or (info.hoff_idx is not None
                                     and info.hoff_idx not in self._hoff_ready):
                return None
            return (_T_HEAD, row, m.yaw, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is WheelOdometry:
            v, w = m.v, m.yaw_rate
            return (_T_ODOM, row, 0.0 if v is None else v, 0.0 if w is None else w, m.v_var,
                    m.yaw_rate_var, 0.0, 0.0, (v is not None) | (w is not None) << 1, 1.0)
        if cls is GpsFix:
            if m.enu is None or m.status < 0 or not self._aligned:
                return None
            (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
            rf = 1.0 if info.tau <= 0.0 else self._gps_factor(m, info.tau, prev)
            return (_T_GPS, row, m.enu[0], m.enu[1], c00, c11, c01, c10, 0, rf)
        if cls is WheelSpeeds and self._wheel[0] is not None and self._wheel[1] is not None:
            return (_T_WHEELS, row, m.left, m.right, m.left_var, m.right_var, 0.0, 0.0, 0, 1.0)
        return None

    def _run_event(self, m, p) -> None:
        """Predict to ``m.t`` and update with ``m`` (packed as ``p``) in one kernel call."""
        kf = self.kf
        t = m.t
        self._gap_steps(t)
        dt = t - self.t
        code = self._uni_event(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, t, *p)
        if code:
            code = kf.settle(code, self._uni_event, dt, t, *p)
        if dt > 0.0:
            self.t = t
        if code & _DEFER:  # predicted; the update needs Python (lock-out, singular S)
            self._apply((m,))
            return
        if self._gps_corr and p[0] == _T_GPS and not code & _REJECTED:
            # fused: the next fix's inflation counts from it
            self._fused_fix(m.sensor, t)
        if self._tw_on:  # what _apply records, for the next prediction's densities
            self._twist_msg(m, self._sensors[m.sensor])

    def _run_stacked(self, ts: float, buf: list, packs: list) -> None:
        """A fixed-rate step at ``ts``: predict and one stacked update in one kernel call."""
        self._gap_steps(ts)
        dt = ts - self.t
        mb = np.array(packs, dtype=float).reshape(-1, 10)
        kf = self.kf
        k = len(packs)
        code = kf.settle(self._uni_stacked(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, ts, mb, k),
                         self._uni_stacked, dt, ts, mb, k)
        if dt > 0.0:
            self.t = ts
        if code & _DEFER:
            self._apply(buf)
            return
        if self._gps_corr:  # the kernel's verdicts on the fixes (flags column: fused)
            for i, p in enumerate(packs):
                if p[0] == _T_GPS and mb[i, 8] == 1.0:
                    self._fused_fix(buf[i].sensor, buf[i].t)
        if self._tw_on:
            sensors = self._sensors
            for m in buf:
                self._twist_msg(m, sensors[m.sensor])

    def _gap_steps(self, t: float) -> None:
        """Over a gap to ``t`` (more than ``MAX_PREDICT_DT``), predict all but the last of the
        equal steps of at most that; the last is the caller's (the kernels predict it with
        their update), so that every path splits a gap alike."""
        n = math.ceil((t - self.t) / MAX_PREDICT_DT - 1e-9)
        for k in range(1, n):
            self._predict_step(self.t + (t - self.t) / (n - k + 1))

    def _predict_to(self, t: float) -> None:
        """Predict to ``t``, in equal steps of at most ``MAX_PREDICT_DT`` over a gap."""
        if t - self.t <= 0.0:
            return  # same stamp (or a tiny reorder): apply at the current state time
        self._gap_steps(t)
        self._predict_step(t)

    def _predict_step(self, t: float) -> None:
        """One prediction step to ``t`` (> the state's time)."""
        dt = t - self.t
        kf = self.kf
        xs = kf.x.tolist()
        ks = self._ks
        if self._lie:
            # the world-frame step's F and Q mapped to the pose error's coordinates
            nz = self.noise
            kv, kw = (1.0, 1.0) if ks is None else (xs[ks], xs[ks + 1])
            x1, y1, p1, F, q = scaled_step_terms(
                xs[0], xs[1], xs[2], xs[3], xs[4], kv, kw, dt,
                self.motion == "euler", nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading,
                self._w_true)
            F, q = se2_error_terms(xs[2], p1, F, q)
            self._F_flat[self._if] = F if ks is not None else F[:7] + F[12:]
        elif ks is None:
            x1, y1, p1, J = self._step_jac(xs[0], xs[1], xs[2], xs[3], xs[4], dt)
            j0, j1 = J[0], J[1]
            # one flat fancy-index assignment each for F and Q: element assignments cost
            # ~100 ns apiece, the (row, col) fancy index twice the flat one
            self._F_flat[self._if] = (j0[2], j0[3], j0[4], j1[2], j1[3], j1[4], dt)
            q = unicycle_process_noise(xs[2], xs[3], dt, self.noise)
        else:
            nz = self.noise
            x1, y1, p1, F, q = scaled_step_terms(
                xs[0], xs[1], xs[2], xs[3], xs[4], xs[ks], xs[ks + 1], dt,
                self.motion == "euler", nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading,
                self._w_true)
            self._F_flat[self._if] = F
        self._Q_flat[self._iq] = q + q + tuple([w * dt for w in self._walks])
        xs[0], xs[1], xs[2] = x1, y1, p1
        kf.predict(self._F, self._Q, xs)
        self.t = t

    def _twist_msg(self, m, info: _Sensor) -> None:
        """With stated acceleration limits: record the twist components message ``m`` measures
        (odometry and wheel speeds: v, w; a used gyro: w) for :meth:`_twist_seen`. Both paths
        call it once per message they apply, before the next prediction."""
        if isinstance(m, GyroYawRate):
            if info.use_w and self._amax[1] is not None:
                self._twist_seen(m.sensor, 4, m.t)
        elif isinstance(m, WheelOdometry):
            if m.v is not None:
                self._twist_seen(m.sensor, 3, m.t)
            if m.yaw_rate is not None:
                self._twist_seen(m.sensor, 4, m.t)
        elif isinstance(m, WheelSpeeds):
            self._twist_seen(m.sensor, 3, m.t)
            self._twist_seen(m.sensor, 4, m.t)

    def _twist_seen(self, sensor: str, comp: int, t: float) -> None:
        """Record a measurement of v (comp 3) or w (4) by ``sensor`` at ``t``; with stated
        acceleration limits, re-derive the twist densities when the shortest sample period of
        that component's sensors changes by more than 10 %."""
        key = (sensor, comp)
        last = self._tw_last.get(key)
        self._tw_last[key] = t
        if last is None or not t > last:
            return
        per = self._tw_period[comp]
        old = min(per.values()) if per else None
        per[sensor] = t - last
        new = min(per.values())
        if old is None or abs(new - old) > 0.1 * old:
            p3, p4 = self._tw_period[3], self._tw_period[4]
            self.noise = twist_densities(*self._amax, min(p3.values()) if p3 else None,
                                         min(p4.values()) if p4 else None, self.noise)
            if self.compiled and self.kf is not None:  # the kernels' copy of the densities
                self.kf.set_noise(self._noise_floats())

    def _apply(self, ms) -> None:
        """Assemble the piecewise measurement model of the messages ``ms`` -- per measurement its
        innovation, sparse H rows and R -- and update (module docstring, "Measurements")."""
        kf = self.kf
        x = kf.x.tolist()  # python floats: cheaper than numpy scalars in the scalar code below
        blocks: list[tuple] = []
        t = self.t
        tw = self._tw_on
        ks = self._ks
        corr: list[tuple] = []  # correlated GPS fixes: (block index, sensor, stamp, factor)
        prev: dict[str, float] = {}
        for m in ms:
            info = self._sensors.get(m.sensor) or self._sensor(m.sensor)
            if tw:  # (the sample periods set the densities of the next prediction)
                self._twist_msg(m, info)
            if isinstance(m, GyroYawRate):
                if info.uses is not None and "yaw_rate" not in info.uses:
                    continue
                bi = info.bias_idx
                if ks is not None and not self._w_true:  # it sees k_w om (+ bias)
                    kw, om = x[ks + 1], x[4]
                    b, bcol = (info.bias, ()) if bi is None else (x[bi], ((bi, 1.0),))
                    y = m.yaw_rate - (kw * om + b)
                    rows = (((4, kw), (ks + 1, om), *bcol),)
                elif bi is None:
                    y = m.yaw_rate - (x[4] + info.bias)
                    rows = _ROWS_W
                else:
                    y = m.yaw_rate - (x[4] + x[bi])
                    rows = info.rows
                blocks.append((m.sensor, "gyro", (y,), rows, ((m.var,),), info.gate))
            elif isinstance(m, Heading):
                if info.uses is not None and "yaw" not in info.uses:
                    continue
                if not self._aligned:
                    self.log.rejected[(m.sensor, "before_init")] += 1
                    continue
                hi = info.hoff_idx
                if hi is None:
                    hpred = x[2] + info.hoff
                    rows = _ROWS_PSI
                else:
                    if hi not in self._hoff_ready:
                        self._init_offset(t, m, hi)
                        x = kf.x.tolist()
                        continue
                    hpred = x[2] + x[hi]
                    rows = info.rows_h
                y = (m.yaw - hpred + _PI) % _TWO_PI - _PI
                blocks.append((m.sensor, "heading", (y,), rows, ((m.var,),), info.gate))
            elif isinstance(m, WheelOdometry):
                # the odometry's twist is the state's (with scale states, the odometry-frame
                # twist; the scales enter the motion, not this linear measurement)
                if m.v is not None:
                    blocks.append((m.sensor, "v", (m.v - x[3],), _ROWS_V, ((m.v_var,),),
                                   info.gate))
                if m.yaw_rate is not None:
                    if self._w_true:  # the odometry reports the true yaw rate / k_w
                        kw = x[ks + 1]
                        y1 = m.yaw_rate - x[4] / kw
                        rows = (((4, 1.0 / kw), (ks + 1, -x[4] / (kw * kw))),)
                    else:
                        y1, rows = m.yaw_rate - x[4], _ROWS_W
                    blocks.append((m.sensor, "yaw_rate", (y1,), rows, ((m.yaw_rate_var,),),
                                   info.gate))
            elif isinstance(m, GpsFix):
                if m.enu is None or m.status < 0:
                    self.log.rejected[(m.sensor, "no_fix" if m.status < 0 else "no_enu")] += 1
                    continue
                if not self._aligned:
                    self._pairs.append((x[0], x[1], m.enu[0], m.enu[1],
                                        0.5 * float(m.cov[0][0] + m.cov[1][1])))
                    self._pair_fix[m.sensor] = m.t
                    e0, n0 = self._pairs[0][2], self._pairs[0][3]
                    if math.hypot(m.enu[0] - e0, m.enu[1] - n0) >= self.init_distance:
                        self._align(t)
                        x = kf.x.tolist()
                    continue
                y, rows = self._gps_model(m, info, x)
                cv = m.cov.tolist()
                if info.tau > 0.0:
                    corr.append((len(blocks), m.sensor, m.t,
                                 self._gps_factor(m, info.tau, prev)))
                blocks.append((m.sensor, "gps", y, rows,
                               ((cv[0][0], cv[0][1]), (cv[1][0], cv[1][1])), info.gate))
            elif isinstance(m, WheelSpeeds):
                r, L = self._wheel
                if r is None or L is None:
                    raise ValueError("WheelSpeeds need robot.wheel_radius and robot.track_width")
                k = 0.5 * L / r
                # the nominal geometry turns the state's (odometry-frame) twist into wheel speeds
                if self._w_true:  # (the odometry-frame yaw rate is w / k_w)
                    kw = x[ks + 1]
                    k /= kw
                    dk = x[4] * k / kw
                    rows = (((3, 1.0 / r), (4, -k), (ks + 1, dk)),
                            ((3, 1.0 / r), (4, k), (ks + 1, -dk)))
                else:
                    rows = (((3, 1.0 / r), (4, -k)), ((3, 1.0 / r), (4, k)))
                vr, wr = x[3] / r, x[4] * k
                blocks.append((m.sensor, "wheels", (m.left - (vr - wr), m.right - (vr + wr)),
                               rows, ((m.left_var, 0.0), (0.0, m.right_var)), info.gate))
        if blocks:
            xb = kf.x[:3].tolist() if self._lie else None
            # the compiled filter's Python updates (what its kernels defer) are the reference's
            update = kf.update_dense if self.reference or self.compiled else kf.update_sparse
            if not corr:
                update(t, blocks)
            else:  # a fix of a GPS with correlated errors: fused with its inflated covariance
                fuse = [1.0] * len(blocks)
                for i, _, _, f in corr:
                    fuse[i] = f
                update(t, blocks, fuse)
                verdicts = kf.last_verdicts
                for i, sensor, stamp, _ in corr:
                    if verdicts[i]:
                        self._fused_fix(sensor, stamp)
            if xb is not None:
                # KalmanCore added the correction K y; its position part is the body-frame rho
                xa = kf.x.copy()
                x1, y1 = pose_correct(xb[0], xb[1], xb[2], float(xa[0]) - xb[0],
                                      float(xa[1]) - xb[1])
                xa[0], xa[1] = x1, y1
                kf.x = xa

    def _gps_model(self, m: GpsFix, info: _Sensor, x: list) -> tuple[tuple, tuple]:
        """Innovation (east, north, m) and sparse H rows of a fix: the antenna (lever arm
        rotated by the heading) at the fix's measurement time, ``info.delay`` s before the
        state's, reached by the exact constant-twist step backwards (ddfuse.factors.kinematics)."""
        lx, ly = info.lever
        d = info.delay
        c, s = _cos(x[2]), _sin(x[2])
        # d(east, north) / d(x, y) (world) is I; d / d(rho_x, rho_y) (body-frame pose error,
        # X Exp(xi): position + R(psi) rho to first order) is R(psi)
        pe, pn = (((0, c), (1, -s)), ((0, s), (1, c))) if self._lie else (((0, 1.0),), ((1, 1.0),))
        if d == 0.0:
            y = (m.enu[0] - (x[0] + c * lx - s * ly), m.enu[1] - (x[1] + s * lx + c * ly))
            if lx == 0.0 and ly == 0.0:
                return y, _ROWS_XY if not self._lie else (pe, pn)
            return y, ((*pe, (2, -s * lx - c * ly)), (*pn, (2, c * lx - s * ly)))
        ks = self._ks
        kv, kw = (1.0, 1.0) if ks is None else (x[ks], x[ks + 1])
        he, hn, e_p, e_u, e_om, e_kv, e_kw, n_p, n_u, n_om, n_kv, n_kw = delayed_gps_terms(
            x[0], x[1], x[2], x[3], x[4], kv, kw, lx, ly, d, self._w_true)
        y = (m.enu[0] - he, m.enu[1] - hn)
        if ks is None:
            return y, ((*pe, (2, e_p), (3, e_u), (4, e_om)),
                       (*pn, (2, n_p), (3, n_u), (4, n_om)))
        return y, ((*pe, (2, e_p), (3, e_u), (4, e_om), (ks, e_kv), (ks + 1, e_kw)),
                   (*pn, (2, n_p), (3, n_u), (4, n_om), (ks, n_kv), (ks + 1, n_kw)))

    def _init_offset(self, t: float, m: Heading, hi: int) -> None:
        """hoff = wrap(z - psi): variance var(psi) + R, covariance -cov(psi, .) with the rest."""
        kf = self.kf
        x = kf.x.copy()
        x[hi] = (m.yaw - x[2] + _PI) % _TWO_PI - _PI
        P = kf.P.copy()
        row = -P[2, :]
        P[hi, :] = row
        P[:, hi] = row
        P[hi, hi] = P[2, 2] + m.var
        kf.x = x
        kf.P = P
        self._hoff_ready.add(hi)
        self.log.note(t, f"{self.name}: heading offset of {m.sensor} initialised to "
                         f"{math.degrees(x[hi]):.1f} deg")
