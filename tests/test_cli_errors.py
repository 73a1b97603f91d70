"""`ddfuse` on bad input: exit code 2 and exactly one line on stderr naming the file, option
or key, never a traceback; output paths checked before the work; help texts in plain text."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import bagwriter as bw
import pytest
from ddfuse.evaluation.cli import main

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_600_000_000.0


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, out: str, err: str, *names: str) -> None:
    assert code == 2
    lines = err.strip("\n").split("\n")
    assert len(lines) == 1, err
    assert lines[0].startswith("ddfuse: error: "), err
    assert "Traceback" not in err
    for n in names:
        assert n in lines[0], (n, err)
    assert out == ""


def _imu_bag(tmp_path: Path, fmt: str, name: str = "b") -> Path:
    recs = [("/imu", bw.imu(T0 + 0.01 * i, wcov=bw.diag(1, 1, 1))) for i in range(3000)]
    return bw.write_bag(bw.bag_path(tmp_path, name, fmt), fmt, recs)


def _copy(bag: Path, fmt: str, dest: Path) -> tuple[Path, Path]:
    if fmt == "ros1":
        shutil.copy(bag, dest)
        return dest, dest
    shutil.copytree(bag, dest)
    return dest, dest / bw.storage_file(bag, fmt).name


@pytest.mark.parametrize("name", ["missing.bag", "missing_ros2_dir", "missing.mcap"])
def test_inspect_missing_bag(tmp_path, capsys, name):
    p = tmp_path / name
    assert_one_line_error(*run(["inspect", str(p)], capsys), str(p))


@pytest.mark.parametrize("content", [b"", os.urandom(2048), b"#ROSBAG V2.0\n" + b"\0" * 64,
                                     b"hello\n" * 100])
def test_inspect_garbage_bag(tmp_path, capsys, content):
    p = tmp_path / "garbage.bag"
    p.write_bytes(content)
    assert_one_line_error(*run(["inspect", str(p)], capsys), str(p))


def test_inspect_not_a_bag(tmp_path, capsys):
    d = tmp_path / "empty_dir"
    d.mkdir()
    assert_one_line_error(*run(["inspect", str(d)], capsys), str(d))
    m = d / "lonely.mcap"
    m.write_bytes(b"\x89MCAP0\r\n" + os.urandom(100))
    assert_one_line_error(*run(["inspect", str(m)], capsys), str(m))
    t = tmp_path / "README.txt"
    t.write_text("not a bag\n")
    assert_one_line_error(*run(["inspect", str(t)], capsys), str(t))


@pytest.mark.parametrize("fmt", bw.FORMATS)
def test_inspect_truncated_bag(tmp_path, capsys, fmt):
    bag = _imu_bag(tmp_path, fmt)
    cut, storage = _copy(bag, fmt, bw.bag_path(tmp_path, "cut", fmt))
    with open(storage, "r+b") as f:
        f.truncate(storage.stat().st_size // 2)
    if fmt == "ros1":
        # read from the front without its index, as 'ddfuse run' does: the facts of what could
        # be read on stdout, then one line saying the bag is truncated, exit 2
        code, out, err = run(["inspect", str(cut)], capsys)
        assert code == 2 and err.startswith("ddfuse: error: ") and err.strip().count("\n") == 0
        assert str(cut) in err and "truncated" in err and "Traceback" not in err
        row = next(line for line in out.splitlines() if line.startswith("# /imu"))
        assert 0 < int(row.split()[3]) < 3000
        assert "# suggested config" in out
    else:
        assert_one_line_error(*run(["inspect", str(cut)], capsys), str(cut))
    # the intact bag inspects fine
    code, out, err = run(["inspect", str(bag)], capsys)
    assert code == 0 and "/imu" in out and "3000" in out and err == ""




@pytest.mark.parametrize("fmt", [
    "ros1",
    "sqlite3",
    "mcap",
])
def test_inspect_damaged_bag(tmp_path, capsys, fmt):
    bag = _imu_bag(tmp_path, fmt)
    bad, storage = _copy(bag, fmt, bw.bag_path(tmp_path, "bad", fmt))
    size = storage.stat().st_size
    with open(storage, "r+b") as f:
        f.seek(size // 2)
        f.write(b"\xff" * 5000)
    code, out, err = run(["inspect", str(bad)], capsys)
    if fmt == "ros1":
        # a ROS1 bag is read from the front up to the damage: the facts of what was read, then
        # the one error line
        assert out.startswith(f"# bag: {bad}") and "/imu" in out
        out = ""
    assert_one_line_error(code, out, err, str(bad))


def test_command_line_exit_code_and_stderr(tmp_path):
    """The real process: exit status 2, one stderr line, nothing on stdout."""
    p = tmp_path / "nothing_here.bag"
    r = subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "inspect", str(p)],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stdout == ""
    assert r.stderr.strip("\n").count("\n") == 0 and str(p) in r.stderr
    assert r.stderr.startswith("ddfuse: error: ")


def test_command_line_run_writes_everything_before_its_fast_exit(tmp_path):
    """The real process ends with os._exit after main: its stdout (piped, so buffered) and
    every output file must be complete, and the exit status main's."""
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "run", "--estimators", "ekf",
                        "--no-report", "-o", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.rstrip().endswith("no report (--no-report)")
    assert "wall time" in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["wall_s"]["total"] > 0 and m["estimators"]["ekf"]["samples"] > 0
    rows = (out / "ekf.csv").read_text().splitlines()
    assert len(rows) == m["estimators"]["ekf"]["samples"] + 1


def test_command_line_reader_that_stops_early():
    """``ddfuse inspect BAG | head -1``: when the reader has closed the pipe, the program ends
    with status 141 (128 + SIGPIPE) and no traceback, instead of a BrokenPipeError. (``true``
    reads nothing and exits at once, so the first write fails whatever the timing.)"""
    r = subprocess.run(f"{sys.executable} -m ddfuse.evaluation.cli inspect data/sample_husky.bag "
                       "| true; echo \"rc=${PIPESTATUS[0]}\"",
                       shell=True, executable="/bin/bash", cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert "Traceback" not in r.stderr and "BrokenPipe" not in r.stderr, r.stderr
    assert r.stdout.strip() == "rc=141", (r.stdout, r.stderr)


@pytest.mark.parametrize("argv", [["run", "--lag", "-1"], ["bench", "--lag", "0"],
                                  ["mc", "husky", "--lag", "nan"], ["run", "--lag", "ten"]])
def test_a_lag_that_is_not_positive_seconds_is_refused_before_any_work(argv, capsys):
    """It reached gtsam before: an IndexError on 'x0' inside the first update, per estimator."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert f"argument --lag: expected seconds > 0, got '{argv[-1]}'" in err
    assert "Traceback" not in err


def test_a_gps_holdout_that_withholds_nothing_is_said(tmp_path, capsys):
    """window:T0:T1 past the end of the data: the run goes on (there may be truth to score
    against), and stderr says that nothing was withheld."""
    code = main(["run", "-o", str(tmp_path / "out"), "--estimators", "ekf", "--no-report",
                 "--gps-holdout", "window:9000:9100"])
    err = capsys.readouterr().err
    assert code == 0
    assert ("ddfuse: warning: --gps-holdout window:9000:9100 withheld no GPS fix (the data "
            "span") in err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["gps_holdout_fixes"] == 0 and m["estimators"]["ekf"]["gps_holdout_rmse_m"] is None


@pytest.mark.parametrize("command", ["run", "online", "bench"])
def test_a_missing_bag_without_a_config_is_named_as_missing(tmp_path, capsys, command):
    """Not 'no config given': the config is looked up next to the bag, which is not there."""
    bag = tmp_path / "nowhere.bag"
    code, out, err = run([command, str(bag)], capsys)
    assert_one_line_error(code, out, err, str(bag), "no such bag")


def test_lag_sweep_refuses_a_bad_holdout_before_any_work(capsys):
    with pytest.raises(SystemExit) as e:
        main(["lag-sweep", "--gps-holdout", "every:x"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    assert "--gps-holdout: expected every:K (K >= 2) or window:T0:T1, got 'every:x'" in err


def test_a_config_no_estimator_can_run_on_is_refused(tmp_path, capsys):
    """GPS alone: every estimator needs the motion between measurements (odometry or wheel
    speeds). Before, `run` printed an empty table and `lag-sweep` ran the smoother anyway."""
    cfg = tmp_path / "gps_only.yaml"
    cfg.write_text("sensors:\n  gps:\n  - topic: /fix\n    noise: {horizontal: 1.0}\n"
                   "frame: {datum: first_fix}\n")
    bag = str(ROOT / "data" / "sample_husky.bag")
    code, out, err = run(["run", bag, "-c", str(cfg), "-o", str(tmp_path / "o")], capsys)
    assert_one_line_error(code, out, err, "no estimator can run on the config's sensors (gps)",
                          "an odometry or wheels sensor")
    code, out, err = run(["run", bag, "-c", str(cfg), "--estimators", "ekf_igvc"], capsys)
    assert_one_line_error(code, out, err, "ekf_igvc", "needs an odometry or wheels sensor, and gps")
    code, out, err = run(["lag-sweep", bag, "-c", str(cfg)], capsys)
    assert_one_line_error(code, out, err, str(cfg), "smoother needs an odometry or wheels sensor")


def test_an_output_directory_that_is_a_file_is_one_line(tmp_path, capsys):
    out = tmp_path / "results"
    out.write_text("not a directory")
    code, stdout, err = run(["run", "-o", str(out), "--estimators", "ekf", "--no-report"],
                            capsys)
    assert_one_line_error(code, stdout, err, f"-o {out}: is a file, not a directory")


# --- output paths of the delegated sub-commands (simulate, plot-sim, lag-sweep, mc) ---------

def _not_called(*args, **kwargs):
    raise AssertionError("the work ran although its output path was already known to be bad")


def test_mc_output_dir_that_is_a_file_fails_before_any_seed(tmp_path, capsys, monkeypatch):
    """It failed in write_report, after every seed had run: a 20-seed run lost."""
    import ddfuse.evaluation.cli.mc as mc

    monkeypatch.setattr(mc, "monte_carlo", _not_called)
    afile = tmp_path / "afile"
    afile.write_text("keep")
    code, out, err = run(["mc", "husky", "--seeds", "2", "--duration", "30", "-o", str(afile)],
                         capsys)
    assert_one_line_error(code, out, err, f"-o {afile}: is a file, not a directory")
    below = afile / "sub"
    code, out, err = run(["mc", "husky", "--seeds", "2", "-o", str(below)], capsys)
    assert_one_line_error(code, out, err, f"-o {below}: {afile} is a file, not a directory")
    assert afile.read_text() == "keep"


def test_mc_that_cannot_write_at_the_end_prints_the_table_and_keeps_the_json(
        tmp_path, capsys, monkeypatch):
    import ddfuse.evaluation.cli.mc as mc

    outdir = tmp_path / "results"
    real = mc.monte_carlo

    def then_break_the_outdir(*args, **kwargs):
        res = real(*args, **kwargs)
        outdir.write_text("a file appeared where the results go")
        return res

    monkeypatch.setattr(mc, "monte_carlo", then_break_the_outdir)
    code, out, err = run(["mc", "husky", "--seeds", "1", "--duration", "20", "--jobs", "1",
                          "--estimators", "ekf", "-o", str(outdir)], capsys)
    assert code == 2 and "Traceback" not in err
    # A cold numba cache adds its notices ("compiling ...", "compiled ...") before the error.
    line = "\n".join(x for x in err.strip("\n").splitlines()
                     if not x.startswith(("ddfuse: compiling ", "ddfuse: compiled ")))
    assert "\n" not in line and line.startswith(f"ddfuse: error: -o {outdir}: could not write "
                                                "the results (")
    assert "| ekf | 1 |" in out and "| dr | 1 |" in out  # the table is on stdout
    kept = Path(line.split("the JSON in ")[1])
    try:
        data = json.loads(kept.read_text())
        assert data["scenario"] == "husky" and set(data["summary"]) == {"ekf", "dr"}
    finally:
        kept.unlink()


def test_mc_real_process_output_dir_that_is_a_file(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    r = subprocess.run([sys.executable, "-m", "ddfuse", "mc", "husky", "--seeds", "2",
                        "--duration", "30", "-o", str(afile)],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr == f"ddfuse: error: -o {afile}: is a file, not a directory\n"


def test_lag_sweep_json_in_a_missing_directory_fails_before_the_sweep(tmp_path, capsys,
                                                                      monkeypatch):
    import ddfuse.evaluation.cli.lag_sweep as ls

    monkeypatch.setattr(ls, "lag_sweep", _not_called)
    target = tmp_path / "nonexist_dir" / "x.json"
    code, out, err = run(["lag-sweep", "--json", str(target)], capsys)
    assert_one_line_error(code, out, err,
                          f"--json {target}: no such directory {target.parent}")
    afile = tmp_path / "afile"
    afile.write_text("")
    code, out, err = run(["lag-sweep", "--json", str(afile / "x.json")], capsys)
    assert_one_line_error(code, out, err, f"{afile} is a file, not a directory")


def test_lag_sweep_json_that_cannot_be_written_after_the_sweep_keeps_the_table(
        tmp_path, capsys, monkeypatch):
    import ddfuse.evaluation.cli.lag_sweep as ls

    sub = tmp_path / "sub"
    sub.mkdir()
    row = {"estimator": "ekf", "lag_s": None, "rmse_m": 0.1234, "score": "truth",
           "nees_mean": 1.0, "rtf": 100.0, "update_ms": None}

    def sweep_then_lose_the_directory(*args, **kwargs):
        sub.rmdir()
        return [row]

    monkeypatch.setattr(ls, "lag_sweep", sweep_then_lose_the_directory)
    code, out, err = run(["lag-sweep", "--json", str(sub / "x.json")], capsys)
    assert code == 2 and "| ekf | - | 0.123 |" in out
    assert err.count("\n") == 1 and err.startswith(f"ddfuse: error: --json {sub / 'x.json'}: "
                                                   "could not write it (")


@pytest.mark.parametrize("command", ["simulate", "plot-sim"])
def test_simulate_and_plot_sim_output_under_a_file_fail_before_simulating(
        tmp_path, capsys, monkeypatch, command):
    import ddfuse.evaluation.cli.plot_sim
    import ddfuse.evaluation.cli.simulate

    monkeypatch.setattr(ddfuse.evaluation.cli.simulate, "simulate", _not_called)
    monkeypatch.setattr(ddfuse.evaluation.cli.plot_sim, "simulate", _not_called)
    afile = tmp_path / "afile"
    afile.write_text("")
    target = afile / ("x.bag" if command == "simulate" else "x.png")
    code, out, err = run([command, "husky", "-o", str(target)], capsys)
    assert_one_line_error(code, out, err, f"-o {target}: {afile} is a file, not a directory")


def test_plot_sim_refuses_an_image_format_it_cannot_write(tmp_path, capsys, monkeypatch):
    import ddfuse.evaluation.cli.plot_sim

    monkeypatch.setattr(ddfuse.evaluation.cli.plot_sim, "simulate", _not_called)
    target = tmp_path / "x.xyz"
    code, out, err = run(["plot-sim", "husky", "-o", str(target)], capsys)
    assert_one_line_error(code, out, err, f"-o {target}: cannot write a .xyz image", "png")


def test_delegated_commands_report_os_errors_in_one_line_but_not_bugs(tmp_path, capsys,
                                                                      monkeypatch):
    """An OSError while writing (here a refused permission) is one line naming the file; any
    other exception is a bug and keeps its traceback."""
    import ddfuse.evaluation.cli.plot_sim

    target = tmp_path / "x.png"

    def denied(res, out, title=None):
        raise PermissionError(13, "Permission denied", str(out))

    monkeypatch.setattr(ddfuse.evaluation.cli.plot_sim, "plot_sim", denied)
    code, out, err = run(["plot-sim", "husky", "--duration", "20", "-o", str(target)], capsys)
    assert_one_line_error(code, out, err, f"{target}: Permission denied")

    def bug(res, out, title=None):
        raise KeyError("a programming error")

    monkeypatch.setattr(ddfuse.evaluation.cli.plot_sim, "plot_sim", bug)
    with pytest.raises(KeyError, match="a programming error"):
        main(["plot-sim", "husky", "--duration", "20", "-o", str(target)])


# --- input validation ------------------------------------------------------------------------

def _usage_error(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Traceback" not in err
    return err


@pytest.mark.parametrize("every", ["0", "-1", "nan"])
def test_online_every_must_be_positive(every, capsys):
    err = _usage_error(["online", "data/sample_husky.bag", "--every", every], capsys)
    assert f"argument --every: expected seconds > 0, got '{every}'" in err


@pytest.mark.parametrize("command", [["run"], ["online", "data/sample_husky.bag"], ["bench"],
                                     ["mc", "husky"]])
@pytest.mark.parametrize("value", ["", " , "])
def test_an_empty_estimator_list_is_refused(command, value, capsys):
    """It silently ran the default estimators."""
    err = _usage_error([*command, "--estimators", value], capsys)
    assert (f"argument --estimators: expected comma-separated estimator names, got {value!r} "
            "(leave --estimators out for the default set)") in err


def test_an_unknown_estimator_is_refused_before_any_work(capsys):
    err = _usage_error(["mc", "husky", "--estimators", "ekf,kalman"], capsys)
    assert "argument --estimators: unknown estimator 'kalman' (known: ekf," in err


@pytest.mark.parametrize("command", ["run", "lag-sweep"])
@pytest.mark.parametrize(("spec", "message"), [
    ("window:-50:10", "window:T0:T1 needs T0 >= 0 (seconds from the bag's first message), got "
                      "T0 = -50 in 'window:-50:10'"),
    ("window:210:150", "window:T0:T1 needs T0 < T1 (seconds from the bag's first message), got "
                       "T0 = 210, T1 = 150 in 'window:210:150'"),
    ("window:5:5", "window:T0:T1 needs T0 < T1 (seconds from the bag's first message), got "
                   "T0 = 5, T1 = 5 in 'window:5:5'"),
    ("every:1", "expected every:K (K >= 2) or window:T0:T1, got 'every:1'"),
])
def test_a_gps_holdout_window_says_what_is_wrong(command, spec, message, capsys):
    err = _usage_error([command, "--gps-holdout", spec], capsys)
    assert f"argument --gps-holdout: {message}" in err


@pytest.mark.parametrize(("option", "value", "minimum"), [
    ("--jobs", "0", 1), ("--jobs", "-1", 1), ("--seeds", "0", 1), ("--first-seed", "-1", 0)])
def test_mc_counts_are_checked(option, value, minimum, capsys):
    err = _usage_error(["mc", "husky", option, value], capsys)
    assert f"argument {option}: expected an integer >= {minimum}, got '{value}'" in err


# --- help text -------------------------------------------------------------------------------

def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main([*argv, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


def test_help_texts_are_plain(capsys):
    mc = _help(["mc"], capsys)
    assert "95% chi-square band" in mc and "%%" not in mc
    assert _help(["plot-sim"], capsys).startswith("usage: ddfuse plot-sim ")
    sweep = _help(["lag-sweep"], capsys)
    assert "each scored by ddfuse.evaluation.pipeline.score:" in sweep
    assert "withheld by --gps-holdout;" in sweep
    assert "``" not in sweep and ":func:" not in sweep


# --- online output ---------------------------------------------------------------------------

def test_online_prints_a_header_once_and_always_the_final_estimate(capsys):
    code = main(["online", "data/sample_husky.bag", "--estimators", "ekf", "--every", "1000"])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.splitlines()
    header = [ln for ln in lines if "since the first message" in ln]
    assert len(header) == 1 and lines[0] == header[0]
    for unit in ("t = s", "(x m, y m, yaw deg)", "in ENU about the GPS datum (x east, y north",
                 "1-sigma (m, m, deg)"):
        assert unit in header[0]
    rows = [ln for ln in lines if ln.startswith("t=")]
    # the first message, then (every 1000 s of a 120 s bag prints nothing more) the final one
    assert len(rows) == 2 and rows[0].startswith("t=    0.00 s  ekf (")
    assert rows[1].endswith("(final)") and "+- (" in rows[1]
    assert 119.0 < float(rows[1][2:].split()[0]) < 120.0


def test_an_unknown_gps_model_is_refused_with_the_choices(capsys):
    with pytest.raises(SystemExit) as e:
        main(["run", "--gps-model", "huber"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --gps-model: invalid choice: 'huber'" in err
    assert "dcs" in err and "Traceback" not in err


def test_gps_model_replaces_the_configs_for_every_estimator_and_is_recorded(tmp_path):
    """The sample's config gates (model 'default'); --gps-model dcs runs the EKF's robust
    update instead (another track) and metrics.json says which model ran."""
    out = {}
    for model in ("default", "dcs"):
        argv = ["run", "-o", str(tmp_path / model), "--estimators", "ekf", "--no-report"]
        assert main(argv + (["--gps-model", model] if model != "default" else [])) == 0
        out[model] = json.loads((tmp_path / model / "metrics.json").read_text())
    assert out["default"]["gps_model"] == "default" and out["dcs"]["gps_model"] == "dcs"
    assert (out["default"]["estimators"]["ekf"]["ate_rmse_m"]
            != out["dcs"]["estimators"]["ekf"]["ate_rmse_m"])
