"""The ground-truth screen (``ddfuse.estimation.truth_screen``): truth samples no robot can
produce are left out of the scores, and only those."""

import math

import numpy as np
from ddfuse.estimation.truth_screen import impossible_samples, screen_truth

RATE = 50.0  # Hz, as MRCLAM's truth


def _truth(yaw: np.ndarray, speed: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    t = 1.5e9 + np.arange(len(yaw)) / RATE
    x = speed * (t - t[0])
    return t, np.column_stack([x, np.zeros_like(x), yaw])


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_a_yaw_interpolated_the_long_way_across_pi_is_left_out_and_nothing_else():
    # the robot heads at +-pi (yaw steps across the wrap at 0.3 rad/s); the resampler put
    # four samples on the long way round, MRCLAM's artefact
    yaw = _wrap(3.10 + 0.3 / RATE * np.arange(200))
    yaw[100:104] = _wrap(yaw[99] - 2 * np.pi * np.arange(1, 5) / 5)
    keep, found = screen_truth("/ground_truth", *_truth(yaw), speed_limit=0.75,
                               yaw_rate_limit=5.0)
    assert np.flatnonzero(~keep).tolist() == [100, 101, 102, 103]
    assert (found.dropped, found.stretches, found.unresolved) == (4, 1, 0)
    assert found.max_yaw_rate > 50.0
    line = found.warning(1.5e9)
    assert line.startswith("/ground_truth: 4 of 200 ground-truth samples in 1 stretch(es)")
    assert "t=2.00 s" in line and "robot.max_yaw_rate 5" in line and "max_speed" not in line


def test_the_fastest_turn_the_robot_can_do_and_the_wrap_itself_are_kept():
    # 4.9 rad/s (under the 5 rad/s limit) through several wraps, with mocap-sized noise
    rng = np.random.default_rng(3)
    yaw = _wrap(4.9 / RATE * np.arange(1000) + rng.normal(0, 0.005, 1000))
    drop, unresolved = impossible_samples(*_truth(yaw), speed_limit=0.75, yaw_rate_limit=5.0)
    assert not drop.any() and unresolved == 0


def test_a_jump_that_stays_is_kept_and_counted_not_guessed():
    yaw = np.r_[np.zeros(50), np.full(50, 1.0)]
    keep, found = screen_truth("/gt", *_truth(yaw), speed_limit=0.75, yaw_rate_limit=5.0)
    assert keep.all() and found.dropped == 0 and found.unresolved == 1
    assert "1 step(s) of the truth beyond those limits kept" in found.warning(0.0)


def test_a_position_excursion_is_left_out_and_named_by_speed():
    t, pose = _truth(np.zeros(100))
    pose[40:42, 1] += 2.0  # a marker swap: 2 m off for two samples
    keep, found = screen_truth("/vicon", t, pose, speed_limit=0.75, yaw_rate_limit=5.0)
    assert np.flatnonzero(~keep).tolist() == [40, 41]
    assert "moves at up to" in found.warning(t[0]) and "turns at" not in found.warning(t[0])


def test_a_truth_without_heading_or_too_short_is_not_screened():
    t, pose = _truth(np.zeros(100))
    pose[40, 0] += 5.0
    pose[:, 2] = math.nan  # a NavSatFix truth: its noise is not known here
    drop, unresolved = impossible_samples(t, pose, 0.75, 5.0)
    assert not drop.any() and unresolved == 0
    drop, _ = impossible_samples(t[:2], np.array([[0, 0, 0], [9, 0, 3]], float), 0.75, 5.0)
    assert not drop.any()
    _, found = screen_truth("/gt", *_truth(np.zeros(10)), 0.75, 5.0)
    assert found.warning(0.0) is None


def test_an_excursion_longer_than_the_limit_is_kept_and_counted():
    t, pose = _truth(np.zeros(300))
    pose[50:200, 1] += 2.0  # 3 s away: a mocap that lost the robot, not a glitch
    keep, found = screen_truth("/vicon", t, pose, speed_limit=0.75, yaw_rate_limit=5.0)
    assert keep.all() and found.unresolved == 2


def test_a_return_that_leaves_again_at_once_is_part_of_the_excursion():
    # MRCLAM at 1245.6 s: -3.14, X, 2.75, 3.14 -- under a generous 10 rad/s limit the robot
    # could reach 2.75 from -3.14 in two steps, but 2.75 leaves at once for 3.14
    yaw = np.r_[np.full(50, -3.14), -1.2, 2.75, np.full(50, 3.14)]
    drop, unresolved = impossible_samples(*_truth(yaw), speed_limit=0.75, yaw_rate_limit=10.0)
    assert np.flatnonzero(drop).tolist() == [50, 51] and unresolved == 0


def test_inspect_notes_a_pose_truth_that_spins_and_says_nothing_of_a_clean_one():
    from ddfuse.estimation import baginfo, rosmsg

    def recs(yaw):
        return [(1.5e9 + k / RATE, (0.1 * k / RATE, 0.0, 0.0),
                 (0.0, 0.0, math.sin(a / 2), math.cos(a / 2)), (0.0,) * 3, (0.0,) * 3,
                 (0.0,) * 36) for k, a in enumerate(yaw)]

    yaw = _wrap(3.10 + 0.3 / RATE * np.arange(200))
    clean = baginfo.TopicInfo("/ground_truth", rosmsg.ODOMETRY, 200)
    baginfo._summarise(clean, recs(yaw))
    yaw[100:104] = _wrap(yaw[99] - 2 * np.pi * np.arange(1, 5) / 5)
    spun = baginfo.TopicInfo("/ground_truth", rosmsg.ODOMETRY, 200)
    baginfo._summarise(spun, recs(yaw))
    assert clean.notes == ["looks like ground truth (pose used for scoring only)"]
    assert len(spun.notes) == 2 and spun.notes[1].startswith(
        "4 of 200 ground-truth samples in 1 stretch(es) left out of the scores")
