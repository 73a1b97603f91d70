"""The filters' compiled path (numba kernels, ddfuse.ekf_baseline.kalman_jit, the default)
against their Python reference (``reference=True``: KalmanCore's gate, lock-out bookkeeping,
predict and log; the kernels' prediction, gate bookkeeping and log are their own code, the gain
and Joseph update are ``ekf_baseline.joseph``'s in both). On streams
carrying every sensor kind, a heading that crosses +-pi, outliers the gates reject, a GPS jump
that locks the gate out until a recovery, an odometry yaw rate the gyro keeps contradicting
(the corroboration verdict and its hold-off), and on the real Husky bag, every estimate (state
and covariance) agrees to 1e-9 at every step, and so does the log of innovations, rejections
and notes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import ROOT, shared_bag
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation import geodesy
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.factors.kinematics import se2_step

DATUM = (47.397742, 8.545594, 488.0)
R_WHEEL, TRACK = 0.165, 0.555
START = (2.0, -1.0, 3.0)  # heading near pi: the first turn carries it across the seam
OFFSET, BIAS = 0.3, 0.01  # heading offset (rad), gyro bias (rad/s)


def _stream(seed: int, duration: float = 40.0, gps_jump: tuple | None = None,
            odom_w_bias: float = 0.0, odom_fast_after: float | None = None) -> list:
    """Every measurement kind the filters use, at its own rate, with outliers: every 23rd GPS
    fix 40 m off, every 31st heading 1.5 rad off, every 41st odometry speed 3 m/s off.
    ``gps_jump`` (t s, east m, north m): every fix from t on is moved by that much (a kidnapped
    robot: the gate locks out, then recovers); ``odom_w_bias`` (rad/s) added to the odometry's
    yaw rate after 10 s (the gyro contradicts it: rejected, not recovered);
    ``odom_fast_after`` (s): odometry and wheel speeds at 20 Hz from then on."""
    rng = np.random.default_rng(seed)
    pose = START
    dt = 0.01
    out = []
    k_fix = k_head = k_odom = 0
    for k in range(int(duration / dt)):
        t = k * dt
        v = 1.0 + 0.3 * math.sin(0.2 * t)
        w = 0.4 * math.sin(0.15 * t) + 0.1
        if k % 4 == 0:  # 25 Hz IMU: gyro, accel, heading
            out.append(GyroYawRate(t, w + BIAS + rng.normal(0, 0.01), 1e-4, "/imu"))
            out.append(ForwardAccel(t, 0.06 * math.cos(0.2 * t) + rng.normal(0, 0.05), 0.0025,
                                    "/imu"))
            k_head += 1
            yaw = pose[2] + OFFSET + rng.normal(0, 0.02) + (1.5 if k_head % 31 == 0 else 0.0)
            out.append(Heading(t, (yaw + math.pi) % (2 * math.pi) - math.pi, 4e-4, "/imu",
                               "compass"))
        fast = odom_fast_after is not None and t >= odom_fast_after
        if k % (5 if fast else 10) == 3:  # 10 Hz odometry and wheel speeds, their own clock
            k_odom += 1
            out.append(WheelOdometry(t, v + rng.normal(0, 0.02) + (3.0 if k_odom % 41 == 0
                                                                    else 0.0),
                                     w + rng.normal(0, 0.05) + (odom_w_bias if t > 10.0
                                                                else 0.0),
                                     4e-4, 2.5e-3, "/odom"))
            wl, wr = (v - 0.5 * TRACK * w) / R_WHEEL, (v + 0.5 * TRACK * w) / R_WHEEL
            out.append(WheelSpeeds(t, wl + rng.normal(0, 0.1), wr + rng.normal(0, 0.1), 0.01,
                                   0.01, "/joint_states"))
        if k % 40 == 7:  # 2.5 Hz GPS
            k_fix += 1
            e = pose[0] + rng.normal(0, 0.5) + (40.0 if k_fix % 23 == 0 else 0.0)
            n = pose[1] + rng.normal(0, 0.5)
            if gps_jump is not None and t >= gps_jump[0]:
                e += gps_jump[1]
                n += gps_jump[2]
            lat, lon, alt = geodesy.enu_to_geodetic(e, n, 0.0, *DATUM)
            cov = np.array([[0.25, 0.05, 0.0], [0.05, 0.3, 0.0], [0.0, 0.0, 1.0]])
            out.append(GpsFix(t, lat, lon, alt, cov, 0, "/fix", (e, n, 0.0)))
        pose = se2_step(*pose, v, w, dt)
    return out


def _config(estimate_offsets: bool, rate="event", accel_limits: tuple | None = None):
    """With ``estimate_offsets`` also every calibration: gyro bias, heading offset, odometry
    scales (the geometry's uncertainty stated) and a GPS delay; ``accel_limits`` the robot's
    (max_accel m/s^2, max_yaw_accel rad/s^2)."""
    imu = {"topic": "/imu", "use": ["yaw", "yaw_rate", "accel"]}
    gps = {"topic": "/fix", "lever_arm": [0.3, -0.1]}
    robot = {"wheel_radius": R_WHEEL, "track_width": TRACK}
    if estimate_offsets:
        imu.update(heading_offset="estimate", gyro_bias="estimate")
        gps["delay"] = 0.15
        robot.update(wheel_radius_std=0.003, track_width_std=0.02)
    else:
        imu.update(heading_offset=OFFSET, gyro_bias=BIAS)
    if accel_limits is not None:
        robot.update(max_accel=accel_limits[0], max_yaw_accel=accel_limits[1])
    return parse_config({
        "sensors": {
            "odometry": [{"topic": "/odom"}],
            "wheels": [{"topic": "/joint_states", "joints": ["l", "r"], "noise": {"speed": 0.1}}],
            "imu": [imu],
            "gps": [gps],
        },
        "robot": robot,
        "frame": {"datum": list(DATUM)},
        "initial_pose": list(START),
        "ekf": {"rate": rate},
    })


def _run_both(make, stream):
    """Feed ``stream`` to a compiled filter and a reference filter (``make(reference)``);
    compare every estimate on the way."""
    fast, ref = make(False), make(True)
    assert fast.compiled and not ref.compiled
    n_est = 0
    for m in stream:
        fast.process(m)
        ref.process(m)
        a, b = fast.estimate(), ref.estimate()
        assert (a is None) == (b is None)
        if a is None:
            continue
        n_est += 1
        assert a.t == b.t
        np.testing.assert_allclose(a.state, b.state, rtol=1e-9, atol=1e-9, err_msg=str(m))
        np.testing.assert_allclose(a.state_cov, b.state_cov, rtol=1e-9,
                                   atol=1e-9 * np.abs(b.state_cov).max(), err_msg=str(m))
        assert np.array_equal(a.state_cov, a.state_cov.T)
    fast.finish()
    ref.finish()
    assert n_est > 0.5 * len(stream)
    assert fast.log.rejected == ref.log.rejected
    assert fast.log.messages == ref.log.messages
    ia, ib = fast.innovations, ref.innovations
    assert [(i.t, i.sensor, i.kind, i.accepted) for i in ia] == \
        [(i.t, i.sensor, i.kind, i.accepted) for i in ib]
    for x, y in zip(ia, ib, strict=True):
        np.testing.assert_allclose(x.residual, y.residual, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(x.cov, y.cov, rtol=1e-9, atol=1e-12)
        assert x.nis == pytest.approx(y.nis, rel=1e-7, abs=1e-12)
    return fast


def _unicycle(cfg, pose_error="se2"):
    return lambda ref: UnicycleEkf(cfg, reference=ref, pose_error=pose_error)


def _igvc(cfg, motion="euler", datum=None):
    return lambda ref: IgvcEkf(cfg, motion=motion, reference=ref, datum=datum)


def _grid(fast, *axes):
    """The product of ``axes`` as pytest params: the combinations in ``fast`` in the default
    suite, the rest of the grid marked slow."""
    import itertools

    return [pytest.param(*c, marks=() if c in fast else pytest.mark.slow)
            for c in itertools.product(*axes)]


@pytest.mark.parametrize(("rate", "estimate_offsets", "pose_error"),
                         _grid({("event", True, "se2"), (10.0, False, "world")},
                               ["event", 10.0], [True, False], ["se2", "world"]))
def test_unicycle_compiled_matches_reference(estimate_offsets, rate, pose_error):
    cfg = _config(estimate_offsets, rate)
    stream = _stream(1)
    fast = _run_both(_unicycle(cfg, pose_error), stream)
    assert fast.pose_error == pose_error and fast.estimate().pose_error == pose_error
    assert len(fast.state_names) == (9 if estimate_offsets else 5)
    kinds = {(i.kind, i.accepted) for i in fast.innovations}
    # every measurement model was used, and the gate rejected the GPS and heading outliers
    assert {k for k, _ in kinds} == {"gyro", "heading", "v", "yaw_rate", "wheels", "gps"}
    assert ("gps", False) in kinds and ("heading", False) in kinds and ("v", False) in kinds


@pytest.mark.parametrize(("rate", "estimate_offsets"),
                         _grid({("event", True)}, ["event", 10.0], [True, False]))
def test_unicycle_compiled_matches_reference_with_acceleration_limits(estimate_offsets, rate):
    """The robot's acceleration limits stated: the twist densities follow the observed sample
    periods (twist_densities), at the start and again when odometry and wheel speeds go from
    10 to 20 Hz at 20 s; the compiled predictions use the same densities as the reference's
    at every step (the kernels keep a copy in their arrays)."""
    cfg = _config(estimate_offsets, rate, accel_limits=(0.5, 0.4))
    stream = _stream(5, odom_fast_after=20.0)
    fast = _run_both(_unicycle(cfg), stream)
    # v: odometry / wheel speeds, now 0.05 s apart; w: also the gyro, 0.04 s
    assert fast.noise.acc == pytest.approx(0.5 * math.sqrt(0.05), rel=1e-6)
    assert fast.noise.yaw_acc == pytest.approx(0.4 * math.sqrt(0.04), rel=1e-6)
    fp = fast.kf.fp
    assert tuple(fp[fast.kf.kj.FP_NOISE:fast.kf.kj.FP_NOISE + 2]) == \
        (fast.noise.acc, fast.noise.yaw_acc)


@pytest.mark.slow
@pytest.mark.parametrize(("motion", "estimate_offsets"),
                         [("euler", False), ("icc", False), ("euler", True), ("icc", True)])
def test_igvc_compiled_matches_reference(motion, estimate_offsets):
    cfg = _config(estimate_offsets)
    stream = _stream(2)
    fast = _run_both(_igvc(cfg, motion), stream)
    assert len(fast.state_names) == (15 if estimate_offsets else 11)
    kinds = {(i.kind, i.accepted) for i in fast.innovations}
    assert {k for k, _ in kinds} == {"gyro", "accel", "heading", "odometry", "wheels", "gps"}
    assert ("gps", False) in kinds and ("heading", False) in kinds


def test_stream_crosses_the_heading_seam():
    """The comparison above is only a test of angle wrapping if the heading crosses +-pi."""
    cfg = _config(False)
    ekf = UnicycleEkf(cfg)
    psi = []
    for m in _stream(1):
        ekf.process(m)
        e = ekf.estimate()
        if e is not None:
            psi.append(e.pose[2])
    assert min(psi) < -3.0 and max(psi) > 3.0
    assert any(a * b < 0 and abs(a) > 3.0 for a, b in zip(psi[:-1], psi[1:], strict=True))


@pytest.mark.parametrize("rate", ["event", 10.0])
def test_unicycle_compiled_lockout_matches_reference(rate):
    """A GPS jump of 25 m at 20 s locks the GPS gate out until the recovery inflates P: the
    compiled filter (which hands the lock-out to Python) takes the same decisions as the
    reference, step by step.

    Calibration states off: with them, heading and compass offset are observed almost only
    through their sum, and after the recovery's ~10^4-fold inflation rounding differences along
    that direction grow to a few 1e-9 rad, beyond the
    1e-9 compared here. The Husky bag test below covers a recovery with the offsets estimated."""
    cfg = _config(False, rate)
    stream = _stream(3, duration=45.0, gps_jump=(20.0, 25.0, -5.0))
    fast = _run_both(_unicycle(cfg), stream)
    assert fast.kf.recoveries
    assert fast.log.rejected[("/fix", "gate")] >= 4


def test_unicycle_compiled_corroboration_matches_reference():
    """An odometry yaw rate 0.6 rad/s off from 10 s on: odometry and wheel speeds are rejected
    again and again while the gyro is accepted -- KalmanCore's corroboration verdict ('not
    recovering'), then rejections during its hold-off, which the kernels handle themselves."""
    cfg = _config(True)
    stream = _stream(3, duration=45.0, odom_w_bias=0.6)
    fast = _run_both(_unicycle(cfg), stream)
    assert any("not recovering" in msg for msg in fast.log.messages)
    assert fast.log.rejected[("/odom", "gate")] > 50


@pytest.mark.parametrize("motion", ["euler", pytest.param("icc", marks=pytest.mark.slow)])
def test_igvc_compiled_lockout_matches_reference(motion):
    cfg = _config(False)  # (calibration states off: see the unicycle test above)
    stream = _stream(4, duration=45.0, gps_jump=(20.0, 25.0, -5.0))
    fast = _run_both(_igvc(cfg, motion), stream)
    assert fast.kf.recoveries


def _husky_slice(seconds: float, white_gps: bool = False):
    """The shipped config and the first ``seconds`` of the Husky bag's measurements;
    ``white_gps``: its GPS fused as white (correlation_time 0)."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config

    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    if white_gps:
        for s in cfg.of_kind("gps"):
            s.correlation_time = 0.0
    stream = read_stream(shared_bag("rl_husky_gps.bag"), cfg)
    t_end = stream.t0 + seconds
    return cfg, stream, [m for m in stream.measurements if m.t <= t_end]


# slow: the agreement the synthetic streams (lock-out and recovery, every sensor kind), the
# sample bag and test_gps_correlation_ekf (correlated fixes) check, on 80 s of real data
@pytest.mark.slow
@pytest.mark.parametrize("rate, white_gps", [("event", True), (10.0, True), ("event", False)])
def test_unicycle_compiled_matches_reference_on_husky_bag(rate, white_gps):
    """The first 80 s of the real Husky bag (compass offset and gyro bias estimated, the GPS
    alignment), event by event and at 10 Hz. With the GPS fused as white the slice has a GPS
    gate lock-out and its recovery at ~54 s; with the shipped config's correlation_time (19 s)
    every fix is fused with its inflated covariance, and none is locked out."""
    cfg, _, ms = _husky_slice(80.0, white_gps)
    if rate != "event":
        cfg.ekf.rate = rate
    fast = _run_both(_unicycle(cfg), ms)
    assert bool(fast.kf.recoveries) == white_gps and len(fast.state_names) == 7


@pytest.mark.slow
@pytest.mark.parametrize("rate", ["event", 10.0])
def test_unicycle_compiled_matches_reference_on_sample_bag(rate):
    """The simulated sample bag (data/sample_husky.bag) as ddfuse runs it: odometry scale
    states, acceleration limits, gyro bias, compass offset, a delayed GPS."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.runner import initial_pose

    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    cfg.ekf.rate = rate
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    pose = initial_pose(cfg.initial_pose, stream)
    fast = _run_both(lambda ref: UnicycleEkf(cfg, initial_pose=pose, reference=ref),
                     stream.measurements)
    assert fast.state_names[-2:] == ("k_v", "k_w") and fast.noise.acc < 1.0


@pytest.mark.slow  # test_igvc_compiled_matches_reference(_lockout)'s agreement on real data
def test_igvc_compiled_matches_reference_on_husky_bag():
    cfg, stream, ms = _husky_slice(80.0)
    fast = _run_both(_igvc(cfg, datum=stream.datum), ms)
    assert fast.kf.recoveries


def test_buffered_log_reads_like_a_list():
    """The compiled filter's log: innovations read twice are the same records (the buffer is
    drained once), reading in the middle of a run keeps the records already read in place, and
    the records are in time order, the ones the Python path logged (the recovery) included."""
    cfg = _config(False)
    ekf = UnicycleEkf(cfg)
    assert ekf.compiled and isinstance(ekf.log, jit.BufferedLog)
    stream = _stream(3, duration=30.0, gps_jump=(20.0, 25.0, -5.0))
    for m in stream[:len(stream) // 2]:
        ekf.process(m)
    first = list(ekf.log.innovations)
    def key(i):
        return (i.t, i.sensor, i.kind, i.nis, i.accepted)

    first = [key(i) for i in first]
    assert first and [key(i) for i in ekf.log.innovations] == first
    for m in stream[len(stream) // 2:]:
        ekf.process(m)
    ekf.finish()
    inns = list(ekf.log.innovations)
    assert [key(i) for i in inns[:len(first)]] == first and len(inns) > len(first)
    assert all(a.t <= b.t for a, b in zip(inns[:-1], inns[1:], strict=True))
    assert ekf.kf.recoveries
    t_rec = ekf.kf.recoveries[0][0]
    assert any(i.t == t_rec and i.kind == "gps" and i.accepted for i in inns)


@pytest.mark.parametrize("rate", ["event", 10.0])
def test_unicycle_compiled_matches_reference_with_rate_states(rate):
    """The twist's rates (robot.twist_walk speed_rate and yaw_rate_rate, as the first stage of
    ``ddfuse tune`` sets them): two integrated walks, with every calibration state; the
    kernels' and the reference's predictions agree at every step."""
    cfg = _config(True, rate)
    cfg.robot.twist_walk = {"speed_rate": 0.3, "yaw_rate_rate": 0.2}
    fast = _run_both(_unicycle(cfg), _stream(3))
    assert fast.state_names[-2:] == ("acc", "yacc")
    x = fast.estimate().state
    assert abs(x[-2]) < 0.5 and abs(x[-1]) < 0.5  # the drive's accelerations: <= 0.06, 0.06
