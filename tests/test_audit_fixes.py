"""User-facing fixes from the fresh-eyes audit (docs in the test names): the report's "Not run"
reasons, the events header, figures with nothing to draw, the online header's frame, lag-sweep
with nothing to score against, --help and the summary's formatting."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import replace
from pathlib import Path

import pytest
from ddfuse.evaluation import cli, plots, report
from ddfuse.evaluation.results import load_run
from ddfuse.evaluation.scores import EstimatorScores, RunSummary

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


@pytest.fixture(scope="module")
def seed002_run(tmp_path_factory) -> Path:
    """The landmark sample (wheel speeds with the robot's geometry), ekf_landmark alone."""
    out = tmp_path_factory.mktemp("seed002") / "out"
    assert cli.main(["run", str(SEED002), "-o", str(out), "--estimators", "ekf_landmark"]) == 0
    return out


def test_not_run_says_dr_is_off_by_default_on_a_wheel_speed_config(seed002_run):
    """The config has /joint_states wheels and robot.wheel_radius/track_width, so dr can run:
    the reason is that it is off by default, not a missing sensor (audit #3)."""
    page = (seed002_run / "report.html").read_text()
    assert "dr: needs" not in page
    assert "dr: off by default, --estimators dr runs it" in page
    run = load_run(seed002_run)
    assert [s["kind"] for s in run.metrics["data"]["sensors"]].count("wheels") == 1
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


def test_events_header_counts_lockout_recoveries_as_accepted_as_the_gating_table_does(
        seed002_run):
    """A kidnapped robot (test_unicycle): the GPS gate rejects fixes until its lock-out
    recovery fuses one. The estimator counts that recovery in log.rejected; the events header
    must not add it to the rejections, or it disagrees with the gating table (audit #5: MRCLAM
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
    [head] = re.findall(r"<summary>ekf: (.*?)</summary>", report._config(run))
    assert f"{table_rejected} rejected by the gate" in head, head
    assert f"{recoveries} lock-out recover" in head and "(measurement accepted)" in head
    assert "dropped" not in head  # nothing else was refused here


def test_events_header_of_the_mrclam_counts():
    """metrics.json's entry of ekf_landmark on mrclam1_robot1.bag (audit #5), and of a
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


@pytest.fixture(scope="module")
def dr_run(tmp_path_factory) -> Path:
    """The embedded sample, dead reckoning alone: no covariance, no innovation."""
    out = tmp_path_factory.mktemp("dr") / "out"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cli.main(["run", "-o", str(out), "--estimators", "dr"]) == 0
    out.joinpath("warnings.txt").write_text("\n".join(str(w.message) for w in caught))
    return out


def test_no_blank_figures_when_nothing_has_a_covariance_or_an_innovation(dr_run):
    """dr alone (audit #6): no nis.png (it was a blank white image), no covariance.png (empty
    axes), each replaced by a note saying why, and no matplotlib legend warning."""
    names = sorted(p.name for p in (dr_run / "plots").iterdir())
    assert "nis.png" not in names and "covariance.png" not in names and "nees.png" not in names
    assert "errors.png" in names and "trajectories.png" in names
    page = (dr_run / "report.html").read_text()
    figs = page.split("<h2>Figures</h2>")[1].split("<h2>Data</h2>")[0]
    assert len(re.findall(r"<img ", figs)) == len([n for n in names if n.endswith(".png")])
    assert "No NIS figure: no estimator logged an innovation" in figs
    assert "No covariance figure: dr has no covariance." in figs
    assert "No NEES figure: dr has no covariance." in figs
    assert "No per-estimator trajectory figure: dr is the only estimate" in figs
    # nothing promised that is not there
    assert "NIS of each innovation" not in figs and "Trace of the position covariance" not in figs
    [errors_caption] = [c for c in re.findall(r"<figcaption>(.*?)</figcaption>", figs)
                        if c.startswith("Errors against")]
    assert "±3σ" not in errors_caption and "No envelope: dr has no covariance." in errors_caption
    assert "No artists with labels" not in (dr_run / "warnings.txt").read_text()
    run = load_run(dr_run)
    assert plots.nis(run) is None and plots.covariance(run) is None
    # the errors panel draws no envelope, so its legend names none
    fig, _ = plots.errors(run)
    assert "±3σ" not in [t.get_text() for ax in fig.axes if ax.get_legend()
                         for t in ax.get_legend().get_texts()]


def test_a_track_without_covariance_is_named_where_the_others_have_one(dr_run, seed002_run):
    """Beside tracks with a covariance: the figures are drawn, and their captions say dr is
    not in them (no envelope, not drawn)."""
    run = load_run(seed002_run)
    dr = load_run(dr_run).tracks["dr"]
    run.tracks = {**run.tracks, "dr": dr}
    cap = report.captions(run)
    assert "Not drawn: dr (it has no covariance)." in cap["covariance"]
    assert "Not drawn: dr" in cap["nees"]
    assert plots.covariance(run) is not None
    _, errors_caption = plots.errors(run)
    assert "±3σ envelope" in errors_caption and "dr has no covariance, so no envelope." in \
        errors_caption


def _online_header(bag: Path, capsys) -> str:
    assert cli.main(["online", str(bag), "--estimators", "ekf", "--every", "100000"]) == 0
    return capsys.readouterr().out.splitlines()[0]


def test_online_names_the_landmark_maps_frame_on_mrclam(mrclam_bag, capsys):
    """MRCLAM has no GPS: the frame is the landmark map's, as run's report says, not ENU
    (audit #7)."""
    head = _online_header(mrclam_bag, capsys)
    assert "ENU" not in head and "east" not in head
    assert "in the landmark map's frame (yaw counter-clockwise from x)" in head


def test_online_names_the_start_pose_frame_on_jackal(jackal_bag, capsys):
    head = _online_header(jackal_bag, capsys)
    assert "ENU" not in head and "east" not in head
    assert "in the start-pose frame" in head


def test_online_frame_is_the_reports_frame(mrclam_bag, jackal_bag, husky_bag, seed002_run):
    """online_frame gives plots.frame the facts run records: the same frame as each report."""
    from ddfuse.estimation.config import load_config

    for bag, kind in ((mrclam_bag, "map"), (jackal_bag, "start"), (husky_bag, "enu"),
                      (SEED002, "map")):
        cfg = load_config(cli._config_for(bag, None))
        assert cli.online_frame(bag, cfg)["kind"] == kind, bag
    m = json.loads((seed002_run / "metrics.json").read_text())
    cfg = load_config(cli._config_for(SEED002, None))
    assert cli.online_frame(SEED002, cfg) == plots.frame(m)


def test_lag_sweep_refuses_before_decoding_when_the_config_has_no_truth(tmp_path, capsys):
    """rl_jackal's config names no ground_truth topic: with no --gps-holdout there is nothing
    to score, said in one line, exit 2, before the bag is opened (here it does not even exist)
    rather than after a table of dashes with exit 0 (audit #8)."""
    from ddfuse.evaluation.lag_sweep import lag_sweep

    jackal_cfg = ROOT / "data" / "configs" / "rl_jackal.yaml"
    with pytest.raises(ValueError, match="needs ground truth or --gps-holdout") as e:
        lag_sweep(tmp_path / "absent.bag", jackal_cfg)
    assert str(jackal_cfg) in str(e.value) and "names no ground_truth topic" in str(e.value)
    # a hold-out cannot help a config without GPS either
    with pytest.raises(ValueError,
                       match=r"--gps-holdout every:5: .*rl_jackal\.yaml has no gps sensor"):
        lag_sweep(tmp_path / "absent.bag", jackal_cfg, holdout="every:5")
    bag = tmp_path / "jackal.bag"
    bag.write_bytes(b"")
    code = cli.main(["lag-sweep", str(bag), "-c", str(jackal_cfg)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    [line] = err.strip().splitlines()
    assert line.startswith("ddfuse: error: lag-sweep needs ground truth or --gps-holdout")


def test_lag_sweep_refuses_a_hold_out_that_withholds_nothing(husky_bag, capsys):
    """No truth and a window after the data: every RMSE would be '-' under a 'gps_holdout'
    header; it is refused after decoding, before any estimator runs."""
    code = cli.main(["lag-sweep", str(husky_bag), "--lags", "2", "--gps-holdout",
                     "window:1000:2000"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert "--gps-holdout window:1000:2000 withholds none of its 989 GPS fixes" in err


def test_lag_sweep_scores_against_what_the_stream_has():
    """_scored_against on decoded streams: the truth when there is some, else the withheld
    fixes (runner's rule: every K-th from the first), else refused."""
    import numpy as np
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.measurements import GpsFix, GroundTruthPose, Stream
    from ddfuse.evaluation.lag_sweep import _scored_against

    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    fixes = [GpsFix(t=float(t), lat=42.0, lon=-71.0, alt=0.0, cov=np.eye(3)) for t in range(4)]
    no_truth = Stream(measurements=fixes)
    assert _scored_against(no_truth, "b.bag", cfg, "every:2") == "gps_holdout"
    with pytest.raises(ValueError, match="withholds none of its 4 GPS fixes"):
        _scored_against(no_truth, "b.bag", cfg, "window:10:20")
    with pytest.raises(ValueError, match="b.bag has no ground truth$"):
        _scored_against(no_truth, "b.bag", cfg, None)
    truth = Stream(measurements=fixes, ground_truth=[GroundTruthPose(0.0, 0.0, 0.0, 0.0)])
    assert _scored_against(truth, "b.bag", cfg, None) == "truth"
    assert _scored_against(truth, "b.bag", cfg, "window:10:20") == "truth"


def test_run_help_lists_every_estimator_the_parser_accepts(capsys):
    """dr was missing from `run --help` (audit #10): every name --estimators accepts is listed."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    listed = text.split("--estimators LIST comma-separated: ")[1].split(" (")[0]
    assert [n.strip() for n in listed.split(",")] == list(TRACK_TO_SPEC)
    assert "default: all but dr" in text


def _readme_cell(command: str) -> tuple[str, str]:
    """(synopsis, description) of ``ddfuse COMMAND`` in the README's command table."""
    for line in (ROOT / "README.md").read_text().splitlines():
        if line.startswith(f"| `ddfuse {command} ") or line.startswith(f"| `ddfuse {command}`"):
            synopsis, text = line[2:].split("` | ", 1)
            return synopsis, text
    raise AssertionError(f"no README row for ddfuse {command}")


@pytest.mark.parametrize("command", ["run", "online", "lag-sweep", "bench", "report", "inspect"])
def test_readme_synopsis_has_every_option_of_the_help(command, capsys):
    """The README's table lacked lag-sweep's -c and online's --reorder-window (audit #11)."""
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    usage = " ".join(capsys.readouterr().out.split("\n\n")[0].split())
    options = set(re.findall(r"\[(-[-\w]+)", usage)) - {"-h"}
    synopsis, _ = _readme_cell(command)
    missing = [o for o in options if not re.search(rf"{re.escape(o)}\b", synopsis)]
    assert not missing, (command, missing, synopsis)


def test_readme_says_which_estimators_online_refuses():
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED

    _, text = _readme_cell("online")
    refused = text.split("Not ")[1].split(":")[0]
    assert sorted(re.findall(r"`(\w+)`", refused)) == sorted(ONLINE_TRACKS_REFUSED)


def test_readme_places_the_wall_time_line_where_run_prints_it(tmp_path, capsys):
    """The wall-time split is the summary's second-to-last line, the last one saying where
    the results are (audit #12)."""
    assert cli.main(["run", "-o", str(tmp_path / "o"), "--estimators", "ekf",
                     "--no-report"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-2].startswith("wall time ") and lines[-1].startswith("results in ")
    _, text = _readme_cell("run")
    assert "`wall time` line, the one before the last (`results in ...`)" in text


def test_a_drift_that_rounds_to_zero_has_no_sign():
    """The GPS-outage table printed -0.00 (audit #13)."""
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
    """`ekf_igvc ... 33358.134 ERROR: no estimate` (audit #14): a real-time factor of an
    estimator that only turned measurements away is no speed; '-' in the summary and the
    report's table, metrics.json's rtf kept (its runtime is real)."""
    import io

    m = json.loads((seed002_run / "metrics.json").read_text())
    ran = m["estimators"]["ekf_landmark"]
    dead = {**ran, "samples": 0, "final_xy": None, "ate_rmse_m": None, "yaw_rmse_deg": None,
            "nees_mean": None, "rtf": 33358.134, "error": "no estimate: it never started"}
    m["estimators"] = {"ekf_landmark": ran, "ekf": dead}
    out = io.StringIO()
    cli._print_summary(m, out)
    rows = {ln.split()[0]: ln for ln in out.getvalue().splitlines()[2:4]}
    assert "33358" not in rows["ekf"]
    assert rows["ekf"].split("ERROR:")[0].split()[-1] == "-"
    assert f"{ran['rtf']:.3f}" in rows["ekf_landmark"]
    table = report._summary_table(RunSummary.from_json(m))
    assert "33358" not in table and f"{ran['rtf']:.0f}" in table
