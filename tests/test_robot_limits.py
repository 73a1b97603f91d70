"""The plausibility screen: twist samples and GPS fixes the robot cannot produce are rejected and
counted before any estimator, with one warning line per topic; the anchor re-anchors."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.bags import BagStream, read_stream
from ddfuse.estimation.config import load_config, parse_config_text
from ddfuse.estimation.live import LiveConverter
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, WheelOdometry, WheelSpeeds
from ddfuse.estimation.robot_limits import HOLD_S, REANCHOR, TWIST_HOLD_S, RobotLimits

ROOT = Path(__file__).resolve().parents[1]
T0 = 1700000000.0
DATUM = (47.0, 8.0, 400.0)

ODOM_GPS = """
sensors:
  odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.02, yaw_rate: 0.02}}]
  imu: [{topic: /imu, use: [yaw_rate], noise: {yaw_rate: 0.01}}]
  gps: [{topic: /fix, noise: {horizontal: 1.0}}]
  wheels: [{topic: /joints, joints: [l, r], noise: {speed: 0.05}}]
robot: {wheel_radius: 0.1, track_width: 0.5%s}
frame: {datum: [47.0, 8.0, 400.0]}
"""


def _screen(robot: str = ", max_speed: 1.5, max_yaw_rate: 2.0"):
    rejected: Counter = Counter()
    return RobotLimits(parse_config_text(ODOM_GPS % robot), rejected), rejected


def _odo(i: int, v: float, w: float = 0.1) -> WheelOdometry:
    return WheelOdometry(T0 + 0.1 * i, v, w, 0.02 ** 2, 0.02 ** 2, "/odom")


def _fix(t: float, e: float, n: float, sd: float = 1.0) -> GpsFix:
    f = GpsFix(t, 0.0, 0.0, 0.0, np.diag([sd * sd, sd * sd, 4.0]), 0, "/fix")
    f.enu = (e, n, 0.0)
    return f


def _speeds(values: list[float]) -> list[WheelOdometry]:
    return [_odo(i, v) for i, v in enumerate(values)]


def test_a_speed_beyond_the_top_speed_is_rejected_and_counted():
    screen, rejected = _screen()
    values = [1.0] * 20
    values[10] = 1e6
    passed = [screen.admit(m) for m in _speeds(values)]
    assert passed == [i != 10 for i in range(20)]
    ((topic, reason), n), = rejected.items()
    assert (topic, n) == ("/odom", 1) and "robot.max_speed" in reason
    (w,) = screen.warnings()
    assert w.startswith("topic /odom: 1 sample(s) rejected") and "speed 1e+06 m/s" in w
    assert "limit 1.5 m/s" in w and f"t={T0 + 1.0:.3f}" in w


def test_one_warning_line_per_topic_and_reason_with_the_count():
    screen, rejected = _screen()
    values = [1.0] * 30
    values[5] = values[15] = values[25] = 1e6
    for m in _speeds(values):
        screen.admit(m)
    (w,) = screen.warnings()
    assert "3 sample(s)" in w and f"t={T0 + 0.5:.3f}" in w  # the first one's time


def test_a_jump_within_the_top_speed_but_beyond_the_acceleration_is_rejected():
    screen, rejected = _screen("")  # default limits: 50 m/s, 20 m/s^2
    values = [1.0] * 20
    values[10] = 20.0
    assert [screen.admit(m) for m in _speeds(values)] == [i != 10 for i in range(20)]
    ((_, reason), n), = rejected.items()
    assert n == 1 and "robot.max_accel" in reason


def test_the_configured_max_accel_is_the_acceleration_limit():
    screen, _ = _screen(", max_accel: 0.5")
    # 0.3 m/s in 0.1 s is 3 m/s^2: beyond 0.5 m/s^2 plus 6 sigma (0.17 m/s)
    assert [screen.admit(m) for m in _speeds([1.0, 1.0, 1.3, 1.0])] == [True, True, False, True]


def test_a_glitch_as_the_first_sample_re_anchors_after_consecutive_agreeing_ones():
    screen, rejected = _screen("")
    values = [20.0] + [1.0] * 10
    passed = [screen.admit(m) for m in _speeds(values)]
    # the glitch is the anchor; REANCHOR samples agreeing with each other replace it, and
    # the next one, fitting them, is passed on
    assert passed == [True] + [False] * REANCHOR + [True] * (10 - REANCHOR)
    assert sum(rejected.values()) == REANCHOR


def test_a_real_step_faster_than_the_limit_is_followed_after_the_re_anchor():
    """Against an anchor not yet confirmed by REANCHOR samples the run re-anchors at once;
    against a confirmed one once it spans TWIST_HOLD_S; either way the sample after the
    re-anchoring one is the first passed on."""
    screen, _ = _screen("")
    values = [0.0] * 4 + [15.0] * 10  # 150 m/s^2 for one period: beyond the default 20
    passed = [screen.admit(m) for m in _speeds(values)]
    assert passed == [True] * 4 + [False] * REANCHOR + [True] * (10 - REANCHOR)
    screen, _ = _screen(", max_accel: 0.5")  # 3 m/s from 0 would take 6 s at the limit
    ms = _speeds([0.0] * 10 + [3.0] * 30)
    passed = [screen.admit(m) for m in ms]
    held = next(i for i in range(10, 40) if ms[i].t - ms[10].t >= TWIST_HOLD_S)
    assert passed == [True] * 10 + [False] * (held - 9) + [True] * (39 - held)


@pytest.mark.parametrize("n", [REANCHOR, REANCHOR + 2, 10])
def test_a_dropout_shorter_than_the_hold_reaches_no_estimator(n):
    """A wheel-speed driver that reports 0 for up to a second while the robot drives at 1 m/s
    (stated max_accel 0.5 m/s^2). Before, the REANCHOR-th zero was passed on and the return
    rejected for REANCHOR - 1 samples: on data/sample_husky.bag the smoother held 0.5 s of
    standing still and its ATE went 0.101 -> 0.313 m for the rest of the run (batch 0.082 ->
    0.247; 10 zeros: 0.607 m). Now a run against a confirmed anchor waits TWIST_HOLD_S, and
    the sample after it decides: back at the old anchor's speed, it is passed and the zeros
    never are."""
    screen, rejected = _screen(", max_accel: 0.5")
    values = [1.0] * 10 + [0.0] * n + [1.0] * 10
    passed = [screen.admit(m) for m in _speeds(values)]
    assert passed == [True] * 10 + [False] * n + [True] * 10
    assert sum(rejected.values()) == n


def test_a_stop_held_past_the_hold_is_followed():
    """2 s of zeros after 1 m/s (beyond max_accel 0.5): a real stop (or a wrong limit). The
    run re-anchors once it spans TWIST_HOLD_S and the zeros after it are passed on."""
    screen, _ = _screen(", max_accel: 0.5")
    ms = _speeds([1.0] * 10 + [0.0] * 20)
    passed = [screen.admit(m) for m in ms]
    held = next(i for i in range(10, 30) if ms[i].t - ms[10].t >= TWIST_HOLD_S)
    assert passed == [True] * 10 + [False] * (held - 9) + [True] * (29 - held)


def test_samples_that_do_not_agree_with_each_other_do_not_re_anchor():
    screen, _ = _screen("")
    values = [1.0] * 3 + [20.0, 40.0] * 5 + [1.0]
    passed = [screen.admit(m) for m in _speeds(values)]
    assert passed == [True] * 3 + [False] * 10 + [True]


def test_a_gyro_rate_beyond_the_top_yaw_rate_is_rejected():
    screen, rejected = _screen()
    ms = [GyroYawRate(T0 + 0.02 * i, 30.0 if i == 7 else 0.2, 1e-4, "/imu") for i in range(20)]
    assert [screen.admit(m) for m in ms] == [i != 7 for i in range(20)]
    ((topic, reason), n), = rejected.items()
    assert topic == "/imu" and "robot.max_yaw_rate" in reason and n == 1


def test_wheel_speeds_are_screened_through_the_geometry():
    screen, rejected = _screen()
    # 10 rad/s on wheels of 0.1 m is 1 m/s; 100 rad/s is 10 m/s
    ms = [WheelSpeeds(T0 + 0.1 * i, w, w, 0.0025, 0.0025, "/joints")
          for i, w in enumerate([10.0] * 5 + [100.0] + [10.0] * 5)]
    assert [screen.admit(m) for m in ms] == [i != 5 for i in range(11)]
    assert rejected[("/joints", "speed beyond the robot's top speed (robot.max_speed)")] == 1


def _drive(n: int, v: float = 1.0, period: float = 0.4) -> list[GpsFix]:
    return [_fix(T0 + period * i, v * period * i, 0.0) for i in range(n)]


def test_a_held_gps_jump_is_rejected_while_the_top_speed_cannot_explain_it():
    screen, rejected = _screen()  # 1.5 m/s
    fixes = _drive(150)  # 60 s at 1 m/s, 2.5 Hz
    jumped = range(50, 100)  # 20 s, 50 m north
    for i in jumped:
        fixes[i].enu = (fixes[i].enu[0], 50.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert passed == [i not in jumped for i in range(150)]
    (w,) = screen.warnings()
    assert "topic /fix: 50 sample(s) rejected" in w and "robot.max_speed" in w


def test_a_held_gps_jump_stays_rejected_though_the_aged_anchor_could_reach_it():
    screen, _ = _screen()
    fixes = _drive(300, v=0.0)
    for i in range(50, 150):  # 40 s 50 m away: the top speed reaches it after ~28 s
        fixes[i].enu = (0.0, 50.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert passed == [i not in range(50, 150) for i in range(300)]


def test_a_jump_held_longer_than_hold_s_is_taken_and_the_return_re_anchors():
    screen, _ = _screen()
    fixes = _drive(400, v=0.0)
    for i in range(50, 250):  # 80 s, beyond HOLD_S = 60 s
        fixes[i].enu = (0.0, 50.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    first = passed.index(True, 50)
    assert first == 50 + round(HOLD_S / 0.4) + 1 and all(passed[first:250])
    # back where the robot was before the jump: the return re-anchors after REANCHOR fixes
    assert passed[250:] == [False] * (REANCHOR - 1) + [True] * (150 - REANCHOR + 1)


def test_a_jumped_fix_within_the_aged_anchors_reach_is_still_part_of_the_jump():
    """The robot drives south while the GPS holds 50 m north: late in the jump the jumped fixes
    come within the top speed's reach of the last fix before it; they go on the held jump and
    are rejected, and the true fixes after it are taken at once."""
    screen, _ = _screen()  # 1.5 m/s
    fixes = [_fix(T0 + 0.4 * i, 0.0, -1.0 * 0.4 * i) for i in range(150)]
    for i in range(50, 100):  # 20 s
        fixes[i].enu = (0.0, fixes[i].enu[1] + 50.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert passed == [i not in range(50, 100) for i in range(150)]


def test_the_return_from_a_jump_accepted_within_reach_is_not_held_as_a_new_jump():
    """Urban seed 15's pattern: two jumped fixes (8 m, then 11 m north) come within the top
    speed's reach of the fix before them and are accepted; the true track after them is out of
    the last one's reach at first. It is the track the screen followed before the jump, so it
    re-anchors after REANCHOR fixes, not held for HOLD_S as a jump from the jumped anchor."""
    screen, rejected = _screen()  # 1.5 m/s: 0.6 m + 8.5 m in 0.4 s
    fixes = _drive(300)  # 120 s east at 1 m/s, 2.5 Hz
    for i, north in ((50, 8.0), (51, 11.0)):
        fixes[i].enu = (fixes[i].enu[0], north, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert all(passed[:52])  # the jump is within reach: taken
    back = passed.index(True, 52)
    assert back == 52 + REANCHOR - 1 and all(passed[back:])
    assert sum(rejected.values()) == back - 52


def test_a_wrongly_taken_return_is_undone_by_the_next_run_back():
    """The same pattern, then the receiver goes back to the jumped side for good (the "return"
    was the wrong choice): the side it left is the other one, so that run re-anchors after
    REANCHOR fixes too, not after HOLD_S."""
    screen, _ = _screen()
    fixes = _drive(300)
    for i, north in ((50, 8.0), (51, 11.0)):
        fixes[i].enu = (fixes[i].enu[0], north, 0.0)
    for f in fixes[100:]:
        f.enu = (f.enu[0], 11.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert passed[52:100] == [False] * (REANCHOR - 1) + [True] * (48 - REANCHOR + 1)
    assert passed[100:] == [False] * (REANCHOR - 1) + [True] * (200 - REANCHOR + 1)


def test_a_datum_shift_that_persists_while_driving_is_held_for_hold_s_then_taken():
    """A shift of 30 m north from fix 50 on, for good, while the robot drives east: held (the
    fixes before it are all on the anchor's side: no return), then taken after HOLD_S."""
    screen, _ = _screen()
    fixes = _drive(300)
    for f in fixes[50:]:
        f.enu = (f.enu[0], 30.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    first = passed.index(True, 50)
    assert first == 50 + round(HOLD_S / 0.4) + 1 and all(passed[first:])
    assert all(passed[:50])


def test_an_earlier_outlier_does_not_let_a_later_jump_through():
    screen, _ = _screen()
    fixes = _drive(400, v=0.0)
    fixes[20].enu = (0.0, 30.0, 0.0)
    for i in range(200, 300):  # 40 s, long after the outlier
        fixes[i].enu = (0.0, 50.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert passed == [i != 20 and i not in range(200, 300) for i in range(400)]


def test_good_fixes_after_a_single_outlier_are_taken():
    screen, _ = _screen()
    fixes = _drive(40)
    fixes[20].enu = (fixes[20].enu[0], 9.5, 0.0)  # just beyond 0.6 + 8.5 m
    assert [screen.admit(f) for f in fixes] == [i != 20 for i in range(40)]


def test_a_glitch_as_the_first_fix_re_anchors():
    screen, _ = _screen()
    fixes = _drive(20)
    fixes[0].enu = (0.0, 80.0, 0.0)
    assert [screen.admit(f) for f in fixes] == \
        [True] + [False] * (REANCHOR - 1) + [True] * (20 - REANCHOR)


def test_a_fix_after_a_long_outage_is_taken():
    screen, rejected = _screen()
    fixes = [*_drive(10), _fix(T0 + 4.0 + 60.0, 70.0, 0.0)]  # 60 s later, 66 m on
    assert all(screen.admit(f) for f in fixes) and not rejected


def test_the_stated_sigma_of_the_fixes_widens_what_is_plausible():
    screen, _ = _screen()
    fixes = [_fix(T0, 0.0, 0.0, 3.0), _fix(T0 + 0.4, 20.0, 0.0, 3.0)]  # 6 sigma: 25 m
    assert all(screen.admit(f) for f in fixes)


# --- in the stream, bag and live -------------------------------------------------------------

def _bag(tmp_path: Path, glitch: dict) -> Path:
    recs = []
    for i in range(100):
        t = T0 + 0.1 * i
        recs.append(("/odom", bw.odometry(t, glitch.get(i, 1.0), 0.1)))
        if i % 4 == 0:
            lat, lon, _ = geodesy.enu_to_geodetic(0.1 * i, 0.0, 0.0, *DATUM)
            recs.append(("/fix", bw.navsatfix(t, lat, lon, DATUM[2])))
    return bw.write_bag(tmp_path / "g.bag", "ros1", recs)


CFG = """
sensors:
  odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.02, yaw_rate: 0.02}}]
  gps: [{topic: /fix, noise: {horizontal: 1.0}}]
robot: {max_speed: 1.5}
frame: {datum: [47.0, 8.0, 400.0]}
"""


def test_the_bag_stream_rejects_counts_and_warns(tmp_path):
    bag = _bag(tmp_path, {50: 1e6})
    bs = BagStream(bag, parse_config_text(CFG))
    out = [m for m in bs if isinstance(m, WheelOdometry)]
    assert len(out) == 99 and max(m.v for m in out) == 1.0
    reason = "speed beyond the robot's top speed (robot.max_speed)"
    assert bs.rejected[("/odom", reason)] == 1
    (w,) = [w for w in bs.warnings if "physically implausible" in w]
    assert w.startswith(f"{bag}: topic /odom: 1 sample(s)") and "1e+06 m/s" in w
    assert "limit 1.5 m/s" in w


def test_the_live_converter_rejects_and_counts(tmp_path):
    bag = _bag(tmp_path, {50: 1e6})
    cfg = parse_config_text(CFG)
    conv = LiveConverter(cfg)
    store = bw.typestore("ros1")
    passed = []
    for i in range(100):
        msg = bw.odometry(T0 + 0.1 * i, 1e6 if i == 50 else 1.0, 0.1).build(store)
        passed += conv.convert("/odom", msg, received=T0 + 0.1 * i)
    assert len(passed) == 99
    assert conv.rejected[("/odom", "speed beyond the robot's top speed (robot.max_speed)")] == 1
    assert bag.exists()


@pytest.mark.parametrize("bag,cfg", [("sample_husky.bag", "sample_husky.yaml"),
                                     ("sample_seed002.bag", "sample_seed002.yaml")])
def test_the_clean_sample_bags_lose_nothing_to_the_screen(bag, cfg):
    s = read_stream(ROOT / "data" / bag, load_config(ROOT / "data" / cfg))
    assert s.rejected == {}


# --- aided by the odometry --------------------------------------------------------------------

CAR = ", max_speed: 25.0, max_yaw_rate: 2.0"  # a car at 10 m/s, top speed 2.5 times that


def _with_odometry(fixes: list[GpsFix], v: float = 10.0) -> list:
    """``fixes`` merged in stamp order with 10 Hz odometry of a car driving east at ``v``."""
    n = round((fixes[-1].t - T0) / 0.1) + 1
    return sorted([*fixes, *(_odo(i, v, 0.0) for i in range(n))], key=lambda m: m.t)


def _car(n: int, v: float = 10.0) -> list[GpsFix]:
    return [_fix(T0 + 0.5 * i, v * 0.5 * i, 0.0, sd=1.5) for i in range(n)]


def _fix_results(screen: RobotLimits, ms: list) -> list[bool]:
    return [ok for m, ok in ((m, screen.admit(m)) for m in ms) if isinstance(m, GpsFix)]


def test_an_nlos_run_after_a_gap_of_rejected_fixes_does_not_become_the_anchor():
    """Urban seed 10's pattern (150-220 s): 4 NLOS fixes 42 m off are rejected, the 3 true fixes
    after them come 2.5 s after the last accepted one (provisional to the GPS alone), and a
    burst of 13 fixes 42 m off follows. GPS alone, 5 of the burst re-anchored on the
    provisional anchor, the burst confirmed itself, and the true fixes after it were held as a
    jump for HOLD_S (60 s). The odometry vouches for the true fixes after the rejected ones and
    puts the burst off the dead-reckoned track: every true fix passes, no jumped one."""
    screen, _ = _screen(CAR)
    fixes = _car(240)  # 120 s east at 10 m/s, 2 Hz
    jumped = [*range(60, 64), *range(67, 80)]
    for i in jumped:
        fixes[i].enu = (fixes[i].enu[0], 42.0, 0.0)
    passed = _fix_results(screen, _with_odometry(fixes))
    assert passed == [i not in jumped for i in range(240)]


def test_gps_alone_holds_the_true_fixes_after_that_nlos_run():
    """The same fixes without odometry: the screen has only the GPS's word (the behaviour above
    is the odometry's doing)."""
    screen, _ = _screen(CAR)
    fixes = _car(240)
    for i in [*range(60, 64), *range(67, 80)]:
        fixes[i].enu = (fixes[i].enu[0], 42.0, 0.0)
    passed = [screen.admit(f) for f in fixes]
    assert not any(passed[80:80 + round(HOLD_S / 0.5)])


def test_a_jump_within_the_top_speeds_reach_is_rejected_off_the_dead_reckoned_track():
    """15 m north for one fix at 10 m/s: within the top speed's 12.5 m plus 12.7 m of noise, so
    the GPS alone takes it; the odometry puts the car on the line (15 m against 12.7 m of noise
    and 1.8 m of drift)."""
    fixes = _car(100)
    fixes[50].enu = (fixes[50].enu[0], 15.0, 0.0)
    aided, _ = _screen(CAR)
    assert _fix_results(aided, _with_odometry(fixes)) == [i != 50 for i in range(100)]
    alone, _ = _screen(CAR)
    assert all(alone.admit(f) for f in fixes)


def test_a_gps_wrong_for_minutes_is_rejected_counted_then_said_by_the_estimator():
    """From 40 s on every fix is 60 m north (a wrong datum) while the robot drives east at
    2 m/s: the screen rejects the shifted fixes, counted and warned, until the odometry's own
    drift allowance covers 60 m (well before HOLD_S: the screen no longer holds a jump on the
    GPS's word alone where the odometry can tell); then the EKF under the robust model judges
    them and says that GPS and odometry disagree and that it follows the odometry: neither
    silently trusted nor silently dropped."""
    import test_gps_robust as gr
    from ddfuse.ekf_baseline.unicycle import UnicycleEkf
    from drives import straight_drive

    cfg = gr._cfg("cauchy")  # the robust-GPS tests' drive: wheels, gyro, 5 Hz fixes
    rejected: Counter = Counter()
    screen = RobotLimits(cfg, rejected)
    ekf = UnicycleEkf(cfg, initial_pose=(0.0, 0.0, 0.0))
    passed = []
    for m in straight_drive(gr.DATUM, 0.0, 2.0, 120.0, np.random.default_rng(11),
                            r_wheel=gr.R_WHEEL,
                            sig_wheel=0.1, sig_gyro=0.01, sig_gps=1.0,
                            fix_hook=lambda t, e, n: (e, n + 60.0) if t >= 40.0 else (e, n)):
        if isinstance(m, GpsFix):
            m.enu = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *gr.DATUM)
        ok = screen.admit(m)
        if isinstance(m, GpsFix):
            passed.append((m.t, ok))
        if ok:
            ekf.process(m)
    ekf.finish()
    assert all(ok for t, ok in passed if t < 40.0)
    taken = next(t for t, ok in passed if t >= 40.0 and ok)
    assert 45.0 < taken < 40.0 + HOLD_S
    assert sum(rejected.values()) == sum(1 for t, ok in passed if 40.0 <= t < taken)
    (w,) = screen.warnings()
    assert "robot.max_speed" in w
    said = [n for n in ekf.log.messages if "disagree" in n]
    assert said and "following the odometry" in said[0]
    assert float(said[0].split(":")[0][2:]) >= taken


def test_a_stated_noise_far_below_the_samples_scatter_does_not_reject_good_samples():
    """Odometry at 50 Hz, true sd 0.05 m/s, stated 0.002 (25x too small): before, 6 sigma of
    the stated noise rejected ~1 in 4 good samples as faster speed changes than the robot can
    make. The screen now allows for the samples' own scatter once it has read it, still rejects
    a glitch, and says the scatter in its warnings."""
    from ddfuse.estimation.robot_limits import SCATTER_START

    screen, rejected = _screen("")
    rng = np.random.default_rng(3)
    n, glitch = 600, 400
    t = T0 + 0.02 * np.arange(n)
    v = 1.0 + 0.5 * np.sin(0.5 * (t - T0)) + rng.normal(0.0, 0.05, n)
    v[glitch] += 3.0  # 150 m/s^2 against the default 20, and 40 sd of the scatter
    passed = [screen.admit(WheelOdometry(t[i], float(v[i]), None, 0.002 ** 2, 0.0, "/odom"))
              for i in range(n)]
    late = [i for i in range(SCATTER_START + 2, n) if not passed[i]]
    assert late == [glitch]
    assert sum(rejected.values()) < 30
    (said,) = [w for w in screen.warnings() if "scatter" in w]
    sd = float(said.split("scatter with sd ")[1].split()[0])
    assert 0.035 < sd < 0.07 and "stated 0.002 m/s" in said  # a median of 64: ~16 % sd


def test_held_values_read_no_scatter_and_the_stated_noise_rules():
    screen, _ = _screen("")
    values = [1.0] * 60 + [1.5] + [1.0] * 5  # 25 m/s^2: beyond 20 plus 6 x 0.001 sd
    ms = [WheelOdometry(T0 + 0.02 * i, x, None, 0.001 ** 2, 0.0, "/odom")
          for i, x in enumerate(values)]
    assert [screen.admit(m) for m in ms] == [i != 60 for i in range(66)]
    assert not [w for w in screen.warnings() if "scatter" in w]


def test_a_restored_anchor_stays_confirmed():
    """After a dropout restored it, the anchor is as confirmed as before: a second dropout
    right after it waits TWIST_HOLD_S too (it would re-anchor after REANCHOR samples, and the
    sample after it passed, were the restored anchor taken for a new one)."""
    screen, _ = _screen(", max_accel: 0.5")
    t = [m.t for m in _speeds([0.0] * 20)]
    n = next(k for k in range(1, 20) if t[k] - t[0] >= TWIST_HOLD_S) + 1  # re-anchors at the n-th
    values = [1.0] * 10 + [0.0] * n + [1.0] + [0.0] * 8 + [1.0] * 5
    passed = [screen.admit(m) for m in _speeds(values)]
    assert passed == [v == 1.0 for v in values]
