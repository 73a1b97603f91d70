"""Seed 002's known-map landmark EKF on the real MRCLAM bag (slow; skips without the data).

Facts from ../shared/data/README-mrclam1_robot1.md: dead reckoning from the ground-truth start
ends 3.6 m and 97 deg off; range residuals have a robust sigma of 0.085 m, bearing residuals
0.018 rad (the messages' nominal 0.1 m / 0.05 rad); the robot stands still for 9.5 s and the
sightings come in bursts with gaps up to 36.6 s, which is where a Mahalanobis gate locks out.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import shared_bag
from ddfuse.ekf_baseline.landmark import LandmarkEkf
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import parse_config
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.measurements import WheelOdometry

pytestmark = pytest.mark.slow

MEASURED_RANGE_SIGMA = 0.085  # m, README-mrclam1_robot1.md
MEASURED_BEARING_SIGMA = 0.018  # rad


def _cfg(bag, noise: dict | None = None, gate=0.9999):
    lm = {"topic": "/landmarks", "map": str(bag.parent / "mrclam1_robot1.landmarks.yaml"),
          "gate": gate}
    if noise:
        lm["noise"] = noise
    return parse_config({
        "sensors": {"odometry": [{"topic": "/odom", "use": ["v", "yaw_rate"]}],
                    "landmarks": [lm]},
        "ground_truth": {"topic": "/ground_truth"},
        "initial_pose": "ground_truth",
    })


@pytest.fixture(scope="module")
def streams():
    """Both configs' streams, read once for the module (reading takes a few seconds)."""
    bag = shared_bag("mrclam1_robot1.bag")
    nominal = _cfg(bag)
    measured = _cfg(bag, {"range": MEASURED_RANGE_SIGMA, "bearing": MEASURED_BEARING_SIGMA})
    try:
        return {"nominal": (nominal, read_stream(bag, nominal)),
                "measured": (measured, read_stream(bag, measured))}
    except BagError as e:
        if "header stamps jump" not in str(e):
            raise
        # Known reader bug (reported): read_stream caches decoded messages by id(raw), and
        # CPython reuses the id of a freed bytes object, so about a third of the landmark
        # messages decode as a stale earlier one. The bag itself is fine (stamps = record
        # times). This marks the tests xfail only for that exact symptom.
        pytest.xfail(f"ddfuse.estimation.bags.read_stream id(raw) decode cache: {e}")


def _run(cfg, stream, odometry_only=False):
    """Run a LandmarkEkf from the first ground-truth pose; position and yaw errors at every
    ground-truth stamp (the odometry and the ground truth share the 0.02 s grid)."""
    truth = {round(g.t, 2): g for g in stream.ground_truth}
    g0 = stream.ground_truth[0]
    ekf = LandmarkEkf(cfg, initial_pose=(g0.x, g0.y, g0.yaw))
    meas = [m for m in stream.measurements
            if not odometry_only or isinstance(m, WheelOdometry)]
    pos, yaw = [], []
    for i, m in enumerate(meas):
        ekf.process(m)
        if i + 1 < len(meas) and meas[i + 1].t == m.t:
            continue
        g = truth.get(round(m.t, 2))
        if g is None:
            continue
        e = ekf.estimate()
        pos.append(math.hypot(e.pose[0] - g.x, e.pose[1] - g.y))
        yaw.append((e.pose[2] - g.yaw + math.pi) % (2 * math.pi) - math.pi)
    return ekf, np.array(pos), np.array(yaw)


def _rmse(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2)))


def test_stream_matches_the_readme(streams):
    cfg, s = streams["nominal"]
    # 75000 truth messages; the 30 samples of the resampled Vicon yaw's 17 full-turn spins
    # (at the default 10 rad/s limit) are left out (estimation.truth_screen)
    assert len(s.ground_truth) == 75000 - 30
    assert sum(isinstance(m, WheelOdometry) for m in s.measurements) == 75000
    assert len(s.measurements) - 75000 == 4771
    assert len(s.landmarks) == 15


def test_known_map_ekf_beats_dead_reckoning(streams):
    cfg, s = streams["nominal"]
    _, dr_pos, dr_yaw = _run(cfg, s, odometry_only=True)
    ekf, pos, yaw = _run(cfg, s)
    rmse, dr = _rmse(pos), _rmse(dr_pos)
    print(f"\nMRCLAM known-map EKF (nominal noise): position RMSE {rmse:.3f} m, max {pos.max():.3f}"
          f" m, final {pos[-1]:.3f} m, yaw RMSE {_rmse(yaw):.3f} rad; dead reckoning RMSE "
          f"{dr:.3f} m, final {dr_pos[-1]:.2f} m / {math.degrees(abs(dr_yaw[-1])):.0f} deg; "
          f"gate rejections {ekf.rejected[('/landmarks', 'gate')]}, "
          f"recoveries {len(ekf.kf.recoveries)}")
    # the README's dead-reckoning facts: the same odometry path gives the same end error
    assert dr_pos[-1] == pytest.approx(3.6, abs=0.1)
    assert math.degrees(abs(dr_yaw[-1])) == pytest.approx(97, abs=2)
    # three times the measured range sigma: the landmarks are ~1-5 m away, bursts are sparse
    assert rmse < 3 * MEASURED_RANGE_SIGMA
    assert dr > 3 * rmse
    assert pos[-1] < 3 * MEASURED_RANGE_SIGMA
    acc = [i for i in ekf.innovations if i.accepted]
    assert len(acc) > 0.95 * 4771


def test_gate_lockout_is_recovered_with_the_measured_noise(streams):
    """With the measured (tighter) sigmas the gate locks out during the sighting gaps; the
    core's recovery must keep the filter on the landmarks."""
    cfg, s = streams["measured"]
    ekf, pos, yaw = _run(cfg, s)
    rmse = _rmse(pos)
    print(f"\nMRCLAM known-map EKF (measured noise, gate 0.9999): position RMSE {rmse:.3f} m, "
          f"max {pos.max():.3f} m, yaw RMSE {_rmse(yaw):.3f} rad, gate rejections "
          f"{ekf.rejected[('/landmarks', 'gate')]}, lock-out recoveries {len(ekf.kf.recoveries)}")
    assert ekf.kf.recoveries, "expected the gate to lock out at least once on this bag"
    assert rmse < 3 * MEASURED_RANGE_SIGMA
    assert pos.max() < 1.5
    assert pos[-1] < 3 * MEASURED_RANGE_SIGMA
