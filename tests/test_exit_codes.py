"""`ddfuse run` exit codes and the hints of an estimator that never started: a run where every
estimator ends in ERROR exits 3 (after writing what they had), and the hint names what the
estimator waited for, not `initial_pose: ground_truth` when the config does not set it."""

from __future__ import annotations

import json
from pathlib import Path

import bagwriter as bw
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.cli.guard import NO_ESTIMATE

T0 = 1_600_000_000.0
CONFIG = """sensors:
  odometry:
  - topic: /odom
    use: [v, yaw_rate]
    noise: {v: 0.05, yaw_rate: 0.05}
  imu:
  - topic: /imu
    use: [yaw, yaw_rate]
    noise: {yaw: 0.05, yaw_rate: 0.02}
    heading_offset: 0.0
  gps:
  - topic: /fix
frame: {datum: [47.0, 8.0, 0.0]}
"""


def _bag_without_heading(tmp_path: Path) -> Path:
    """30 s of odometry, GPS fixes at one spot and an IMU that gives no orientation
    (orientation_covariance[0] = -1): an EKF told the compass's heading offset waits for a
    heading that never comes; the smoother for a GPS track that never moves."""
    recs = []
    for k in range(600):
        t = T0 + 0.05 * k
        recs.append(("/odom", bw.odometry(t, 0.5)))
        if k % 2 == 0:
            recs.append(("/imu", bw.imu(t, wcov=bw.diag(1e-4, 1e-4, 1e-4),
                                        ocov=[-1.0] + [0.0] * 8)))
        if k % 4 == 0:
            recs.append(("/fix", bw.navsatfix(t, 47.0, 8.0)))
    bag = bw.write_bag(tmp_path / "noheading.bag", "ros1", recs)
    (tmp_path / "noheading.yaml").write_text(CONFIG)
    return bag


def test_a_run_where_every_estimator_fails_exits_3_and_names_what_they_waited_for(
        tmp_path, capsys):
    """Before: exit 0, and each EKF's row blamed 'initial_pose: ground_truth', which the config
    does not set."""
    bag = _bag_without_heading(tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(bag), "-o", str(out), "--no-report"]) == NO_ESTIMATE == 3
    stdout, stderr = capsys.readouterr()
    assert stderr.strip().splitlines()[-1] == (
        f"ddfuse: error: every estimator ended in ERROR (the rows above say why); what they had "
        f"is in {out}/")
    m = json.loads((out / "metrics.json").read_text())
    assert all(e["error"] for e in m["estimators"].values())
    for name in ("ekf", "ekf_igvc"):
        err = m["estimators"][name]["error"]
        assert "ground_truth" not in err, err
        assert err.endswith("it takes its start heading from the orientation of /imu "
                            "(heading_offset given), and none reached it (see the topic's "
                            "rejected messages); initial_pose: [x, y, yaw] in the config "
                            "starts it from a known pose"), err
    assert "ground_truth" not in stdout


def test_one_estimator_that_works_keeps_exit_code_0(tmp_path, capsys):
    bag = _bag_without_heading(tmp_path)
    cfg = tmp_path / "noheading.yaml"
    cfg.write_text(CONFIG + "initial_pose: [0.0, 0.0, 0.0]\n")
    assert main(["run", str(bag), "-c", str(cfg), "-o", str(tmp_path / "out"),
                 "--estimators", "ekf", "--no-report"]) == 0
    assert "ERROR" not in capsys.readouterr().out


def test_online_where_every_estimator_fails_exits_3(tmp_path, capsys):
    """Before: 0, as if the replay had given estimates."""
    bag = _bag_without_heading(tmp_path)
    assert main(["online", str(bag)]) == NO_ESTIMATE
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "ddfuse: error: every estimator failed or never gave an estimate (the lines above say "
        "why)")
    cfg = tmp_path / "noheading.yaml"
    cfg.write_text(CONFIG + "initial_pose: [0.0, 0.0, 0.0]\n")
    assert main(["online", str(bag), "-c", str(cfg), "--estimators", "ekf"]) == 0
