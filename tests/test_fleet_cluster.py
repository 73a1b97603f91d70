"""ddfuse fleet, mc, lag-sweep and tune give the same numbers, to the last digit, run serially in
this process, on a Dask LocalCluster and on a scheduler with two workers started here as
separate processes (``dask scheduler`` / ``dask worker`` on 127.0.0.1, torn down at the end);
only the timing fields (``fleet.TIMING_KEYS``) differ. And a bag whose task kills its worker
process, on such a cluster, is retried once, then its row says so while the others finish."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from ddfuse.evaluation.cli import main
from ddfuse.evaluation.fleet import TIMING_KEYS

pytestmark = pytest.mark.integration
START_TIMEOUT_S = 120.0  # the scheduler and both workers up; bounded whatever the load
ESTIMATORS = "ekf,ekf_igvc,smoother,smoother_lagged"
MC_TIMING = frozenset({"runtime_s", "runtime_mean", "wall_s"})


def _without_timing(v, outdir: str):
    if isinstance(v, dict):
        return {k: _without_timing(x, outdir) for k, x in v.items() if k not in TIMING_KEYS}
    if isinstance(v, list):
        return [_without_timing(x, outdir) for x in v]
    return v.replace(outdir, "OUTDIR") if isinstance(v, str) else v


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:  # each started in its own session: its group is it and its children
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=20)


@contextlib.contextmanager
def _cluster(tmp_path: Path, env: dict | None = None):
    """The address of a scheduler with two single-threaded worker processes (each under a
    nanny, which restarts it if it dies) on 127.0.0.1; ``env``: added to their environment."""
    distributed = pytest.importorskip("distributed")
    sfile = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")  # noqa: SIM115 - closed at teardown
    common = dict(stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path,
                  env={**os.environ, **(env or {})})
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler",
                               "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sfile)], **common)]
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not sfile.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert sfile.is_file(), (tmp_path / "dask.log").read_text()
        procs += [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker",
                                    "--scheduler-file", str(sfile), "--nthreads", "1",
                                    "--host", "127.0.0.1", "--no-dashboard",
                                    "--name", f"w{k}"], **common) for k in range(2)]
        address = json.loads(sfile.read_text())["address"]
        with distributed.Client(address, timeout=30) as c:
            c.wait_for_workers(2, timeout=max(1.0, deadline - time.monotonic()))
        yield address
    finally:
        _stop(procs)
        log.close()


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """The address of a scheduler with two single-threaded worker processes on 127.0.0.1."""
    with _cluster(tmp_path_factory.mktemp("dask")) as address:
        yield address


def test_fleet_numbers_are_the_same_serially_on_local_processes_and_on_a_cluster(
        scheduler, tmp_path):
    bags = tmp_path / "bags"
    for seed in (1, 2, 3):
        assert main(["simulate", "random", "--seed", str(seed), "--duration", "30", "-o",
                     str(bags / f"drive{seed}.bag")]) == 0
    (bags / "broken.bag").write_bytes(b"not a bag")  # its error row the same everywhere
    (bags / "broken.yaml").write_bytes((bags / "drive1.yaml").read_bytes())
    runs = {"serial": ["--jobs", "1"], "local": ["--jobs", "2"],
            "cluster": ["--scheduler", scheduler]}
    docs = {}
    for name, opts in runs.items():
        out = tmp_path / name
        # the reports aside (each bag's, three times): the test below has the workers render
        assert main(["fleet", str(bags), "-o", str(out), "--estimators", ESTIMATORS,
                     "--no-report", *opts]) == 0
        doc = json.loads((out / "fleet.json").read_text())
        docs[name] = _without_timing(doc, str(out))
    assert docs["serial"]["bags_ran"] == 3 and len(docs["serial"]["rows"]) == 3 * 4 + 1
    assert all(r["score_m"] is not None for r in docs["serial"]["rows"] if r["estimator"])
    assert "broken.bag" in docs["serial"]["bags"][0]["error"]
    assert docs["local"] == docs["serial"]
    assert docs["cluster"] == docs["serial"]
    for seed in (1, 2, 3):  # the tracks too, byte for byte
        for track in ("ekf.tum", "smoother.tum"):
            ref = (tmp_path / "serial" / f"drive{seed}" / track).read_bytes()
            for name in ("local", "cluster"):
                assert (tmp_path / name / f"drive{seed}" / track).read_bytes() == ref


def test_mc_numbers_are_the_same_in_this_process_and_on_a_cluster(scheduler, tmp_path):
    from ddfuse.evaluation.montecarlo import monte_carlo

    def numbers(mc) -> str:  # as JSON text: dead reckoning's NEES is NaN, never == itself
        def strip(v):
            if isinstance(v, dict):
                return {k: strip(x) for k, x in v.items() if k not in MC_TIMING}
            return [strip(x) for x in v] if isinstance(v, list) else v

        return json.dumps(strip(mc.to_json()), sort_keys=True)

    kw = dict(estimators=["ekf", "ekf_igvc"], duration=20.0)
    serial = numbers(monte_carlo("husky", [0, 1, 2], jobs=1, **kw))
    assert numbers(monte_carlo("husky", [0, 1, 2], scheduler=scheduler, **kw)) == serial


def test_lag_sweep_rows_are_the_same_in_this_process_and_on_a_cluster(scheduler):
    from ddfuse.evaluation.engine import Engine
    from ddfuse.evaluation.lag_sweep import lag_sweep
    from ddfuse.evaluation.shipped import DATA

    def numbers(rows):
        return [{k: v for k, v in r.items() if k not in ("rtf", "update_ms")} for r in rows]

    bag, cfg = DATA / "sample_husky.bag", DATA / "sample_husky.yaml"
    serial = lag_sweep(bag, cfg, (0.5, 10.0))
    with Engine(scheduler) as eng:
        assert numbers(lag_sweep(bag, cfg, (0.5, 10.0), engine=eng)) == numbers(serial)


def test_tune_gives_the_same_config_in_this_process_and_on_a_cluster(scheduler, tmp_path,
                                                                     capsys):
    bag = tmp_path / "drive.bag"
    assert main(["simulate", "husky", "--seed", "3", "--duration", "10", "-o", str(bag)]) == 0
    capsys.readouterr()
    assert main(["tune", str(bag), "--jobs", "1", "-o", str(tmp_path / "serial.yaml")]) == 0
    serial_table = capsys.readouterr().out
    assert main(["tune", str(bag), "--scheduler", scheduler, "-o",
                 str(tmp_path / "cluster.yaml")]) == 0
    cap = capsys.readouterr()
    assert f"ddfuse: tune: the runs on Dask scheduler {scheduler} (2 workers)" in cap.err
    tuned = (tmp_path / "serial.yaml").read_text()
    assert " tuned" in serial_table  # some value was tuned: the comparison is not of defaults
    assert (tmp_path / "cluster.yaml").read_text() == tuned

    def values(table: str) -> list[str]:  # the table without its first line (runs, seconds)
        return table.splitlines()[1:-1]  # ... and its last (where the config went)

    assert values(cap.out) == values(serial_table)


# Run in each worker process of the cluster below (PYTHONPATH): the worker that opens a bag
# named kill_worker.bag dies at once, as one the OOM killer ends would.
_KILL_HOOK = """
import os, sys

def _die_on_the_bag(event, args):
    if event == "open" and str(args[0]).endswith("kill_worker.bag"):
        os._exit(137)

sys.addaudithook(_die_on_the_bag)
"""


def test_a_bag_that_kills_its_worker_is_retried_once_then_its_row_says_so(tmp_path, capsys):
    bags = tmp_path / "bags"
    for name, seed in (("drive1", 1), ("kill_worker", 2), ("drive3", 3)):
        assert main(["simulate", "husky", "--seed", str(seed), "--duration", "10", "-o",
                     str(bags / f"{name}.bag")]) == 0
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(textwrap.dedent(_KILL_HOOK))
    # the user's scheduler decides how often a task may kill a worker: here once more, no more
    env = {"PYTHONPATH": os.pathsep.join([str(hook), os.environ.get("PYTHONPATH", "")]),
           "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "1"}
    (tmp_path / "dask").mkdir()
    out = tmp_path / "out"
    with _cluster(tmp_path / "dask", env) as address:
        assert main(["fleet", str(bags), "-o", str(out), "--estimators", "ekf,smoother",
                     "--scheduler", address]) == 0
    doc = json.loads((out / "fleet.json").read_text())
    by_bag = {b["bag"]: b for b in doc["bags"]}
    assert (doc["bags_ran"], doc["bags_failed"]) == (2, 1)
    killed = by_bag["kill_worker"]
    assert killed["error"].startswith("KilledWorker") and "\n" not in killed["error"]
    assert killed["path"] == str(bags / "kill_worker.bag")
    assert [r for r in doc["rows"] if r["bag"] == "kill_worker"] == [
        {"bag": "kill_worker", "estimator": None, "error": killed["error"]}]
    # two workers died on it (the first try and the retry), as the workers' log says
    log = (tmp_path / "dask" / "dask.log").read_text()
    assert log.count("exited with status 137") == 2, log[-3000:]
    for name in ("drive1", "drive3"):  # the others ran, their reports rendered by the workers
        assert by_bag[name]["error"] is None
        assert sorted(by_bag[name]["ranking"]) == ["ekf", "smoother"]
        assert (out / name / "report.html").is_file()
    assert not (out / "kill_worker" / "metrics.json").exists()
    assert "kill_worker: ERROR: KilledWorker" in capsys.readouterr().err
