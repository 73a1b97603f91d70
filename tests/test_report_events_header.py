"""The report's events header per estimator: gate rejections, other drops and lock-out
recoveries counted as the gating table counts them."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

from ddfuse.evaluation import report
from ddfuse.evaluation.results import load_run
from ddfuse.evaluation.scores import EstimatorScores

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def test_events_header_counts_lockout_recoveries_as_accepted_as_the_gating_table_does(
        seed002_run):
    """A kidnapped robot (test_unicycle): the GPS gate rejects fixes until its lock-out
    recovery fuses one. The estimator counts that recovery in log.rejected; the events header
    must not add it to the rejections, or it disagrees with the gating table (MRCLAM
    'ekf_landmark: 3 events, 75 rejected' against 72 in the table)."""
    from ddfuse.ekf_baseline.unicycle import UnicycleEkf
    from ddfuse.evaluation import consistency
    from test_unicycle import SIM_NOISE, make_cfg, run_filter, simulate

    run = simulate(71, kidnap=(40.0, 15.0, -5.0), stand_still=30.0, duration=70.0,
                   gps_sigma=0.3)
    ekf = UnicycleEkf(make_cfg(), noise=SIM_NOISE, initial_pose=(0.0, 0.0, 0.7),
                      lockout_count=5, lockout_time=1.0)
    run_filter(ekf, run)
    recoveries = len(ekf.kf.recoveries)
    assert recoveries >= 1
    # what ddfuse.evaluation.pipeline writes into metrics.json for it
    e = {"events": ekf.log.messages,
         "rejected": {f"{s}: {why}": n for (s, why), n in ekf.log.rejected.items()},
         "nis": {label: s.as_dict() for label, s in consistency.nis_by_sensor(
             consistency.InnovationTable.from_innovations(ekf.log.innovations)).items()}}
    table_rejected = sum(s["rejected"] for s in e["nis"].values())
    assert table_rejected >= 4
    # the report's Configuration section with this entry in place of the run's
    run = load_run(seed002_run)
    run.summary = replace(run.summary, estimators={"ekf": EstimatorScores.from_json(e)})
    section = report._config(run, report.run_config(run))
    [head] = re.findall(r"<summary>ekf: (.*?)</summary>", section)
    assert f"{table_rejected} rejected by the gate" in head, head
    assert f"{recoveries} lock-out recover" in head and "(measurement accepted)" in head
    assert "dropped" not in head  # nothing else was refused here


def test_events_header_of_the_mrclam_counts():
    """metrics.json's entry of ekf_landmark on mrclam1_robot1.bag, and of a
    Husky EKF that waited for its start (other reasons counted apart)."""
    e = {"events": ["a", "b", "c"],
         "rejected": {"/landmarks: gate": 72, "/landmarks: lockout_recovery": 3}}
    assert report.event_summary(EstimatorScores.from_json(e)) == (
        "3 events, 72 rejected by the gate, 3 lock-out recoveries (measurement accepted)")
    assert report._rejection_lines(e["rejected"]) == [
        "rejected /landmarks: gate: 72",
        "lock-out recovery, measurement accepted /landmarks: 3"]
    e = {"events": ["a"], "rejected": {"/imu/data: before_init": 194, "/fix: gate": 4,
                                       "/fix: lockout_recovery": 1}}
    assert report.event_summary(EstimatorScores.from_json(e)) == (
        "1 event, 4 rejected by the gate, 194 dropped for other reasons, 1 lock-out recovery "
        "(measurement accepted)")
    assert report.event_summary(EstimatorScores.from_json({"events": []})) == "0 events"
