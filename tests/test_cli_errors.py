"""`ddfuse` on bad input: exit code 2 and exactly one line on stderr naming the file, no
traceback. (Only `inspect` reads a bag today; `run` with a config will join these cases.)"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import bagwriter as bw
import pytest

from evaluation.cli import main

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
        row = next(line for line in out.splitlines() if line.startswith("/imu"))
        assert 0 < int(row.split()[2]) < 3000
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
    assert_one_line_error(*run(["inspect", str(bad)], capsys), str(bad))


def test_command_line_exit_code_and_stderr(tmp_path):
    """The real process: exit status 2, one stderr line, nothing on stdout."""
    p = tmp_path / "nothing_here.bag"
    r = subprocess.run([sys.executable, "-m", "evaluation.cli", "inspect", str(p)],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stdout == ""
    assert r.stderr.strip("\n").count("\n") == 0 and str(p) in r.stderr
    assert r.stderr.startswith("ddfuse: error: ")


def test_command_line_run_writes_everything_before_its_fast_exit(tmp_path):
    """The real process ends with os._exit after main: its stdout (piped, so buffered) and
    every output file must be complete, and the exit status main's."""
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "evaluation.cli", "run", "--estimators", "ekf",
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
    r = subprocess.run(f"{sys.executable} -m evaluation.cli inspect data/sample_husky.bag "
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
    assert_one_line_error(code, stdout, err, str(out), "a file where a directory is needed")
