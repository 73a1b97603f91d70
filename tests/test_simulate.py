"""The simulator: noise statistics, truth kinematics, determinism, scenario shapes.

Noise tests compare each sensor's error against the truth with the standard deviation the config
states; with 10^4 samples the sample std of a correct Gaussian is within ~0.7 % (1 sigma) of the
true one, so the 5 % bound fails only for a wrong model, not by chance.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.geodesy import geodetic_to_enu
from ddfuse.evaluation import simulate as sim

N = 10_000  # samples per noise check


@pytest.fixture(scope="module")
def husky_long():
    """Husky sensors over 4100 s: >= 10^4 samples of every sensor, including GPS at 2.5 Hz."""
    return sim.simulate("long", seed=7, duration=4100.0)


@pytest.fixture(scope="module")
def seed002_long():
    return sim.simulate("seed002", seed=7, duration=1100.0)


def _check_std(resid: np.ndarray, std: float, what: str) -> float:
    resid = np.asarray(resid)[:N]
    assert len(resid) == N, f"{what}: only {len(resid)} samples"
    s = float(np.std(resid, ddof=1))
    assert abs(s / std - 1.0) < 0.05, f"{what}: sample std {s:.5g} vs configured {std:.5g}"
    # The mean is zero within 4 standard errors.
    assert abs(resid.mean()) < 4.0 * std / math.sqrt(N), f"{what}: mean {resid.mean():.3g}"
    return s / std


def test_config_noise_is_the_simulated_noise(husky_long, seed002_long, tmp_path):
    """The config written next to the bag validates and states SimResult.noise()."""
    for res in (husky_long, seed002_long):
        cfg_tree = sim.sim_config(res, "map.yaml")
        if res.landmarks is not None:
            (tmp_path / "map.yaml").write_text("landmarks: {'1': [0, 0]}\n")
        cfg = parse_config(cfg_tree, base=tmp_path)
        noise = res.noise()
        for s in cfg.sensors:
            assert s.noise == pytest.approx(noise[s.kind]), s.kind
        assert cfg.robot.wheel_radius == res.scenario.nominal_geometry.wheel_radius
        assert cfg.robot.wheel_radius != res.scenario.true_geometry.wheel_radius
        assert cfg.robot.track_width != res.scenario.true_geometry.track_width
        # the stated geometry uncertainty covers the true geometry's offset (within 1 sigma)
        std = res.scenario.geometry_std
        assert (cfg.robot.wheel_radius_std, cfg.robot.track_width_std) == \
            (std.wheel_radius, std.track_width)
        assert abs(res.scenario.true_geometry.wheel_radius - cfg.robot.wheel_radius) \
            <= cfg.robot.wheel_radius_std
        assert abs(res.scenario.true_geometry.track_width - cfg.robot.track_width) \
            <= cfg.robot.track_width_std
        assert cfg.initial_pose == "ground_truth"
        assert cfg.datum == (res.scenario.datum if res.scenario.datum else "first_fix")
    husky = parse_config(sim.sim_config(husky_long))
    imu = husky.of_kind("imu")[0]
    assert imu.heading_offset == "estimate" and imu.gyro_bias == "estimate"
    assert imu.noise["gyro_bias_walk"] == husky_long.scenario.imu.gyro_bias_walk
    assert imu.noise["heading_offset_walk"] == 0.0  # the simulated offset is constant
    assert husky.of_kind("gps")[0].delay == husky_long.scenario.gps.delay


def test_odometry_noise(husky_long):
    res = husky_long
    enc, noise = res.encoders, res.noise()["odometry"]
    r, L = res.scenario.nominal_geometry.wheel_radius, res.scenario.nominal_geometry.track_width
    # The reference is the NOMINAL-geometry twist of the TRUE interval-mean wheel speeds: the
    # calibration error is a systematic scale, not noise.
    _check_std(enc.v - 0.5 * r * (enc.true_left + enc.true_right), noise["v"], "odometry v")
    _check_std(enc.yaw_rate - r * (enc.true_right - enc.true_left) / L, noise["yaw_rate"],
               "odometry yaw rate")


def test_odometry_carries_the_calibration_error(husky_long):
    """Odometry speed and yaw rate are scaled by nominal/true geometry against the truth."""
    res = husky_long
    enc, sc = res.encoders, res.scenario
    tg, ng = sc.true_geometry, sc.nominal_geometry
    edges = np.concatenate([[enc.t[0] - 1.0 / sc.encoders.rate], enc.t])
    true_v = np.diff(0.5 * tg.wheel_radius * np.add(*res.truth.wheel_angles(edges))) \
        / np.diff(edges)
    moving = true_v > 0.5
    ratio = np.sum(enc.v[moving]) / np.sum(true_v[moving])
    assert ratio == pytest.approx(ng.wheel_radius / tg.wheel_radius, rel=2e-4)
    turning = np.abs(res.truth.at(enc.t)[4]) > 0.2
    slope = np.polyfit(res.truth.at(enc.t)[4][turning], enc.yaw_rate[turning], 1)[0]
    expected = (ng.wheel_radius / tg.wheel_radius) * (tg.track_width / ng.track_width)
    assert slope == pytest.approx(expected, rel=5e-3)


def test_wheel_speed_noise(seed002_long):
    enc = seed002_long.encoders
    s = seed002_long.noise()["wheels"]["speed"]
    _check_std(enc.left - enc.true_left, s, "left wheel speed")
    _check_std(enc.right - enc.true_right, s, "right wheel speed")
    # The true interval means are the wheel-angle differences of the exact truth.
    edges = np.concatenate([[enc.t[0] - 0.1], enc.t])
    al, _ = seed002_long.truth.wheel_angles(edges)
    np.testing.assert_allclose(enc.true_left, np.diff(al) / np.diff(edges), atol=1e-9)
    # JointState positions are the accumulated counts: consistent with the speeds.
    np.testing.assert_allclose(np.diff(enc.counts_left * enc.tick),
                               enc.left[1:] * np.diff(enc.t), atol=1e-9)


def test_imu_noise(husky_long):
    res = husky_long
    imu, spec, noise = res.imu, res.scenario.imu, res.noise()["imu"]
    _, _, yaw, v, w = res.truth.at(imu.t)
    _check_std(imu.yaw_rate - w - imu.bias, noise["yaw_rate"], "gyro z")
    _check_std(imu.gyro_xy[:, 0], noise["yaw_rate"], "gyro x")
    _check_std(sim.wrap(imu.yaw - yaw - spec.heading_offset), noise["yaw"], "heading")
    _check_std(imu.accel[:, 0] - res.truth.accel(imu.t), noise["accel"], "forward accel")
    _check_std(imu.accel[:, 1] - v * w, noise["accel"], "lateral accel")
    _check_std(imu.accel[:, 2] - sim.G, noise["accel"], "vertical accel")
    _check_std(imu.roll, spec.tilt_std, "roll")
    # Gyro bias: a random walk of the stated density, starting at the stated value.
    steps = np.diff(imu.bias) / np.sqrt(np.diff(imu.t))
    _check_std(steps, spec.gyro_bias_walk, "gyro bias walk")
    assert imu.bias[0] == pytest.approx(spec.gyro_bias0, abs=5 * spec.gyro_bias_walk)


def test_gps_noise_delay_and_outliers(husky_long):
    res = husky_long
    gps, spec, noise = res.gps, res.scenario.gps, res.noise()["gps"]
    np.testing.assert_allclose(gps.t - gps.t_measured, spec.delay, atol=1e-12)
    # Independent route: lat/lon/alt back to ENU, truth evaluated at the stamp minus the delay.
    e, n, u = geodetic_to_enu(gps.lat, gps.lon, gps.alt, *res.scenario.datum)
    x, y, _, _, _ = res.truth.at(gps.t - spec.delay)
    good = ~gps.outlier
    _check_std((e - x)[good], noise["horizontal"], "GPS east")
    _check_std((n - y)[good], noise["horizontal"], "GPS north")
    _check_std(u[good], noise["vertical"], "GPS up")
    # Outliers: tens of metres off, at about the configured rate.
    off = np.hypot(e - x, n - y)[gps.outlier]
    assert off.min() > spec.outlier_range[0] - 5 * noise["horizontal"]
    assert off.max() < spec.outlier_range[1] + 5 * noise["horizontal"]
    n_nominal = res.duration * spec.rate
    assert gps.outlier.sum() == pytest.approx(spec.outlier_prob * n_nominal,
                                              abs=5 * math.sqrt(spec.outlier_prob * n_nominal))
    missing = n_nominal - len(gps.t)
    assert missing == pytest.approx(spec.dropout_prob * n_nominal,
                                    abs=5 * math.sqrt(spec.dropout_prob * n_nominal) + 2)


def test_landmark_noise_and_visibility(seed002_long):
    res = seed002_long
    lm, spec, noise = res.landmarks, res.scenario.landmarks, res.noise()["landmarks"]
    x, y, yaw, _, _ = res.truth.at(lm.t)
    p = lm.positions[lm.index]
    true_r = np.hypot(p[:, 0] - x, p[:, 1] - y)
    true_b = sim.wrap(np.arctan2(p[:, 1] - y, p[:, 0] - x) - yaw)
    _check_std(lm.range - true_r, noise["range"], "landmark range")
    _check_std(sim.wrap(lm.bearing - true_b), noise["bearing"], "landmark bearing")
    assert true_r.max() <= spec.max_range and true_r.min() >= spec.min_range
    assert np.abs(true_b).max() <= 0.5 * spec.fov
    # Detection probability: sightings / visible (scan, landmark) pairs.
    scans = lm.scan_t
    assert set(np.unique(lm.t)) <= set(scans)
    sx, sy, syaw, _, _ = res.truth.at(scans)
    dx = lm.positions[None, :, 0] - sx[:, None]
    dy = lm.positions[None, :, 1] - sy[:, None]
    rr = np.hypot(dx, dy)
    bb = sim.wrap(np.arctan2(dy, dx) - syaw[:, None])
    visible = (rr >= spec.min_range) & (rr <= spec.max_range) & (np.abs(bb) <= 0.5 * spec.fov)
    assert len(lm.t) / visible.sum() == pytest.approx(spec.detect_prob, abs=0.01)


def test_truth_substeps_are_exact_constant_twists_of_the_wheel_model():
    """Each substep's relative pose is the SE(2) exponential of the twist that the true wheel
    speeds give through the TRUE radius and track (checked by an independent chord formula)."""
    res = sim.simulate("figure-eight", seed=2, duration=120.0)
    tr, g = res.truth, res.scenario.true_geometry
    v = 0.5 * g.wheel_radius * (tr.wheel_left + tr.wheel_right)
    w = g.wheel_radius * (tr.wheel_right - tr.wheel_left) / g.track_width
    dyaw = np.diff(tr.yaw)
    np.testing.assert_allclose(dyaw, w * tr.dt, atol=1e-12)
    c, s = np.cos(tr.yaw[:-1]), np.sin(tr.yaw[:-1])
    dx, dy = np.diff(tr.x), np.diff(tr.y)
    fwd, left = c * dx + s * dy, -s * dx + c * dy
    # A constant twist moves along a chord at half the heading change, of length
    # 2 (v / w) sin(w dt / 2).
    # 2 (v / w) sin(w dt / 2), written with w dt (not the differenced yaw, which loses digits
    # when w is tiny) and well conditioned at w = 0: v dt sin(a/2) / (a/2).
    chord = np.hypot(fwd, left)
    half = 0.5 * w * tr.dt
    expected = v * tr.dt * np.sinc(half / np.pi)
    np.testing.assert_allclose(chord, np.abs(expected), rtol=1e-9, atol=1e-13)
    moving = chord > 1e-6
    np.testing.assert_allclose(np.arctan2(left, fwd)[moving], half[moving], atol=1e-9)


def test_ground_truth_finite_differences_match_the_wheel_model():
    """Central differences of the published 20 Hz truth give the wheel-model speed and yaw rate,
    with no sideways motion (no slip), to the O(dt^2) accuracy of a central difference."""
    res = sim.simulate("husky", seed=4, duration=200.0)
    gt, g = res.ground_truth, res.scenario.true_geometry
    h = gt.t[2] - gt.t[0]
    yaw = np.unwrap(gt.yaw)
    vx, vy = (gt.x[2:] - gt.x[:-2]) / h, (gt.y[2:] - gt.y[:-2]) / h
    c, s = np.cos(yaw[1:-1]), np.sin(yaw[1:-1])
    fwd, side = c * vx + s * vy, -s * vx + c * vy
    w_fd = (yaw[2:] - yaw[:-2]) / h
    # Wheel model at the same instants: true wheel speeds through the true geometry.
    i, _ = res.truth._index(gt.t[1:-1])
    wl, wr = res.truth.wheel_left[i], res.truth.wheel_right[i]
    v_wm = 0.5 * g.wheel_radius * (wl + wr)
    w_wm = g.wheel_radius * (wr - wl) / g.track_width
    # Truncation bound: h^2/6 |v'''| with the speeds used here (|w| <= 0.5 rad/s, v <= 1 m/s):
    # the lateral term v w^2 h^2 / 6 ~ 4e-4; zero-order hold over 0.01 s substeps adds
    # |dv/dt| dt/2 ~ 2e-3.
    assert np.max(np.abs(fwd - v_wm)) < 3e-3
    assert np.max(np.abs(side)) < 3e-3
    assert np.max(np.abs(w_fd - w_wm)) < 3e-3
    assert gt.v == pytest.approx(0.5 * g.wheel_radius * (
        res.truth.wheel_left + res.truth.wheel_right)[res.truth._index(gt.t)[0]])


def test_truth_accel_is_the_derivative_of_speed():
    res = sim.simulate("loop-stops", seed=0, duration=100.0)
    t = np.linspace(1.0, 99.0, 5000)
    h = 0.05
    fd = (res.truth.at(t + h)[3] - res.truth.at(t - h)[3]) / (2 * h)
    # Piecewise-constant substep speeds: the central difference over 0.1 s has error <= dt |a|/h.
    assert np.max(np.abs(res.truth.accel(t) - fd)) < 0.02
    assert np.max(np.abs(res.truth.accel(t))) > 0.2  # the check is not vacuous: it accelerates


def test_loop_stops_really_stops_and_figure_eight_closes():
    res = sim.simulate("loop-stops", seed=0, duration=400.0)
    stopped = res.truth.v == 0.0
    starts = np.flatnonzero(np.diff(stopped.astype(int)) == 1)
    assert len(starts) >= 8  # four stops per lap, two laps or more
    # Heading after one full lap of the rounded rectangle is the start heading + 2 pi.
    sc = res.scenario.trajectory
    a, b = sc.loop_size
    r = sc.corner_radius
    lap = 2 * (a - 2 * r) + 2 * (b - 2 * r) + 2 * math.pi * r
    s = np.cumsum(res.truth.v) * res.truth.dt
    k = np.searchsorted(s, lap)
    assert res.truth.yaw[k] - sc.start[2] == pytest.approx(2 * math.pi, abs=1e-5)
    assert math.hypot(res.truth.x[k] - sc.start[0], res.truth.y[k] - sc.start[1]) < 1e-3
    f8 = sim.simulate("figure-eight", seed=0, duration=400.0)
    gt = f8.ground_truth
    assert np.ptp(gt.x) == pytest.approx(2 * f8.scenario.trajectory.half_width, rel=0.02)
    assert np.ptp(gt.y) == pytest.approx(f8.scenario.trajectory.half_width, rel=0.02)


def _fields(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def _assert_same(a, b) -> None:
    for name, x in _fields(a).items():
        y = getattr(b, name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            _assert_same(x, y)
        else:
            assert x == y, name


def test_deterministic_per_seed_and_seeds_differ():
    for name in ("husky", "seed002", "gps-outage"):
        a = sim.simulate(name, seed=11, duration=60.0)
        b = sim.simulate(name, seed=11, duration=60.0)
        _assert_same(a, b)
    a = sim.simulate("seed002", seed=1, duration=60.0)
    b = sim.simulate("seed002", seed=2, duration=60.0)
    assert not np.allclose(a.truth.x, b.truth.x)  # random path differs
    assert not np.allclose(a.landmarks.positions, b.landmarks.positions)
    a = sim.simulate("husky", seed=1, duration=60.0)
    b = sim.simulate("husky", seed=2, duration=60.0)
    np.testing.assert_array_equal(a.truth.x, b.truth.x)  # the lawnmower path is fixed
    assert not np.allclose(a.gps.enu[:10], b.gps.enu[:10])
    assert not np.allclose(a.imu.yaw_rate, b.imu.yaw_rate)


@pytest.mark.parametrize("name", ["seed002", "random"])
def test_duration_cuts_the_random_drive_not_redraws_it(name):
    """--duration gives the first part of the scenario's default-duration drive: the same truth
    (here at t = 20 s and up to where the shorter run ramps down to rest) and, with landmarks,
    the same map. A longer run drives the same path up to the default duration's ramp-down."""
    default = sim.simulate(name, seed=0)
    ramp = default.scenario.trajectory.ramp
    at20 = np.array([20.0])
    for duration in (60.0, default.duration + 100.0):
        run = sim.simulate(name, seed=0, duration=duration)
        for a, b in zip(run.truth.at(at20), default.truth.at(at20), strict=True):
            np.testing.assert_array_equal(a, b)
        m = int(round((min(duration, default.duration) - ramp) / default.truth.dt))
        np.testing.assert_array_equal(run.truth.x[:m], default.truth.x[:m])
        np.testing.assert_array_equal(run.truth.yaw[:m], default.truth.yaw[:m])
    short = sim.simulate(name, seed=0, duration=60.0)
    if default.landmarks is not None:
        np.testing.assert_array_equal(short.landmarks.positions, default.landmarks.positions)
    # the same through a Scenario object (what `ddfuse mc --duration` simulates)
    via = sim.simulate(sim.get_scenario(name), seed=0, duration=60.0)
    np.testing.assert_array_equal(via.truth.x, short.truth.x)


def test_sensor_streams_are_independent():
    """Changing one sensor's settings leaves the other sensors' samples unchanged."""
    base = sim.get_scenario("husky", duration=60.0)
    a = sim.simulate(base, seed=3)
    b = sim.simulate(dataclasses.replace(base, gps=dataclasses.replace(
        base.gps, outlier_prob=0.5, dropout_prob=0.3)), seed=3)
    _assert_same(a.imu, b.imu)
    _assert_same(a.encoders, b.encoders)
    assert len(b.gps.t) < len(a.gps.t)


def test_outage_has_no_fixes():
    res = sim.simulate("gps-outage", seed=0)
    a, b = res.scenario.gps.outages[0]
    assert b - a == 60.0
    assert not np.any((res.gps.t_measured >= a) & (res.gps.t_measured < b))
    gaps = np.diff(res.gps.t)
    assert gaps.max() >= 60.0
    assert res.gps.outlier.sum() >= 5


def test_long_generates_fast():
    t = time.perf_counter()
    res = sim.simulate("long", seed=0)
    elapsed = time.perf_counter() - t
    assert res.duration == 7200.0
    assert len(res.imu.t) == pytest.approx(7200 * 30, abs=2)
    assert elapsed < 20.0, f"2 h simulation took {elapsed:.1f} s"


def test_unknown_scenario_and_bad_duration():
    with pytest.raises(ValueError, match="unknown scenario"):
        sim.simulate("nope")
    with pytest.raises(ValueError, match="duration"):
        sim.simulate("husky", duration=1.0)


def test_dead_reckoning_with_perfect_calibration_follows_the_truth():
    """With nominal = true geometry and near-noiseless encoders, the odometry dead reckoning of
    plot_sim reproduces the truth; with the scenario's miscalibration it does not. This ties the
    encoder model (interval means stamped at the interval end) to the truth."""
    from ddfuse.evaluation.plot_sim import dead_reckoning

    base = sim.get_scenario("husky", duration=120.0)
    exact = dataclasses.replace(
        base, nominal_geometry=base.true_geometry,
        encoders=dataclasses.replace(base.encoders, speed_std=1e-4, counts_per_rev=10**7))
    for sc, lo, hi in ((exact, 0.0, 0.02), (base, 1.0, np.inf)):
        res = sim.simulate(sc, seed=0)
        t, x, y, yaw = dead_reckoning(res)
        tx, ty, tyaw, _, _ = res.truth.at(t)
        err = np.hypot(x - tx, y - ty).max()
        assert lo <= err < hi, err
    assert np.abs(sim.wrap(yaw - tyaw)).max() > 0.05  # the miscalibrated run also turns wrong


def test_plot_sim_writes_a_png(tmp_path):
    from ddfuse.evaluation.cli.plot_sim import main

    out = tmp_path / "p.png"
    assert main(["gps-outage", "--duration", "240", "-o", str(out)]) == 0
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


def test_a_short_straight_drive_states_no_zero_acceleration_limit():
    """The first 10 s of husky drive straight: the simulated yaw acceleration is 0, and a
    stated limit of 0 would hold the twist fixed (the config refuses it). The config leaves it
    out and loads; a drive that turns states its limit."""
    short = sim.sim_config(sim.simulate("husky", seed=0, duration=10.0))
    assert "max_yaw_accel" not in short["robot"] and short["robot"]["max_accel"] > 0.0
    parse_config(short)
    assert sim.sim_config(sim.simulate("husky", seed=0, duration=60.0))["robot"][
        "max_yaw_accel"] > 0.0
