"""The typed scores (ddfuse.evaluation.scores) and metrics.json: one is the other's
serialisation, both ways, with the records the evaluation modules define inside."""

from __future__ import annotations

import json

import numpy as np
from ddfuse.evaluation.consistency import Consistency, SensorNis
from ddfuse.evaluation.metrics import OutageDrift, Stats
from ddfuse.evaluation.pipeline import score
from ddfuse.evaluation.scores import EstimatorScores, RunSummary
from test_scores_pipeline import _pose, _result, _track


def _scored() -> RunSummary:
    """Two tracks against a truth, fixes withheld in a 30 s outage and every 5th elsewhere."""
    t = np.arange(0.0, 120.0, 0.1)
    fix_t = np.arange(1.0, 119.0, 0.4)
    used = (fix_t < 40.0) | (fix_t >= 70.0)
    withheld = ~used | (np.arange(len(fix_t)) % 5 == 0)
    tracks = {"ekf": _track(t, 0.1 + 0.05 * np.clip(t - 40.0, 0.0, None)),
              "smoother": _track(t[t >= 5.0], 0.2)}
    return score(_result(tracks, fix_t, _pose(fix_t)[:, :2], withheld,
                         truth=_track(np.arange(0.0, 120.0, 0.05))))


def test_a_scored_run_reads_back_equal_through_json():
    s = _scored()
    d = json.loads(json.dumps(s.to_json()))
    assert RunSummary.from_json(d) == s
    assert RunSummary.from_json(d).to_json() == d
    e = s.estimators["ekf"]
    # the evaluation modules' own records, not copies
    assert isinstance(e.ate.none.position_m, Stats) and isinstance(e.nees, Consistency)
    assert all(isinstance(n, SensorNis) for n in e.nis.values())
    [drift] = e.gps_outages
    assert isinstance(drift, OutageDrift) and drift.reference == "truth"
    assert drift.drift_per_m > 0.0  # the ekf drifts 5 cm/s from the outage on
    assert d["estimators"]["ekf"]["ate_rmse_m"] == e.ate_rmse_m
    assert d["estimators"]["ekf"]["ate"]["none"]["heading_deg"]["n"] == e.ate.pairs
    assert d["ate_common"]["span_s"] == list(s.ate_common.span_s)


def test_metrics_json_keys_keep_their_order():
    d = _scored().to_json()
    assert list(d)[:3] == ["bag", "duration_s", "decode_s"]
    assert list(d["estimators"]["ekf"])[:3] == ["final_xy", "samples", "ate_rmse_m"]
    assert list(d["estimators"]["ekf"])[-3:] == ["pose_error", "ate_common_rmse_m", "span_s"]
    assert "rpe_note" not in d["estimators"]["ekf"]  # only where the truth has no heading


def test_an_unscored_outage_keeps_its_short_entry():
    o = OutageDrift(10.0, 20.0)
    assert o.to_json() == {"t0": 10.0, "t1": 20.0, "drift_per_m": None}
    assert OutageDrift.from_json(o.to_json()) == o


def test_a_partial_dictionary_reads_with_absent_keys_none():
    e = EstimatorScores.from_json({"ate_rmse_m": 0.3, "nis": {"/fix gps": {"verdict": "Pass"}},
                                   "nees": {"mean": 3.1, "band": [0.2, 9.3]}})
    assert e.ate_rmse_m == 0.3 and e.gps_holdout_rmse_m is None and e.samples is None
    assert e.nis["/fix gps"].nis.verdict == "Pass" and e.nis["/fix gps"].sensor is None
    assert e.nees.band == (0.2, 9.3) and e.nees.ratio is None
    s = RunSummary.from_json({"estimators": {"ekf": {}}, "lag_s": 10.0})
    assert s.lag_s == 10.0 and s.data is None and s.estimators["ekf"].error is None
