"""The command line's usage contract: usage errors in one line, the output directory checked
first, a GPS hold-out without a gps sensor refused before decoding, the summary of a truncated
run printed before its error line, the --help texts, --version and ``python -m``."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from ddfuse.evaluation.cli import main

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def _not_called(*args, **kwargs):
    raise AssertionError("the work ran although the input was already known to be bad")


def _usage(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    out, err = capsys.readouterr()
    assert e.value.code == 2 and out == ""
    return err


# --- a usage error is one line, 'ddfuse: error: <sub-command>: ...' -------------------------------

@pytest.mark.parametrize(("argv", "line"), [
    (["run", "--lag", "-3"],
     "ddfuse: error: run: argument --lag: expected seconds > 0, got '-3' "
     "(see ddfuse run --help)"),
    (["run", "--gps-holdout", "every:1"],
     "ddfuse: error: run: argument --gps-holdout: expected every:K (K >= 2) or window:T0:T1, "
     "got 'every:1' (see ddfuse run --help)"),
    (["run", "--estimators", "ekff"],
     "ddfuse: error: run: argument --estimators: unknown estimator 'ekff' (known: ekf, "
     "ekf_igvc, ekf_landmark, ekf_slam, smoother, smoother_lagged, batch, dr) "
     "(see ddfuse run --help)"),
    (["run", "--reorder-window", "-1"],
     "ddfuse: error: run: argument --reorder-window: expected seconds >= 0, got '-1' "
     "(see ddfuse run --help)"),
    (["bench", "--lag", "0"],
     "ddfuse: error: bench: argument --lag: expected seconds > 0, got '0' "
     "(see ddfuse bench --help)"),
    (["online"],
     "ddfuse: error: online: the following arguments are required: bag "
     "(see ddfuse online --help)"),
    (["frob"],
     "ddfuse: error: argument command: invalid choice: 'frob' (choose from 'inspect', 'run', "
     "'report', 'online', 'node', 'bench', 'tune', 'fleet', 'compare', 'simulate', 'plot-sim', "
     "'lag-sweep', 'mc') "
     "(see ddfuse --help)"),
    # the sub-commands that parse their own arguments
    (["lag-sweep", "--lags", "x"],
     "ddfuse: error: lag-sweep: --lags: expected comma-separated seconds, got 'x' "
     "(see ddfuse lag-sweep --help)"),
    (["mc", "husky", "--jobs", "0"],
     "ddfuse: error: mc: argument --jobs: expected an integer >= 1, got '0' "
     "(see ddfuse mc --help)"),
    (["simulate", "husky"],
     "ddfuse: error: simulate: the following arguments are required: -o/--output "
     "(see ddfuse simulate --help)"),
    (["plot-sim", "husky", "--seed", "-1", "-o", "x.png"],
     "ddfuse: error: plot-sim: argument --seed: expected an integer >= 0, got '-1' "
     "(see ddfuse plot-sim --help)"),
])
def test_a_usage_error_is_one_line_naming_the_sub_command(argv, line, capsys):
    assert _usage(argv, capsys) == line + "\n"


def test_a_usage_error_in_the_real_process():
    r = subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "run", "--lag", "-3"],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr == ("ddfuse: error: run: argument --lag: expected seconds > 0, got '-3' "
                        "(see ddfuse run --help)\n")


# --- --gps-holdout needs a gps sensor -------------------------------------------------------------

def test_run_gps_holdout_without_a_gps_sensor_is_refused_before_decoding(tmp_path, capsys,
                                                                         monkeypatch):
    """It ran and exited 0 with 'withheld no GPS fix (the data span 119.9 s ...)'."""
    import ddfuse.evaluation.pipeline


    monkeypatch.setattr(ddfuse.evaluation.pipeline, "run_bag", _not_called)
    out = tmp_path / "out"
    code = main(["run", str(SEED002), "--gps-holdout", "every:5", "-o", str(out)])
    o, err = capsys.readouterr()
    assert code == 2 and o == ""
    assert err == (f"ddfuse: error: --gps-holdout every:5: {SEED002.with_suffix('.yaml')} has no "
                   "gps sensor\n")
    assert not out.exists()


def test_lag_sweep_gps_holdout_without_a_gps_sensor_is_refused_before_decoding(capsys,
                                                                               monkeypatch):
    """seed002 has ground truth: the sweep ran, scored against the truth, the option ignored."""
    import ddfuse.evaluation.lag_sweep

    monkeypatch.setattr(ddfuse.evaluation.lag_sweep, "read_stream", _not_called)
    code = main(["lag-sweep", str(SEED002), "--gps-holdout", "window:10:20"])
    o, err = capsys.readouterr()
    assert code == 2 and o == ""
    assert err == (f"ddfuse: error: --gps-holdout window:10:20: "
                   f"{SEED002.with_suffix('.yaml')} has no gps sensor\n")


# --- the output directory is checked first, naming the option -------------------------------------

def test_run_output_dir_that_is_a_file_is_refused_first(tmp_path, capsys, monkeypatch):
    import ddfuse.evaluation.cli.run

    monkeypatch.setattr(ddfuse.evaluation.cli.run, "config_for", _not_called)
    afile = tmp_path / "afile"
    afile.write_text("keep")
    code = main(["run", "-o", str(afile)])
    o, err = capsys.readouterr()
    assert code == 2 and o == ""
    assert err == f"ddfuse: error: -o {afile}: is a file, not a directory\n"
    code = main(["run", "-o", str(afile / "sub")])
    assert capsys.readouterr().err == (f"ddfuse: error: -o {afile / 'sub'}: {afile} is a file, "
                                       "not a directory\n")
    assert afile.read_text() == "keep"


def test_report_on_a_file_names_it(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("")
    code = main(["report", str(afile)])
    assert code == 2
    assert capsys.readouterr().err == f"ddfuse: error: OUTDIR {afile}: is a file, not a directory\n"


# --- a truncated bag: the summary of what was written, then the error line ------------------------

def test_run_on_a_truncated_bag_prints_the_summary_before_the_error(tmp_path, capsys):
    bag = tmp_path / "trunc.bag"
    bag.write_bytes((ROOT / "data" / "sample_husky.bag").read_bytes()[:400_000])
    shutil.copy(ROOT / "data" / "sample_husky.yaml", tmp_path / "trunc.yaml")
    out = tmp_path / "out"
    code = main(["run", str(bag), "-o", str(out), "--estimators", "ekf", "--no-report"])
    stdout, err = capsys.readouterr()
    assert code == 2
    assert err.count("\n") == 1 and err.startswith(f"ddfuse: error: {bag}: bag is truncated")
    assert err.rstrip().endswith(f"could be read are in {out}")
    lines = stdout.splitlines()
    assert lines[0].startswith(f"{bag}: ") and "measurements, decoded in" in lines[0]
    head = lines[1].split()
    assert head[:3] == ["rank", "estimator", "output"] and head[-1] == "final_xy"
    assert lines[2].split()[:2] == ["1", "ekf"] and lines[4].startswith("wall time ")
    assert (out / "metrics.json").is_file()


# --- --help ---------------------------------------------------------------------------------------

def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())


FALLBACK = ("config YAML (default: the bag's path with .yaml; else, for the real bags ddfuse "
            "ships a config for, data/configs/<bag's stem>.yaml)")


@pytest.mark.parametrize("command", [["run"], ["lag-sweep"], ["online"]])
def test_help_of_c_states_the_shipped_config_fallback(command, capsys):
    assert f"-c CONFIG, --config CONFIG {FALLBACK}" in _help(command, capsys)


def test_help_of_online_and_bench_describe_every_argument(capsys):
    online = _help(["online"], capsys)
    assert "bag bag to replay: ROS1 .bag, ROS2 bag directory or .mcap" in online
    bench = _help(["bench"], capsys)
    assert ("-c CONFIG, --config CONFIG config YAML for every bag given (default: per bag, the "
            "bag's path with .yaml; else,") in bench


@pytest.mark.parametrize(("command", "option"), [
    (["run"], "--lag S"), (["bench"], "--lag S"), (["mc"], "--lag S"), (["mc"], "--duration S"),
    (["simulate"], "--duration S"), (["plot-sim"], "--duration S"),
    (["run"], "--reorder-window S"), (["online"], "--every S")])
def test_seconds_options_show_metavar_s(command, option, capsys):
    assert option in _help(command, capsys)


def test_online_unknown_estimator_lists_only_what_online_runs(capsys):
    err = _usage(["online", "data/sample_husky.bag", "--estimators", "foo"], capsys)
    assert err == ("ddfuse: error: online: argument --estimators: unknown estimator 'foo' "
                   "(known: ekf, ekf_igvc, ekf_landmark, ekf_slam, smoother, dr) "
                   "(see ddfuse online --help)\n")


# --- the program's entry points and its version ---------------------------------------------------

def test_version_is_the_installed_packages(capsys):
    import ddfuse

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out == f"ddfuse {ddfuse.__version__}\n"


@pytest.mark.parametrize("module", ["ddfuse", "ddfuse.evaluation.cli"])
def test_python_dash_m_runs_the_command_line(module, tmp_path):
    import ddfuse

    r = subprocess.run([sys.executable, "-m", module, "--version"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert (r.returncode, r.stdout, r.stderr) == (0, f"ddfuse {ddfuse.__version__}\n", "")
