"""The known-map landmark EKF's compiled path (numba kernels ``lm_predict`` / ``lm_sighting``,
``ekf_baseline.landmark_compiled``) against its Python path, step by step on a simulated seed002
bag: wheel-speed input and the odometry scale states, a gated outlier, a gate lock-out whose
recovery the kernel defers to Python, a landmark at the body origin (deferred too), a landmark
not in the map, range-only sightings, a gap; Euler motion with the robot's slip; wheel odometry
(v, yaw rate) input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from ddfuse.ekf_baseline.landmark import LandmarkEkf
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import LANDMARK_NOT_IN_MAP, load_config
from ddfuse.estimation.gaps import GAP_S
from ddfuse.estimation.measurements import LandmarkObservation, WheelOdometry, WheelSpeeds
from ddfuse.estimation.runner import initial_pose
from ddfuse.evaluation.simulate import simulate, write_bag

TOL = 1e-9
OUTLIER_T = 20.0  # s after the start: one sighting 3 m long (gated)
LOCKOUT = (30.0, 33.0)  # s after the start: every sighting 1.5 m long (a lock-out, recovered)
GAP = (40.0, 40.0 + GAP_S + 1.0)  # s after the start: nothing at all


@pytest.fixture(scope="module")
def seed002(tmp_path_factory):
    """(config, start pose, map, measurements) of a 60 s seed002 drive, with the cases above."""
    sim = simulate("seed002", seed=3, duration=60.0)
    bag, cfg_path, _ = write_bag(sim, tmp_path_factory.mktemp("seed002") / "s.bag")
    cfg = load_config(cfg_path)
    stream = read_stream(bag, cfg)
    pose = initial_pose(cfg.initial_pose, stream)
    t0 = stream.measurements[0].t
    sightings = [m for m in stream.measurements if isinstance(m, LandmarkObservation)]
    # a map landmark where the filter starts, sighted before the first odometry sample (the
    # filter at rest there): range 0, no bearing
    lmap = dict(stream.landmarks, origin=(pose[0], pose[1]))
    s0 = sightings[0]
    extra = [dataclasses.replace(s0, t=t0, landmark_id="origin", range=0.0, bearing=0.0),
             dataclasses.replace(s0, t=t0 + 5.0, landmark_id="not-in-map")]
    meas = []  # (the sort below is stable: the sighting of 'origin' stays the first message)
    outlier_done = False
    for i, m in enumerate(stream.measurements):
        dt = m.t - t0
        if GAP[0] <= dt < GAP[1]:
            continue
        if isinstance(m, LandmarkObservation):
            if LOCKOUT[0] <= dt < LOCKOUT[1]:
                m = dataclasses.replace(m, range=m.range + 1.5)
            elif dt >= OUTLIER_T and not outlier_done:
                m = dataclasses.replace(m, range=m.range + 3.0)
                outlier_done = True
            elif i % 7 == 0:
                m = dataclasses.replace(m, has_bearing=False)
        meas.append(m)
    meas = sorted(extra + meas, key=lambda m: m.t)
    return cfg, pose, lmap, meas


def _lockstep(cfg, pose, lmap, meas, **kw):
    """Both paths over ``meas``: after every message their state and covariance agree within
    TOL; returns the two filters."""
    a = LandmarkEkf(cfg, initial_pose=pose, landmarks=lmap, compiled=True, **kw)
    b = LandmarkEkf(cfg, initial_pose=pose, landmarks=lmap, compiled=False, **kw)
    for m in meas:
        a.process(m)
        b.process(m)
        np.testing.assert_allclose(a.kf.x, b.kf.x, rtol=0.0, atol=TOL)
        np.testing.assert_allclose(a.kf.P, b.kf.P, rtol=0.0, atol=TOL)
        assert a.t == b.t
    a.finish()
    b.finish()
    np.testing.assert_allclose(a.kf.x, b.kf.x, rtol=0.0, atol=TOL)
    np.testing.assert_allclose(a.kf.P, b.kf.P, rtol=0.0, atol=TOL)
    return a, b


def _same_logs(a, b) -> None:
    ia, ib = a.log.innovations, b.log.innovations
    assert len(ia) == len(ib) > 0
    for p, q in zip(ia, ib, strict=True):
        assert (p.t, p.sensor, p.kind, p.accepted) == (q.t, q.sensor, q.kind, q.accepted)
        assert p.nis == pytest.approx(q.nis, rel=0.0, abs=TOL)
        np.testing.assert_allclose(p.residual, q.residual, rtol=0.0, atol=TOL)
        np.testing.assert_allclose(p.cov, q.cov, rtol=0.0, atol=TOL)
    assert a.log.rejected == b.log.rejected
    assert a.log.messages == b.log.messages
    assert [r[:2] for r in a.kf.recoveries] == [r[:2] for r in b.kf.recoveries]
    for p, q in zip(a.kf.recoveries, b.kf.recoveries, strict=True):
        assert p[2] == pytest.approx(q[2], rel=1e-9)  # the inflation
    ea, eb = a.estimate(), b.estimate()
    assert ea.state_names == eb.state_names
    np.testing.assert_allclose(ea.state_cov, eb.state_cov, rtol=0.0, atol=TOL)


def test_compiled_path_matches_python_on_seed002_with_wheels_and_scale_states(seed002):
    cfg, pose, lmap, meas = seed002
    assert any(isinstance(m, WheelSpeeds) for m in meas)
    a, b = _lockstep(cfg, pose, lmap, meas)
    assert a.compiled and not b.compiled
    assert a.n_base == 5 and a.estimate().state_names[3:5] == ("k_v", "k_w")
    _same_logs(a, b)
    rej = a.log.rejected
    sensor = next(m.sensor for m in meas if isinstance(m, LandmarkObservation))
    assert rej[(sensor, "gate")] >= 2  # the outlier and the lock-out's run
    assert rej[(sensor, LANDMARK_NOT_IN_MAP)] == 1
    # what the kernel deferred, done by the Python update on the kernels' arrays
    assert rej[(sensor, "degenerate")] == 1  # the landmark at the body origin
    assert len(a.kf.recoveries) >= 1  # the lock-out's recovery
    assert any("lock-out" in text for text in a.log.messages)
    assert any("gap" in text for text in a.log.messages)
    assert any(len(i.residual) == 1 for i in a.log.innovations)  # range-only sightings


@pytest.mark.slow
def test_compiled_path_matches_python_with_euler_motion_and_slip(seed002):
    cfg, pose, lmap, meas = seed002
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(
        cfg.robot, slip={"longitudinal": 0.05, "lateral": 0.02, "heading": 0.01}))
    a, b = _lockstep(cfg, pose, lmap, meas, motion="euler")
    _same_logs(a, b)


def test_compiled_path_matches_python_with_wheel_odometry_input(seed002):
    """(v, yaw rate) samples, the seed's control input, without the scale states."""
    cfg, pose, lmap, meas = seed002
    r, L = cfg.robot.wheel_radius, cfg.robot.track_width
    odo = [WheelOdometry(m.t, *m.twist(r, L), sensor="odom") if isinstance(m, WheelSpeeds)
           else m for m in meas]
    cfg = dataclasses.replace(cfg, robot=dataclasses.replace(
        cfg.robot, wheel_radius_std=None, track_width_std=None))
    a, b = _lockstep(cfg, pose, lmap, odo)
    assert a.n_base == 3
    _same_logs(a, b)


def test_compiled_path_matches_python_with_correlated_sightings(seed002):
    """A landmark sensor's correlation_time: both paths fuse each sighting with R times the
    same factor (the gate and the log keep R), and the filter is less sure than fusing the
    same sightings as white."""
    cfg, pose, lmap, meas = seed002
    sensor = next(m.sensor for m in meas if isinstance(m, LandmarkObservation))
    sensors = [dataclasses.replace(s, correlation_time=2.0) if s.name == sensor else s
               for s in cfg.sensors]
    a, b = _lockstep(dataclasses.replace(cfg, sensors=sensors), pose, lmap, meas)
    _same_logs(a, b)
    white = LandmarkEkf(cfg, initial_pose=pose, landmarks=lmap, compiled=True)
    for m in meas:
        white.process(m)
    white.finish()
    assert np.trace(a.kf.P[:2, :2]) > 1.5 * np.trace(white.kf.P[:2, :2])
