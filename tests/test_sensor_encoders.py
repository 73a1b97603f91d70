"""Wheel encoders with GPS on a real-format bag: the simulator's husky-encoders scenario writes
the wheel speeds as a robot's driver does (sensor_msgs/JointState, no odometry) and NavSatFix
fixes in a ROS1 bag; every estimator the config allows runs on it (docs/design/sensors.md)."""

from __future__ import annotations

import pytest
import yaml
from ddfuse.estimation.config import parse_config_text
from ddfuse.evaluation.estimators import SPECS
from ddfuse.evaluation.simulate import get_scenario
from rosbags.highlevel import AnyReader
from sensor_runs import errors, sim_bag, variant

pytest.importorskip("gtsam")


def test_every_estimator_runs_on_wheel_encoders_and_gps(tmp_path):
    """40 s of husky-encoders: the bag holds JointState and NavSatFix (and the truth) only, its
    config wheels and gps; the estimators that config allows are ekf, ekf_igvc, smoother and
    batch (and dr), each runs and with the GPS stays within 0.5 m of the truth, at most half
    the error of the wheels alone (dr). The wheel speeds are the encoders' that husky's
    odometry twist is made from (same seed): the unicycle EKF fed the JointState gives the
    errors it gives on that twist (measured: equal to 1e-15 m; the smoother's to 5e-12 m)."""
    sc = get_scenario("husky-encoders")
    assert sc.imu is None and sc.encoders.joint_topic and not sc.encoders.odometry_topic
    bag, cfg = sim_bag(tmp_path, "husky-encoders", 0, 40.0)
    with AnyReader([bag]) as r:
        types = {c.topic: c.msgtype for c in r.connections}
    assert types["/joint_states"] == "sensor_msgs/msg/JointState"
    assert types["/fix"] == "sensor_msgs/msg/NavSatFix"
    assert set(cfg["sensors"]) == {"wheels", "gps"}
    allowed = [n for n, s in SPECS.items() if s.allowed(parse_config_text(yaml.safe_dump(cfg)))]
    assert set(allowed) == {"ekf", "ekf_igvc", "smoother", "batch", "dr"}
    e = errors(bag, cfg, allowed)
    for name in ("ekf", "ekf_igvc", "smoother", "batch"):
        assert e[name].n > (100 if name == "batch" else 300), name  # batch: keyframes
        assert e[name].pos_rmse < 0.5, (name, e[name])
        assert e[name].pos_rmse < 0.5 * e["dr"].pos_rmse, (name, e[name], e["dr"])
    odo_bag, odo_cfg = sim_bag(tmp_path, "husky", 0, 40.0)
    odo = errors(odo_bag, variant(odo_cfg, imu=None), ["ekf"])["ekf"]
    assert e["ekf"].pos_rmse == pytest.approx(odo.pos_rmse, abs=1e-9)
