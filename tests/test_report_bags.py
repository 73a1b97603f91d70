"""`ddfuse run` and its report on the real bags (slow; skipped without ../shared/data)."""

from __future__ import annotations

import json
import re

import pytest
from ddfuse.evaluation import cli


@pytest.mark.slow
def test_husky_report_with_gps_holdout(husky_bag, tmp_path):
    out = tmp_path / "husky"
    assert cli.main(["run", str(husky_bag), "-o", str(out), "--estimators", "ekf,smoother",
                     "--gps-holdout", "every:5"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    # the data's documented facts: 989 fixes, no truth. Its "about 395 m of path" is the
    # polyline through the fixes, lengthened by their noise; the odometry integrates to 359 m,
    # 349 m at its fitted speed scale 0.972 (docs/results/smoother_monte_carlo.md)
    assert m["data"]["path_length_m"] == pytest.approx(349, abs=15)
    assert m["data"]["gps_fixes"] == 989 and m["gps_holdout_fixes"] == 989 // 5
    assert not m["has_ground_truth"]
    for name in ("ekf", "smoother"):
        e = m["estimators"][name]
        assert e["ate_rmse_m"] is None and e["nees"] is None
        assert 0.3 < e["gps_holdout_rmse_m"] < 5.0
        assert e["nis"]["/fix gps"]["n"] > 700
        # the receiver's error wanders over seconds (every track: 3.8-7.9 s with the fixes fused
        # as white, 10.6-18.7 s with the shipped correlation_time of 19 s)
        assert 2.0 < e["gps_residual_corr_s"] < 25.0
    assert m["data"]["gps_fix_interval_s"] == pytest.approx(0.4, abs=0.01)
    # the data README: the neighbouring fixes predict a fix to about 0.16 m
    assert m["gps_holdout_interpolation_rmse_m"] == pytest.approx(0.16, abs=0.03)
    page = (out / "report.html").read_text()
    # every track on the same fixes: the filters have no estimate before their heading is known
    scored = m["gps_holdout_scored_fixes"]
    assert 180 < scored < 197
    assert {m["estimators"][n]["gps_holdout_m"]["n"] for n in ("ekf", "smoother")} == {scored}
    assert f"Score: RMS distance to the {scored} of the 197 GPS fixes withheld" in page
    # of the best track (the smoother since the shipped correlation_time of 19 s)
    assert re.search(r"Caution: the GPS residuals to (ekf|smoother) stay correlated for", page)
    assert page.count("data:image/png;base64,") == 7  # no NEES figure without truth


@pytest.mark.slow
def test_mrclam_report_scores_against_truth(mrclam_bag, tmp_path):
    out = tmp_path / "mrclam"
    assert cli.main(["run", str(mrclam_bag), "-o", str(out), "--estimators",
                     "ekf,ekf_landmark"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    dr, lm = m["estimators"]["ekf"], m["estimators"]["ekf_landmark"]
    # dead reckoning ends metres off (README: 3.6 m and 97 deg); the landmarks carry the estimate
    assert lm["ate_rmse_m"] < 0.5 < dr["ate_rmse_m"]
    assert lm["nis"]["/landmarks landmark"]["n"] > 4000
    assert m["data"]["path_length_from"] == "ground truth"
    # the Vicon truth's 17 full-turn "spins" (a resampling artefact) are not scored
    assert any(re.search(r"/ground_truth: 31 of 75000 ground-truth samples in 17 stretch", w)
               for w in m["warnings"]), m["warnings"]
    page = (out / "report.html").read_text()
    assert "Best here: ekf_landmark" in page and "it is dead reckoning" in page
