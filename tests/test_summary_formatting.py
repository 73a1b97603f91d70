"""Number formatting of the run summary and the report's tables: no signed zero, no speed for
an estimator that never estimated (the terminal's table has no speed column: rtf is in
metrics.json and the report, which explains it)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from ddfuse.evaluation import report
from ddfuse.evaluation.cli.run import print_summary
from ddfuse.evaluation.scores import RunSummary

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def test_a_drift_that_rounds_to_zero_has_no_sign():
    """The GPS-outage table printed -0.00."""
    m = {"data": {"t0": 0.0}, "gps_outages": [{"t0": 40.0, "t1": 60.0}],
         "estimators": {name: {"gps_outages": [{"distance_m": 20.0, "error_start_m": 0.1,
                                                "error_end_m": 0.1, "error_max_m": 0.2,
                                                "drift_per_m": drift, "reference": "truth"}]}
                        for name, drift in (("ekf_igvc", -0.00002), ("ekf", 0.00002),
                                            ("smoother", 0.0123))}}
    cells = re.findall(r"<td>([-+]?\d+\.\d\d)</td><td class=\"l\">truth",
                       report._outage_table(RunSummary.from_json(m)))
    assert cells == ["0.00", "0.00", "+1.23"]
    assert report.signed(-0.004) == "0.00" and report.signed(0.004) == "0.00"
    assert report.signed(-0.006) == "-0.01" and report.signed(0.25) == "+0.25"
    assert report.signed(-0.04, "+.1f") == "0.0" and report.signed(-10.0, "+.1f") == "-10.0"


def test_an_estimator_that_never_estimated_gets_no_speed(seed002_run):
    """`ekf_igvc ... 33358.134 ERROR: no estimate`: a real-time factor of an
    estimator that only turned measurements away is no speed; '-' in the summary and the
    report's table, metrics.json's rtf kept (its runtime is real)."""
    import io

    m = json.loads((seed002_run / "metrics.json").read_text())
    ran = m["estimators"]["ekf_landmark"]
    dead = {**ran, "samples": 0, "final_xy": None, "ate_rmse_m": None, "yaw_rmse_deg": None,
            "nees_mean": None, "rtf": 33358.134, "error": "no estimate: it never started"}
    m["estimators"] = {"ekf_landmark": ran, "ekf": dead}
    out = io.StringIO()
    print_summary(RunSummary.from_json(m), out)
    rows = {ln.split()[1]: ln for ln in out.getvalue().splitlines()[2:4]}
    # the terminal's short table has no speed column at all (the report's table explains it)
    assert "33358" not in out.getvalue() and f"{ran['rtf']:.3f}" not in out.getvalue()
    assert rows["ekf"].split()[0] == "-"  # unranked, last
    assert rows["ekf"].split("ERROR:")[0].split()[4:] == ["-"] * 4  # "real time"
    table = report._summary_table(RunSummary.from_json(m))
    assert "33358" not in table and f"{ran['rtf']:.0f}" in table
