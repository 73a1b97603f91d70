"""ddfuse fleet and mc give the same numbers, to the last digit, run serially in this process, on a
Dask LocalCluster and on a scheduler with two workers started here as separate processes
(``dask scheduler`` / ``dask worker`` on 127.0.0.1, torn down at the end); only the timing
fields (``fleet.TIMING_KEYS``) differ."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

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


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """The address of a scheduler with two single-threaded worker processes on 127.0.0.1."""
    distributed = pytest.importorskip("distributed")
    tmp_path = tmp_path_factory.mktemp("dask")
    sfile = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")  # noqa: SIM115 - closed at teardown
    common = dict(stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path)
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
        assert main(["fleet", str(bags), "-o", str(out), "--estimators", ESTIMATORS,
                     *opts]) == 0
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
