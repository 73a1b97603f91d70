"""The run's warning when the GPS residuals stay correlated but the fixes are fused as white."""

from __future__ import annotations

from pathlib import Path

import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation.pipeline import GPS_CORRELATED_INTERVALS, gps_correlation_warnings
from ddfuse.evaluation.scores import RunSummary


def _cfg(tmp_path: Path, tau: float | None):
    p = tmp_path / "c.yaml"
    extra = "" if tau is None else f"\n      correlation_time: {tau}"
    p.write_text("sensors:\n  odometry:\n    - topic: /odom\n  gps:\n    - topic: /fix" + extra
                 + "\n")
    return load_config(p)


def _metrics(corr: list, interval: float = 0.4, error: str | None = None) -> RunSummary:
    ests = {f"e{i}": {"gps_residual_corr_s": c, "error": None} for i, c in enumerate(corr)}
    if error:
        ests["stopped"] = {"gps_residual_corr_s": 100.0, "error": error}
    return RunSummary.from_json({"data": {"gps_fix_interval_s": interval}, "estimators": ests})


def test_correlated_residuals_with_white_fixes_warn_with_a_value(tmp_path):
    """rl_husky_gps.bag's figures: 5.2 and 5.4 s at 0.4 s; the median rounded up is offered."""
    (w,) = gps_correlation_warnings(_metrics([5.168, 5.396]), _cfg(tmp_path, None))
    assert w.startswith("/fix: the GPS residuals to the tracks stay correlated for 5.3 s "
                        "(median of 2 tracks), 13 fix intervals of 0.4 s")
    assert "set correlation_time: 6 under the GPS sensor" in w
    # a stopped estimator's residuals are not the data's
    (w,) = gps_correlation_warnings(_metrics([5.168, 5.396], error="boom"), _cfg(tmp_path, None))
    assert "for 5.3 s (median of 2 tracks)" in w


@pytest.mark.parametrize("corr, tau", [
    ([0.0, 0.0], None),  # white fixes (the simulated husky, gps-outage, the sample bag)
    ([GPS_CORRELATED_INTERVALS * 0.4 * 0.99], None),  # just short of the threshold
    ([5.2, 5.4], 6.0),  # already modelled
    ([], None),  # no track measured it
])
def test_no_warning(tmp_path, corr, tau):
    assert gps_correlation_warnings(_metrics(corr), _cfg(tmp_path, tau)) == []


def test_just_over_the_threshold_warns(tmp_path):
    c = GPS_CORRELATED_INTERVALS * 0.4 * 1.01
    assert len(gps_correlation_warnings(_metrics([c]), _cfg(tmp_path, None))) == 1
