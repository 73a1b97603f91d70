"""ddfuse compare: per bag and estimator better, worse or the same beyond the tolerances, from
metrics.json, run directories and fleet.json alike; exit 1 on a regression, 0 otherwise."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.compare_scores import Score, compare, load_scores


def _metrics(path: Path, bag: str = "/bags/drive.bag", **ate) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    ests = {n: {"ate_rmse_m": v, "samples": 10, "error": None if v is not None else "diverged"}
            for n, v in ate.items()}
    path.write_text(json.dumps({"bag": bag, "estimators": ests}))
    return path


def _fleet(path: Path, rows: list[tuple]) -> Path:
    path.write_text(json.dumps({"bags": [], "rows": [
        {"bag": b, "estimator": e, "score": "ate" if e else None, "score_m": v,
         "error": err} for b, e, v, err in rows]}))
    return path


def test_a_change_counts_only_beyond_both_tolerances():
    base = {("d", "ekf"): Score("ate", 1.0), ("d", "smoother"): Score("ate", 0.1),
            ("d", "batch"): Score("ate", 1.0)}
    new = {("d", "ekf"): Score("ate", 1.04), ("d", "smoother"): Score("ate", 0.115),
           ("d", "batch"): Score("ate", 0.9)}
    got = {p.estimator: (p.status, p.delta_m, p.delta_pct) for p in compare(base, new)}
    # 4 cm on 1 m is within 5%; 1.5 cm on 10 cm is beyond both 1 cm and 5%
    assert got == {"ekf": ("same", 0.04, 4.0), "smoother": ("worse", 0.015, 15.0),
                   "batch": ("better", -0.1, -10.0)}
    assert compare(base, new, tol_m=0.02)[1].status == "same"
    assert compare(base, new, tol_pct=3.0)[0].status == "worse"


def test_lost_missing_new_and_incomparable_scores():
    base = {("a", "ekf"): Score("ate", 1.0), ("a", "dr"): Score("ate", 5.0),
            ("b", "ekf"): Score("holdout", 2.0), ("c", "ekf"): Score("ate", 1.0)}
    new = {("a", "ekf"): Score(None, None, "diverged"), ("b", "ekf"): Score("ate", 2.0),
           ("c", "ekf"): Score("ate", 1.0), ("d", "ekf"): Score("ate", 1.0)}
    got = {(p.bag, p.estimator): p.status for p in compare(base, new)}
    assert got == {("a", "ekf"): "lost", ("a", "dr"): "missing", ("b", "ekf"): "incomparable",
                   ("c", "ekf"): "same", ("d", "ekf"): "new"}


def test_metrics_json_run_directory_and_fleet_json_read_alike(tmp_path):
    m = _metrics(tmp_path / "run" / "metrics.json", ekf=0.5, smoother=None)
    want = {("drive", "ekf"): Score("ate", 0.5, None),
            ("drive", "smoother"): Score("ate", None, "diverged")}
    assert load_scores(m) == load_scores(m.parent) == want
    f = _fleet(tmp_path / "fleet.json", [("drive", "ekf", 0.5, None),
                                         ("drive", "smoother", None, "diverged"),
                                         ("broken", None, None, "broken.bag: not a bag")])
    assert load_scores(f) == {**want, ("broken", None): Score(None, None, "broken.bag: not a bag")}


def test_two_single_runs_pair_by_estimator_whatever_their_bags_names(tmp_path, capsys):
    base = _metrics(tmp_path / "base.json", bag="/old/sample.bag", ekf=0.5, smoother=0.4)
    new = _metrics(tmp_path / "new.json", bag="/new/place/sample_v2.bag", ekf=0.5,
                   smoother=0.4)
    assert main(["compare", str(base), str(new)]) == 0
    out = capsys.readouterr().out
    assert "sample_v2                ekf              SAME" in out
    assert out.endswith("2 compared (tolerance 0.01 m and 5%): 2 same; no regression\n")


def test_exit_1_on_a_regression_and_the_json_says_what(tmp_path, capsys):
    base = _fleet(tmp_path / "base.json", [("a", "ekf", 0.5, None), ("b", "ekf", 0.5, None)])
    new = _fleet(tmp_path / "new.json", [("a", "ekf", 0.7, None), ("b", "ekf", 0.3, None)])
    out = tmp_path / "cmp.json"
    assert main(["compare", str(base), str(new), "--json", str(out)]) == 1
    doc = json.loads(out.read_text())
    assert doc["regressions"] == 1 and doc["counts"] == {"worse": 1, "better": 1}
    assert doc["pairs"][0]["status"] == "worse" and doc["pairs"][0]["delta_m"] == 0.2
    assert "a                        ekf              WORSE        0.500 m (ate) -> 0.700 m " \
           "(ate) (+0.200 m, +40.0%)" in capsys.readouterr().out
    assert main(["compare", str(base), str(base)]) == 0


@pytest.mark.parametrize("content,what", [
    ("{", "not JSON"), ('{"a": 1}', "neither a metrics.json (no 'estimators') nor a fleet.json")])
def test_an_input_that_is_no_scores_is_one_line_and_exit_2(tmp_path, capsys, content, what):
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    good = _metrics(tmp_path / "m.json", ekf=0.5)
    assert main(["compare", str(good), str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ddfuse: error: {bad}: {what}") and err.count("\n") == 1
    assert main(["compare", str(tmp_path), str(good)]) == 2
    assert "a directory without metrics.json or fleet.json" in capsys.readouterr().err
