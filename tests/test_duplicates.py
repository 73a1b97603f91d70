"""Exact duplicate messages (same topic, header stamp and content; recorded twice) are dropped,
counted per topic in ``rejected`` and warned about; a message with the same stamp and other
content is kept. Before: fused twice, silently (sample, every sensor message doubled: ekf NEES
2.89 -> 4.2)."""

from __future__ import annotations

from pathlib import Path

import bagedit
import bagwriter as bw
import pytest
from ddfuse.estimation.bags import BagStream, read_stream
from ddfuse.estimation.config import load_config, parse_config
from ddfuse.estimation.duplicates import DUPLICATE
from rosbags.highlevel import AnyReader

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"
SAMPLE_CFG = ROOT / "data" / "sample_husky.yaml"
SENSORS = ("/odom", "/imu/data", "/fix")
T0 = 1_600_000_000.0  # s
IMU_CFG = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}


@pytest.fixture(scope="module")
def doubled(tmp_path_factory) -> Path:
    return bagedit.duplicate(SAMPLE, tmp_path_factory.mktemp("dup") / "dup.bag", SENSORS)


def _values(stream) -> list[str]:
    return [repr(m) for m in stream.measurements]


@pytest.mark.parametrize("new_seq", [False, True])
def test_every_message_twice_gives_the_clean_stream_and_counts(doubled, tmp_path, new_seq):
    """A copy with another ROS1 header seq (a republisher) is a duplicate all the same."""
    bag = (bagedit.duplicate(SAMPLE, tmp_path / "seq.bag", SENSORS, new_seq=True) if new_seq
           else doubled)
    cfg = load_config(SAMPLE_CFG)
    clean = read_stream(SAMPLE, cfg)
    bs = BagStream(bag, cfg)
    ms = list(bs)
    assert [repr(m) for m in ms] == _values(clean)
    with AnyReader([SAMPLE]) as r:
        counts = {c.topic: c.msgcount for c in r.connections}
    assert {t: n for (t, why), n in bs.rejected.items() if why == DUPLICATE} == \
        {t: counts[t] for t in SENSORS}
    lines = [w for w in bs.warnings if "exact duplicates" in w]
    assert len(lines) == len(SENSORS) and all(str(bag) in w for w in lines)
    assert not [w for w in bs.warnings if "%) rejected" in w]  # said once, not twice


@pytest.mark.parametrize("fmt", bw.FORMATS)
def test_same_stamp_other_content_is_kept_and_a_repeat_is_not(tmp_path, fmt):
    recs = []
    for i in range(20):
        t = T0 + 0.01 * i
        recs.append(("/imu", bw.imu(t, angvel=(0, 0, 0.1), wcov=bw.diag(1, 1, 1))))
        if i == 5:  # same stamp, another reading: kept
            recs.append(("/imu", bw.imu(t, angvel=(0, 0, 0.2), wcov=bw.diag(1, 1, 1))))
        if i == 9:  # the same message again: dropped
            recs.append(("/imu", bw.imu(t, angvel=(0, 0, 0.1), wcov=bw.diag(1, 1, 1))))
    bag = bw.write_bag(bw.bag_path(tmp_path, "b", fmt), fmt, recs)
    s = read_stream(bag, parse_config(IMU_CFG))
    assert len(s.measurements) == 21
    assert s.rejected == {("/imu", DUPLICATE): 1}


@pytest.mark.slow
def test_a_doubled_sample_run_scores_as_the_clean_one(doubled, tmp_path):
    clean, _ = bagedit.ekf_metrics(SAMPLE, SAMPLE_CFG, tmp_path / "clean")
    ekf, warnings = bagedit.ekf_metrics(doubled, SAMPLE_CFG, tmp_path / "doubled")
    assert ekf["nees_mean"] == clean["nees_mean"] and ekf["ate_rmse_m"] == clean["ate_rmse_m"]
    assert sum("exact duplicates" in w for w in warnings) == 3
