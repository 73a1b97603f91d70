"""``ddfuse lag-sweep`` on the embedded simulated sample (it has ground truth)."""

from pathlib import Path

import pytest
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.lag_sweep import format_table, lag_sweep

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.mark.slow
def test_longer_lag_smooths_more():
    """At 0.5 s the lagged output has almost no future data, so it is close to the filtered
    output; at 10 s it is better (on this sample by ~10 %: with GPS of 1 m sigma the filtered
    output is already close to what 25 more fixes can add). The filtered output does not depend
    on the lag."""
    rows = lag_sweep(DATA / "sample_husky.bag", DATA / "sample_husky.yaml", (0.5, 10.0))
    by = {(r["estimator"], r["lag_s"]): r for r in rows}
    assert len(rows) == 5 and all(r["score"] == "truth" for r in rows)
    assert by[("ekf", None)]["rmse_m"] is not None
    short, long_ = by[("smoother_lagged", 0.5)]["rmse_m"], by[("smoother_lagged", 10.0)]["rmse_m"]
    assert long_ < 0.95 * short, (short, long_)
    f1, f2 = by[("smoother", 0.5)]["rmse_m"], by[("smoother", 10.0)]["rmse_m"]
    assert abs(short - f1) < 0.25 * f1, (short, f1)
    assert abs(f1 - f2) < 0.05 * f1, (f1, f2)
    table = format_table(rows)
    assert table.count("\n") == 6 and "| smoother_lagged | 10 |" in table


@pytest.mark.parametrize("lags", ["0,2", "a,b", ""])
def test_bad_lags_are_refused(lags, capsys):
    with pytest.raises(SystemExit) as e:
        main(["lag-sweep", "--lags", lags])
    assert e.value.code == 2
    assert "--lags" in capsys.readouterr().err


@pytest.mark.slow
def test_gps_model_replaces_the_configs_for_every_point(tmp_path):
    """--gps-model dcs sweeps the robust model: the EKF's and the smoother's rows move (the
    sample's config gates), as `ddfuse run --gps-model` would."""
    import json

    rows = {}
    for model in ("default", "dcs"):
        out = tmp_path / f"{model}.json"
        argv = ["lag-sweep", "--lags", "2", "--json", str(out)]
        assert main(argv + (["--gps-model", model] if model != "default" else [])) == 0
        rows[model] = {(r["estimator"], r["lag_s"]): r["rmse_m"]
                       for r in json.loads(out.read_text())}
    assert rows["default"].keys() == rows["dcs"].keys()
    for key in rows["default"]:
        assert rows["default"][key] != rows["dcs"][key], key


@pytest.mark.slow
def test_without_truth_the_nees_is_the_hold_outs(tmp_path):
    """Scored against withheld fixes (the sample's config without its truth), the NEES column
    is each track's NEES on those fixes (``gps_holdout_nees``), not an empty truth NEES."""
    import yaml

    cfg = yaml.safe_load((DATA / "sample_husky.yaml").read_text())
    cfg.pop("ground_truth")
    cfg.pop("initial_pose")
    config = tmp_path / "no_truth.yaml"
    config.write_text(yaml.safe_dump(cfg))
    rows = lag_sweep(DATA / "sample_husky.bag", config, (2.0,), holdout="every:5")
    assert {r["score"] for r in rows} == {"gps_holdout"} and len(rows) == 3
    assert all(r["nees_mean"] is not None and 0.1 < r["nees_mean"] < 20.0 for r in rows), rows
    assert "| NEES (gps_holdout) |" in format_table(rows)
