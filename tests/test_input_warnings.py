"""What the bag reader warns of reaches the user: run's stderr and metrics.json, online's
stderr (a topic mostly dropped as late said nothing outside a count in metrics.json)."""

from __future__ import annotations

import json

import bagwriter as bw
import pytest
from ddfuse.evaluation.cli import main

T0 = 1_700_000_000.0
CONFIG = {"sensors": {"odometry": [{"topic": "/odom", "noise": {"v": 0.05, "yaw_rate": 0.05}}],
                      "gps": [{"topic": "/fix", "noise": {"horizontal": 1.0}}]}}


def _late_bag(tmp_path):
    """60 s driving east at 1 m/s; the fixes recorded 1.5 s after their stamp."""
    recs = [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.0), T0 + 0.1 * i) for i in range(600)]
    recs += [("/fix", bw.navsatfix(T0 + 0.5 * k, 42.0, -71.0 + 0.5 * k / 82_000.0),
              T0 + 0.5 * k + 1.5) for k in range(118)]
    recs.sort(key=lambda r: r[2])
    return bw.write_bag(bw.bag_path(tmp_path, "late", "ros1"), "ros1", recs)


def test_a_topic_mostly_dropped_as_late_is_warned_of_by_run_and_online(tmp_path, capsys):
    bag = _late_bag(tmp_path)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(json.dumps(CONFIG))
    out = tmp_path / "out"
    # the 9 fixes left cannot align the ekf's track: it never gives an
    # estimate, and run says so with exit 3 (every estimator in ERROR)
    assert main(["run", str(bag), "-c", str(cfg), "-o", str(out), "--no-report",
                 "--estimators", "ekf"]) == 3
    err = capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    (w,) = [w for w in m["warnings"] if "dropped as late" in w]
    assert "/fix" in w and "reorder_window to at least 1.5 s" in w and w in err
    # online passes late ones on to each estimator that can use them (the ekf cannot): the
    # same advice, worded for that
    assert main(["online", str(bag), "-c", str(cfg), "--estimators", "ekf"]) == 3
    (w,) = [w for w in capsys.readouterr().err.splitlines() if "came late" in w]
    assert "/fix: 109 of 118 measurements (92 %) came late" in w
    assert "dropped by the others" in w and "reorder_window to at least 1.5 s" in w


@pytest.mark.slow
def test_bench_says_the_readers_warnings_once(tmp_path, capsys):
    bag = _late_bag(tmp_path)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(json.dumps(CONFIG))
    assert main(["bench", str(bag), "-c", str(cfg), "--estimators", "ekf,smoother"]) == 0
    err = capsys.readouterr().err
    assert err.count("dropped as late") == 1 and "reorder_window to at least 1.5 s" in err
