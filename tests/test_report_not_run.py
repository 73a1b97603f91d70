"""The report's "Not run" reasons: an estimator off by default is not called one with a
missing sensor; a saved config that no longer loads falls back to metrics.json's sensor list."""

from __future__ import annotations

from pathlib import Path

import pytest
from ddfuse.evaluation import report
from ddfuse.evaluation.results import load_run

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def test_not_run_says_dr_is_off_by_default_on_a_wheel_speed_config(seed002_run):
    """The config has /joint_states wheels and robot.wheel_radius/track_width, so dr can run:
    the reason is that it is off by default, not a missing sensor."""
    page = (seed002_run / "report.html").read_text()
    assert "dr: needs" not in page
    assert "dr: off by default, --estimators dr runs it" in page
    run = load_run(seed002_run)
    assert [s.kind for s in run.summary.data.sensors].count("wheels") == 1
    # without the saved config text: judged on metrics.json's sensor list
    why = dict(report.not_run(run.summary))["dr"]
    assert why.startswith("off by default, --estimators dr runs it"), why
    cfg = report.run_config(run)
    assert cfg is not None and cfg.robot.wheel_radius == pytest.approx(0.1)
    assert dict(report.not_run(run.summary, cfg))["dr"] == why


def test_not_run_still_names_a_missing_sensor(seed002_run):
    """The sample has no GPS: ekf_igvc is refused for its sensors, with the saved config as
    without it."""
    run = load_run(seed002_run)
    for cfg in (report.run_config(run), None):
        assert dict(report.not_run(run.summary, cfg))["ekf_igvc"].startswith("needs ")


def test_a_saved_config_that_no_longer_loads_falls_back_to_the_sensor_list(seed002_run):
    run = load_run(seed002_run)
    run.config_text = "sensors: [not, a, mapping]\n"
    assert report.run_config(run) is None
    run.config_text = None
    assert report.run_config(run) is None
