"""`ddfuse inspect BAG [-o FILE.yaml]`: stdout one YAML document (facts as comments, then the
config), -o writes the config alone, and the GPS correlation_time it suggests is the one `run`
asks for (one rule: ``estimation.gps_scatter``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from ddfuse.estimation.baginfo import bag_info, suggest_config
from ddfuse.estimation.config import load_config
from ddfuse.evaluation.cli import main


@pytest.fixture(scope="module")
def multipath_bag(tmp_path_factory) -> Path:
    """120 s of the simulated husky-multipath: GPS errors a 30 s Gauss-Markov process."""
    bag = tmp_path_factory.mktemp("mp") / "mp.bag"
    assert main(["simulate", "husky-multipath", "--seed", "1", "--duration", "120",
                 "-o", str(bag)]) == 0
    return bag


def test_stdout_is_one_yaml_document_whose_config_loads(multipath_bag, tmp_path, capsys):
    assert main(["inspect", str(multipath_bag)]) == 0
    out = capsys.readouterr().out
    assert "\n# /fix  " in out and "sensor_msgs/NavSatFix" in out  # the table
    assert "# /fix: the interpolation of the" in out
    p = tmp_path / "redirected.yaml"
    p.write_text(out)  # `ddfuse inspect BAG > redirected.yaml`
    assert yaml.safe_load(out) == suggest_config(bag_info(multipath_bag))
    assert load_config(p).of_kind("gps")[0].correlation_time > 0


def test_output_file_holds_the_config_alone_and_stdout_the_facts(multipath_bag, tmp_path,
                                                                 capsys):
    cfg_path = tmp_path / "suggested.yaml"
    assert main(["inspect", str(multipath_bag), "-o", str(cfg_path)]) == 0
    out = capsys.readouterr().out
    assert "# /fix: the interpolation of the" in out
    assert out.endswith(f"# suggested config written to {cfg_path}\n")
    assert "sensors:" not in out
    text = cfg_path.read_text()
    assert "neighbouring fixes" not in text and "sensor_msgs/NavSatFix" not in text
    tree = yaml.safe_load(text)
    info = bag_info(multipath_bag)
    assert tree == suggest_config(info)
    # the measured correlation time (true 30 s), with where it came from above it
    (fix,) = [t for t in info.topics if t.topic == "/fix"]
    tau = tree["sensors"]["gps"][0]["correlation_time"]
    assert tau == fix.scatter.recommended == pytest.approx(30, rel=0.2)
    lines = text.splitlines()
    at = lines.index(f"    correlation_time: {tau}")
    assert lines[at - 1].startswith("    # correlation_time s: from the fixes' scatter (296 fixes")
    assert not list(tmp_path.glob(".*partial*"))


def test_output_file_that_cannot_be_written_is_one_line_naming_it(multipath_bag, tmp_path,
                                                                  capsys):
    target = tmp_path / "no_such_dir" / "cfg.yaml"
    assert main(["inspect", str(multipath_bag), "-o", str(target)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ddfuse: error: cannot write ") and str(target) in err
    assert "\n" not in err and not target.exists()


def test_inspect_and_run_give_one_correlation_time(multipath_bag, tmp_path, capsys):
    """The file inspect writes runs; with its value run says nothing, with 0 run asks for that
    same value."""
    cfg_path = tmp_path / "suggested.yaml"
    assert main(["inspect", str(multipath_bag), "-o", str(cfg_path)]) == 0
    tau = yaml.safe_load(cfg_path.read_text())["sensors"]["gps"][0]["correlation_time"]
    white = tmp_path / "white.yaml"
    white.write_text(cfg_path.read_text().replace(f"correlation_time: {tau}",
                                                  "correlation_time: 0"))
    warnings = {}
    for name, cfg in (("suggested", cfg_path), ("white", white)):
        out = tmp_path / name
        assert main(["run", str(multipath_bag), "-c", str(cfg), "-o", str(out),
                     "--estimators", "ekf", "--no-report"]) == 0
        m = json.loads((out / "metrics.json").read_text())
        assert m["estimators"]["ekf"]["samples"] > 0
        warnings[name] = [w for w in m["warnings"] if "correlation_time" in w]
    capsys.readouterr()
    assert warnings["suggested"] == []
    (w,) = warnings["white"]
    assert w.endswith(f"set correlation_time: {tau} under the GPS sensor "
                      "(`ddfuse inspect` suggests the same)")


def test_inspect_and_run_give_one_gps_model_for_bursts(tmp_path, capsys):
    """Fixes that leave the odometry's track in three bursts: inspect suggests the robust GPS
    model with why above it, and run with that config has nothing more to say about them;
    with the model taken out, run says the same thing inspect did."""
    import bagwriter as bw

    bag = bw.bursts_bag(tmp_path / "bursts.bag", (47.0, 8.0, 400.0))
    cfg_path = tmp_path / "suggested.yaml"
    assert main(["inspect", str(bag), "-o", str(cfg_path)]) == 0
    out = capsys.readouterr().out
    assert "# /fix: disagreed with the odometry's dead reckoning 3 times" in out
    text = cfg_path.read_text()
    assert load_config(cfg_path).gps.model == "dcs"
    lines = text.splitlines()
    at = lines.index("gps: {model: dcs}")
    assert lines[at - 1].startswith("# gps.model dcs: /fix disagreed with the odometry's dead "
                                    "reckoning in 3 bursts")
    gating = tmp_path / "gating.yaml"
    gating.write_text(text.replace("gps: {model: dcs}", "gps: {model: default}"))
    said = {}
    for name, cfg in (("suggested", cfg_path), ("gating", gating)):
        assert main(["run", str(bag), "-c", str(cfg), "-o", str(tmp_path / name),
                     "--estimators", "ekf", "--no-report"]) == 0
        m = json.loads((tmp_path / name / "metrics.json").read_text())
        said[name] = [w for w in m["warnings"] if "come and go in bursts" in w]
        assert [b["episodes"] for b in m["data"]["gps_bursts"]] == [3]
        assert m["gps_model"] == load_config(cfg).gps.model
    capsys.readouterr()
    assert said["suggested"] == []
    (w,) = said["gating"]
    assert "gps: {model: dcs} in the config, or ddfuse run --gps-model dcs" in w
