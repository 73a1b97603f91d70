"""Seed 002's landmark EKFs: models, known-map localisation and SLAM on synthetic data.

The simulation draws everything from the filter's own noise model (white odometry errors held
for one sample, Gaussian range/bearing noise, an initial pose drawn from the initial covariance),
so the filter must be consistent: its NEES must sit in the chi-square band.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from ddfuse.ekf_baseline.landmark import (
    LandmarkEkf,
    LandmarkSlamEkf,
    landmark_from_range_bearing,
    motion_step,
    range_bearing,
)
from ddfuse.estimation.config import LANDMARK_NOT_IN_MAP, Config, SensorConfig
from ddfuse.estimation.measurements import LandmarkObservation, WheelOdometry, WheelSpeeds
from ddfuse.factors.kinematics import se2_step
from scipy.stats import chi2

SIG_V, SIG_W = 0.15, 0.15  # odometry noise per 50 Hz sample, m/s and rad/s
SIG_R, SIG_B = 0.1, 0.05  # sighting noise, m and rad
DT_ODO = 0.02
LANDMARKS = {
    "a": (4.0, 3.0), "b": (-3.0, 5.0), "c": (-6.0, -2.0), "d": (2.0, -6.0), "e": (7.0, -1.0),
    "f": (0.5, 8.0), "g": (-8.0, 4.0), "h": (5.0, 6.5),
}
INIT_STD = (0.1, 0.1, 0.05)


def make_cfg(gate: float | None = 0.9999) -> Config:
    return Config(sensors=[
        SensorConfig(kind="odometry", topic="/odom", name="odom", use=("v", "yaw_rate"),
                     gate=gate),
        SensorConfig(kind="landmarks", topic="/landmarks", name="landmarks",
                     use=("range", "bearing"), gate=gate),
    ])


def simulate(seed: int, duration: float = 120.0, sight_period: float = 0.25,
             max_range: float = 7.0, range_only_every: int = 0):
    """True poses at the odometry stamps, the noisy measurement stream, and the start pose.

    Odometry as wheel odometry reports it: the sample stamped t is the twist over (t - DT, t];
    a first sample at 0 starts the clock."""
    rng = np.random.default_rng(seed)
    n = int(round(duration / DT_ODO))
    pose = (0.0, 0.0, 0.3)
    truth = [(0.0, *pose)]
    meas = [WheelOdometry(0.0, 0.0, 0.0, SIG_V**2, SIG_W**2, "odom")]
    k_sight = max(1, int(round(sight_period / DT_ODO)))
    count = 0
    for k in range(n):
        t = k * DT_ODO
        # steer after a point running along a figure eight through the landmark field
        tx, ty = 6.0 * math.sin(0.06 * t), 4.0 * math.sin(0.12 * t)
        v = 0.5 + 0.1 * math.sin(0.3 * t)
        err = (math.atan2(ty - pose[1], tx - pose[0]) - pose[2] + math.pi) % (2 * math.pi)
        w = max(-0.8, min(0.8, 1.5 * (err - math.pi)))
        if k % k_sight == 0 and k > 0:
            for lid, (lx, ly) in LANDMARKS.items():
                dx, dy = lx - pose[0], ly - pose[1]
                r = math.hypot(dx, dy)
                if r > max_range:
                    continue
                b = math.atan2(dy, dx) - pose[2]
                count += 1
                ro = range_only_every and count % range_only_every == 0
                zb = (b + rng.normal(0, SIG_B) + math.pi) % (2 * math.pi) - math.pi
                meas.append(LandmarkObservation(t, lid, r + rng.normal(0, SIG_R),
                                                math.nan if ro else zb, SIG_R**2,
                                                math.nan if ro else SIG_B**2,
                                                has_bearing=not ro, sensor="landmarks"))
        meas.append(WheelOdometry(t + DT_ODO, v + rng.normal(0, SIG_V), w + rng.normal(0, SIG_W),
                                  SIG_V**2, SIG_W**2, "odom"))
        pose = se2_step(*pose, v, w, DT_ODO)
        truth.append((t + DT_ODO, *pose))
    start = np.array(truth[0][1:]) + rng.normal(0, INIT_STD)
    return np.array(truth), meas, tuple(start)


def errors_over_time(make_filter, truth, meas):
    """Run the filter; after all messages of each stamp, its pose error and covariance."""
    ekf = make_filter()
    res = []
    i = 0
    while i < len(meas):
        t = meas[i].t
        while i < len(meas) and meas[i].t == t:
            ekf.process(meas[i])
            i += 1
        k = int(round(t / DT_ODO))
        est = ekf.estimate()
        e = np.array(est.pose) - truth[k, 1:]
        e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
        res.append((t, e, est.pose_cov))
    return ekf, res


def dead_reckoning(truth, meas, start):
    pose = start
    errs = []
    for m in meas:
        if isinstance(m, WheelOdometry):
            k = int(round(m.t / DT_ODO))
            if k > 0:  # the sample stamped t moves the robot over (t - DT, t]
                pose = se2_step(*pose, m.v, m.yaw_rate, DT_ODO)
            errs.append(np.hypot(*(np.array(pose[:2]) - truth[k, 1:3])))
    return float(np.sqrt(np.mean(np.square(errs))))


def test_models_jacobians_match_central_differences():
    rng = random.Random(4)
    h = 1e-6
    for _ in range(50):
        pose = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5),
                         rng.choice([rng.uniform(-math.pi, math.pi), math.pi - 1e-9,
                                     -math.pi + 1e-9])])
        lm = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10)])

        def h_of(p, l, h0):
            z = range_bearing(p, l)[0]
            z[1] = h0[1] + ((z[1] - h0[1] + math.pi) % (2 * math.pi) - math.pi)  # unwrap
            return z

        h0, Hp, Hl = range_bearing(pose, lm)
        assert -math.pi <= h0[1] < math.pi
        num_p = np.array([(h_of(pose + h * e, lm, h0) - h_of(pose - h * e, lm, h0)) / (2 * h)
                          for e in np.eye(3)]).T
        num_l = np.array([(h_of(pose, lm + h * e, h0) - h_of(pose, lm - h * e, h0)) / (2 * h)
                          for e in np.eye(2)]).T
        np.testing.assert_allclose(Hp, num_p, atol=1e-6, rtol=0)
        np.testing.assert_allclose(Hl, num_l, atol=1e-6, rtol=0)
        # range-only rows are the range rows
        hr, Hpr, Hlr = range_bearing(pose, lm, with_bearing=False)
        assert hr.shape == (1,) and np.allclose(Hpr, Hp[:1]) and np.allclose(Hlr, Hl[:1])
        # the inverse model and its Jacobians
        r, b = rng.uniform(0.5, 8), rng.uniform(-math.pi, math.pi)
        l, Gp, Gz = landmark_from_range_bearing(pose, r, b)
        back = range_bearing(pose, l)[0]
        assert back[0] == pytest.approx(r, abs=1e-12)
        assert abs((back[1] - b + math.pi) % (2 * math.pi) - math.pi) < 1e-12
        num_gp = np.array([(landmark_from_range_bearing(pose + h * e, r, b)[0]
                            - landmark_from_range_bearing(pose - h * e, r, b)[0]) / (2 * h)
                           for e in np.eye(3)]).T
        num_gz = np.array([(landmark_from_range_bearing(pose, r + h * e[0], b + h * e[1])[0]
                            - landmark_from_range_bearing(pose, r - h * e[0], b - h * e[1])[0])
                           / (2 * h) for e in np.eye(2)]).T
        np.testing.assert_allclose(Gp, num_gp, atol=1e-6, rtol=0)
        np.testing.assert_allclose(Gz, num_gz, atol=1e-6, rtol=0)
        # motion models: F and G
        for kind in ("exact", "euler"):
            v, w, dt = rng.uniform(-1, 1), rng.choice([0.0, 1e-9, rng.uniform(-1, 1)]), 0.1
            p1, F, G = motion_step(pose, v, w, dt, kind)

            def mv(p, u, p1=p1, kind=kind, dt=dt):
                q = motion_step(p, u[0], u[1], dt, kind)[0]
                q[2] = p1[2] + ((q[2] - p1[2] + math.pi) % (2 * math.pi) - math.pi)
                return q

            u = np.array([v, w])
            num_f = np.array([(mv(pose + h * e, u) - mv(pose - h * e, u)) / (2 * h)
                              for e in np.eye(3)]).T
            num_g = np.array([(mv(pose, u + h * e) - mv(pose, u - h * e)) / (2 * h)
                              for e in np.eye(2)]).T
            np.testing.assert_allclose(F, num_f, atol=1e-6, rtol=0)
            np.testing.assert_allclose(G, num_g, atol=1e-6, rtol=0)


def test_known_map_ekf_accuracy_and_consistency():
    """Position RMSE below the range noise and >= 3x better than dead reckoning; the average
    NEES over several runs inside the 99 % chi-square band."""
    seeds = range(6)
    nees_runs = []
    for seed in seeds:
        truth, meas, start = simulate(seed)
        ekf, res = errors_over_time(
            lambda start=start: LandmarkEkf(make_cfg(), initial_pose=start, landmarks=LANDMARKS,
                                            init_std=INIT_STD), truth, meas)
        e = np.array([r[1] for r in res])
        rmse = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
        dr = dead_reckoning(truth, meas, start)
        assert rmse < SIG_R, (seed, rmse)
        assert dr > 3 * rmse, (seed, rmse, dr)
        # NEES of the pose every 0.5 s (the filter's errors are correlated over shorter times)
        nees = [float(r[1] @ np.linalg.solve(r[2], r[1])) for r in res[::25]]
        nees_runs.append(nees)
        gated = sum(not i.accepted for i in ekf.innovations)
        assert gated <= 0.002 * len(ekf.innovations) + 1
        assert not ekf.kf.recoveries
    nees = np.array([n[: min(map(len, nees_runs))] for n in nees_runs])
    k = nees.size
    mean = float(nees.mean())
    lo, hi = chi2.ppf(0.005, 3 * k) / k, chi2.ppf(0.995, 3 * k) / k
    # the samples are not independent (autocorrelated over a few seconds); allow a margin of
    # the band's width on each side rather than pretending they are
    width = hi - lo
    assert lo - width < mean < hi + width, (mean, lo, hi)


def test_known_map_ekf_range_only_and_wheel_speeds():
    """Range-only sightings (every third) still localise; WheelSpeeds drive the pose too."""
    truth, meas, start = simulate(11, duration=60.0, range_only_every=3)
    assert any(not m.has_bearing for m in meas if isinstance(m, LandmarkObservation))
    r, L = 0.1, 0.5
    cfg = make_cfg()
    cfg.robot.wheel_radius, cfg.robot.track_width = r, L
    wheel_meas = []
    for m in meas:
        if isinstance(m, WheelOdometry):
            wl = (m.v - 0.5 * L * m.yaw_rate) / r
            wr = (m.v + 0.5 * L * m.yaw_rate) / r
            # same noise as the odometry it was made from: var_v = r^2 (var_l + var_r) / 4 ...
            var = 2 * SIG_V**2 / r**2
            wheel_meas.append(WheelSpeeds(m.t, wl, wr, var, var, "wheels"))
        else:
            wheel_meas.append(m)
    for stream in (meas, wheel_meas):
        ekf, res = errors_over_time(
            lambda: LandmarkEkf(cfg, initial_pose=start, landmarks=LANDMARKS,
                                init_std=INIT_STD), truth, stream)
        e = np.array([x[1] for x in res])
        rmse = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
        assert rmse < SIG_R, rmse
        kinds = {len(i.residual) for i in ekf.innovations}
        assert kinds == {1, 2}


def test_unknown_landmark_is_rejected_and_counted():
    ekf = LandmarkEkf(make_cfg(), initial_pose=(0.0, 0.0, 0.0), landmarks=LANDMARKS)
    ekf.process(WheelOdometry(0.0, 0.0, 0.0, 0.01, 0.01, "odom"))
    ekf.process(LandmarkObservation(0.1, "zz", 2.0, 0.1, 0.01, 0.0025, True, "landmarks"))
    ekf.finish()  # the sighting waits for the odometry sample covering it; the stream ends
    assert ekf.rejected[("landmarks", LANDMARK_NOT_IN_MAP)] == 1
    assert LANDMARK_NOT_IN_MAP == "landmark id not in the map"  # the bag reader's reason too
    assert not ekf.innovations


def test_gate_lockout_recovers_after_a_kidnap():
    """A filter told a wrong start pose (2 m off) is locked out by its own gate; the core's
    recovery must bring it back onto the landmarks instead of dead reckoning forever."""
    truth, meas, start = simulate(3, duration=60.0)
    wrong = (start[0] + 1.5, start[1] - 1.5, start[2])
    ekf, res = errors_over_time(
        lambda: LandmarkEkf(make_cfg(), initial_pose=wrong, landmarks=LANDMARKS,
                            init_std=(0.02, 0.02, 0.01)), truth, meas)
    assert ekf.kf.recoveries, "expected a gate lock-out and its recovery"
    late = np.array([r[1] for r in res if r[0] > 30.0])
    assert float(np.sqrt(np.mean(late[:, 0] ** 2 + late[:, 1] ** 2))) < SIG_R


def test_slam_initialisation_covariance_matches_monte_carlo():
    """The new landmark's covariance and its cross-covariance with the pose equal the sample
    covariance of g(pose, r, b) over pose and measurement noise (to sampling error)."""
    cfg = make_cfg(gate=None)
    P0 = np.array([[0.04, 0.01, 0.005], [0.01, 0.09, -0.01], [0.005, -0.01, 0.02]])
    ekf = LandmarkSlamEkf(cfg, initial_pose=(1.0, 2.0, 0.4))
    ekf.kf.P = P0.copy()
    r, b, rv, bv = 4.0, 0.7, 0.04, 0.01
    ekf.process(LandmarkObservation(0.0, "x", r, b, rv, bv, True, "landmarks"))
    assert ekf.kf.n == 5 and "x" in ekf.slots
    rng = np.random.default_rng(0)
    n = 400_000
    poses = rng.multivariate_normal([1.0, 2.0, 0.4], P0, n)
    rr = r + rng.normal(0, math.sqrt(rv), n)
    bb = b + rng.normal(0, math.sqrt(bv), n)
    a = poses[:, 2] + bb
    lx, ly = poses[:, 0] + rr * np.cos(a), poses[:, 1] + rr * np.sin(a)
    joint = np.cov(np.vstack([poses.T, lx, ly]))
    P = ekf.kf.P
    # linearisation error of this (fairly nonlinear) map is second order in the std devs (~5 %)
    np.testing.assert_allclose(P[3:, 3:], joint[3:, 3:], rtol=0.06, atol=2e-3)
    np.testing.assert_allclose(P[3:, :3], joint[3:, :3], rtol=0.06, atol=2e-3)
    assert np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > 0


def test_slam_maps_landmarks_and_tracks():
    """Unknown landmarks: each is mapped on its first bearing sighting; the pose stays within
    twice the range noise and >= 3x better than dead reckoning; NEES stays near its dof.

    The start pose is known well (1 cm, 5 mrad) because SLAM cannot observe the map's global
    position and rotation: with the 5 cm / 0.05 rad start of the other tests, that anchor error
    times the ~5 m to the landmarks would dominate. EKF-SLAM is known to become overconfident
    (the heading is linearised at changing estimates; Bailey et al. 2006, Huang et al. 2008), so
    the NEES bound is twice the dof, not the chi-square band."""
    init = (0.01, 0.01, 0.005)
    nees_all = []
    for seed in range(4):
        truth, meas, start = simulate(seed, duration=120.0, range_only_every=5)
        start = tuple(truth[0][1:] + np.random.default_rng(100 + seed).normal(0, init))
        ekf, res = errors_over_time(
            lambda start=start: LandmarkSlamEkf(make_cfg(), initial_pose=start, init_std=init),
            truth, meas)
        e = np.array([r[1] for r in res])
        rmse = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
        dr = dead_reckoning(truth, meas, start)
        assert rmse < 2 * SIG_R and dr > 3 * rmse, (seed, rmse, dr)
        nees_all += [float(r[1] @ np.linalg.solve(r[2], r[1])) for r in res[::25]]
        mapped = ekf.landmark_positions()
        seen = {m.landmark_id for m in meas
                if isinstance(m, LandmarkObservation) and m.has_bearing}
        assert set(mapped) == seen
        for lid, (x, y) in mapped.items():
            assert math.hypot(x - LANDMARKS[lid][0], y - LANDMARKS[lid][1]) < 0.5, lid
        est = ekf.estimate()
        assert len(est.state) == 3 + 2 * len(mapped) == len(est.state_names)
        assert np.linalg.eigvalsh(ekf.kf.P).min() > 0
    assert np.mean(nees_all) < 2 * 3, np.mean(nees_all)


def test_sightings_wait_for_the_odometry_sample_covering_them():
    """A sample stamped t is the twist over (previous sample, t]: a sighting inside that
    interval is applied once that sample arrives, at its own time, with that sample's twist."""
    lm = {"a": (5.0, 0.0)}
    ekf = LandmarkEkf(make_cfg(gate=None), initial_pose=(0.0, 0.0, 0.0), landmarks=lm,
                      init_std=(1e-6, 1e-6, 1e-6))
    ekf.process(WheelOdometry(0.0, 0.0, 0.0, 1e-6, 1e-6, "odom"))
    ekf.process(LandmarkObservation(0.5, "a", 4.5, 0.0, 0.01, 0.0025, True, "landmarks"))
    assert not ekf.innovations and ekf.t == 0.0  # waiting for the sample covering 0.5 s
    ekf.process(WheelOdometry(1.0, 1.0, 0.0, 1e-6, 1e-6, "odom"))  # 1 m/s over (0, 1]
    inn = ekf.innovations[0]
    # at 0.5 s the robot was at x = 0.5 (the new sample's twist): predicted range 4.5
    assert inn.t == 0.5 and inn.residual[0] == pytest.approx(0.0, abs=1e-9)
    assert ekf.t == 1.0 and ekf.estimate().pose[0] == pytest.approx(1.0, abs=1e-6)
    # after the last sample, finish() applies what is left with its twist held
    ekf.process(LandmarkObservation(1.5, "a", 3.5, 0.0, 0.01, 0.0025, True, "landmarks"))
    ekf.finish()
    assert ekf.innovations[-1].t == 1.5
    assert ekf.innovations[-1].residual[0] == pytest.approx(0.0, abs=1e-6)


def test_odometry_scale_states_learn_a_miscalibrated_robot():
    """Odometry 4 % slow in speed and 5 % fast in yaw rate (as if radius and track were off):
    with the geometry's uncertainty in the config the filter carries k_v, k_w (true twist =
    k * odometry), finds them within 3 sigma, and tracks better than without them."""
    truth, meas, start = simulate(21)
    kv_true, kw_true = 1.04, 0.95
    bad = [WheelOdometry(m.t, m.v / kv_true, m.yaw_rate / kw_true, m.v_var, m.yaw_rate_var,
                         m.sensor) if isinstance(m, WheelOdometry) else m for m in meas]
    rmse = {}
    for with_scale in (False, True):
        cfg = make_cfg()
        cfg.robot.wheel_radius, cfg.robot.track_width = 0.1, 0.5
        if with_scale:
            cfg.robot.wheel_radius_std, cfg.robot.track_width_std = 0.005, 0.025
        ekf, res = errors_over_time(
            lambda cfg=cfg: LandmarkEkf(cfg, initial_pose=start, landmarks=LANDMARKS,
                                        init_std=INIT_STD), truth, bad)
        e = np.array([r[1] for r in res])
        rmse[with_scale] = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
    est = ekf.estimate()
    assert est.state_names[:5] == ("x", "y", "yaw", "k_v", "k_w")
    sd = np.sqrt(np.diag(est.state_cov))
    assert abs(est.state[3] - kv_true) < 3 * sd[3] and sd[3] < 0.01
    assert abs(est.state[4] - kw_true) < 3 * sd[4] and sd[4] < 0.01
    assert rmse[True] < 0.8 * rmse[False], rmse


def test_slam_first_estimates_jacobians_keep_heading_unobservable():
    """FEJ: the global heading is unobservable in SLAM (only the initial pose anchors it), so
    the robot's heading variance can never honestly drop below its initial value. With the
    Jacobians at the first estimates it does not; with them at the current estimates (the
    standard EKF, emulated here by switching the FEJ hooks off) the sightings fake
    information about it -- the known cause of EKF-SLAM's overconfidence."""
    from ddfuse.ekf_baseline.landmark import _OdometryDrivenEkf

    class StandardSlam(LandmarkSlamEkf):
        def _first_estimates_motion(self, Fp):
            pass

        def _measure(self, m, landmark, lcols, jac_at=None, fuse=1.0, ref=None):
            _OdometryDrivenEkf._measure(self, m, landmark, lcols, fuse=fuse, ref=ref)

    truth, meas, start = simulate(31, duration=60.0)
    var0 = INIT_STD[2] ** 2
    min_var = {}
    for cls in (LandmarkSlamEkf, StandardSlam):
        ekf = cls(make_cfg(), initial_pose=start, init_std=INIT_STD)
        v = []
        for m in meas:
            ekf.process(m)
            v.append(ekf.kf.P[2, 2])
        min_var[cls.__name__] = min(v) / var0
    assert min_var["LandmarkSlamEkf"] > 0.9, min_var
    assert min_var["StandardSlam"] < 0.8, min_var


def test_prediction_jacobian_with_scale_states_matches_central_differences():
    """d(pose after a step)/d(x, y, psi, k_v, k_w) as predict_to hands it to the core, for the
    known-map filter (the SLAM filter's first-estimates Jacobian differs on purpose)."""
    cfg = make_cfg()
    cfg.robot.wheel_radius, cfg.robot.track_width = 0.1, 0.5
    cfg.robot.wheel_radius_std, cfg.robot.track_width_std = 0.005, 0.025
    # the Python path (its core is stubbed); the compiled one agrees with it to 1e-9
    # (tests/test_landmark_compiled.py)
    ekf = LandmarkEkf(cfg, initial_pose=(1.0, -2.0, 2.9), landmarks=LANDMARKS, compiled=False)
    ekf.v, ekf.w, ekf.v_var, ekf.w_var = 0.8, -0.6, 0.01, 0.01
    x0 = np.array([1.0, -2.0, 2.9, 1.03, 0.95])
    got = {}

    class Stub:  # stands in for the KalmanCore: records what the prediction hands it
        n = 5

        def predict(self, F, Q, x_pred):
            got["F"], got["x"] = F.copy(), np.array(x_pred)

    ekf.kf = Stub()

    def step(x):
        ekf.kf.x, ekf.t = x.copy(), 0.0
        ekf.predict_to(0.3)
        out = got["x"].copy()
        out[2] = x[2] + ((out[2] - x[2] + math.pi) % (2 * math.pi) - math.pi)
        return out

    step(x0)
    F = got["F"]
    h = 1e-6
    num = np.array([(step(x0 + h * e) - step(x0 - h * e)) / (2 * h) for e in np.eye(5)]).T
    np.testing.assert_allclose(F, num, atol=1e-6)
    assert abs(F[0, 3]) > 0.1 and abs(F[2, 4]) > 0.1  # the scale columns are really there


def test_split_prediction_adds_the_same_noise_errata_002_2():
    """Errata 002 #2: the odometry noise is held for its sample period tau = 0.1 s, so its
    covariance per step of dt is G diag(var_v, var_w) G^T tau / dt. Splitting the period at
    0.13 s (as a sighting does) must leave the added covariance unchanged: the exact motion
    steps compose exactly, so the only difference is the second-order transport of the first
    part's noise (at most 0.04 % of the largest entry measured; tolerance 0.1 % of it). The
    seed's per-step G Q G^T, proportional to dt^2, would lose 1 - (0.3^2 + 0.7^2) = 42 % of
    it."""

    def predicted(splits):
        ekf = LandmarkEkf(make_cfg(), initial_pose=(1.0, 2.0, 0.4), landmarks=LANDMARKS,
                          init_std=(0.0, 0.0, 0.0))
        ekf.process(WheelOdometry(0.0, 0.0, 0.0, SIG_V**2, SIG_W**2, "odom"))
        ekf.process(WheelOdometry(0.1, 0.8, 0.5, SIG_V**2, SIG_W**2, "odom"))
        P0 = ekf.kf.P.copy()  # the noise of (0, 0.1]
        assert ekf.tau == pytest.approx(0.1) and ekf.t == pytest.approx(0.1)
        for t in splits:
            ekf.predict_to(t)
        return ekf, P0

    one, P0 = predicted([0.2])
    two, _ = predicted([0.13, 0.2])
    np.testing.assert_allclose(two.kf.x, one.kf.x, atol=1e-12)
    added_one, added_two = one.kf.P - P0, two.kf.P - P0
    # (P0 itself is the noise of (0, 0.1] and is transported the same way in both)
    assert np.trace(added_one) > 4e-4
    np.testing.assert_allclose(added_two, added_one, rtol=1e-3, atol=1e-3 * np.abs(added_one).max())


def test_range_only_sighting_of_an_unmapped_landmark_is_counted_not_used_errata_002_11():
    """Errata 002 #11: a range-only first sighting cannot place a landmark. LandmarkSlamEkf
    counts it as 'range_only_unmapped', adds no state and makes no update; once the landmark is
    mapped from a range/bearing sighting, a range-only sighting of it is an ordinary update and
    is not counted."""
    ekf = LandmarkSlamEkf(make_cfg(), initial_pose=(0.0, 0.0, 0.0), init_std=INIT_STD)
    ekf.process(WheelOdometry(0.0, 0.0, 0.0, SIG_V**2, SIG_W**2, "odom"))
    ekf.process(LandmarkObservation(0.05, "a", 5.0, math.nan, SIG_R**2, math.nan,
                                    has_bearing=False, sensor="landmarks"))
    ekf.process(WheelOdometry(0.1, 0.0, 0.0, SIG_V**2, SIG_W**2, "odom"))
    assert ekf.rejected[("landmarks", "range_only_unmapped")] == 1
    assert ekf.kf.n == 3 and not ekf.slots and not ekf.innovations
    assert np.all(np.isfinite(ekf.kf.x)) and np.all(np.isfinite(ekf.kf.P))

    b = math.atan2(3.0, 4.0)
    ekf.process(LandmarkObservation(0.15, "a", 5.0, b, SIG_R**2, SIG_B**2, sensor="landmarks"))
    ekf.process(LandmarkObservation(0.17, "a", 5.05, math.nan, SIG_R**2, math.nan,
                                    has_bearing=False, sensor="landmarks"))
    ekf.process(WheelOdometry(0.2, 0.0, 0.0, SIG_V**2, SIG_W**2, "odom"))
    assert ekf.slots == {"a": 3} and ekf.kf.n == 5
    assert ekf.rejected[("landmarks", "range_only_unmapped")] == 1
    (inn,) = ekf.innovations  # the mapped landmark's range-only sighting, used
    assert len(inn.residual) == 1 and inn.accepted
