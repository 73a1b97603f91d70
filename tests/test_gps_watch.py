"""The GPS watch: a sustained disagreement between GPS and the odometry's dead reckoning is
reported with its topic, start, end and size; agreeing data reports nothing."""

from __future__ import annotations

import math

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import parse_config_text
from ddfuse.estimation.gps_watch import MIN_FIXES, WINDOW_S, GpsWatch
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelOdometry

T0 = 1700000000.0
DATUM = (47.0, 8.0, 400.0)
CFG = """
sensors:
  odometry: [{topic: /odom, use: [v], noise: {v: 0.02}}]
  imu: [{topic: /imu, use: [yaw_rate], noise: {yaw_rate: 0.01}}]
  gps: [{topic: /fix, noise: {horizontal: 1.0}}]
frame: {datum: [47.0, 8.0, 400.0]}
"""


def _drive(duration: float, jump=None, seed: int = 1):
    """A robot driving a circle (1 m/s, 0.05 rad/s): odometry and gyro at 10 Hz, GPS at 2.5 Hz
    with 1 m noise; ``jump`` (t_start, t_end, dn) offsets the fixes in that interval north."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(int(duration * 10)):
        t = T0 + 0.1 * i
        out.append(WheelOdometry(t, 1.0, None, 4e-4, math.nan, "/odom"))
        out.append(GyroYawRate(t, 0.05, 1e-4, "/imu"))
        if i % 4 == 0:
            yaw = 0.05 * 0.1 * i
            e, n = 20.0 * math.sin(yaw), 20.0 * (1.0 - math.cos(yaw))
            e, n = e + rng.normal(), n + rng.normal()
            if jump and jump[0] <= t - T0 < jump[1]:
                n += jump[2]
            f = GpsFix(t, 0.0, 0.0, 0.0, np.diag([1.0, 1.0, 4.0]), 0, "/fix")
            f.enu = (e, n, 0.0)
            out.append(f)
    return out


def _watch(ms):
    w = GpsWatch(parse_config_text(CFG))
    for m in ms:
        w.feed(m)
    w.finish()
    return w


def test_agreeing_gps_and_odometry_report_nothing():
    w = _watch(_drive(120.0))
    assert w.on and w.episodes == [] and w.warnings() == []


def test_a_held_jump_is_one_episode_with_its_interval_and_size():
    w = _watch(_drive(120.0, jump=(60.0, 80.0, 50.0)))
    (ep,) = w.episodes
    assert ep.topic == "/fix"
    assert abs(ep.start - (T0 + 60.0)) < 0.5 and abs(ep.end - (T0 + 79.6)) < 0.5
    assert ep.fixes >= 45 and 40.0 < ep.size_m < 60.0 and ep.allowed_m < ep.size_m / 2
    (line,) = w.warnings()
    assert line.startswith("topic /fix: GPS disagreed with the odometry's dead reckoning from "
                           f"t={ep.start:.3f} to t={ep.end:.3f} (60.0-79.6 s into the input")


def test_each_compared_fix_carries_the_watch_verdict():
    """``GpsFix.odometry_agrees``: None for the fixes of the first WINDOW_S (nothing old enough
    to compare with), False inside a held jump, True elsewhere; the smoother reads it to tell
    a wrong estimate (the fixes move as the odometry does) from a wrong GPS."""
    ms = _drive(120.0, jump=(40.0, 60.0, 30.0))
    _watch(ms)
    fixes = [m for m in ms if isinstance(m, GpsFix)]
    for f in fixes:
        dt = f.t - T0
        if dt < WINDOW_S:
            assert f.odometry_agrees is None
        elif 40.0 <= dt < 60.0:
            assert f.odometry_agrees is False
        elif dt >= 60.0 + WINDOW_S or dt < 40.0:
            assert f.odometry_agrees is True


def test_a_jump_that_lasts_to_the_end_is_closed_there():
    (ep,) = _watch(_drive(90.0, jump=(60.0, 100.0, 50.0))).episodes
    assert abs(ep.end - (T0 + 89.6)) < 0.5


def test_fewer_than_min_fixes_flagged_are_no_episode():
    ms = _drive(60.0)
    fixes = [m for m in ms if isinstance(m, GpsFix)]
    for f in fixes[100:100 + MIN_FIXES - 1]:
        f.enu = (f.enu[0], f.enu[1] + 50.0, 0.0)
    assert _watch(ms).episodes == []


def test_rejected_twist_samples_do_not_move_the_dead_reckoning():
    w = GpsWatch(parse_config_text(CFG))
    ms = _drive(60.0)
    for m in ms:
        bad = isinstance(m, WheelOdometry) and abs(m.t - (T0 + 30.0)) < 1e-6
        if bad:
            m.v = 1e6
        w.feed(m, accepted=not bad)
    w.finish()
    assert w.episodes == []


def test_without_gps_or_odometry_the_watch_is_off():
    cfg = parse_config_text(CFG.replace("  gps: [{topic: /fix, noise: {horizontal: 1.0}}]\n", ""))
    assert not GpsWatch(cfg).on


def test_the_bag_stream_reports_an_episode_as_a_warning(tmp_path):
    recs = []
    for i in range(800):  # 80 s straight east at 1 m/s; fixes 50 m north from 40 s to 60 s
        t = T0 + 0.1 * i
        recs.append(("/odom", bw.odometry(t, 1.0, 0.0)))
        recs.append(("/imu", bw.imu(t, wcov=bw.diag(1e-4, 1e-4, 1e-4))))
        if i % 4 == 0:
            dn = 50.0 if 400 <= i < 600 else 0.0
            lat, lon, _ = geodesy.enu_to_geodetic(0.1 * i, dn, 0.0, *DATUM)
            recs.append(("/fix", bw.navsatfix(t, lat, lon, DATUM[2])))
    bag = bw.write_bag(tmp_path / "j.bag", "ros1", recs)
    # a generous top speed: the screen lets the jump through, the watch reports it
    bs = BagStream(bag, parse_config_text(CFG + "robot: {max_speed: 200.0}\n"))
    for _ in bs:
        pass
    (w,) = [w for w in bs.warnings if "disagreed" in w]
    assert w.startswith(f"{bag}: topic /fix: GPS disagreed with the odometry's dead reckoning "
                        f"from t={T0 + 40.0:.3f} to t={T0 + 59.6:.3f}")


@pytest.mark.parametrize("model", ["default", "gaussian", "dcs"])
def test_bursts_of_disagreement_suggest_a_robust_model_where_the_model_gates(tmp_path, model):
    """Three bursts of 40 m are three episodes; under a model that gates each fix the stream
    says once more what they look like and which model is for them; under a robust one not."""
    bag = bw.bursts_bag(tmp_path / "b.bag", DATUM)
    cfg = parse_config_text(CFG + f"robot: {{max_speed: 200.0}}\ngps: {{model: {model}}}\n")
    bs = BagStream(bag, cfg)
    for _ in bs:
        pass
    episodes = [w for w in bs.warnings if "dead reckoning from" in w]
    summary = [w for w in bs.warnings if "disagreed with the odometry 3 times" in w]
    assert len(episodes) == 3
    if model == "dcs":
        assert summary == []
    else:
        (w,) = summary
        assert f"gps.model '{model}' gates each fix" in w and "gps: {model: dcs}" in w
        assert "(15 fixes, up to 31 m)" in w  # the distances differ by 31 m at most
