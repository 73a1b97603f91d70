"""An estimate as ROS message fields: the planar pose, covariance and twist laid into ROS's
6x6 layout and REP-105 frames, and the position back to latitude/longitude."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.estimate_msgs import (
    PLANAR_VARIANCE,
    TWIST_UNKNOWN_VARIANCE,
    fix_of,
    odometry_of,
    transform_of,
)
from ddfuse.estimation.estimator import Estimate
from scipy.spatial.transform import Rotation

P = np.array([[0.5, 0.1, 0.02], [0.1, 0.3, -0.01], [0.02, -0.01, 0.04]])


def _estimate(names=("x", "y", "psi", "v", "w")):
    state = np.array([3.0, -4.0, 2.5, 1.2, -0.3])
    cov = np.diag([0.5, 0.3, 0.04, 0.01, 0.002])
    cov[3, 4] = cov[4, 3] = 0.001
    return Estimate(12.5, (3.0, -4.0, 2.5), P, state=state, state_cov=cov, state_names=names)


def test_pose_covariance_goes_to_rows_x_y_yaw_and_the_planar_axes_are_tight():
    o = odometry_of(_estimate(), "map", "base_link")
    assert (o.frame_id, o.child_frame_id, o.stamp) == ("map", "base_link", 12.5)
    c = np.array(o.pose_covariance).reshape(6, 6)
    assert np.allclose(c[np.ix_((0, 1, 5), (0, 1, 5))], P)
    assert np.allclose(np.diag(c)[2:5], PLANAR_VARIANCE)
    assert np.all(np.linalg.eigvalsh(c) > 0) and np.allclose(c, c.T)
    assert o.position == (3.0, -4.0, 0.0)
    yaw = Rotation.from_quat(o.orientation).as_euler("ZYX")[0]
    assert yaw == pytest.approx(2.5)


@pytest.mark.parametrize("names", [("x", "y", "psi", "v", "w"),
                                   ("x", "y", "psi", "v", "psi_dot")])
def test_twist_in_the_base_frame_from_the_speed_and_yaw_rate_states(names):
    o = odometry_of(_estimate(names), "map", "base_link")
    assert o.linear == (1.2, 0.0, 0.0) and o.angular == (0.0, 0.0, -0.3)
    c = np.array(o.twist_covariance).reshape(6, 6)
    assert c[0, 0] == 0.01 and c[5, 5] == 0.002 and c[0, 5] == c[5, 0] == 0.001
    assert np.all(np.linalg.eigvalsh(c) > 0)


def test_an_estimator_without_a_twist_says_so_with_a_huge_variance():
    e = Estimate(1.0, (0.0, 0.0, 0.0), P)
    o = odometry_of(e, "map", "base_link")
    c = np.array(o.twist_covariance).reshape(6, 6)
    assert o.linear == (0.0, 0.0, 0.0) and c[0, 0] == c[5, 5] == TWIST_UNKNOWN_VARIANCE


def test_the_fix_lands_where_the_local_position_is_about_the_datum():
    datum = (43.47, -80.54, 330.0)
    f = fix_of(_estimate(), datum, "base_link")
    e, n, u = geodesy.geodetic_to_enu(f.latitude, f.longitude, f.altitude, *datum)
    assert (e, n) == pytest.approx((3.0, -4.0), abs=1e-6) and abs(u) < 1e-6
    c = np.array(f.position_covariance).reshape(3, 3)
    assert np.allclose(c[:2, :2], P[:2, :2]) and f.position_covariance_type == 3


def test_a_non_finite_covariance_is_sent_as_nan_never_as_exact():
    e = Estimate(1.0, (0.0, 0.0, 0.0), np.full((3, 3), math.nan))
    c = np.array(odometry_of(e, "map", "base_link").pose_covariance).reshape(6, 6)
    assert np.isnan(c[0, 0]) and np.isnan(c[5, 5])


def test_the_transform_is_the_robots_pose():
    t = transform_of(_estimate(), "map", "base_link")
    assert t.translation == (3.0, -4.0, 0.0)
    assert t.rotation == odometry_of(_estimate(), "map", "base_link").orientation


def test_the_tf_source_is_the_configured_estimator_else_the_smoother_else_the_first():
    from ddfuse.estimation.estimate_msgs import tf_source

    assert tf_source(["ekf", "smoother"]) == "smoother"
    assert tf_source(["ekf", "ekf_igvc"]) == "ekf"
    assert tf_source(["ekf", "smoother"], "ekf") == "ekf"
    assert tf_source(["ekf", "smoother"], "none") is None
    assert tf_source(["batch", "smoother"], "ekf") == "smoother"  # not run: the default rule
    assert tf_source([]) is None
