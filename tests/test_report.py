"""`ddfuse run` writes a self-contained report.html from saved results; `ddfuse report OUTDIR`
re-renders it from those results alone; bad directories give one error line and exit 2."""

from __future__ import annotations

import base64
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from estimation.runner import Trajectory
from evaluation import cli
from evaluation.export import read_csv, write_csv
from evaluation.results import load_run

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
    assert len(imgs) == 7 and all(i.startswith(PNG) for i in imgs)
    assert sorted(p.name for p in (sample_run / "plots").iterdir()) == sorted(
        f"{n}.png" for n in ("trajectories", "trajectories_each", "errors", "nees", "nis",
                             "covariance", "latency"))
    m = json.loads((sample_run / "metrics.json").read_text())
    for name in ("ekf", "smoother", "smoother_lagged"):
        assert f"<b>{name}</b>" in page
        ate = m["estimators"][name]["ate_rmse_m"]
        assert f"{ate:.3f}" in page  # the summary table shows the saved number
    best = min(m["estimators"], key=lambda n: m["estimators"][n]["ate_rmse_m"])
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
    assert capsys.readouterr().out.strip() == str(copy / "report.html")
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
    assert run.gps_withheld.sum() == run.metrics["gps_holdout_fixes"]
    assert len(run.innovations["ekf"]) == sum(
        s["n"] for s in run.metrics["estimators"]["ekf"]["nis"].values())
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
    bars = cli._Bars(delay=2.0, clock=lambda: now[0])
    bars.update("decode", 0.5)
    assert bars.bar is None  # a short run shows nothing
    now[0] = 3.0
    bars.update("estimate", 1.0)
    assert bars.bar is None  # a stage that is already done starts no bar
    bars.update("estimate", 0.2)
    assert bars.bar is not None and "estimate" in bars.tasks
    bars.stop()
    assert cli._progress() is None  # pytest's captured output is not a terminal


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
    assert code == 2 and len(err.strip().split("\n")) == 1 and str(bag) in err
    page = (out / "report.html").read_text()
    assert "The bag is damaged; these results cover what could be read" in page
    assert json.loads((out / "metrics.json").read_text())["duration_s"] < 100


@pytest.mark.parametrize("n", [0, 1, 7, 3000])
def test_track_files_are_byte_for_byte_what_savetxt_wrote(tmp_path, n):
    """write_tum/write_csv format all rows in one go; the files must stay exactly those of
    np.savetxt with the formats they always had (NaN and inf included)."""
    from estimation.runner import Trajectory
    from evaluation import export

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
