"""``ddfuse run --tune``: tuning on the bag, then the comparison with the config as given (in
OUT/shipped) and tuned (in OUT), tuned.yaml, tuning.json, the report's "What tuning changed";
a bag with nothing to tune runs once with the given config and says why; Ctrl-C while tuning
leaves nothing written."""

from __future__ import annotations

import contextlib
import io
import json
import math
import signal
from html.parser import HTMLParser
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
import yaml
from ddfuse.estimation.config import load_config
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.scores import RunSummary

OFF = 3.0  # the given config's noise values, times the simulator's true ones
NOISE = {"odometry": ("v", "yaw_rate"), "imu": ("yaw", "yaw_rate"), "gps": ("horizontal",)}
ESTIMATORS = "ekf,smoother,smoother_lagged"


def _off_config(true_yaml: Path, out: Path) -> Path:
    d = yaml.safe_load(true_yaml.read_text())
    for kind, keys in NOISE.items():
        for k in keys:
            d["sensors"][kind][0]["noise"][k] *= OFF
    out.write_text(yaml.safe_dump(d, sort_keys=False))
    return out


def _main(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def tuned_run(tmp_path_factory):
    """A 30 s simulated Husky drive whose config states every noise value 3x too large, run
    with --tune (GPS hold-out every:5) into OUT."""
    tmp = tmp_path_factory.mktemp("run_tune")
    bag = tmp / "husky.bag"
    assert main(["simulate", "husky", "--seed", "3", "--duration", "30", "-o", str(bag)]) == 0
    off = _off_config(bag.with_suffix(".yaml"), tmp / "off.yaml")
    out = tmp / "out"
    code, stdout, stderr = _main(["run", str(bag), "-c", str(off), "--tune", "-o", str(out),
                                  "--gps-holdout", "every:5", "--estimators", ESTIMATORS])
    assert code == 0, stderr
    return out, off, bag.with_suffix(".yaml"), stdout


def _summary(path: Path) -> RunSummary:
    return RunSummary.from_json(json.loads(path.read_text()))


@pytest.mark.slow
def test_run_tune_writes_the_tuned_run_in_out_and_the_given_configs_in_shipped(tuned_run):
    out, off, _, stdout = tuned_run
    for name in ("metrics.json", "report.html", "run.npz", "tuned.yaml", "tuning.json",
                 "shipped/metrics.json", "shipped/report.html", "shipped/run.npz"):
        assert (out / name).is_file(), name
    tuned, given = _summary(out / "metrics.json"), _summary(out / "shipped" / "metrics.json")
    assert tuned.config == str(out / "tuned.yaml") and given.config == str(off)
    assert set(tuned.estimators) == set(given.estimators) == set(ESTIMATORS.split(","))
    # the one line on the terminal: what tuning changed for the best estimator
    line = next(x for x in stdout.splitlines() if x.startswith("tuning: "))
    assert "values tuned" in line and "-> " in line and "NEES" in line


@pytest.mark.slow
def test_tuning_json_holds_the_values_before_and_after_and_the_tuned_config_has_them(
        tuned_run):
    out, off, true_yaml, _ = tuned_run
    t = json.loads((out / "tuning.json").read_text())
    assert t["applied"] and t["why_not"] is None and t["gps_holdout"] == "every:5"
    assert t["estimator"] == "ekf" and t["estimator_runs"] > 0 and t["wall_s"] > 0
    values = {v["key"]: v for v in t["values"]}
    gps = values["sensors.gps[0].noise.horizontal"]
    truth = yaml.safe_load(true_yaml.read_text())["sensors"]["gps"][0]["noise"]["horizontal"]
    assert gps["before"] == pytest.approx(OFF * truth) and gps["status"] == "tuned"
    assert abs(math.log(gps["after"] / truth)) < 0.3  # from 3x off to within 30 %
    assert values["robot.slip.lateral"]["status"] == "not informed"
    assert "do not inform" in values["robot.slip.lateral"]["reason"]
    # the tuned config is what ran in OUT: its GPS noise is the tuned value (3 digits)
    cfg = load_config(out / "tuned.yaml")
    assert cfg.sensor("/fix").noise["horizontal"] == float(f"{gps['after']:.3g}")
    assert load_config(off).sensor("/fix").noise["horizontal"] == pytest.approx(OFF * truth)
    assert set(t["nis"]["before"]) == set(t["nis"]["after"]) >= {"/fix gps", "/imu/data heading"}
    assert all(t["holdout_rmse_m"][k] > 0 for k in ("before", "after"))
    assert all(t["holdout_nees"][k] > 0 for k in ("before", "after"))


def _ratio_error(m: RunSummary, name: str, label: str) -> float:
    return abs(math.log(m.estimators[name].nis[label].nis.ratio))


@pytest.mark.slow
def test_the_tuned_runs_nis_is_closer_to_expected_than_the_off_configs(tuned_run):
    out, _, _, _ = tuned_run
    tuned, given = _summary(out / "metrics.json"), _summary(out / "shipped" / "metrics.json")
    for label in ("/fix gps", "/imu/data heading", "/odom yaw_rate"):
        # 3x too large a noise: NIS about 1/9 of expected; tuned, about 1
        assert _ratio_error(tuned, "ekf", label) < 0.5 < _ratio_error(given, "ekf", label)
    for label in ("/fix gps", "/imu/data heading"):
        assert _ratio_error(tuned, "smoother", label) < _ratio_error(given, "smoother", label)


class _Section(HTMLParser):
    """The tables (rows of cell texts) and list items of the report's "What tuning changed"."""

    def __init__(self) -> None:
        super().__init__()
        self.inside, self.tables, self.items, self.cell = False, [], [], None
        self.heading: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "h2":
            self.heading = []
        elif self.inside and tag == "table":
            self.tables.append([])
        elif self.inside and tag == "tr":
            self.tables[-1].append([])
        elif self.inside and tag in ("td", "th", "li"):
            self.cell = []
        elif tag == "br" and self.cell is not None:
            self.cell.append(" ")

    def handle_endtag(self, tag):
        if tag == "h2":
            self.inside = "".join(self.heading) == "What tuning changed"
            self.heading = None
        elif self.inside and tag in ("td", "th"):
            self.tables[-1][-1].append(" ".join("".join(self.cell).split()))
            self.cell = None
        elif self.inside and tag == "li":
            self.items.append("".join(self.cell).strip())
            self.cell = None

    def handle_data(self, data):
        if self.heading is not None:
            self.heading.append(data)
        elif self.cell is not None:
            self.cell.append(data)


def section(page: str) -> _Section:
    p = _Section()
    p.feed(page)
    return p


@pytest.mark.slow
def test_report_says_what_tuning_changed_values_and_both_scores(tuned_run):
    import re

    out, _, _, _ = tuned_run
    page = (out / "report.html").read_text()
    assert "<script" not in page.lower() and not re.search(
        r'(src|href)="(?!data:image/png;base64,)', page)  # still self-contained
    s = section(page)
    assert len(s.tables) == 2, "a table of the values and one of the scores"
    t = json.loads((out / "tuning.json").read_text())
    gps = next(v for v in t["values"] if v["key"] == "sensors.gps[0].noise.horizontal")
    row = next(r for r in s.tables[0] if r[0].startswith("sensors.gps[0].noise.horizontal"))
    assert row[1] == f"{gps['before']:.3g}" and row[2] == f"{gps['after']:.3g}"
    assert row[4] == "tuned"
    tuned, given = _summary(out / "metrics.json"), _summary(out / "shipped" / "metrics.json")
    head, *rows = s.tables[1]
    assert head[1].startswith("ATE, common stamps [m], given") and head[2] == "tuned"
    for r in rows:
        name = r[0]
        assert r[1] == f"{given.estimators[name].ate_common_rmse_m:.3f}"
        assert r[2] == f"{tuned.estimators[name].ate_common_rmse_m:.3f}"
        assert r[3].startswith(f"{given.estimators[name].nees_mean:.2f}")
        assert r[4].startswith(f"{tuned.estimators[name].nees_mean:.2f}")
    gps_col = head.index("NIS /fix gps: given → tuned")
    ekf = next(r for r in rows if r[0] == "ekf")
    g, k = given.estimators["ekf"].nis["/fix gps"].nis, tuned.estimators["ekf"].nis["/fix gps"].nis
    assert ekf[gps_col] == f"{g.ratio:.3f} {g.verdict} → {k.ratio:.3f} {k.verdict}"
    assert sum("ranking on ATE, common stamps" in x for x in s.items) == 1
    # the given config's report is a plain one
    assert section((out / "shipped" / "report.html").read_text()).tables == []


# --- a bag with nothing to tune; Ctrl-C while tuning -------------------------------------

STATIC = """sensors:
  odometry:
  - topic: /odom
    use: [v, yaw_rate]
    noise: {v: 0.03, yaw_rate: 0.03}
  imu:
  - topic: /imu
    use: [yaw_rate]
    noise: {yaw_rate: 0.03}
"""


@pytest.fixture
def static_bag(tmp_path) -> Path:
    """1 s of a robot standing still: odometry at 10 Hz, a gyro at 30 Hz, nothing absolute
    (no GPS, no compass): too few innovations to inform any noise value (5 s informs the
    gyro's once the twist walk is tuned with it: 150 samples at rest are how a gyro's noise is
    measured)."""
    rng = np.random.default_rng(1)
    recs = []
    for k in range(30):
        t = 100.0 + k / 30.0
        if k % 3 == 0:
            recs.append(("/odom", bw.odometry(t, rng.normal(0, 0.01), rng.normal(0, 0.01))))
        recs.append(("/imu", bw.imu(t, angvel=(0.0, 0.0, rng.normal(0, 0.01)))))
    bag = bw.write_bag(tmp_path / "static.bag", "ros1", recs)
    bag.with_suffix(".yaml").write_text(STATIC)
    return bag


@pytest.fixture(autouse=True)
def _ctrl_c(ctrl_c_raises):
    """_Bars' SIGINT raises KeyboardInterrupt here, also in an xdist worker."""


class _Bars:
    """Progress bars as the command line sees them (``terminal.Bars``' interface): records the
    stages; at the first update of stage ``interrupt_at`` it raises SIGINT, as Ctrl-C on the
    terminal would."""

    def __init__(self, interrupt_at: str | None = None) -> None:
        self.bar, self.stages, self.interrupt_at = None, [], interrupt_at

    def update(self, stage: str, fraction: float) -> None:
        if stage not in self.stages:
            self.stages.append(stage)
        if stage == self.interrupt_at:
            self.interrupt_at = None  # once, as one Ctrl-C
            signal.raise_signal(signal.SIGINT)

    def stop(self) -> None:
        pass


@pytest.mark.slow
def test_a_bag_with_nothing_to_tune_runs_with_the_given_config_and_says_why(
        static_bag, tmp_path, monkeypatch):
    bars = _Bars()
    monkeypatch.setattr("ddfuse.evaluation.cli.run.progress", lambda: bars)
    out = tmp_path / "out"
    out.mkdir()
    (out / "tuned.yaml").write_text("an earlier --tune run's")
    code, _, err = _main(["run", str(static_bag), "--tune", "-o", str(out),
                          "--estimators", "ekf"])
    assert code == 0
    assert "ddfuse: warning: tuning changed nothing: no value is informed by the data" in err
    assert not (out / "tuned.yaml").exists() and not (out / "shipped").exists()
    t = json.loads((out / "tuning.json").read_text())
    assert not t["applied"] and "too short or too static" in t["why_not"]
    assert {v["status"] for v in t["values"]} == {"not informed"}
    assert _summary(out / "metrics.json").config == str(static_bag.with_suffix(".yaml"))
    items = section((out / "report.html").read_text()).items
    assert any(x.startswith("Nothing: the tuned values were not applied: no value is "
                            "informed") for x in items)
    # progress: the tuning's stages, then the run's, as other commands show them
    assert bars.stages[:2] == ["tuning: read", "tuning: information at the start"]
    assert "given config: decode + estimate" in bars.stages
    # a later run without --tune into the same directory: its report has no tuning section
    other = tmp_path / "other.yaml"
    other.write_text(STATIC)
    assert _main(["run", str(static_bag), "-c", str(other), "-o", str(out),
                  "--estimators", "ekf"])[0] == 0
    assert "What tuning changed" not in (out / "report.html").read_text()


def test_ctrl_c_while_tuning_exits_130_and_writes_nothing(static_bag, tmp_path, monkeypatch):
    bars = _Bars(interrupt_at="tuning: information at the start")
    monkeypatch.setattr("ddfuse.evaluation.cli.run.progress", lambda: bars)
    out = tmp_path / "out"
    code, stdout, err = _main(["run", str(static_bag), "--tune", "-o", str(out)])
    assert code == 130
    assert err == "ddfuse: interrupted (Ctrl-C) while tuning: nothing written\n"
    assert not out.exists() and stdout == ""


def test_a_bag_that_cannot_be_read_whole_is_not_tuned_and_tuning_json_says_why(tmp_path):
    root = Path(__file__).resolve().parents[1] / "data"
    bag = tmp_path / "cut.bag"
    bag.write_bytes((root / "sample_husky.bag").read_bytes()[:300_000])  # breaks off
    bag.with_suffix(".yaml").write_text((root / "sample_husky.yaml").read_text())
    out = tmp_path / "out"
    code, _, err = _main(["run", str(bag), "--tune", "-o", str(out), "--estimators", "ekf",
                          "--no-report"])
    assert code == 2 and "bag is truncated" in err  # the run's own error, after its results
    t = json.loads((out / "tuning.json").read_text())
    assert not t["applied"] and t["why_not"].startswith("the bag could not be read whole")
    assert (out / "metrics.json").is_file() and not (out / "tuned.yaml").exists()


def _holdout_summary(**rmse: float) -> RunSummary:
    from ddfuse.evaluation.scores import EstimatorScores

    return RunSummary(gps_holdout="every:5", gps_holdout_fixes=40, gps_holdout_scored_fixes=40,
                      estimators={n: EstimatorScores(samples=100, gps_holdout_rmse_m=v)
                                  for n, v in rmse.items()})


def test_without_truth_the_section_ranks_on_the_holdout_and_shows_no_nees():
    from ddfuse.evaluation.report_tuning import _comparison_table, change_line, ranking_sentence

    given, tuned = _holdout_summary(ekf=2.0, smoother=1.5), _holdout_summary(ekf=1.0,
                                                                             smoother=1.2)
    assert ranking_sentence(given, tuned) == (
        "The ranking on GPS hold-out RMSE changed (rank given → tuned): ekf 2 → 1; "
        "smoother 1 → 2. The best is now ekf (1.000 m), was smoother (1.500 m).")
    assert "the same with both configs: smoother, ekf" in ranking_sentence(given, given)
    table = _comparison_table(given, tuned)
    assert "NEES" not in table.split("</tr>")[0] and "No NEES: the bag has no ground truth" in table
    line = change_line({"applied": True, "values": [{"status": "tuned"}]}, tuned, given)
    assert line == ("tuning: 1 value tuned (tuned.yaml, tuning.json); for ekf (best with it): "
                    "GPS hold-out RMSE 2.000 -> 1.000 m, NIS Fail on 0 -> 0 of 0 sensors")


def test_the_section_shows_each_configs_hold_out_nees_beside_its_score():
    """The given config scores 3.6 m with a covariance that does not cover it (NEES 6.9,
    Fail), the tuned one 5.9 m with one that does (1.0, Pass): both columns, both verdicts."""
    import numpy as np
    from ddfuse.evaluation.consistency import summarize
    from ddfuse.evaluation.report_tuning import _comparison_table, change_line
    from ddfuse.evaluation.scores import EstimatorScores

    chi = np.random.default_rng(0).chisquare(2, 150)

    def run(rmse, scale):
        e = EstimatorScores(samples=100, gps_holdout_rmse_m=rmse,
                            gps_holdout_nees=summarize(scale * chi, 2))
        return RunSummary(gps_holdout="window:150:210", gps_holdout_fixes=150,
                          gps_holdout_scored_fixes=150, estimators={"ekf": e})

    given, tuned = run(3.6, 3.45), run(5.9, 1.0)
    table = _comparison_table(given, tuned)
    head, row = table.split("</tr>")[:2]
    assert "<th>hold-out NEES, given</th><th>tuned</th>" in head
    g, t = given.estimators["ekf"].gps_holdout_nees, tuned.estimators["ekf"].gps_holdout_nees
    assert g.verdict == "Fail" and t.verdict == "Pass"
    assert f'{g.mean:.2f} <span class="Fail">Fail</span>' in row
    assert f'{t.mean:.2f} <span class="Pass">Pass</span>' in row
    assert "whether the covariance covers the hold-out error" in table
    line = change_line({"applied": True, "values": [{"status": "tuned"}]}, tuned, given)
    assert f"hold-out NEES {g.mean:.2f} Fail -> {t.mean:.2f} Pass, NIS Fail" in line


@pytest.mark.slow
def test_ctrl_c_in_the_given_configs_run_keeps_the_tuned_results_and_the_report_says_so(
        tmp_path, monkeypatch):
    bag = tmp_path / "husky.bag"
    assert main(["simulate", "husky", "--seed", "4", "--duration", "15", "-o", str(bag)]) == 0
    off = _off_config(bag.with_suffix(".yaml"), tmp_path / "off.yaml")
    bars = _Bars(interrupt_at="given config: decode + estimate")
    monkeypatch.setattr("ddfuse.evaluation.cli.run.progress", lambda: bars)
    out = tmp_path / "out"
    code, _, err = _main(["run", str(bag), "-c", str(off), "--tune", "-o", str(out),
                          "--estimators", "ekf"])
    assert code == 130 and "interrupted" in err, err
    assert _summary(out / "metrics.json").interrupted is None  # the tuned run is whole
    assert _summary(out / "shipped" / "metrics.json").interrupted
    items = section((out / "report.html").read_text()).items
    assert any(x.startswith("No side-by-side scores: the given config's run was stopped early")
               for x in items)
