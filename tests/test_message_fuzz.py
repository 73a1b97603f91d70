"""One bad message value must not cost a track: data/sample_husky.bag with one field of one
message (or of a burst of 5 or 10 consecutive messages of its topic) set to a hostile value,
drawn per case from its own seed; every estimator runs without an error and ends within 1.5x
its clean ATE + 0.05 m. The campaign this keeps (428 cases, the class it found):
docs/results/message_fuzz.md."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.runner import run
from ddfuse.evaluation import estimators as registry
from hostile_corpus import SAMPLE_BAG, SAMPLE_CONFIG, Bag

pytestmark = pytest.mark.slow

FIELDS = {
    "/odom": ["twist.twist.linear.x", "twist.twist.angular.z", "twist.covariance[0]",
              "twist.covariance[35]", "pose.pose.position.x", "header.stamp"],
    "/imu/data": ["orientation.x", "orientation.z", "orientation.w", "angular_velocity.z",
                  "linear_acceleration.x", "orientation_covariance[8]",
                  "angular_velocity_covariance[8]", "header.stamp"],
    "/fix": ["latitude", "longitude", "altitude", "position_covariance[0]",
             "position_covariance[1]", "status.status", "header.stamp"],
}
VALUES = {"nan": lambda c: math.nan, "inf": lambda c: math.inf, "-inf": lambda c: -math.inf,
          "0": lambda c: 0.0, "-1": lambda c: -1.0, "1e12": lambda c: 1e12,
          "-1e12": lambda c: -1e12, "x1000": lambda c: c * 1000.0, "neg": lambda c: -c}
STAMPS = {"back 1 s": -1.0, "back 1000 s": -1000.0, "ahead 0.5 s": 0.5, "ahead 1e6 s": 1e6}
CASES = 24
# the class the campaign found, always in: a wheel driver's dropout of 0.5 s and a second of
# reversed speeds (before: smoother 0.313 and 1.228 m ATE against 0.101 clean)
FOUND = [("/odom", "twist.twist.linear.x", "0", 5, 0.3),
         ("/odom", "twist.twist.linear.x", "neg", 10, 0.6)]


def _set(msg, path: str, value: str) -> None:
    *parents, last = path.split(".")
    obj = msg
    for p in parents:
        obj = getattr(obj, p)
    if last == "stamp":
        st = obj.stamp
        t = st.sec + st.nanosec * 1e-9 + STAMPS[value]
        st.sec, st.nanosec = int(t), int(round((t - int(t)) * 1e9)) % 1_000_000_000
    elif last.endswith("]"):
        name, idx = last[:-1].split("[")
        arr = np.array(getattr(obj, name), dtype=np.float64)
        arr[int(idx)] = VALUES[value](arr[int(idx)])
        setattr(obj, name, arr)
    elif isinstance(getattr(obj, last), int):  # NavSatStatus.status, an int8
        v = VALUES[value](float(getattr(obj, last)))
        setattr(obj, last, int(max(-128, min(127, v))) if math.isfinite(v) else -1)
    else:
        setattr(obj, last, float(VALUES[value](getattr(obj, last))))


def _case(i: int) -> tuple[str, str, str, int, float]:
    rng = random.Random(7000 + i)
    topic = rng.choice(sorted(FIELDS))
    field = rng.choice(FIELDS[topic])
    value = rng.choice(sorted(STAMPS if field == "header.stamp" else VALUES))
    burst = rng.choice([1, 1, 5, 10])
    return topic, field, value, burst, rng.uniform(0.1, 0.9)


def _ate(bag, cfg) -> dict[str, float]:
    stream = read_stream(bag, cfg)
    runs = run(stream, registry.build(cfg, stream, registry.select(cfg, None))).runs
    gt = np.array([(g.t, g.x, g.y) for g in stream.ground_truth])
    out = {}
    for name, r in runs.items():
        assert r.error is None, f"{name}: {r.error}"
        t, p = np.asarray(r.trajectory.t), np.asarray(r.trajectory.pose)
        e = np.hypot(p[:, 0] - np.interp(t, gt[:, 0], gt[:, 1]),
                     p[:, 1] - np.interp(t, gt[:, 0], gt[:, 2]))
        out[name] = float(np.sqrt(np.mean(e * e)))
    return out


@pytest.fixture(scope="module")
def clean():
    cfg = load_config(SAMPLE_CONFIG)
    return cfg, Bag.read(SAMPLE_BAG), _ate(SAMPLE_BAG, cfg)


@pytest.mark.parametrize("case", [_case(i) for i in range(CASES)] + FOUND,
                         ids=[f"random{i}" for i in range(CASES)] + ["dropout", "reversed"])
def test_one_hostile_value_keeps_every_track(case, clean, tmp_path):
    cfg, source, ref = clean
    topic, field, value, burst, at = case
    bag = Bag(source.conns, [list(r) for r in source.records], source.store)
    recs = bag.of(topic)
    k = int(at * (len(recs) - burst))
    for rec in recs[k:k + burst]:
        bag.edit(rec, lambda m: _set(m, field, value))
    ate = _ate(bag.write(tmp_path / "case.bag"), cfg)
    what = f"{topic} {field} = {value} on {burst} message(s) from #{k}"
    assert ate.keys() == ref.keys(), what
    worse = {n: (round(a, 3), round(ref[n], 3)) for n, a in ate.items()
             if not a <= 1.5 * ref[n] + 0.05}
    assert not worse, f"{what}: ATE (hostile, clean) {worse}"
