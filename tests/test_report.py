"""`ddfuse run` writes a self-contained report.html from saved results; `ddfuse report OUTDIR`
re-renders it from those results alone; bad directories give one error line and exit 2."""

from __future__ import annotations

import base64
import html
import json
import math
import re
import shutil
from dataclasses import replace
from pathlib import Path

import matplotlib.colors
import matplotlib.pyplot as plt
import numpy as np
import pytest
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation import cli, plots, report
from ddfuse.evaluation.cli.terminal import Bars, progress
from ddfuse.evaluation.estimators import SPECS, TRACK_TO_SPEC
from ddfuse.evaluation.export import read_csv, write_csv
from ddfuse.evaluation.results import load_run
from ddfuse.evaluation.scores import DataFacts, RunSummary

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory) -> Path:
    """The embedded sample, two estimators, a 20 s GPS outage (one run for the module)."""
    out = tmp_path_factory.mktemp("run") / "out"
    code = cli.main(["run", "-o", str(out), "--estimators", "ekf,smoother,smoother_lagged",
                     "--gps-holdout", "window:40:60"])
    assert code == 0
    return out


def _images(page: str) -> list[bytes]:
    return [base64.b64decode(b) for b in re.findall(r'src="data:image/png;base64,([^"]+)"', page)]


def test_run_writes_a_self_contained_report(sample_run):
    page = (sample_run / "report.html").read_text()
    # one file: no script, no stylesheet or image fetched from anywhere
    assert "<script" not in page.lower()
    assert not re.search(r'(src|href)="(?!data:image/png;base64,)', page)
    assert "http://" not in page and "https://" not in page
    imgs = _images(page)
    assert len(imgs) == 8 and all(i.startswith(PNG) for i in imgs)
    assert sorted(p.name for p in (sample_run / "plots").iterdir()) == sorted(
        f"{n}.png" for n in ("trajectories", "trajectory_zooms", "trajectories_each", "errors",
                             "nees", "nis", "covariance", "latency"))
    m = json.loads((sample_run / "metrics.json").read_text())
    for name in ("ekf", "smoother", "smoother_lagged"):
        assert f"<b>{name}</b>" in page
        ate = m["estimators"][name]["ate_rmse_m"]
        assert f"{ate:.3f}" in page  # the summary table shows the saved number
    # ranked on the common span and stamps (pipeline._common_ate)
    best = min(m["estimators"], key=lambda n: m["estimators"][n]["ate_common_rmse_m"])
    assert f"Best here: {best} with" in page
    assert "GPS outage 40-60 s" in page or "GPS outage 39-60 s" in page
    assert "sample_husky.yaml" in page and "heading_offset: estimate" in page  # the config


def test_metrics_json_holds_evo_style_scores_and_consistency(sample_run):
    m = json.loads((sample_run / "metrics.json").read_text())
    e = m["estimators"]["ekf"]
    for key in ("final_xy", "ate_rmse_m", "rpe_rmse_m", "nees_mean", "gps_holdout_rmse_m",
                "runtime_s", "rtf", "update_ms"):
        assert e[key] is not None, key
    assert e["ate"]["none"]["position_m"]["rmse"] == e["ate_rmse_m"]
    assert set(e["ate"]["none"]["position_m"]) == {"rmse", "mean", "median", "std", "min",
                                                   "max", "n"}
    # aligning can only lower the RMSE (SE(2) minimises it over rigid motions)
    assert e["ate"]["se2"]["position_m"]["rmse"] <= e["ate_rmse_m"] + 1e-9
    assert e["rpe"]["10m"]["unit"] == "m" and e["rpe"]["1s"]["position_m"]["n"] > 50
    gps = e["nis"]["/fix gps"]
    assert gps["dof"] == 2 and gps["accepted"] + gps["rejected"] == gps["n"]
    assert gps["verdict"] in ("Pass", "Warn", "Fail")
    [outage] = m["gps_outages"]
    assert outage["t1"] - outage["t0"] == pytest.approx(20.0, abs=0.5)
    drift = e["gps_outages"][0]
    assert drift["reference"] == "truth" and drift["distance_m"] > 10
    assert m["data"]["path_length_from"] == "ground truth"
    assert m["data"]["gps_fixes_withheld"] == m["gps_holdout_fixes"] > 40


def test_metrics_json_is_the_run_summarys_serialisation_byte_for_byte(sample_run):
    text = (sample_run / "metrics.json").read_text()
    summary = load_run(sample_run).summary
    assert json.dumps(summary.to_json(), indent=2) + "\n" == text
    assert RunSummary.from_json(summary.to_json()) == summary
    assert summary.estimators["ekf"].ate.none.position_m.rmse == summary.estimators[
        "ekf"].ate_rmse_m


def test_calibration_states_at_the_end_are_reported_and_match_the_simulated_truth(sample_run):
    """Every estimator's gyro bias, heading offset and odometry scales at the end of the run,
    with its sigma, in metrics.json and the report. The sample's truth (data/sample_husky.yaml):
    heading offset 0.35 rad, k_v = 0.1635 / 0.165 = 0.9909, k_w = k_v 0.555 / 0.5826 = 0.9440;
    each within 3 of the estimator's sigmas (the gyro bias walks: its truth is not stated). The
    smoother's two outputs meet at the newest keyframe."""
    m = json.loads((sample_run / "metrics.json").read_text())
    finals = {n: e["final_state"]["states"] for n, e in m["estimators"].items()}
    assert set(finals) == {"ekf", "smoother", "smoother_lagged"}
    kv_true = 0.1635 / 0.165
    for name, st in finals.items():
        assert list(st) == ["bg", "hoff", "k_v", "k_w"], name
        for label, true in (("hoff", 0.35), ("k_v", kv_true), ("k_w", kv_true * 0.555 / 0.5826)):
            v, sd = st[label]["value"], st[label]["sigma"]
            assert sd > 0 and abs(v - true) < 3 * sd, (name, label, v, sd)
    assert finals["smoother"] == finals["smoother_lagged"]
    page = (sample_run / "report.html").read_text()
    table = page.split("<h2>Calibration at the end of the run</h2>")[1].split("</table>")[0]
    hoff = finals["ekf"]["hoff"]
    assert (f"{np.degrees(hoff['value']):.2f} ± {np.degrees(hoff['sigma']):.2f}" in table)
    assert "odometry yaw-rate scale k_w" in table


def test_report_re_renders_from_saved_results_only(sample_run, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(sample_run, copy)
    first = (copy / "report.html").read_text()
    (copy / "report.html").unlink()
    shutil.rmtree(copy / "plots")
    assert cli.main(["report", str(copy)]) == 0
    # the run's headline, then the page's path last
    out = capsys.readouterr().out.strip().splitlines()
    assert out[0].startswith("---- headline ") and out[1].startswith("Best: ")
    assert out[-1] == str(copy / "report.html")
    again = (copy / "report.html").read_text()
    assert _images(again) == _images(first)
    strip = re.compile(r"<p class='sub'>.*?</p>")
    assert strip.sub("", again).replace(str(copy), "X") == strip.sub("", first).replace(
        str(sample_run), "X")


def _assert_one_line(code, capsys, path):
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = err.strip().split("\n")
    assert len(lines) == 1 and lines[0].startswith("ddfuse: error: ") and str(path) in lines[0]


def test_report_on_a_directory_without_results(tmp_path, capsys):
    _assert_one_line(cli.main(["report", str(tmp_path)]), capsys, tmp_path)
    missing = tmp_path / "nope"
    _assert_one_line(cli.main(["report", str(missing)]), capsys, missing)


def test_report_on_damaged_results(sample_run, tmp_path, capsys):
    bad = tmp_path / "bad"
    shutil.copytree(sample_run, bad)
    (bad / "run.npz").write_bytes(b"not a zip")
    _assert_one_line(cli.main(["report", str(bad)]), capsys, bad)
    (bad / "run.npz").write_bytes((sample_run / "run.npz").read_bytes())
    (bad / "metrics.json").write_text("{")
    _assert_one_line(cli.main(["report", str(bad)]), capsys, bad)


def test_saved_run_round_trip(sample_run):
    run = load_run(sample_run)
    assert list(run.tracks) == ["ekf", "smoother", "smoother_lagged"]
    assert run.log_owner["smoother_lagged"] == "smoother"
    assert run.gps_withheld.sum() == run.summary.gps_holdout_fixes
    assert len(run.innovations["ekf"]) == sum(
        s.nis.n for s in run.summary.estimators["ekf"].nis.values())
    assert run.truth is not None and run.truth.t[0] > 1.6e9
    # output stamps are distinct (one sample per output tick)
    assert np.all(np.diff(run.tracks["ekf"].t) > 0)


def test_csv_keeps_epoch_stamps_and_nan(tmp_path):
    t = 1_700_000_000.0 + np.array([0.025339603, 0.125339508])
    cov = np.full((2, 3, 3), np.nan)
    cov[0] = np.diag([1e-4, 2e-4, 3e-5])
    tr = Trajectory(t, np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 0.5]]), cov)
    write_csv(tmp_path / "a.csv", tr)
    back = read_csv(tmp_path / "a.csv")
    np.testing.assert_allclose(back.t, t, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.isnan(back.pose), np.isnan(tr.pose))
    np.testing.assert_allclose(back.cov[0], cov[0])
    assert np.isnan(back.cov[1]).all()


def test_progress_bars_wait_and_stay_quiet_off_a_terminal(capsys):
    now = [0.0]
    bars = Bars(delay=2.0, clock=lambda: now[0])
    bars.update("decode", 0.5)
    assert bars.bar is None  # a short run shows nothing
    now[0] = 3.0
    bars.update("estimate", 1.0)
    assert bars.bar is None  # a stage that is already done starts no bar
    bars.update("estimate", 0.2)
    assert bars.bar is not None and "estimate" in bars.tasks
    bars.stop()
    assert progress() is None  # pytest's captured output is not a terminal


def test_run_on_a_damaged_bag_reports_what_was_read(tmp_path, capsys):
    bag = tmp_path / "damaged.bag"
    shutil.copy(ROOT / "data" / "sample_husky.bag", bag)
    shutil.copy(ROOT / "data" / "sample_husky.yaml", tmp_path / "damaged.yaml")
    data = bytearray(bag.read_bytes())
    data[len(data) // 2: len(data) // 2 + 5000] = b"\xff" * 5000  # a bad copy mid-file
    bag.write_bytes(bytes(data))
    out = tmp_path / "out"
    code = cli.main(["run", str(bag), "-o", str(out), "--estimators", "ekf"])
    _, err = capsys.readouterr()
    # the reader reads past the damaged chunk (estimation.ros1_scan): the run completes, and
    # the terminal and the report say what was lost and that the estimators bridged the gap
    assert code == 0
    (damage,) = [ln for ln in err.splitlines() if "damaged record at byte" in ln]
    assert str(bag) in damage and "messages lost; reading went on" in damage
    assert any("gap(s) with no message" in ln for ln in err.splitlines())
    page = html.unescape((out / "report.html").read_text())
    assert damage.removeprefix("ddfuse: warning: ") in page
    assert json.loads((out / "metrics.json").read_text())["duration_s"] > 110


@pytest.mark.parametrize("n", [0, 1, 7, 3000])
def test_track_files_are_byte_for_byte_what_savetxt_wrote(tmp_path, n):
    """write_tum/write_csv format all rows in one go; the files must stay exactly those of
    np.savetxt with the formats they always had (NaN and inf included)."""
    from ddfuse.estimation.runner import Trajectory
    from ddfuse.evaluation import export

    rng = np.random.default_rng(n)
    t = 1.7e9 + np.cumsum(rng.random(n))
    pose, cov = rng.normal(size=(n, 3)) * 100, rng.normal(size=(n, 3, 3))
    if n > 3:
        cov[2], pose[1, 2], pose[3, 0] = np.nan, np.nan, np.inf
    tr = Trajectory(t, pose, cov)
    export.write_tum(tmp_path / "a.tum", tr)
    export.write_csv(tmp_path / "a.csv", tr)
    yaw = np.nan_to_num(pose[:, 2])
    z = np.zeros(n)
    np.savetxt(tmp_path / "b.tum", np.column_stack([t, pose[:, 0], pose[:, 1], z, z, z,
                                                    np.sin(yaw / 2), np.cos(yaw / 2)]),
               fmt="%.9f %.6f %.6f %.6f %.9f %.9f %.9f %.9f")
    np.savetxt(tmp_path / "b.csv", np.column_stack([t, pose, cov.reshape(n, 9)]), delimiter=",",
               header=",".join(export.CSV_COLUMNS), comments="", fmt=["%.9f"] + ["%.10g"] * 12)
    for ext in ("tum", "csv"):
        assert (tmp_path / f"a.{ext}").read_bytes() == (tmp_path / f"b.{ext}").read_bytes()


# --- what the report and its figures say on runs without GPS, without truth, or neither ---

def _sample_config(tmp: Path, *, truth: bool) -> Path:
    """data/sample_husky.yaml without its GPS (and without its truth unless ``truth``): the
    estimators' local frame is then the start pose (or the truth's, starting on it)."""
    import yaml

    cfg = yaml.safe_load((ROOT / "data" / "sample_husky.yaml").read_text())
    del cfg["sensors"]["gps"], cfg["frame"]
    if not truth:
        del cfg["ground_truth"], cfg["initial_pose"]
    cfg["smoother"] = {"lag": 10.0, "keyframe": "rate", "keyframe_rate": 5.0}
    path = tmp / ("truth_no_gps.yaml" if truth else "no_gps.yaml")
    path.write_text(yaml.safe_dump(cfg))
    return path


def _run_sample(tmp: Path, truth: bool) -> Path:
    out = tmp / "out"
    assert cli.main(["run", str(ROOT / "data" / "sample_husky.bag"), "-c",
                     str(_sample_config(tmp, truth=truth)), "-o", str(out),
                     "--estimators", "ekf,smoother"]) == 0
    return out


@pytest.fixture(scope="module")
def no_gps_run(tmp_path_factory) -> Path:
    """The sample without GPS and without truth (like rl_jackal.bag)."""
    return _run_sample(tmp_path_factory.mktemp("nogps"), truth=False)


@pytest.fixture(scope="module")
def truth_no_gps_run(tmp_path_factory) -> Path:
    """The sample with its truth but without GPS (like mrclam, without the landmarks)."""
    return _run_sample(tmp_path_factory.mktemp("truth"), truth=True)


def _section(page: str, heading: str) -> str:
    return page.split(f"<h2>{heading}</h2>")[1].split("<h2>")[0]


def _row(page: str, key: str) -> str:
    return re.search(rf'<td class="l">{key}</td><td class="l">(.*?)</td>', page).group(1)


def test_no_error_figure_without_gps_or_truth_and_the_report_says_why(no_gps_run):
    m = json.loads((no_gps_run / "metrics.json").read_text())
    assert m["data"]["gps_fixes"] == 0 and not m["has_ground_truth"]  # the case under test
    page = (no_gps_run / "report.html").read_text()
    assert not (no_gps_run / "plots" / "errors.png").exists()
    assert 'alt="errors"' not in page
    assert "No error figure: the bag has neither ground truth nor GPS fixes" in page
    # trajectories, the close-up where they disagree most, each, nis, covariance, latency
    assert len(_images(page)) == 6


def test_data_table_names_this_runs_frame_and_omits_what_it_cannot_measure(no_gps_run, sample_run):
    page = (no_gps_run / "report.html").read_text()
    assert _row(page, "local frame").startswith("the start pose: origin where the robot started")
    assert "or the start pose" not in page
    assert _row(page, "path length").startswith("not measured: no ground truth or GPS fixes")
    assert _row(page, "GPS fixes") == "none"
    enu = (sample_run / "report.html").read_text()
    d = json.loads((sample_run / "metrics.json").read_text())["data"]
    assert _row(enu, "local frame").startswith(f"ENU about the GPS datum {d['datum'][0]:.6f}°")
    # fixes present, none withheld: said so, not "0 withheld (None)"
    m = {"data": {"gps_fixes": 989, "gps_fixes_withheld": 0}, "gps_holdout": None}
    assert report._gps_fixes(RunSummary.from_json(m)) == "989, none withheld (no --gps-holdout)"
    m = {"data": {"gps_fixes": 989, "gps_fixes_withheld": 197}, "gps_holdout": "every:5"}
    assert report._gps_fixes(RunSummary.from_json(m)) == "989, of which 197 withheld (every:5)"


def test_frame_of_each_kind_of_run():
    def run(datum=None, landmarks=0, initial_pose=None):
        return RunSummary(data=DataFacts(datum=datum, landmarks=landmarks),
                          initial_pose=initial_pose)

    datum = run(datum=[47.4, 8.5, 488.0])
    assert plots.frame(datum)["kind"] == "enu" and plots.frame(datum)["x"] == "x east"
    lm = run(landmarks=15, initial_pose="first ground-truth pose")
    assert plots.frame(lm)["kind"] == "map" and "east" not in plots.frame(lm)["x"]
    assert plots.frame(run(initial_pose="first ground-truth pose"))["kind"] == "truth"
    given = run(initial_pose=[1.0, 2.0, math.pi / 2])
    assert plots.frame(given)["kind"] == "given" and "90.0°" in plots.frame(given)["text"]
    assert plots.frame(run())["kind"] == "start"
    assert plots.frame(RunSummary())["kind"] == "start"  # no data facts at all
    # a metrics.json dictionary (online_frame's facts) is read as its summary
    assert plots.frame({"data": {"datum": [47.4, 8.5, 488.0], "landmarks": 0}}) == \
        plots.frame(datum)
    assert plots.frame({"data": {}, "initial_pose": [1.0, 2.0, math.pi / 2]}) == \
        plots.frame(given)


def test_estimators_not_run_are_named_with_the_reason(no_gps_run, sample_run):
    summary = _section((no_gps_run / "report.html").read_text(), "Summary")
    igvc = SPECS["ekf_igvc"]
    assert f"ekf_igvc: needs {igvc.needs}, which the config does not have" in summary
    assert "ekf_landmark: needs" in summary
    # allowed by the config but not asked for with --estimators
    assert "batch: not among the estimators asked for (--estimators ekf,smoother)" in summary
    assert "dr: off by default" in summary
    ran = set(json.loads((no_gps_run / "metrics.json").read_text())["estimators"])
    assert ran.isdisjoint(n for n, _ in report.not_run(RunSummary.from_json(
        json.loads((no_gps_run / "metrics.json").read_text()))))
    # the sample has GPS: ekf_igvc could have run, it was not asked for
    with_gps = json.loads((sample_run / "metrics.json").read_text())
    assert dict(report.not_run(RunSummary.from_json(with_gps)))["ekf_igvc"] == \
        "not among the estimators asked for (--estimators ekf,smoother,smoother_lagged)"
    assert with_gps["estimators_requested"] == ["ekf", "smoother", "smoother_lagged"]
    # one estimator's track not asked for, its other one asked for: said, not silently absent
    lagged_only = {**with_gps, "estimators_requested": ["ekf", "smoother_lagged"],
                   "estimators": {k: v for k, v in with_gps["estimators"].items()
                                  if k != "smoother"}}
    assert dict(report.not_run(RunSummary.from_json(lagged_only)))["smoother"] == (
        "computed for smoother_lagged (the same estimator) but not asked for (--estimators "
        "ekf,smoother_lagged)")
    # results written before metrics.json recorded the request: judged on the config alone
    del with_gps["estimators_requested"]
    assert dict(report.not_run(RunSummary.from_json(with_gps)))["ekf_igvc"] == \
        "not among the estimators asked for (--estimators)"
    # asked for but no track (e.g. the list was edited by hand): not called "not asked for"
    with_gps["estimators_requested"] = ["ekf", "ekf_igvc"]
    assert dict(report.not_run(RunSummary.from_json(with_gps)))["ekf_igvc"] == \
        "asked for, but it produced no track"


def test_event_times_are_seconds_since_the_first_measurement(no_gps_run):
    m = json.loads((no_gps_run / "metrics.json").read_text())
    t0 = m["data"]["t0"]
    assert t0 > 1e9  # the sample's stamps are epoch: an unconverted one would show
    [started] = [e for e in m["estimators"]["ekf"]["events"] if "started" in e]
    t_abs = float(started.split(":")[0][2:])
    page = (no_gps_run / "report.html").read_text()
    assert abs(t_abs - t0) < 1e-3  # it starts at the first measurement: t=0
    assert "t=0.000 s: ekf_unicycle: started" in page
    assert not re.search(r"t=1\d{9}", page)
    assert "Times are seconds since the first measurement" in page
    assert report.relative_event("t=1432235556.439: x", 1432235500.0) == "t=56.439 s: x"
    assert report.relative_event("rejected /fix: gate: 4", 1.0) == "rejected /fix: gate: 4"
    assert report.relative_event("t=100.000: x", 100.0003) == "t=0.000 s: x"


def test_summary_footnote_describes_only_the_columns_shown(no_gps_run, sample_run):
    note = _section((no_gps_run / "report.html").read_text(), "Summary").split("</table>")[1]
    assert "<th>ATE" not in _section((no_gps_run / "report.html").read_text(), "Summary")
    assert "ATE" not in note and "RPE" not in note and "RTF:" in note
    full = _section((sample_run / "report.html").read_text(), "Summary").split("</table>")[1]
    assert "ATE against the ground truth" in full and "RPE over 1 s" in full


def test_with_truth_and_no_gps_the_errors_are_against_the_truth(truth_no_gps_run):
    run = load_run(truth_no_gps_run)
    assert run.truth is not None and len(run.gps_t) == 0
    fig, caption = plots.errors(run)
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert len(labels) == 3 * len(run.tracks)
    assert labels[:3] == ["x error (truth frame) [m]", "y error (truth frame) [m]",
                          "heading error [deg]"]
    assert not any("GPS" in lb or "east" in lb for lb in labels)
    assert caption.startswith("Errors against the ground truth") and "outages" not in caption
    page = (truth_no_gps_run / "report.html").read_text()
    assert 'alt="errors"' in page and "the ground truth&#x27;s frame" in page


def test_error_axes_are_named_by_the_frame(sample_run):
    run = load_run(sample_run)
    fig, _ = plots.errors(run)
    assert fig.axes[0].get_ylabel() == "east error [m]"
    mapped = replace(run, summary=replace(run.summary, data=replace(
        run.summary.data, datum=None, landmarks=15)))
    fig, caption = plots.errors(mapped)
    assert [ax.get_ylabel() for ax in fig.axes[:2]] == ["x error (map) [m]", "y error (map) [m]"]
    assert "landmark map's frame" in caption


def test_start_marker_is_the_earliest_position_of_any_source(sample_run):
    run = load_run(sample_run)
    late = {n: Trajectory(tr.t[60:], tr.pose[60:] + 3.0, tr.cov[60:])
            for n, tr in run.tracks.items()}  # tracks start 6 s in, elsewhere
    gps_first = replace(run, truth=None, tracks=late)
    x, y, whose, t = plots.start_point(gps_first)
    assert whose == "GPS fix" and (x, y) == tuple(run.gps_xy[0])
    assert t == pytest.approx(run.gps_t[0] - run.summary.data.t0)
    fig = plots.trajectories(gps_first)
    [marker] = [ln for ln in fig.axes[0].lines if ln.get_label().startswith("start")]
    assert tuple(marker.get_xydata()[0]) == (x, y)
    assert marker.get_label().startswith("start: first GPS fix position")
    # the truth starts first when there is one
    assert plots.start_point(replace(run, tracks=late))[2] == "ground truth"
    # a track that starts first wins
    early = {"ekf": Trajectory(run.gps_t[:1] - 1.0, np.array([[7.0, 8.0, 0.0]]),
                               np.eye(3)[None])}
    assert plots.start_point(replace(gps_first, tracks=early))[:3] == (7.0, 8.0, "ekf")


def _visible_labels(fig, ax, axis: str) -> list[str]:
    fig.canvas.draw()
    getter = ax.get_yticklabels if axis == "y" else ax.get_xticklabels
    lo, hi = sorted(ax.get_ylim() if axis == "y" else ax.get_xlim())
    return [t.get_text() for t in getter()
            if t.get_visible() and t.get_text() and lo <= (t.get_position()[1 if axis == "y"
                                                                                else 0]) <= hi]


def test_log_axes_carry_tick_labels_when_they_span_under_a_decade(sample_run):
    run = load_run(sample_run)
    tracks = {}
    for name, tr in run.tracks.items():
        cov = tr.cov.copy()
        sig = np.radians(np.linspace(0.2, 0.4, len(tr)))  # heading sigma 0.2-0.4 deg
        cov[:, 2, 2] = sig ** 2
        tracks[name] = Trajectory(tr.t, tr.pose, cov)
    fig = plots.covariance(replace(run, tracks=tracks))
    trace_ax, heading_ax = fig.axes[:2]
    labels = _visible_labels(fig, heading_ax, "y")
    assert len(labels) >= 2, labels
    assert {"0.2", "0.3", "0.4"} <= set(labels)
    assert len(_visible_labels(fig, trace_ax, "y")) >= 2
    # a narrow span (no 1-9 step inside) still gets two labels
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0.201, 0.209])
    ax.set_yscale("log")
    plots.label_log_axis(ax.yaxis)
    assert len(_visible_labels(fig, ax, "y")) >= 2
    # many decades: the decades, in plain text (no mathtext, whose parser is costly to build)
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1e-6, 30.0])
    ax.set_yscale("log")
    plots.label_log_axis(ax.yaxis)
    labels = _visible_labels(fig, ax, "y")
    assert {"10\u207b\u2076", "10\u207b\u00b3", "0.1", "1", "10"} <= set(labels), labels
    assert not any("$" in label for label in labels)
    plt.close("all")


def test_every_column_of_the_panels_has_x_tick_labels(sample_run):
    run = load_run(sample_run)
    # six panels of the tall path: 5 in the first row, 1 in the second
    six = {**run.tracks, "batch": run.tracks["smoother"], "dr": run.tracks["ekf"],
           "ekf_igvc": run.tracks["ekf"]}
    fig = plots.trajectories_each(replace(run, tracks=six))
    axes = [ax for ax in fig.axes if ax.axison]
    assert len(axes) == 6
    bottoms = {}
    for ax in axes:  # the lowest drawn panel of each column
        col = round(ax.get_position().x0, 2)
        if col not in bottoms or ax.get_position().y0 < bottoms[col].get_position().y0:
            bottoms[col] = ax
    assert len(bottoms) == 5
    for ax in bottoms.values():
        assert len(_visible_labels(fig, ax, "x")) >= 2, ax.get_title()
        assert ax.get_xlabel() == "x east [m]"
    plt.close("all")


def test_each_estimator_has_one_colour_in_every_figure(sample_run):
    names = list(TRACK_TO_SPEC)
    cols = plots.colors(names)
    assert len(set(cols.values())) == len(names)  # distinct
    assert "tab:red" not in cols.values()  # red marks withheld fixes and rejections
    assert plots.colors(["smoother"]) == {"smoother": cols["smoother"]}
    assert plots.colors(names[::-1]) == cols
    run = load_run(sample_run)
    only = replace(run, tracks={"smoother": run.tracks["smoother"]})
    for r in (run, only):
        [line] = [ln for ln in plots.trajectories(r).axes[0].lines
                  if ln.get_label() == "smoother"]
        assert matplotlib.colors.same_color(line.get_color(), plots.PALETTE["smoother"])
    plt.close("all")


def test_captions_mention_only_what_is_drawn(sample_run, no_gps_run):
    run = load_run(sample_run)
    cap = report.captions(run)
    assert "red circles: withheld" in cap["trajectories"]  # the sample withholds 40-60 s
    assert "ground truth (grey band)" in cap["trajectories_each"]
    nothing_withheld = replace(run, truth=None, gps_withheld=np.zeros_like(run.gps_withheld))
    cap = report.captions(nothing_withheld)
    assert "red" not in cap["trajectories"] and "truth" not in cap["trajectories"]
    assert cap["trajectories_each"].endswith("over the GPS fixes (grey dots).")
    _, err_caption = plots.errors(nothing_withheld)
    assert "withheld" not in err_caption and "not an independent score" in err_caption
    cap = report.captions(load_run(no_gps_run))
    assert "truth" not in cap["trajectories"].split("(no ground truth")[0]
    assert "GPS" not in cap["trajectories_each"].split("with no ground truth or GPS")[0]


@pytest.mark.slow
def test_jackal_report_without_gps_or_truth(jackal_bag, tmp_path):
    out = tmp_path / "jackal"
    assert cli.main(["run", str(jackal_bag), "-c", str(ROOT / "data" / "configs" /
                                                       "rl_jackal.yaml"), "-o", str(out)]) == 0
    page = (out / "report.html").read_text()
    assert not (out / "plots" / "errors.png").exists() and "No error figure" in page
    assert "ekf_igvc: needs an odometry or wheels sensor, and gps" in page
    assert _row(page, "local frame").startswith("the start pose")
    assert "t=0.000 s: ekf_unicycle: started" in page
    # every estimator near robot_localization's own final position on this bag (a peer
    # cross-check; tests/test_unicycle_bags.py): the smoother once counted every v-only
    # odometry message 'nonfinite' (its unused yaw-rate variance) and stayed at the origin
    m = json.loads((out / "metrics.json").read_text())
    for name, e in m["estimators"].items():
        assert math.dist(e["final_xy"], (1.0255, 3.4334)) < 0.5, (name, e["final_xy"])
        assert not any("nonfinite" in k for k in e["rejected"]), (name, e["rejected"])


def test_a_second_run_into_the_same_directory_leaves_no_tracks_of_the_first(tmp_path):
    from ddfuse.estimation.config import load_config
    from ddfuse.evaluation import pipeline

    root = Path(__file__).resolve().parents[1] / "data"
    cfg = load_config(root / "sample_husky.yaml")
    pipeline.run_bag(root / "sample_husky.bag", cfg, tmp_path, names=["ekf", "dr"])
    (tmp_path / "notes.txt").write_text("mine")
    assert (tmp_path / "dr.tum").is_file() and (tmp_path / "dr.csv").is_file()
    pipeline.run_bag(root / "sample_husky.bag", cfg, tmp_path, names=["ekf"])
    assert not (tmp_path / "dr.tum").exists() and not (tmp_path / "dr.csv").exists()
    assert (tmp_path / "ekf.tum").is_file() and (tmp_path / "ground_truth.tum").is_file()
    assert (tmp_path / "notes.txt").read_text() == "mine"  # only what a run wrote


def test_heading_error_lines_break_where_the_angle_wraps():
    from ddfuse.evaluation.plots import _break_wraps

    e = np.array([3.0, 3.1, -3.1, -3.0, 0.1, -0.1])
    out = _break_wraps(e)
    assert np.isnan(out[2]) and np.count_nonzero(np.isnan(out)) == 1
    assert np.array_equal(out[[0, 1, 3, 4, 5]], e[[0, 1, 3, 4, 5]])
