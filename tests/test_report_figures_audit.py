"""The report's figures plot what is scored and draw one row per distinct NIS log; the data
facts, events and warnings headings say what they hold."""

from __future__ import annotations

import numpy as np
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import plots, report
from ddfuse.evaluation.consistency import InnovationTable
from ddfuse.evaluation.results import SavedRun
from ddfuse.evaluation.scores import EstimatorScores, RunSummary


def _run(metrics: dict, tracks: dict, gps_t=None, gps_xy=None, **kw) -> SavedRun:
    gps_t = np.zeros(0) if gps_t is None else gps_t
    gps_xy = np.zeros((0, 2)) if gps_xy is None else gps_xy
    return SavedRun(None, metrics, tracks, None, gps_t, gps_xy,
                    np.tile(np.eye(2) * 0.01, (len(gps_t), 1, 1)), np.zeros(len(gps_t), bool),
                    **kw)


def _line(t: np.ndarray, speed: float = 1.0) -> Trajectory:
    pose = np.column_stack([speed * t, np.zeros_like(t), np.zeros_like(t)])
    return Trajectory(t, pose, np.tile(np.eye(3) * 0.01, (len(t), 1, 1)))


def test_errors_without_truth_compare_the_antenna_where_the_fix_was_taken():
    """sample_husky without truth, GPS delay 0.2 s: the est - fix differences carried the
    motion over the delay (+0.21 m along track at 1 m/s) though the hold-out score removes it.
    A track exactly right, a fix describing the antenna 0.2 s before its stamp, 0.3 m ahead."""
    t = np.arange(0.0, 60.0, 0.1)
    tr = _line(t)
    gps_t = np.arange(5.0, 55.0, 1.0)
    gps_xy = np.column_stack([gps_t - 0.2 + 0.3, np.zeros_like(gps_t)])
    m = {"estimators": {"ekf": {}}, "data": {"t0": 0.0},
         "gps_antenna": {"lever_arm": [0.3, 0.0], "delay_s": 0.2}}
    fig, caption = plots.errors(_run(m, {"ekf": tr}, gps_t, gps_xy))
    east = fig.axes[0].lines[0].get_ydata()
    assert np.abs(east).max() < 1e-9  # it was 0.2 - 0.3 = -0.1 m throughout
    assert "its GPS antenna (lever arm 0.3, 0 m) 0.2 s before the fix's stamp" in caption


def test_nis_figure_draws_one_row_for_the_batchs_copy_of_the_smoothers_innovations():
    t = np.arange(0.0, 30.0, 0.5)
    table = InnovationTable(t, np.full(len(t), "/fix"), np.full(len(t), "gps"),
                            np.ones(len(t)), np.full(len(t), 2), np.ones(len(t), bool))
    same = {"/fix gps": {"verdict": "Pass", "ratio": 0.5, "outside": 0.0}}
    m = {"estimators": {"smoother": {"nis": same}, "batch": {"nis": dict(same)}},
         "data": {"t0": 0.0}}
    run = _run(m, {"smoother": _line(t), "batch": _line(t)},
               innovations={"smoother": table, "batch": table},
               log_owner={"smoother": "smoother", "batch": "batch"})
    fig = plots.nis(run)
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert len(titles) == 1 and titles[0].startswith("smoother: /fix gps")


def test_nis_titles_of_long_topics_stay_within_their_column():
    """rl_husky_gps.bag's ``/husky_velocity_controller/odom yaw_rate`` ran into the next
    panel's title in a row of five sensors."""
    t = np.arange(0.0, 30.0, 0.5)
    topics = [("/imu/data", "gyro"), ("/husky_velocity_controller/odom", "v"),
              ("/husky_velocity_controller/odom", "yaw_rate"), ("/imu/data", "heading"),
              ("/a_long_namespace/gps_receiver/fix", "gps")]
    n = len(t)
    sensor = np.array([topics[i % 5][0] for i in range(n)])
    kind = np.array([topics[i % 5][1] for i in range(n)])
    table = InnovationTable(t, sensor, kind, np.ones(n), np.ones(n, int), np.ones(n, bool))
    nis = {f"{a} {b}": {"verdict": "Fail", "ratio": 0.01, "outside": 0.49} for a, b in topics}
    m = {"estimators": {"ekf_igvc": {"nis": nis}}, "data": {"t0": 0.0}}
    fig = plots.nis(_run(m, {"ekf_igvc": _line(t)}, innovations={"ekf_igvc": table},
                         log_owner={"ekf_igvc": "ekf_igvc"}))
    r = fig.canvas.get_renderer()
    boxes = sorted((ax.title.get_window_extent(r) for ax in fig.axes if ax.get_title()),
                   key=lambda b: b.x0)
    assert len(boxes) == 5
    for left, right in zip(boxes, boxes[1:], strict=False):
        assert left.x1 < right.x0, (left, right)
    assert all(b.x0 >= 0 and b.x1 <= fig.bbox.width for b in boxes)
    assert fig.axes[2].get_title().startswith("ekf_igvc: /husky_velocity_controller/")


def test_events_say_how_many_were_cut():
    e = {"events": [f"t={i}: e" for i in range(20)], "events_total": 57}
    assert report.event_summary(EstimatorScores.from_json(e)).startswith("first 20 of 57 events")
    one = EstimatorScores.from_json({"events": ["a"], "events_total": 1})
    assert report.event_summary(one) == "1 event"


def test_warnings_heading_and_the_gps_path_length_method():
    m = {"warnings": ["/odom: 40% of its messages dropped"], "data": {
        "path_length_m": 346.4, "path_length_from": "GPS fixes"}, "estimators": {}}
    assert "<h2>Warnings</h2>" in report._warnings(RunSummary.from_json(m))
    assert "346.4 m (through 3 s block medians of the GPS fixes)" in report._facts(
        RunSummary.from_json(m))
