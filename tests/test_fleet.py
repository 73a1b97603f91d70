"""ddfuse fleet: bags found in directories, each in its own output folder, a failing bag a row
of its own while the others run, the ranking per bag and the wins across bags."""

from __future__ import annotations

import html
import json
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.fleet import bag_standing, find_bags, output_names, standings
from ddfuse.evaluation.fleet_page import fleet_html


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory) -> Path:
    """A 10 s simulated husky drive (bag and config beside it)."""
    out = tmp_path_factory.mktemp("sim") / "drive.bag"
    assert main(["simulate", "husky", "--seed", "1", "--duration", "10", "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def sim_mcap(tmp_path_factory) -> Path:
    """The same drive as a ROS 2 bag directory holding an MCAP file (config beside it)."""
    out = tmp_path_factory.mktemp("sim") / "drive2"
    assert main(["simulate", "husky", "--seed", "1", "--duration", "10", "--format", "mcap",
                 "-o", str(out)]) == 0
    return out


def _copy(bag: Path, to: Path, config: bool = True) -> Path:
    to.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(bag, to)
    if config:
        shutil.copy(bag.with_suffix(".yaml"), to.with_suffix(".yaml"))
    return to


def test_a_directory_without_bags_is_one_line_and_exit_2(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("no bag here")
    assert main(["fleet", str(tmp_path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == f"ddfuse: error: {tmp_path}: no bags in it (ROS1 .bag, .mcap, ROS 2 bag " \
                  "directories with metadata.yaml)\n"
    assert not (tmp_path / "out").exists()


def test_bags_are_found_in_subfolders_and_ros2_directories_are_not_entered(tmp_path):
    for p in ("a/x.bag", "b/x.bag", "b/y.mcap", "r2/metadata.yaml", "r2/r2_0.mcap", "c.txt"):
        (tmp_path / p).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / p).write_text("")
    assert find_bags([tmp_path]) == [tmp_path / "a/x.bag", tmp_path / "b/x.bag",
                                     tmp_path / "b/y.mcap", tmp_path / "r2"]


def test_bags_of_the_same_name_get_distinct_output_names():
    bags = [Path("/d/a/x.bag"), Path("/d/b/x.bag"), Path("/d/b/y.bag"), Path("/e/z.bag"),
            Path("/e/z.mcap")]
    assert output_names(bags) == ["a__x", "b__x", "y", "z_bag", "z_mcap"]


def test_a_failing_bag_or_one_without_config_is_a_row_and_the_others_run(sim_bag, sim_mcap,
                                                                          tmp_path, capsys):
    bags = tmp_path / "bags"
    shutil.copytree(sim_mcap, bags / "ros2" / "drive2")
    shutil.copy(sim_mcap.with_suffix(".yaml"), bags / "ros2" / "drive2.yaml")
    _copy(sim_bag, bags / "a" / "drive.bag")
    _copy(sim_bag, bags / "b" / "drive.bag")
    _copy(sim_bag, bags / "unconfigured_drive.bag", config=False)
    broken = _copy(sim_bag, bags / "broken.bag")
    broken.write_bytes(b"not a bag at all")
    out = tmp_path / "out"
    assert main(["fleet", str(bags), "-o", str(out), "--estimators", "ekf,smoother",
                 "--jobs", "1", "--no-report"]) == 0
    doc = json.loads((out / "fleet.json").read_text())
    by_bag = {b["bag"]: b for b in doc["bags"]}
    assert set(by_bag) == {"a__drive", "b__drive", "unconfigured_drive", "broken", "drive2"}
    assert (doc["bags_total"], doc["bags_ran"], doc["bags_failed"]) == (5, 3, 2)
    assert "no config given (-c)" in by_bag["unconfigured_drive"]["error"]
    assert str(broken) in by_bag["broken"]["error"]
    assert "\n" not in by_bag["broken"]["error"]
    for name in ("a__drive", "b__drive", "drive2"):
        assert (out / name / "metrics.json").is_file()
        assert not (out / name / "report.html").exists() and by_bag[name]["report"] is None
        assert by_bag[name]["error"] is None and by_bag[name]["score"] == "ate"
        assert sorted(by_bag[name]["ranking"]) == ["ekf", "smoother"]
    rows = {(r["bag"], r["estimator"]): r for r in doc["rows"]}
    assert rows[("broken", None)]["error"] == by_bag["broken"]["error"]
    # the same bag twice: the same scores, and the same rows as its metrics.json
    a, b = rows[("a__drive", "ekf")], rows[("b__drive", "ekf")]
    assert a["score_m"] == b["score_m"] is not None
    metrics = json.loads((out / "a__drive" / "metrics.json").read_text())
    assert a["ate_rmse_m"] == metrics["estimators"]["ekf"]["ate_rmse_m"]
    assert a["nees_verdict"] == metrics["estimators"]["ekf"]["nees"]["verdict"]
    assert doc["estimators"][by_bag["a__drive"]["ranking"][0]]["scored"] == 3
    cap = capsys.readouterr()
    assert "ddfuse: fleet: 5 bags on this process (--jobs 1)" in cap.err
    assert "ddfuse: fleet: 5/5 bags done" in cap.err
    assert "3 of 5 bags ran" in cap.out


@pytest.mark.slow
def test_each_bag_gets_its_report_and_the_fleet_page_links_it_and_shows_the_failure(
        sim_bag, tmp_path):
    bags = tmp_path / "bags"
    _copy(sim_bag, bags / "drive.bag")
    _copy(sim_bag, bags / "broken.bag").write_bytes(b"not a bag at all")
    out = tmp_path / "out"
    assert main(["fleet", str(bags), "-o", str(out), "--estimators", "ekf", "--jobs", "1"]) == 0
    doc = json.loads((out / "fleet.json").read_text())
    by_bag = {b["bag"]: b for b in doc["bags"]}
    assert by_bag["drive"]["report"] == "drive/report.html"
    assert by_bag["broken"]["report"] is None
    report = (out / "drive" / "report.html").read_text()
    assert "<h1>ddfuse report: drive.bag</h1>" in report
    page = (out / "fleet.html").read_text()
    assert '<a href="drive/report.html">drive</a>' in page
    assert html.escape(by_bag["broken"]["error"]) in page
    assert "http://" not in page and "https://" not in page and "<script" not in page


def test_exit_2_when_no_bag_ran(sim_bag, tmp_path, capsys):
    _copy(sim_bag, tmp_path / "bags" / "unconfigured_drive.bag", config=False)
    assert main(["fleet", str(tmp_path / "bags"), "-o", str(tmp_path / "out"),
                 "--jobs", "1"]) == 2
    assert "0 of 1 bags ran" in capsys.readouterr().out
    assert json.loads((tmp_path / "out" / "fleet.json").read_text())["bags_failed"] == 1


def test_an_unreachable_scheduler_is_one_line_and_exit_2(sim_bag, tmp_path, capsys):
    pytest.importorskip("distributed")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    assert main(["fleet", str(sim_bag), "-o", str(tmp_path / "out"), "--scheduler", address,
                 "--scheduler-timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ddfuse: error: --scheduler {address}: no Dask scheduler answered "
                          "within 1 s") and err.count("\n") == 1


def _rows(**scores):
    return [{"estimator": n, "score_m": v, "error": None} for n, v in scores.items()]


def test_the_ranking_names_a_winner_with_its_margin_or_the_tie_for_first():
    won = bag_standing(_rows(ekf=1.0, smoother=0.5, batch=None))
    assert won == {"ranking": ["smoother", "ekf"], "winner": "smoother", "tied": [],
                   "margin_m": 0.5, "margin_pct": 50.0}
    tied = bag_standing(_rows(ekf=1.0, smoother=0.98, batch=2.0))
    assert tied["winner"] is None and tied["tied"] == ["smoother", "ekf"]
    table = standings([won, tied, bag_standing(_rows(ekf=0.3, smoother=0.4))])
    assert list(table) == ["ekf", "smoother", "batch"]
    assert table["ekf"] == {"scored": 3, "wins": 1, "tied_first": 1, "mean_margin_m": 0.1,
                            "max_margin_m": 0.1, "mean_margin_pct": 25.0}
    assert table["smoother"]["wins"] == 1 and table["smoother"]["mean_margin_m"] == 0.5


def test_the_fleet_page_names_a_tie_and_what_a_bag_is_scored_on():
    rows = [{"bag": "held", "estimator": n, "score": "holdout", "score_m": v, "ate_rmse_m": None,
             "gps_holdout_rmse_m": v, "nees_mean": None, "nees_verdict": None,
             "nis_verdicts": {"/fix gps": "Warn"}, "rtf": 40.0, "error": None}
            for n, v in (("ekf", 1.0), ("smoother", 0.98))]
    bag = {"bag": "held", "path": "/d/held.bag", "error": None, "report": None,
           "score": "holdout", "wall_s": 1.0, **bag_standing(rows)}
    doc = {"engine": "this process (--jobs 1)", "bags_total": 1, "bags_ran": 1,
           "bags_failed": 0, "estimators": standings([bag]), "bags": [bag], "rows": rows,
           "wall_s": 1.0}
    page = fleet_html(doc, stamp="then")
    assert "<td class='l'>tie: smoother, ekf</td>" in page
    assert page.count("GPS hold-out</td>") == 3  # the bag's row and both estimators'
    assert "1 bag without an outright winner" in page
    assert '/fix gps <span class="Warn">Warn</span>' in page
    assert "<a href" not in page  # no report rendered, no link
    # the hold-out NEES beside the hold-out score (a fleet.json written before it had none)
    na = '<td><span class="na">–</span></td>'
    rows[0] |= {"gps_holdout_nees_mean": 6.88, "gps_holdout_nees_verdict": "Fail"}
    held = fleet_html(doc, stamp="then")
    assert '<td>6.88 <span class="Fail">Fail</span></td>' in held
    assert held.count(na) == page.count(na) - 1


def test_fleet_rows_carry_the_hold_out_nees():
    from ddfuse.evaluation.consistency import summarize
    from ddfuse.evaluation.fleet import rows_of
    from ddfuse.evaluation.scores import EstimatorScores, RunSummary

    nees = summarize(np.full(150, 9.0), 2)  # every fix above the 2-dof band
    m = RunSummary(gps_holdout="window:150:210", gps_holdout_fixes=150,
                   gps_holdout_scored_fixes=150, estimators={
                       "ekf": EstimatorScores(samples=10, gps_holdout_rmse_m=3.6,
                                              gps_holdout_nees=nees),
                       "dr": EstimatorScores(samples=10, gps_holdout_rmse_m=9.0)})
    rows = {r["estimator"]: r for r in rows_of(m)}
    assert rows["ekf"]["gps_holdout_nees_mean"] == pytest.approx(9.0)
    assert rows["ekf"]["gps_holdout_nees_verdict"] == "Fail"
    assert rows["dr"]["gps_holdout_nees_mean"] is None
    assert rows["dr"]["gps_holdout_nees_verdict"] is None
