"""A heading sensor's ``correlation_time`` (estimation.heading_correlation): each yaw sample
fused with its variance times the Gauss-Markov inflation of the time since the sensor's
previous sample, by every estimator alike; the gate and the NIS keep the stated variance.

On a drive whose compass error is Gauss-Markov (sigma 0.03 rad, tau 3 s, 50 Hz) and stated as
its stationary variance: fused as white, the estimators' heading is over-confident (NEES far
above 1); with the key, honest."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import ConfigError, parse_config
from ddfuse.estimation.gps_correlation import inflation
from ddfuse.estimation.heading_correlation import HeadingClock
from ddfuse.estimation.measurements import GyroYawRate, Heading, WheelOdometry
from test_ekf_compiled import _config, _run_both, _stream

SIGMA, TAU, RATE = 0.03, 3.0, 50.0


def _cfg(tau: float | None, kind: str = "imu", smoother: bool = False):
    imu = {"topic": "/imu", "use": ["yaw", "yaw_rate"], "noise": {"yaw": SIGMA,
                                                                  "yaw_rate": 0.01}}
    if tau is not None:
        imu["correlation_time"] = tau
    raw = {"sensors": {"odometry": [{"topic": "/odom", "use": ["v"], "noise": {"v": 0.05}}],
                       "imu": [imu]},
           "initial_pose": [0.0, 0.0, 0.3], "ekf": {"rate": "event"}}
    if smoother:
        raw["smoother"] = {"lag": 5.0, "keyframe": "rate", "keyframe_rate": 5.0}
    return parse_config(raw)


def _drive(seed: int, duration: float = 30.0):
    """(stream, truth (t, yaw)): 1 m/s with a wavering yaw rate; a 50 Hz gyro (white, 0.01
    rad/s), 10 Hz odometry speed, a 50 Hz compass whose error is Gauss-Markov."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE
    rho = math.exp(-dt / TAU)
    e = rng.normal(0.0, SIGMA)
    yaw = 0.3
    out, truth = [], []
    for k in range(int(duration * RATE)):
        t = k * dt
        w = 0.3 * math.sin(0.2 * t)
        yaw += w * dt
        e = rho * e + math.sqrt(1.0 - rho * rho) * rng.normal(0.0, SIGMA)
        out.append(GyroYawRate(t, w + rng.normal(0.0, 0.01), 1e-4, "/imu"))
        z = (yaw + e + math.pi) % (2.0 * math.pi) - math.pi
        out.append(Heading(t, z, SIGMA * SIGMA, "/imu", "imu_orientation"))
        if k % 5 == 2:
            out.append(WheelOdometry(t, 1.0 + rng.normal(0.0, 0.05), None, 0.0025, 0.0, "/odom"))
        truth.append((t, yaw))
    return out, np.array(truth)


def _heading_nees(est, stream, truth) -> float:
    """Mean of (yaw error)^2 / var(yaw) over the estimates after the first 5 s."""
    yaw_at = dict(zip(truth[:, 0].tolist(), truth[:, 1].tolist(), strict=True))
    nees = []
    for m in stream:
        est.process(m)
        e = est.estimate()
        if e is None or e.t < 5.0 or e.t not in yaw_at:
            continue
        d = (float(e.pose[2]) - yaw_at[e.t] + math.pi) % (2.0 * math.pi) - math.pi
        nees.append(d * d / float(e.pose_cov[2, 2]))
    est.finish()
    return float(np.mean(nees))


def _sample(t: float, sensor: str = "/imu") -> Heading:
    return Heading(t, 0.1, 1e-4, sensor, "imu_orientation")


def test_clock_factor_from_the_previous_sample_and_asked_again():
    clock = HeadingClock(_cfg(TAU))
    assert clock.factor(_sample(1.0)) == 1.0  # the first sample
    f = clock.factor(_sample(1.02))
    assert f == pytest.approx(inflation(0.02, TAU)) and f > 250.0  # white: off by 300x
    # a fixed-rate step's samples handed again to the Python path: the same factors
    assert clock.factor(_sample(1.04)) == pytest.approx(f)
    assert clock.factor(_sample(1.02)) == f and clock.factor(_sample(1.0)) == 1.0
    assert clock.factor(_sample(21.04)) == pytest.approx(1.0, abs=1e-2)  # 20 s on
    assert clock.factor(_sample(21.06, "/other")) == 1.0  # a sensor without the key
    white = HeadingClock(_cfg(None))
    assert not white and [white.factor(_sample(t)) for t in (1.0, 1.02)] == [1.0, 1.0]


@pytest.mark.parametrize("kind", ["imu", "magnetometer", "local_heading"])
def test_config_key_on_heading_sensors(kind):
    raw = {"topic": "/h", "correlation_time": 2.5}
    if kind == "imu":
        raw["use"] = ["yaw"]
    cfg = parse_config({"sensors": {kind: [raw]}})
    assert cfg.sensors[0].correlation_time == 2.5
    assert HeadingClock(cfg).tau == {"/h": 2.5}
    with pytest.raises(ConfigError, match=rf"sensors\.{kind}\[0\]\.correlation_time"):
        parse_config({"sensors": {kind: [dict(raw, correlation_time=-1.0)]}})


@pytest.mark.slow
@pytest.mark.parametrize("rate", ["event", 10.0])
def test_compiled_matches_reference_with_a_correlated_heading(rate):
    """The kernels' fusion factor for heading samples is the reference's, event-driven and
    in fixed-rate steps (several samples of one sensor per step)."""
    stream = _stream(3, duration=20.0)

    def make(reference):
        cfg = _config(True, rate)
        cfg.sensor("/imu").correlation_time = 2.0
        return UnicycleEkf(cfg, reference=reference)

    _run_both(make, stream)


@pytest.mark.parametrize("make", [
    pytest.param(lambda cfg: UnicycleEkf(cfg), id="ekf"),
    pytest.param(lambda cfg: UnicycleEkf(cfg, reference=True), id="ekf_reference"),
    pytest.param(lambda cfg: IgvcEkf(cfg), id="ekf_igvc"),
])
def test_ekf_heading_honest_with_the_key_over_confident_without(make):
    stream, truth = _drive(1)
    white = _heading_nees(make(_cfg(None)), stream, truth)
    corr = _heading_nees(make(_cfg(TAU)), stream, truth)
    assert white > 10.0  # 50 samples a second taken as independent
    assert 0.3 < corr < 3.0


def test_ekf_nis_keeps_the_stated_variance():
    """The logged heading innovations' S is H P H' + the sample's stated variance, not the
    inflated one the fusion used."""
    stream, _ = _drive(2, duration=10.0)
    ekf = UnicycleEkf(_cfg(TAU), reference=True)
    for m in stream:
        ekf.process(m)
    ekf.finish()
    heads = [i for i in ekf.log.innovations if i.kind == "heading" and i.accepted]
    assert len(heads) > 400
    # S = P_psi + stated var; the inflated one would be 300x the var
    assert max(float(i.cov[0, 0]) for i in heads) < 2.0 * SIGMA * SIGMA + 0.01


def test_smoother_heading_honest_with_the_key_over_confident_without():
    """The smoother averages a keyframe's samples into one factor: fused as white, their
    variance divided by their number (10 per keyframe here)."""
    from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother

    stream, truth = _drive(1)
    white = _heading_nees(FixedLagSmoother(_cfg(None, smoother=True)), stream, truth)
    corr = _heading_nees(FixedLagSmoother(_cfg(TAU, smoother=True)), stream, truth)
    assert white > 10.0
    assert 0.3 < corr < 3.0
