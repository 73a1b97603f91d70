"""Seed 000's EKF near a pole (errata 000 #37): its (lat, lon) state is singular there, so it
refuses to run within POLE_LIMIT_KM of one with a PolarRegionError that says why, instead of
dividing by zero in the great-circle step (or tracking garbage just before it), and the runner
puts that message in the estimator's row while the other estimators go on.

The drives are synthetic: wheel speeds and a gyro for a straight drive, GPS fixes at the true
positions mapped to WGS-84 exactly (``geodesy.enu_to_geodetic`` about the datum)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.igvc import POLE_LIMIT_DEG, IgvcEkf, PolarRegionError
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import Config, RobotConfig, SensorConfig
from ddfuse.estimation.measurements import GpsFix, Stream
from ddfuse.estimation.runner import run
from drives import straight_drive

R_WHEEL, TRACK = 0.165, 0.555
SIG_WHEEL, SIG_GYRO, SIG_GPS = 0.05, 0.01, 0.5
M_PER_DEG = 111_694.0  # m per degree of latitude near the poles (meridian radius 6400 km)


def _cfg(datum=None) -> Config:
    return Config(
        sensors=[SensorConfig(kind="imu", topic="/imu", name="imu", use=("yaw_rate",)),
                 SensorConfig(kind="gps", topic="/fix", name="gps", use=("position",)),
                 SensorConfig(kind="wheels", topic="/joint_states", name="wheels",
                              use=("speeds",), joints=("l", "r"))],
        robot=RobotConfig(wheel_radius=R_WHEEL, track_width=TRACK), datum=datum)


def _drive(datum, yaw: float, v: float, duration: float, seed: int = 3):
    """A straight drive from the datum at ``yaw`` (ENU, rad) and ``v`` m/s (``drives``).
    Returns (measurements, truth (x, y) at each fix)."""
    meas = list(straight_drive(datum, yaw, v, duration, np.random.default_rng(seed),
                               r_wheel=R_WHEEL, sig_wheel=SIG_WHEEL, sig_gyro=SIG_GYRO,
                               sig_gps=SIG_GPS))
    truth = {m.t: (v * m.t * math.cos(yaw), v * m.t * math.sin(yaw)) for m in meas
             if isinstance(m, GpsFix)}
    return meas, truth


def _feed(ekf, meas):
    """Feed ``meas``; return the stamp of the message that raised and the error (or None)."""
    for m in meas:
        try:
            ekf.process(m)
        except Exception as exc:  # noqa: BLE001 -- the test names the type it expects
            return m.t, exc
    return None, None


@pytest.mark.parametrize("reference", [True, False])
def test_a_start_11_m_from_the_pole_is_refused_errata_000_37(reference):
    """The audit's case: the drive re-projected to 11 m from the north pole. Without the check
    the great-circle step's sin(lat) rounded to 1 at the pole and 1/sqrt(1 - sin^2 lat)
    raised a bare ZeroDivisionError 12.6 s in; the filter refuses at its first message instead,
    saying what is singular, where the limit is and what to use."""
    datum = (90.0 - 11.0 / M_PER_DEG, 0.0, 100.0)
    meas, _ = _drive(datum, yaw=math.pi / 2, v=1.0, duration=30.0)
    ekf = IgvcEkf(_cfg(datum), datum=datum, initial_pose=(0.0, 0.0, math.pi / 2),
                  reference=reference)
    t, exc = _feed(ekf, meas)
    assert isinstance(exc, PolarRegionError), exc
    assert t == meas[0].t
    msg = str(exc)
    assert "lat/lon state is singular within 10 km of a pole" in msg
    assert f"|lat| > {POLE_LIMIT_DEG:g} deg" in msg
    assert "11 m from the north pole" in msg
    assert "use ekf or the smoother" in msg


def test_a_start_at_the_first_fix_near_the_south_pole_is_refused_there():
    """Without a datum the first fix is the datum (and the start, with the course from the
    next ones): a first fix 5 km from the south pole is refused at that fix."""
    datum = (-90.0 + 5000.0 / M_PER_DEG, 120.0, 2800.0)
    meas, _ = _drive(datum, yaw=0.3, v=2.0, duration=20.0)
    ekf = IgvcEkf(_cfg(None))
    t, exc = _feed(ekf, meas)
    assert isinstance(exc, PolarRegionError), exc
    fixes = [m.t for m in meas if isinstance(m, GpsFix)]
    assert t == fixes[0]
    assert "south pole" in str(exc) and "the datum is at latitude -89.95" in str(exc)


@pytest.mark.parametrize("reference", [True, False])
def test_driving_into_the_polar_cap_stops_at_the_limit(reference):
    """Starting 10.3 km from the pole and driving towards it at 5 m/s, the filter runs (and
    tracks the fixes) until its state crosses the limit, 250 m on, and stops within a message
    of it: the error names the state's latitude, just inside the limit."""
    r0 = 10_300.0
    datum = (90.0 - r0 / M_PER_DEG, 30.0, 0.0)
    meas, truth = _drive(datum, yaw=math.pi / 2, v=5.0, duration=80.0)
    ekf = IgvcEkf(_cfg(datum), datum=datum, initial_pose=(0.0, 0.0, math.pi / 2),
                  reference=reference)
    t, exc = _feed(ekf, meas)
    assert isinstance(exc, PolarRegionError), exc
    assert "the filter's position is" in str(exc)
    lat = math.degrees(float(ekf.kf.x[0]))
    assert POLE_LIMIT_DEG < lat < POLE_LIMIT_DEG + 1e-5  # at most cm past the limit
    # it got there by tracking: y about the 250 m to the limit, at the time the truth did
    limit_y = r0 - (90.0 - POLE_LIMIT_DEG) * ekf.radius * math.pi / 180.0
    assert abs(5.0 * t - limit_y) < 2.0
    assert abs(float(ekf.kf.x[4]) - 5.0 * t) < 1.0


def test_just_outside_the_limit_the_filter_runs_and_tracks():
    """The refusal is not too eager: 12 km from the pole the drive runs to its end with the
    position within the GPS noise of the truth."""
    datum = (90.0 - 12_000.0 / M_PER_DEG, -45.0, 0.0)
    meas, truth = _drive(datum, yaw=0.0, v=2.0, duration=60.0)
    ekf = IgvcEkf(_cfg(datum), datum=datum, initial_pose=(0.0, 0.0, 0.0))
    t, exc = _feed(ekf, meas)
    assert exc is None
    x, y = truth[max(truth)]
    assert math.hypot(float(ekf.kf.x[3]) - x, float(ekf.kf.x[4]) - y) < 2.0 * SIG_GPS


def test_the_runner_reports_the_refusal_and_keeps_the_other_estimators():
    """Through ``ddfuse.estimation.runner.run``: the EKF's row carries the PolarRegionError message;
    the unicycle EKF (local plane, no lat/lon state) runs the whole drive."""
    datum = (90.0 - 11.0 / M_PER_DEG, 0.0, 100.0)
    meas, _ = _drive(datum, yaw=math.pi / 2, v=1.0, duration=20.0)
    cfg = _cfg(datum)
    pose = (0.0, 0.0, math.pi / 2)
    res = run(Stream(meas, datum=datum, t0=0.0, t1=20.0),
              {"ekf": UnicycleEkf(cfg, initial_pose=pose),
               "ekf_igvc": IgvcEkf(cfg, datum=datum, initial_pose=pose)})
    err = res.runs["ekf_igvc"].error
    assert err is not None and err.startswith("PolarRegionError at t=")
    assert "singular within 10 km of a pole" in err
    assert res.runs["ekf"].error is None
    assert len(res.runs["ekf"].trajectory.t) > 150  # 10 Hz over 20 s
