"""Seed 003's unicycle EKF: Jacobians, process noise, the shared motion model, and accuracy and
consistency on synthetic runs drawn from the filter's own continuous-time model."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from ddfuse.ekf_baseline.unicycle import (
    ProcessNoise,
    UnicycleEkf,
    euler_step_jac,
    se2_log_error,
    se2_retract,
    twist_densities,
    unicycle_process_noise,
)
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.measurements import (
    GpsFix,
    GroundTruthPose,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.factors.kinematics import se2_step, se2_step_jac
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from scipy.linalg import expm
from scipy.stats import chi2

# Truth model: v and w random walks (white accel / yaw accel), pose by the exact constant-twist
# step over 2 ms sub-steps. The filter gets the same densities and no extra slip/heading noise.
SIM_NOISE = ProcessNoise(acc=0.3, yaw_acc=0.2, pos_long=0.0, pos_lat=0.0, heading=0.0,
                         gyro_bias=1e-4, heading_offset=0.01)


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class Run:
    measurements: list
    truth_t: np.ndarray  # (k,)
    truth: np.ndarray  # (k, 7): x, y, psi, v, w, bias, heading offset at truth_t
    extra: dict = field(default_factory=dict)


def simulate(
    seed: int,
    duration: float = 60.0,
    *,
    gps_rate=5.0,
    gps_sigma=0.5,
    odom_rate=50.0,
    v_sigma=0.05,
    gyro_rate=50.0,
    gyro_sigma=0.02,
    odom_w_sigma=None,
    heading_rate=None,
    heading_sigma=0.03,
    bias=0.0,
    offset=0.0,
    noise=SIM_NOISE,
    psi0=0.7,
    v0=1.0,
    wheels=None,
    kidnap=None,
    stand_still=0.0,
) -> Run:
    """Simulate a robot and its sensors. Measurements are noisy with the stated sigmas; GPS
    noise is white; the gyro reads w + bias; the heading reads wrap(psi + offset(t)) with the
    offset a random walk of ``noise.heading_offset``. ``kidnap=(t, dx, dy)`` teleports the
    robot (GPS follows; odometry does not see it). ``stand_still`` seconds at the start with
    v = w = 0 exactly."""
    rng = np.random.default_rng(seed)
    dt = 0.002
    n = int(round(duration / dt))
    x, y, psi, v, w = 0.0, 0.0, psi0, v0, 0.0
    off = offset
    ms = []
    ts, states = [], []
    periods = {"gps": 1 / gps_rate if gps_rate else None, "odom": 1 / odom_rate,
               "gyro": 1 / gyro_rate if gyro_rate else None,
               "heading": 1 / heading_rate if heading_rate else None}
    next_t = {k: (p if p else math.inf) for k, p in periods.items()}
    sq = math.sqrt(dt)
    kidnapped = False
    for k in range(1, n + 1):
        t = k * dt
        if t <= stand_still:
            v_use, w_use = 0.0, 0.0
        else:
            v_use, w_use = v, w
        x, y, psi = se2_step(x, y, psi, v_use, w_use, dt)
        psi = wrap(psi)
        if t > stand_still:
            v += noise.acc * sq * rng.normal()
            w += noise.yaw_acc * sq * rng.normal()
            # keep the synthetic robot in a plausible envelope (reflect rather than clip, to keep
            # the increments Gaussian almost everywhere)
            if v < 0.2 or v > 2.0:
                v = min(max(v, 0.2), 2.0)
            if abs(w) > 0.8:
                w = math.copysign(0.8, w)
        off += noise.heading_offset * sq * rng.normal()
        if kidnap and not kidnapped and t >= kidnap[0]:
            x += kidnap[1]
            y += kidnap[2]
            kidnapped = True
        ts.append(t)
        states.append((x, y, psi, v_use, w_use, bias, off))
        if t + 1e-9 >= next_t["odom"]:
            next_t["odom"] += periods["odom"]
            if wheels is None:
                wz = None if odom_w_sigma is None else w_use + odom_w_sigma * rng.normal()
                ms.append(WheelOdometry(t, v_use + v_sigma * rng.normal(), wz, v_sigma**2,
                                        (odom_w_sigma or 1.0) ** 2, sensor="/odom"))
            else:
                r, L, sw = wheels
                wl = (v_use - 0.5 * L * w_use) / r + sw * rng.normal()
                wr = (v_use + 0.5 * L * w_use) / r + sw * rng.normal()
                ms.append(WheelSpeeds(t, wl, wr, sw**2, sw**2, sensor="/joint_states"))
        if t + 1e-9 >= next_t["gyro"]:
            next_t["gyro"] += periods["gyro"]
            ms.append(GyroYawRate(t, w_use + bias + gyro_sigma * rng.normal(), gyro_sigma**2,
                                  sensor="/imu"))
        if t + 1e-9 >= next_t["heading"]:
            next_t["heading"] += periods["heading"]
            ms.append(Heading(t, wrap(psi + off + heading_sigma * rng.normal()),
                              heading_sigma**2, sensor="/imu"))
        if t + 1e-9 >= next_t["gps"]:
            next_t["gps"] += periods["gps"]
            e = x + gps_sigma * rng.normal()
            nn = y + gps_sigma * rng.normal()
            ms.append(GpsFix(t, 0.0, 0.0, 0.0, np.diag([gps_sigma**2] * 3), 0, sensor="/fix",
                             enu=(e, nn, 0.0)))
    return Run(ms, np.array(ts), np.array(states))


def make_cfg(*, gps=True, odom_use=("v",), imu_use=("yaw_rate",), gyro_bias=0.0,
             heading_offset=0.0, rate="event", wheels=False, initial_pose=None, gate=0.9999):
    sensors = {}
    if wheels:
        sensors["wheels"] = [{"topic": "/joint_states", "joints": ["l", "r"], "gate": gate,
                               "noise": {"speed": 0.2}}]
    else:
        sensors["odometry"] = [{"topic": "/odom", "use": list(odom_use), "gate": gate}]
    if imu_use:
        sensors["imu"] = [{"topic": "/imu", "use": list(imu_use), "gyro_bias": gyro_bias,
                           "heading_offset": heading_offset, "gate": gate}]
    if gps:
        sensors["gps"] = [{"topic": "/fix", "gate": gate}]
    raw = {"sensors": sensors, "ekf": {"rate": rate}}
    if wheels:
        raw["robot"] = {"wheel_radius": 0.1, "track_width": 0.5}
    if initial_pose is not None:
        raw["initial_pose"] = list(initial_pose)
    return parse_config(raw)


def run_filter(ekf, run, every=1):
    """Feed a run; return (times, estimate states, covariances, truth at those times)."""
    ts, xs, Ps, tr = [], [], [], []
    truth_index = {round(t, 6): i for i, t in enumerate(run.truth_t)}
    for k, m in enumerate(run.measurements):
        ekf.process(m)
        if k % every:
            continue
        est = ekf.estimate()
        if est is None or est.t is None:
            continue
        i = truth_index.get(round(est.t, 6))
        if i is None:
            continue
        ts.append(est.t)
        xs.append(est.state)
        Ps.append(est.state_cov)
        tr.append(run.truth[i])
    ekf.finish()
    return np.array(ts), np.array(xs), np.array(Ps), np.array(tr)


def state_error(x, truth, names):
    """Estimate minus truth in the filter's state order, angles wrapped."""
    cols = {"x": 0, "y": 1, "psi": 2, "v": 3, "w": 4, "bg": 5, "hoff": 6}
    e = np.array([x[i] - truth[cols[nm]] for i, nm in enumerate(names)])
    for i, nm in enumerate(names):
        if nm in ("psi", "hoff"):
            e[i] = wrap(e[i])
    return e


# ---------------------------------------------------------------- model pieces


def _numeric_jac(f, x, eps=1e-6):
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x))
    J = np.zeros((f0.size, x.size))
    for j in range(x.size):
        d = np.zeros_like(x)
        d[j] = eps
        J[:, j] = (np.asarray(f(x + d)) - np.asarray(f(x - d))) / (2 * eps)
    return J


def _error_chart(pose_error, x0, x1=None):
    """The filter's error coordinates: (to_state(d): the state at error d from x0, and
    error(x): the error of state x from x1). 'world': the difference (heading wrapped);
    'se2': the pose by X Exp(xi) (ddfuse.ekf_baseline.unicycle.se2_retract / se2_log_error), the
    other states by the difference."""
    x0 = np.asarray(x0, dtype=float)
    x1 = x0 if x1 is None else np.asarray(x1, dtype=float)

    def to_state(d):
        x = x0 + d
        if pose_error == "se2":
            x[:3] = se2_retract(*x0[:3], *d[:3])
        return x

    def error(x):
        e = np.asarray(x, dtype=float) - x1
        e[2] = wrap(e[2])
        if pose_error == "se2":
            e[:3] = se2_log_error(e[0], e[1], e[2], x1[2])
        return e

    return to_state, error


def test_se2_retract_and_log_are_inverse_and_match_the_group():
    """X Exp(d) against the SE(2) matrix exponential (scipy expm of the twist's 3x3 matrix), and
    se2_log_error its inverse, also at a half turn."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        x, y, psi = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)
        d = rng.normal(0.0, 1.0, 3) * (2.0, 2.0, 1.0)
        d[2] = wrap(d[2])
        X = np.array([[math.cos(psi), -math.sin(psi), x], [math.sin(psi), math.cos(psi), y],
                      [0, 0, 1]])
        T = np.array([[0, -d[2], d[0]], [d[2], 0, d[1]], [0, 0, 0]])
        Y = X @ expm(T)
        got = se2_retract(x, y, psi, *d)
        np.testing.assert_allclose(got[:2], Y[:2, 2], atol=1e-12)
        assert wrap(got[2] - math.atan2(Y[1, 0], Y[0, 0])) == pytest.approx(0.0, abs=1e-12)
        back = se2_log_error(got[0] - x, got[1] - y, wrap(got[2] - psi), psi)
        np.testing.assert_allclose(back, d, atol=1e-10)


def _check_predict_jacobian(ekf, x0, dt, pose_error):
    """ekf._F of one ``dt`` s prediction step from state ``x0`` (with any P) against central
    differences through the pose-error chart; returns the predicted state. (A gap longer
    than MAX_PREDICT_DT is predicted in several of these steps.)"""
    n = len(x0)

    def step(xv):
        ekf.kf.x = np.array(xv, dtype=float)
        ekf.kf.P = np.eye(n)
        ekf.t = 0.0
        ekf._predict_step(dt)
        return ekf.kf.x.copy()

    x1 = step(x0)
    to_state, _ = _error_chart(pose_error, x0)
    _, error = _error_chart(pose_error, x0, x1)
    F_num = _numeric_jac(lambda d: error(step(to_state(d))), np.zeros(n))
    ekf.kf.x, ekf.kf.P, ekf.t = x0.copy(), np.zeros((n, n)), 0.0
    ekf._predict_step(dt)
    np.testing.assert_allclose(ekf._F, F_num, atol=1e-7)
    return x1


@pytest.mark.parametrize("pose_error", ["world", "se2"])
@pytest.mark.parametrize("motion", ["exact", "euler"])
@pytest.mark.parametrize("w", [0.0, 1e-4, 0.6])
def test_predict_jacobian_matches_central_differences(motion, w, pose_error):
    """F of the prediction against central differences of the step in the filter's error
    coordinates: for 'se2' the error map xi1 = Log(X1_hat^-1 f(X0_hat Exp(xi0), ...)), whose
    Jacobian is the adjoint Ad(Exp(-tau dt)) and the right Jacobian J_r(tau dt) dt."""
    cfg = make_cfg(imu_use=("yaw", "yaw_rate"), gyro_bias="estimate",
                   heading_offset="estimate", initial_pose=(0, 0, 0))
    ekf = UnicycleEkf(cfg, motion=motion, pose_error=pose_error)
    ekf.process(GyroYawRate(0.0, 0.0, 1e-4, sensor="/imu"))
    assert ekf.state_names == ("x", "y", "psi", "v", "w", "bg", "hoff")
    x0 = np.array([1.0, -2.0, 2.5, 1.3, w, 0.01, 0.3])
    _check_predict_jacobian(ekf, x0, 0.37, pose_error)


def _scaled_cfg(**extra_sensors):
    sensors = {"wheels": [{"topic": "/js", "joints": ["l", "r"], "noise": {"speed": 0.1}}]}
    sensors.update(extra_sensors)
    return parse_config({
        "sensors": sensors,
        "robot": {"wheel_radius": 0.1, "track_width": 0.4, "wheel_radius_std": 0.002,
                  "track_width_std": 0.01},
        "initial_pose": [0, 0, 0],
    })


_GYRO = {"imu": [{"topic": "/imu", "use": ["yaw_rate"], "gyro_bias": 0.0}]}


@pytest.mark.parametrize("motion", ["exact", "euler"])
@pytest.mark.parametrize("gyro", [False, True])
@pytest.mark.parametrize("pose_error", ["world", "se2"])
@pytest.mark.parametrize("w", [0.0, 0.6])
def test_predict_jacobian_with_scale_states_matches_central_differences(w, pose_error, gyro,
                                                                         motion):
    """With odometry scales the body moves with (k_v u, k_w om); with a gyro, state 4 is the
    true yaw rate and the body moves with (k_v u, w): F's scale columns."""
    ekf = UnicycleEkf(_scaled_cfg(**(_GYRO if gyro else {})), pose_error=pose_error,
                      motion=motion)
    ekf.process(WheelSpeeds(0.0, 0.0, 0.0, 0.01, 0.01, sensor="/js"))
    assert ekf.state_names == ("x", "y", "psi", "v_odo", "w" if gyro else "w_odo", "k_v", "k_w")
    x0 = np.array([1.0, -2.0, 2.5, 1.3, w, 1.03, 0.96])
    dt = 0.37
    x1 = _check_predict_jacobian(ekf, x0, dt, pose_error)
    if gyro:  # k_w does not enter the motion
        assert not ekf._F[:5, 6].any()
    # Q is the true-twist Q with the (u, om) rows and columns divided by (k_v, k_w) (by k_v
    # alone when state 4 is the true yaw rate); for the se2 error, mapped by
    # A1^-1 = blockdiag(R(psi1)^T, I) (the chart at the predicted pose)
    Qt = np.zeros((5, 5))
    Qt[np.triu_indices(5)] = unicycle_process_noise(2.5, 1.3 * 1.03, dt, ekf.noise)
    Qt = Qt + np.triu(Qt, 1).T
    T = np.diag([1.0, 1.0, 1.0, 1 / 1.03, 1.0 if gyro else 1 / 0.96])
    if pose_error == "se2":
        c, s = math.cos(x1[2]), math.sin(x1[2])
        T[:2, :2] = [[c, s], [-s, c]]
    np.testing.assert_allclose(ekf._Q[:5, :5], T @ Qt @ T.T, rtol=1e-12, atol=1e-16)


def test_unobservable_odometry_scales_do_not_drift():
    """Wheel speeds alone say nothing about k_v, k_w: they must keep their prior.

    With the odometry twist measured as v / k_v of a true-twist state, the EKF's Jacobians at
    the changing estimates leaked spurious information into the scales (a bias of the EKF as a
    joint parameter estimator, Ljung 1979): on 120 s of seed 002 with exact nominal geometry,
    k_w drifted to 1.08 (2.6 sigma) with 0.3 rad/s^2/sqrt(Hz) yaw-acceleration noise. The
    scales now act in the motion, and the wheel measurements are linear in the state."""
    rng = np.random.default_rng(3)
    ekf = UnicycleEkf(_scaled_cfg())
    r, half = 0.1, 0.2
    for k in range(1200):
        t = 0.1 * k
        v = 0.5 + 0.3 * math.sin(t / 3.0)
        w = 0.4 * math.sin(t / 5.0)
        left = (v - half * w) / r + 0.1 * rng.standard_normal()
        right = (v + half * w) / r + 0.1 * rng.standard_normal()
        ekf.process(WheelSpeeds(t, left, right, 0.01, 0.01, sensor="/js"))
    x, P = ekf.kf.x, ekf.kf.P
    np.testing.assert_allclose(x[5:7], 1.0, atol=1e-12)
    np.testing.assert_allclose(np.diag(P)[5:7], [0.02 ** 2, 0.02 ** 2 + 0.025 ** 2], rtol=1e-9)


@pytest.mark.parametrize("reference", [True, False])
@pytest.mark.parametrize("turning", [False, True])
def test_gyro_and_odometry_yaw_rates_do_not_bias_k_w(turning, reference):
    """Odometry (v, yaw rate) and a gyro, nominal geometry exact (k_v = k_w = 1), 120 s.

    With the odometry-frame yaw rate w_odo as the state and the gyro measured as k_w w_odo,
    every gyro update regressed on the filter's own noisy w_odo: k_w shrank towards 0 (the
    errors-in-variables bias of an EKF estimating a parameter, Ljung 1979) to 0.54 on a
    straight line (8 prior sigmas, no information at all) and to 0.952 +- 0.013 while turning,
    and the prior correlation of the scales dragged k_v to 0.978. With a gyro, state 4 is the
    true yaw rate: the gyro is linear in it, and the odometry's w / k_w regresses on a state
    the gyro pins down. Straight: both scales keep their prior; turning: k_w within 2 sigma."""
    rng = np.random.default_rng(5)
    cfg = _scaled_cfg(odometry=[{"topic": "/odom", "noise": {"v": 0.02, "yaw_rate": 0.06}}],
                      imu=[{"topic": "/imu", "use": ["yaw_rate"], "gyro_bias": 0.0,
                            "noise": {"yaw_rate": 0.01}}])
    cfg.sensors = [s for s in cfg.sensors if s.kind != "wheels"]
    ekf = UnicycleEkf(cfg, reference=reference)
    ms = []
    for k in range(1200):
        t = 0.1 * k + 0.1
        w = 0.3 * math.sin(t / 4.0) if turning else 0.0
        ms.append(WheelOdometry(t, 1.0 + 0.02 * rng.standard_normal(),
                                w + 0.06 * rng.standard_normal(), 0.02 ** 2, 0.06 ** 2,
                                sensor="/odom"))
    for k in range(3600):
        t = k / 30.0 + 0.01
        w = 0.3 * math.sin(t / 4.0) if turning else 0.0
        ms.append(GyroYawRate(t, w + 0.01 * rng.standard_normal(), 0.01 ** 2, sensor="/imu"))
    for m in sorted(ms, key=lambda m: m.t):
        ekf.process(m)
    e = ekf.estimate()
    assert e.state_names[3:] == ("v_odo", "w", "k_v", "k_w")
    (kv, kw), sd = e.state[5:7], np.sqrt(np.diag(e.state_cov)[5:7])
    sd_v, sd_w, _ = cfg.robot.scale_std
    if turning:
        assert abs(kw - 1.0) < 2 * sd[1] and sd[1] < 0.5 * sd_w, (kw, sd)
    else:
        assert abs(kw - 1.0) < 0.05 * sd_w and abs(kv - 1.0) < 0.01 * sd_v, (kv, kw)
        np.testing.assert_allclose(sd, [sd_v, sd_w], rtol=0.02)


class _Capture:
    """Stands in for the filter's KalmanCore and records what an update would be given."""

    def __init__(self, x):
        self.x = np.array(x, dtype=float)
        self.got = {}

    def update_blocks(self, t, z, hx, H, R, blocks, fuse=None):
        """Records the innovations y = z - h(x), H, R and the blocks."""
        self.got.update(y=np.array(z - hx), H=np.array(H), R=np.array(R), blocks=blocks)
        return len(blocks)


def _capture_rows(ekf, m, x):
    """The (y = z - h(x), H, R, blocks) the filter builds for measurement ``m`` at state
    ``x``."""
    kf = ekf.kf
    ekf.kf = cap = _Capture(x)
    try:
        ekf._apply((m,))
    finally:
        ekf.kf = kf
    return cap.got


@pytest.mark.parametrize("gyro", [True, False])
@pytest.mark.parametrize("pose_error", ["world", "se2"])
def test_measurement_jacobians_match_central_differences(pose_error, gyro):
    """Every measurement's H against central differences of its h, with the scale states in
    both conventions: with a gyro state 4 is the true yaw rate (the odometry and the wheels
    see w / k_w), without one the odometry's (the gyro-less config has no bias state)."""
    imu = ({"topic": "/imu", "use": ["yaw", "yaw_rate"], "gyro_bias": "estimate",
            "heading_offset": "estimate"} if gyro else
           {"topic": "/imu", "use": ["yaw"], "heading_offset": "estimate"})
    cfg = parse_config({
        "sensors": {
            "odometry": [{"topic": "/odom"}],
            "wheels": [{"topic": "/js", "joints": ["l", "r"], "noise": {"speed": 0.3}}],
            "imu": [imu],
            "gps": [{"topic": "/fix", "lever_arm": [0.4, -0.2], "delay": 0.25}],
        },
        "robot": {"wheel_radius": 0.17, "track_width": 0.55, "wheel_radius_std": 0.003,
                  "track_width_std": 0.02},
        "initial_pose": [0, 0, 0],
    })
    # the reference path's update (the compiled kernels' are checked against it in
    # tests/test_ekf_compiled.py)
    ekf = UnicycleEkf(cfg, reference=True, pose_error=pose_error)
    calib = ("bg", "hoff") if gyro else ("hoff",)
    assert ekf.state_names == ("x", "y", "psi", "v_odo", "w" if gyro else "w_odo", *calib,
                               "k_v", "k_w")
    ekf.process(Heading(0.0, 0.0, 1e-4, sensor="/imu") if not gyro
                else GyroYawRate(0.0, 0.0, 1e-4, sensor="/imu"))
    hi = ekf.state_names.index("hoff")
    ekf._hoff_ready.add(hi)
    # with odometry scales and a GPS delay: the odometry rows depend on k_v, k_w, the fix's
    # on v and w (the antenna 0.25 s back along the arc)
    x0 = [3.0, 4.0, -2.9, 1.1, 0.4, *((0.02,) if gyro else ()), 2.8, 1.03, 0.96]
    cov = np.array([[1.0, 0.2, 0], [0.2, 2.0, 0], [0, 0, 9]])
    ms = [
        WheelOdometry(0.0, 1.0, 0.3, 0.01, 0.02, sensor="/odom"),
        WheelSpeeds(0.0, 5.0, 7.0, 0.1, 0.2, sensor="/js"),
        *([GyroYawRate(0.0, 0.5, 1e-4, sensor="/imu")] if gyro else []),
        Heading(0.0, 3.0, 1e-3, sensor="/imu"),
        GpsFix(0.0, 0, 0, 0, cov, 0, sensor="/fix", enu=(3.5, 4.2, 0.0)),
    ]
    to_state, _ = _error_chart(pose_error, x0)
    for m in ms:
        got = _capture_rows(ekf, m, x0)

        def h(d, m=m):  # h(x) = z - y: the same Jacobian as -y
            return -_capture_rows(ekf, m, to_state(d))["y"]

        H_num = _numeric_jac(h, np.zeros(len(x0)))
        np.testing.assert_allclose(got["H"], H_num, atol=1e-7, err_msg=type(m).__name__)
    # the scales' columns: the odometry's yaw rate and the wheels depend on k_w exactly when
    # state 4 is the true yaw rate; the gyro never depends on it then
    ks = ekf.state_names.index("k_w")
    for m in ms[:2]:
        assert (np.abs(_capture_rows(ekf, m, x0)["H"][:, ks]).max() > 0.1) == gyro
    if gyro:
        assert _capture_rows(ekf, ms[2], x0)["H"][0, ks] == 0.0
    gps = _capture_rows(ekf, ms[-1], x0)
    np.testing.assert_array_equal(gps["R"], cov[:2, :2])
    # heading prediction is psi + hoff, its innovation wrapped: 3.0 - (-0.1) = 3.1, and with
    # hoff 0.1 smaller 3.2 - 2 pi, across the seam
    head = ms[-2]
    hd = _capture_rows(ekf, head, x0)
    assert hd["y"][0] == pytest.approx(3.0 - (-2.9 + 2.8))
    x_seam = list(x0)
    x_seam[hi] -= 0.1
    assert _capture_rows(ekf, head, x_seam)["y"][0] == pytest.approx(3.2 - 2 * math.pi)


@pytest.mark.parametrize("dt", [0.02, 0.5, 2.0])
def test_process_noise_is_exact_integral_of_linearised_model(dt):
    """Q equals the Van Loan discretisation of the linearised continuous model."""
    psi, v = 2.2, 1.4
    nz = ProcessNoise(acc=0.7, yaw_acc=0.4, pos_long=0.1, pos_lat=0.03, heading=0.02)
    A = np.zeros((5, 5))
    A[0, 2], A[0, 3] = -v * math.sin(psi), math.cos(psi)
    A[1, 2], A[1, 3] = v * math.cos(psi), math.sin(psi)
    A[2, 4] = 1.0
    c, s = math.cos(psi), math.sin(psi)
    Rb = np.array([[c, -s], [s, c]])
    Qc = np.zeros((5, 5))
    Qc[:2, :2] = Rb @ np.diag([nz.pos_long**2, nz.pos_lat**2]) @ Rb.T
    Qc[2, 2] = nz.heading**2
    Qc[3, 3] = nz.acc**2
    Qc[4, 4] = nz.yaw_acc**2
    M = np.zeros((10, 10))
    M[:5, :5] = -A
    M[:5, 5:] = Qc
    M[5:, 5:] = A.T
    E = expm(M * dt)
    Phi = E[5:, 5:].T
    Qvl = Phi @ E[:5, 5:]
    # the slip and heading white noise are not propagated through the model within the step in
    # the closed form (they enter as Qc dt): remove that part's propagation from the reference
    Qc_slip = np.zeros((5, 5))
    Qc_slip[:3, :3] = Qc[:3, :3]
    M2 = M.copy()
    M2[:5, 5:] = Qc_slip
    E2 = expm(M2 * dt)
    Qvl_slip = Phi @ E2[:5, 5:]
    Q_ref = Qvl - Qvl_slip + Qc_slip * dt
    q = unicycle_process_noise(psi, v, dt, nz)
    Q = np.zeros((5, 5))
    Q[np.triu_indices(5)] = q
    Q = Q + np.triu(Q, 1).T
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-9, atol=1e-14)
    assert np.linalg.eigvalsh(Q).min() > 0


def test_ekf_motion_equals_smoother_motion_factor():
    """Fed the same state and interval, the EKF's predicted pose is exactly where the smoother's
    motion factor (the wheel+gyro preintegration of the same constant speed and yaw rate, bias
    included) puts the next keyframe: all nine residuals zero."""
    import gtsam

    cfg = make_cfg(initial_pose=(0, 0, 0), gyro_bias="estimate", heading_offset=0.0)
    ekf = UnicycleEkf(cfg)
    ekf.process(GyroYawRate(0.0, 0.0, 1e-4, sensor="/imu"))
    for si in ([1.0, 2.0, 3.0, 1.5, 0.8, 0.01], [0.0, 0.0, -1.0, 0.7, 1e-9, 0.0],
               [5.0, -3.0, 0.2, 2.0, -2.5, 0.0]):
        dt = 0.8
        ekf.kf.x, ekf.t = np.array(si, dtype=float), 0.0
        ekf._predict_to(dt)
        sj = ekf.kf.x.tolist()
        pim = WheelGyroPreintegration(bg_lin=si[5])
        pim.integrate(dt, si[3], si[4] + si[5], 1e-4, 1e-4)
        values = gtsam.Values()
        values.insert(0, np.array(si + [0.0, 1.0, 1.0]))
        values.insert(1, np.array(sj + [0.0, 1.0, 1.0]))
        err = preintegrated_factor(0, 1, pim).unwhitenedError(values)
        np.testing.assert_allclose(err, 0.0, atol=1e-12)


def test_euler_discretisation_error_order():
    """The seed's Euler step misses the chord by ~ v w dt^2 / 2 sideways; the exact step is the
    limit of many small Euler steps."""
    v, w, dt = 1.0, 0.5, 0.4
    xe, ye, _, _ = euler_step_jac(0.0, 0.0, 0.0, v, w, dt)
    xs, ys, _ = se2_step(0.0, 0.0, 0.0, v, w, dt)
    assert abs(ye - ys) == pytest.approx(v * w * dt * dt / 2, rel=0.05)
    x = y = p = 0.0
    for _ in range(20000):
        x, y, p, _ = euler_step_jac(x, y, p, v, w, dt / 20000)
    assert math.hypot(x - xs, y - ys) < 1e-5
    # and the exact Jacobian is the shared one
    assert se2_step_jac(0.0, 0.0, 0.0, v, w, dt)[:3] == pytest.approx((xs, ys, w * dt))


# ---------------------------------------------------------------- synthetic runs


def _nees_runs(seeds, **kw):
    """Average NEES across seeds at fixed sample times, plus the position RMSE."""
    per_run = []
    sq_pos = []
    for seed in seeds:
        run = simulate(seed, **kw.get("sim", {}))
        ekf = UnicycleEkf(make_cfg(**kw.get("cfg", {})), noise=SIM_NOISE,
                          initial_pose=(0.0, 0.0, 0.7), initial_std=(0.01, 0.005))
        ts, xs, Ps, tr = run_filter(ekf, run)
        names = ekf.state_names
        nees = []
        for x, P, t in zip(xs, Ps, tr, strict=True):
            e = state_error(x, t, names)
            nees.append(float(e @ np.linalg.solve(P, e)))
            sq_pos.append(e[0] ** 2 + e[1] ** 2)
        per_run.append((ts, np.array(nees)))
    return per_run, math.sqrt(np.mean(sq_pos)), names


@pytest.mark.slow
def test_gps_odometry_gyro_accuracy_and_consistency():
    """GPS (0.5 m, 5 Hz), wheel speed (0.05 m/s) and gyro (0.02 rad/s) at 50 Hz, 60 s, 6 seeds.
    Position RMSE well below the GPS sigma; average NEES over runs at 20 sample times inside
    the two-sided 99.9 % chi-square band (n = 5 states)."""
    seeds = range(6)
    per_run, rmse, names = _nees_runs(seeds)
    assert names == ("x", "y", "psi", "v", "w")
    # GPS alone would give 0.5 * sqrt(2) = 0.71 m; fusion with odometry does much better
    assert rmse < 0.15, rmse  # measured 0.072 m over 6 seeds
    sample_times = np.linspace(3.0, 59.0, 20)
    dof = len(names)
    lo, hi = chi2.ppf([0.0005, 0.9995], len(seeds) * dof) / len(seeds)
    means = []
    for ts_ in sample_times:
        vals = [nees[np.searchsorted(ts, ts_)] for ts, nees in per_run]
        means.append(np.mean(vals))
    means = np.array(means)
    # allow at most 1 of 20 (correlated) sample times outside the 99.9 % band, and the overall
    # average within 20 % of n
    assert np.sum((means < lo) | (means > hi)) <= 1, (means, lo, hi)
    assert abs(means.mean() / dof - 1.0) < 0.2, means.mean()


def test_rate_mode_matches_event_mode():
    """Stepping at the fastest sensor's 50 Hz with buffered, stacked updates gives the same
    accuracy as per-message updates (here every message falls on the step grid)."""
    run = simulate(11)
    out = {}
    for rate in ("event", 50.0):
        ekf = UnicycleEkf(make_cfg(rate=rate), noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7))
        ts, xs, Ps, tr = run_filter(ekf, run)
        assert len(ts) > 2000
        out[rate] = math.sqrt(np.mean((xs[:, 0] - tr[:, 0]) ** 2 + (xs[:, 1] - tr[:, 1]) ** 2))
    assert out["event"] < 0.35 and out[50.0] < 0.35
    assert out[50.0] == pytest.approx(out["event"], rel=0.1)


def test_rate_mode_steps_on_grid_and_stacks():
    """At 10 Hz with 50 Hz sensors, each step applies ~5 odometry + 5 gyro messages at once."""
    run = simulate(12, duration=20.0)
    ekf = UnicycleEkf(make_cfg(rate=10.0), noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7))
    times = set()
    for m in run.measurements:
        ekf.process(m)
        e = ekf.estimate()
        times.add(round(e.t, 9))
    ekf.finish()
    grid = np.array(sorted(times))
    # all state times on the 10 Hz grid from the first message (last one: the flush)
    k = (grid[:-1] - grid[0]) * 10.0
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    assert 190 <= len(grid) <= 202
    n_inn = len(ekf.log.innovations)
    assert n_inn == sum(1 for m in run.measurements if not isinstance(m, GroundTruthPose))
    final = ekf.estimate()
    assert math.hypot(final.pose[0] - run.truth[-1, 0], final.pose[1] - run.truth[-1, 1]) < 1.0


def test_gyro_bias_estimated():
    """A 0.05 rad/s gyro bias (3 deg/s) with bias estimation on: the bias converges to within
    3 sigma of its own reported uncertainty and the track stays accurate; with a fixed zero bias
    assumed, the gate rejects the gyro persistently or the track degrades."""
    run = simulate(21, bias=0.05, duration=90.0)
    ekf = UnicycleEkf(make_cfg(gyro_bias="estimate"), noise=SIM_NOISE,
                      initial_pose=(0.0, 0.0, 0.7))
    ts, xs, Ps, tr = run_filter(ekf, run)
    assert ekf.state_names[5] == "bg"
    bg, sbg = xs[-1, 5], math.sqrt(Ps[-1, 5, 5])
    assert abs(bg - 0.05) < 3 * sbg and sbg < 0.005
    rmse = math.sqrt(np.mean((xs[:, 0] - tr[:, 0]) ** 2 + (xs[:, 1] - tr[:, 1]) ** 2))
    assert rmse < 0.35
    ekf0 = UnicycleEkf(make_cfg(gyro_bias=0.0), noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7))
    _, xs0, _, tr0 = run_filter(ekf0, run)
    psi_err0 = np.abs([wrap(a - b) for a, b in zip(xs0[:, 2], tr0[:, 2], strict=True)])
    psi_err = np.abs([wrap(a - b) for a, b in zip(xs[:, 2], tr[:, 2], strict=True)])
    assert np.sqrt(np.mean(psi_err0**2)) > 2 * np.sqrt(np.mean(psi_err**2))


def test_heading_offset_estimated_and_tracks_random_walk():
    """An absolute heading whose offset starts at -2.5 rad and random-walks (0.01 rad/sqrt s):
    with heading_offset: estimate the filter initialises it from the first heading and tracks it
    within 3 sigma at the end; heading error stays small."""
    run = simulate(31, heading_rate=10.0, offset=-2.5, duration=90.0)
    ekf = UnicycleEkf(make_cfg(imu_use=("yaw", "yaw_rate"), heading_offset="estimate"),
                      noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7))
    ts, xs, Ps, tr = run_filter(ekf, run)
    assert ekf.state_names == ("x", "y", "psi", "v", "w", "hoff")
    err = wrap(xs[-1, 5] - tr[-1, 6])
    assert abs(err) < 3 * math.sqrt(Ps[-1, 5, 5]) + 1e-3
    assert any("heading offset" in s for s in ekf.log.messages)
    psi_err = np.array([wrap(a - b) for a, b in zip(xs[:, 2], tr[:, 2], strict=True)])
    assert np.sqrt(np.mean(psi_err**2)) < 0.05
    # no systematic gate rejections of the heading
    assert ekf.log.rejected[("/imu", "gate")] < 5


def test_heading_initialised_from_gps_track():
    """No initial pose, no absolute heading: the true start heading is 2.0 rad; the filter
    dead-reckons, aligns onto the GPS track after 5 m, and then tracks; estimate() is None
    before. The aligned heading is within 3 of its reported sigmas and < 5 deg."""
    run = simulate(41, psi0=2.0, duration=60.0)
    ekf = UnicycleEkf(make_cfg(), noise=SIM_NOISE)
    first = None
    for m in run.measurements:
        ekf.process(m)
        est = ekf.estimate()
        if est is not None and first is None:
            first = est
            i = int(round(est.t / 0.002)) - 1
            err = wrap(est.pose[2] - run.truth[i, 2])
            assert abs(err) < max(3 * math.sqrt(est.pose_cov[2, 2]), 1e-3)
            assert abs(err) < math.radians(5)
            d = math.hypot(est.pose[0] - run.truth[i, 0], est.pose[1] - run.truth[i, 1])
            assert d < 3 * math.sqrt(est.pose_cov[0, 0] + est.pose_cov[1, 1])
        elif first is None:
            assert est is None
    assert first is not None and 3.0 < first.t < 10.0
    assert any("heading initialised from GPS" in s for s in ekf.log.messages)
    final = ekf.estimate()
    assert math.hypot(final.pose[0] - run.truth[-1, 0], final.pose[1] - run.truth[-1, 1]) < 1.0


def test_wheel_speeds_model():
    """Left/right wheel speeds through the wheel radius and track width replace odometry."""
    run = simulate(51, wheels=(0.1, 0.5, 0.2), gyro_rate=None)
    ekf = UnicycleEkf(make_cfg(wheels=True, imu_use=()), noise=SIM_NOISE,
                      initial_pose=(0.0, 0.0, 0.7))
    ts, xs, Ps, tr = run_filter(ekf, run)
    rmse = math.sqrt(np.mean((xs[:, 0] - tr[:, 0]) ** 2 + (xs[:, 1] - tr[:, 1]) ** 2))
    assert rmse < 0.4
    # yaw rate comes only from the wheel speed difference: it must be estimated well
    assert np.sqrt(np.mean((xs[100:, 4] - tr[100:, 4]) ** 2)) < 0.05


def test_dead_reckoning_without_gps_starts_at_origin():
    """Odometry speed + yaw rate only: heading starts at 0 (local frame = start pose); the
    dead-reckoned track matches the truth expressed in the start frame within the odometry
    noise integrated over 30 s."""
    run = simulate(61, psi0=0.0, gps_rate=None, gyro_rate=None, odom_w_sigma=0.02,
                   duration=30.0)
    ekf = UnicycleEkf(make_cfg(gps=False, odom_use=("v", "yaw_rate"), imu_use=()),
                      noise=SIM_NOISE)
    ts, xs, Ps, tr = run_filter(ekf, run)
    assert xs[0, 2] == pytest.approx(0.0, abs=0.01)
    d = math.hypot(xs[-1, 0] - tr[-1, 0], xs[-1, 1] - tr[-1, 1])
    sigma = math.sqrt(Ps[-1, 0, 0] + Ps[-1, 1, 1])
    assert d < 3 * sigma and d < 3.0


def test_gate_lockout_recovery_on_kidnapped_robot():
    """The robot stands still for 30 s (covariance collapses around the GPS mean), then is
    carried 15 m away (GPS jumps, odometry sees nothing). The GPS gate rejects the fixes until
    the lock-out is detected; the filter then inflates P, re-converges, and ends on the truth.
    Without the recovery it would stay 15 m off (checked)."""
    kw = dict(kidnap=(40.0, 15.0, -5.0), stand_still=30.0, duration=70.0, gps_sigma=0.3)
    run = simulate(71, **kw)
    finals = {}
    for count in (5, 10**9):
        ekf = UnicycleEkf(make_cfg(), noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7),
                          lockout_count=count, lockout_time=1.0)
        ts, xs, Ps, tr = run_filter(ekf, run)
        finals[count] = (math.hypot(xs[-1, 0] - tr[-1, 0], xs[-1, 1] - tr[-1, 1]), ekf)
    d, ekf = finals[5]
    assert d < 1.0, d
    assert ekf.kf.recoveries and 40.0 < ekf.kf.recoveries[0][0] < 43.0
    assert any("lock-out" in s for s in ekf.log.messages)
    assert ekf.log.rejected[("/fix", "gate")] >= 4
    d_no, ekf_no = finals[10**9]
    assert d_no > 10.0
    assert ekf_no.log.rejected[("/fix", "gate")] > 100


def test_initial_pose_from_ground_truth_and_config():
    run = simulate(81, duration=10.0)
    cfg = parse_config({
        "sensors": {"odometry": [{"topic": "/odom", "use": ["v"]}],
                    "imu": [{"topic": "/imu", "use": ["yaw_rate"]}],
                    "gps": [{"topic": "/fix"}]},
        "ground_truth": {"topic": "/gt"},
        "initial_pose": "ground_truth",
    })
    ekf = UnicycleEkf(cfg, noise=SIM_NOISE)
    ekf.process(run.measurements[0])
    assert ekf.estimate() is None
    assert ekf.log.rejected[(run.measurements[0].sensor, "before_init")] == 1
    ekf.process(GroundTruthPose(0.02, 1.0, 2.0, 0.7, sensor="/gt"))
    est = ekf.estimate()
    assert est.pose == pytest.approx((1.0, 2.0, 0.7))
    ekf2 = UnicycleEkf(make_cfg(initial_pose=(5.0, 6.0, -1.0)))
    ekf2.process(run.measurements[0])
    assert ekf2.estimate().pose[:2] == pytest.approx((5.0, 6.0), abs=0.1)
    # the constructor argument wins over the config
    ekf3 = UnicycleEkf(make_cfg(initial_pose=(5.0, 6.0, -1.0)), initial_pose=(0.0, 0.0, 0.0))
    ekf3.process(run.measurements[0])
    assert ekf3.estimate().pose[:2] == pytest.approx((0.0, 0.0), abs=0.1)


def test_estimate_is_well_formed():
    run = simulate(91, duration=5.0, heading_rate=10.0)
    ekf = UnicycleEkf(make_cfg(imu_use=("yaw", "yaw_rate"), gyro_bias="estimate",
                               heading_offset="estimate"), initial_pose=(0, 0, 0.7))
    for m in run.measurements:
        ekf.process(m)
        est = ekf.estimate()
        assert -math.pi <= est.pose[2] < math.pi
        assert np.array_equal(est.state_cov, est.state_cov.T)
        assert np.linalg.eigvalsh(est.state_cov).min() > 0
        assert est.pose_cov.shape == (3, 3)
        assert -math.pi <= est.state[6] < math.pi
    assert est.state.shape == (7,) and len(est.state_names) == 7


def test_twist_densities_follow_stated_acceleration_limits_and_sample_periods():
    """Bar-Shalom's CWNA rule: density a_max sqrt(T), T the shortest sample period of the
    sensors measuring that twist component, as observed; without limits, the defaults."""
    base = ProcessNoise()
    nz = twist_densities(0.5, 0.4, 0.1, 0.02, base)
    assert nz.acc == pytest.approx(0.5 * math.sqrt(0.1))
    assert nz.yaw_acc == pytest.approx(0.4 * math.sqrt(0.02))
    assert twist_densities(None, 0.4, 0.1, None, base) == base
    # over one period the random walk's sigma is a_max T: the largest change of the twist
    assert nz.acc * math.sqrt(0.1) == pytest.approx(0.5 * 0.1)

    raw = {"sensors": {"odometry": [{"topic": "/odom", "use": ["v", "yaw_rate"]}],
                       "imu": [{"topic": "/imu", "use": ["yaw_rate"], "gyro_bias": 0.0}]},
           "robot": {"max_accel": 0.5, "max_yaw_accel": 0.4}, "initial_pose": [0, 0, 0]}
    ekf = UnicycleEkf(parse_config(raw))
    assert ekf.noise == base  # nothing observed yet
    for k in range(60):  # odometry at 10 Hz, gyro at 50 Hz
        t = 0.02 * k
        if k % 5 == 0:
            ekf.process(WheelOdometry(t, 1.0, 0.1, 1e-4, 1e-4, sensor="/odom"))
        ekf.process(GyroYawRate(t + 0.001, 0.1, 1e-4, sensor="/imu"))
    assert ekf.noise.acc == pytest.approx(0.5 * math.sqrt(0.1), rel=1e-6)
    assert ekf.noise.yaw_acc == pytest.approx(0.4 * math.sqrt(0.02), rel=1e-6)
    # an explicit ProcessNoise is kept as given
    fixed = ProcessNoise(acc=0.7, yaw_acc=0.6)
    ekf = UnicycleEkf(parse_config(raw), noise=fixed)
    for k in range(10):
        ekf.process(WheelOdometry(0.1 * k, 1.0, 0.1, 1e-4, 1e-4, sensor="/odom"))
    assert ekf.noise == fixed


def test_dead_reckoning_banana_is_gaussian_in_the_filters_error_coordinates():
    """Long, Wolfe, Mashner, Chirikjian 2012 ("The banana distribution is Gaussian"): dead
    reckoning from a start whose heading is uncertain by 0.5 rad, along 6 rad of turning. The
    true poses X_true = X_hat Exp(xi0) Exp(tau t) form a curved banana; in the filter's
    coordinates xi = Log(X_hat^-1 X_true) = Ad(Exp(-tau t)) xi0 they are exactly Gaussian, so
    for 2000 draws of the start from the filter's prior the mean NEES it scores is chi2(3) / 1
    (inside the 99.9 % band of the mean of 2000), while the same covariance read as a
    world-frame Gaussian (the world-error filter's, the same to first order) is far off."""
    from ddfuse.estimation.runner import Trajectory
    from ddfuse.evaluation import metrics

    s0, s2 = 0.01, 0.5
    quiet = ProcessNoise(acc=1e-4, yaw_acc=1e-4, pos_long=0.0, pos_lat=0.0, heading=0.0)
    v, w, rate, T = 1.0, 0.3, 50.0, 20.0
    start = (1.0, 2.0, 0.4)
    finals = {}
    for pe in ("se2", "world"):
        ekf = UnicycleEkf(make_cfg(gps=False, odom_use=("v", "yaw_rate"), imu_use=()),
                          noise=quiet, initial_pose=start, initial_std=(s0, s2),
                          pose_error=pe, reference=True)
        for k in range(int(T * rate) + 1):
            ekf.process(WheelOdometry(k / rate, v, w, 1e-10, 1e-10, sensor="/odom"))
        finals[pe] = ekf.estimate()
    est = finals["se2"]
    assert est.pose_error == "se2" and finals["world"].pose_error == "world"
    np.testing.assert_allclose(est.pose, finals["world"].pose, atol=1e-6)
    # the covariances agree to first order (the same linearisation, two charts)
    np.testing.assert_allclose(est.pose_cov, finals["world"].pose_cov, rtol=1e-3, atol=1e-9)
    rng = np.random.default_rng(7)
    n = 2000
    truth = np.zeros((n, 3))
    for i in range(n):
        xi0 = rng.normal(0.0, 1.0, 3) * (s0, s0, s2)
        x0 = se2_retract(*start, *xi0)
        x1, y1, p1 = se2_step(*x0, v, w, T)  # the constant twist, exactly
        truth[i] = (x1, y1, wrap(p1))
    tt = np.arange(n, dtype=float)
    tr_est = Trajectory(tt, np.tile(est.pose, (n, 1)), np.tile(est.pose_cov, (n, 1, 1)))
    ref = Trajectory(tt, truth, np.full((n, 3, 3), np.nan))
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * n) / n
    nees_se2 = metrics.nees(tr_est, ref, 1e-9, pose_error="se2").mean()
    nees_world = metrics.nees(tr_est, ref, 1e-9, pose_error="world").mean()
    assert lo <= nees_se2 <= hi, (nees_se2, lo, hi)
    assert nees_world > 3.0 * hi, nees_world
