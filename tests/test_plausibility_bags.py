"""Issue 32's cases end to end on the sample bag: one absurd odometry sample, one absurd gyro
sample and a GPS jump held for 20 s leave every estimator within a small factor of its clean
error, and the run's warnings name the topic."""

from __future__ import annotations

from pathlib import Path

import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation.pipeline import run_bag
from rosbags.rosbag1 import Reader, Writer
from rosbags.typesys import Stores, get_typestore

DATA = Path(__file__).resolve().parents[1] / "data"
BAG, CFG = DATA / "sample_husky.bag", DATA / "sample_husky.yaml"
AT = 60.0  # s after the bag's start: where the glitch goes
ESTIMATORS = ["ekf", "ekf_igvc", "smoother", "smoother_lagged", "batch"]


def _edited(out: Path, edit) -> Path:
    """A copy of the sample bag with ``edit(topic, t_rel, msg)`` applied to each message of
    /odom, /imu/data and /fix (returns the message to write, edited or not)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    with Reader(BAG) as r, Writer(out) as w:
        t0 = r.start_time * 1e-9
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                        md5sum=c.digest) for c in r.connections}
        for c, ts, raw in r.messages():
            if c.topic in ("/odom", "/imu/data", "/fix"):
                msg = edit(c.topic, ts * 1e-9 - t0, store.deserialize_ros1(raw, c.msgtype))
                if msg is not None:
                    raw = store.serialize_ros1(msg, c.msgtype)
            w.write(conns[c.id], ts, raw)
    return out


def _once(topic: str, set_value):
    done = []

    def edit(tp, t, msg):
        if tp == topic and t >= AT and not done:
            done.append(t)
            set_value(msg)
            return msg
        return None

    return edit


def _jump(tp, t, msg):
    if tp == "/fix" and AT <= t < AT + 20.0:
        msg.latitude += 50.0 / 111320.0  # 50 m north
        return msg
    return None


def _set_v(value):
    def f(m):
        m.twist.twist.linear.x = value
    return f


def _set_gyro(m):
    m.angular_velocity.z = 30.0


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    out = tmp_path_factory.mktemp("clean")
    return run_bag(BAG, load_config(CFG), out, names=ESTIMATORS)


@pytest.mark.slow
@pytest.mark.parametrize("case,edit,topic,factor", [
    ("v1e6", _once("/odom", _set_v(1e6)), "/odom", 1.2),
    ("v20", _once("/odom", _set_v(20.0)), "/odom", 1.2),
    ("gyro30", _once("/imu/data", _set_gyro), "/imu/data", 1.2),
    ("jump", _jump, "/fix", 1.5),
])
def test_an_implausible_sample_costs_no_estimator_its_track(tmp_path, clean, case, edit, topic,
                                                           factor):
    bag = _edited(tmp_path / f"{case}.bag", edit)
    m = run_bag(bag, load_config(CFG), tmp_path / "out", names=ESTIMATORS)
    for name in ESTIMATORS:
        ate, ref = m.estimators[name].ate_rmse_m, clean.estimators[name].ate_rmse_m
        assert ate <= factor * ref, (name, ate, ref)
    warned = [w for w in m.warnings
              if f"topic {topic}: " in w and "sample(s) rejected as physically implausible" in w]
    assert len(warned) == 1
    if case == "jump":
        (w,) = [w for w in m.warnings if "disagreed" in w]
        assert "60.0-79.6 s into the input" in w
