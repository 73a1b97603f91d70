"""The recording clock stepping back mid-bag (header stamps and record times alike) is found in
the write order of a ROS1 bag (or the arrival order of live input), said in one warning, and the
messages after it re-timed by the step: the stream is the one recorded without the step.

Before: 10 s of data interleaved (or dropped as 'late' with advice to raise reorder_window),
ekf ATE 0.114 -> 1.115 m and NEES 2.9 -> 417 on the sample, batch 6.3 m, no warning."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import bagedit
import numpy as np
import pytest
from ddfuse.estimation.bags import BagStream, read_stream
from ddfuse.estimation.clock_steps import ClockSteps
from ddfuse.estimation.config import load_config
from ddfuse.estimation.live import LiveConverter
from rosbags.highlevel import AnyReader

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"
SAMPLE_CFG = ROOT / "data" / "sample_husky.yaml"
STEP_AT, STEP = 40.0, 10.0  # s into the bag, s back


@pytest.fixture(scope="module")
def stepped(tmp_path_factory) -> Path:
    return bagedit.step_back(SAMPLE, tmp_path_factory.mktemp("step") / "step.bag", STEP_AT, STEP)


@pytest.fixture(scope="module")
def clean():
    return read_stream(SAMPLE, load_config(SAMPLE_CFG))


def test_clock_steps_finds_a_backward_record_time_and_retimes_what_follows():
    steps = ClockSteps(1.0)
    out = [steps.retime("/a", t, t) for t in (10.0, 10.1, 10.2)]
    out += [steps.retime("/a", t, t) for t in (0.3, 0.4)]  # 10 s back
    assert [round(t, 6) for t, _ in out] == [10.0, 10.1, 10.2, 10.2, 10.3]
    assert [round(s, 6) for _, s in steps.steps] == [9.9]
    assert steps.retimed == {"/a": 2}
    # a small backward jitter is not a step
    assert ClockSteps(1.0).retime("/a", 5.0, 5.0) == (5.0, 5.0)
    jitter = ClockSteps(1.0)
    jitter.retime("/a", 5.0, 5.0)
    assert jitter.retime("/a", 4.5, 4.5) == (4.5, 4.5) and not jitter.steps


def test_one_garbled_record_time_is_not_a_step():
    """A record time far ahead (a damaged chunk) that the next record comes back from."""
    steps = ClockSteps(1.0)
    out = [steps.retime("/a", t, rt) for t, rt in ((1.0, 1.0), (1.1, 1e6), (1.2, 1.2))]
    assert out[2] == (1.2, 1.2) and not steps.steps
    # a forward gap that the records keep, then a real step back, is still a step
    for t in [5.0 + 0.1 * k for k in range(ClockSteps.OUTLIER_RUN + 2)] + [0.2]:
        steps.retime("/a", t, t)
    assert [round(s, 6) for _, s in steps.steps] == [5.9]


def test_a_topic_stamped_by_another_clock_keeps_its_stamps():
    steps = ClockSteps(1.0)
    for k in range(3):
        steps.retime("/sys", 10.0 + 0.1 * k, 10.0 + 0.1 * k)
        steps.retime("/gps", 10.05 + 0.1 * k, 10.0 + 0.1 * k)  # the receiver's clock
    t_sys, rt = steps.retime("/sys", 0.3, 0.3)
    t_gps, _ = steps.retime("/gps", 10.35, 0.3)  # its stamp did not step
    assert math.isclose(t_sys, 10.2) and math.isclose(rt, 10.2)
    assert t_gps == 10.35 and steps.retimed == {"/sys": 1}


def test_a_stepped_sample_bag_gives_the_clean_stream_and_one_warning(stepped, clean):
    cfg = load_config(SAMPLE_CFG)
    bs = BagStream(stepped, cfg)
    ms = list(bs)
    assert len(ms) == len(clean.measurements)  # nothing dropped
    assert not bs.rejected
    t = np.array([m.t for m in ms])
    t_clean = np.array([m.t for m in clean.measurements])
    # the step is measured from the record times: exact to a message interval
    assert np.max(np.abs(t - t_clean)) < 0.05
    [w] = [w for w in bs.warnings if "clock stepped back" in w]
    assert str(stepped) in w and re.search(r"stepped back by (9\.9\d|10\.0\d) s", w)
    assert abs(float(re.search(r" at t=([\d.]+) s", w).group(1)) - STEP_AT) < 0.1
    for topic in ("/odom", "/imu/data", "/fix"):
        assert topic in w


def test_a_topic_whose_stamps_did_not_step_is_not_moved(tmp_path, clean):
    bag = bagedit.step_back(SAMPLE, tmp_path / "gps_clock.bag", STEP_AT, STEP,
                            stamps_kept=("/fix",))
    s = read_stream(bag, load_config(SAMPLE_CFG))
    fixes = [m.t for m in s.measurements if m.sensor == "/fix"]
    assert fixes == [m.t for m in clean.measurements if m.sensor == "/fix"]
    assert len(s.measurements) == len(clean.measurements)


def test_live_input_whose_receive_clock_steps_back_is_retimed():
    cfg = replace(load_config(SAMPLE_CFG), initial_pose=None)
    conv = LiveConverter(cfg)
    with AnyReader([SAMPLE]) as reader:
        conns = [c for c in reader.connections if c.topic == "/imu/data"]
        stamps = []
        for i, (c, rec_ns, raw) in enumerate(reader.messages(connections=conns)):
            if i >= 600:
                break
            msg = reader.deserialize(raw, c.msgtype)
            back = STEP if i >= 300 else 0.0
            if back:  # the header stamp and the receive time alike
                msg.header.stamp.sec -= int(back)
            ms = conv.convert("/imu/data", msg, received=rec_ns * 1e-9 - back)
            stamps.append(ms[0].t)
    assert np.all(np.diff(stamps) > 0)  # no jump back
    assert not conv.rejected
    [w] = conv.warnings
    assert "live input" in w and "stepped back by 9.9" in w and "/imu/data (300)" in w


@pytest.mark.slow
def test_a_stepped_sample_run_scores_as_the_clean_one(stepped, tmp_path):
    """ekf ATE on the stepped sample within 10 % of the clean bag's (0.114 m)."""
    clean, _ = bagedit.ekf_metrics(SAMPLE, SAMPLE_CFG, tmp_path / "clean")
    ekf, warnings = bagedit.ekf_metrics(stepped, SAMPLE_CFG, tmp_path / "stepped")
    assert ekf["ate_rmse_m"] < 1.1 * clean["ate_rmse_m"]
    assert any("clock stepped back" in w for w in warnings)


@pytest.mark.slow
def test_a_stepped_husky_bag_keeps_every_message(husky_bag, tmp_path):
    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    bag = bagedit.step_back(husky_bag, tmp_path / "step.bag", 100.0, STEP)
    clean, s = read_stream(husky_bag, cfg), read_stream(bag, cfg)
    assert len(s.measurements) == len(clean.measurements)
    t = np.array([m.t for m in s.measurements])
    assert np.max(np.abs(t - [m.t for m in clean.measurements])) < 0.05
