"""The start pose from the GPS course (``ddfuse.estimation.gps_course``): what it buffers, when
it decides and what it returns, on a synthetic straight drive (no gtsam, no bag)."""

import math

import numpy as np
import pytest
from ddfuse.estimation.gps_course import INIT_DISTANCE, GpsCourseStart
from ddfuse.estimation.measurements import GpsFix, WheelOdometry

HEADING = 0.7  # rad, ENU yaw of the drive
SPEED = 1.0  # m/s


def _drive(fix_var: float, t_move: float = 2.0, t_end: float = 30.0, odo_speed: float = SPEED):
    """Odometry at 10 Hz from ``t_move`` on (``odo_speed``), and exact fixes at 1 Hz from 0.5 s
    on: standing at (10, 20), then SPEED along HEADING from ``t_move``; covariance ``fix_var``
    m^2."""
    out = []
    for i in range(int(t_end * 10) + 1):
        t = 0.1 * i
        if t >= t_move:
            out.append(WheelOdometry(t, odo_speed, 0.0, 1e-4, 1e-4))
        if i % 10 == 5:
            d = SPEED * max(t - t_move, 0.0)
            e, n = 10.0 + d * math.cos(HEADING), 20.0 + d * math.sin(HEADING)
            out.append(GpsFix(t, 0.0, 0.0, 0.0, np.diag((fix_var, fix_var, 1.0)), 0, "/fix",
                              (e, n, 0.0)))
    return out


def _feed(course, ms):
    for m in ms:
        got = course.add(m)
        if got is not None:
            return m, got
    return None, None


def _course(**kw):
    return GpsCourseStart(gyro_names=set(), fixed_bias=0.0, wheel_radius=0.1, track_width=0.5,
                          min_psi_sigma=0.2, odometry_wait=0.5, **kw)


def test_decides_after_the_distance_with_the_heading_and_position_of_the_first_fix():
    ms = _drive(0.01)
    course = _course()
    last, got = _feed(course, ms)
    assert got is not None
    # the baseline starts at the first fix the moving odometry covers (odometry_wait before it)
    first = next(m for m in ms if isinstance(m, GpsFix) and m.t >= 2.0 - 0.5)
    assert got.t == first.t and got.position == pytest.approx(first.enu[:2])
    assert got.heading == pytest.approx(HEADING, abs=1e-9)  # the drive is straight and exact
    assert got.psi_sigma == 0.2 and got.pos_sigma == pytest.approx(0.1)
    # decided at the first fix at least INIT_DISTANCE from the baseline's start
    assert isinstance(last, GpsFix)
    assert math.dist(last.enu[:2], first.enu[:2]) >= INIT_DISTANCE
    assert math.dist(last.enu[:2], first.enu[:2]) < INIT_DISTANCE + SPEED
    # replay: everything buffered from the start on; dropped: the standing fixes before it
    assert got.replay[0].t >= got.t and got.replay[-1] is last
    assert [f.t for f in got.dropped] == [0.5]
    assert course.buffer == [] and course.last_fix is None


def test_poor_fixes_wait_for_a_longer_baseline_and_state_a_wider_sigma():
    good = _feed(_course(), _drive(0.01))[1]
    last, poor = _feed(_course(), _drive(4.0))
    # 2 m fixes: the course's sigma sqrt(4 + 4) / d reaches 0.4 rad only at d >= 7.1 m
    assert math.dist(last.enu[:2], poor.position) >= math.sqrt(8.0) / 0.4
    assert poor.psi_sigma > good.psi_sigma and poor.pos_sigma == pytest.approx(2.0)


def test_waits_while_the_odometry_disagrees_about_having_moved():
    ms = _drive(0.01, odo_speed=0.05)  # the fixes move 28 m, the wheels 1.4 m (slipping)
    course = _course()
    assert _feed(course, ms) == (None, None)
    assert len(course.buffer) == len(ms) and course.last_fix is not None
