"""The execution engine: every backend gives every task's outcome, a failing task is its own
error, an unreachable scheduler is one line, and a worker that dies is retried, then reported."""

from __future__ import annotations

import math
import operator
import os
import socket

import pytest
from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation import engine
from ddfuse.evaluation.engine import Engine, TaskFailed


def _outcomes(eng: Engine, fn, tasks) -> dict[int, tuple]:
    with eng:
        return {o.index: (o.value, o.error) for o in eng.map(fn, tasks)}


def test_serial_engine_gives_each_result_and_a_failing_task_its_own_error():
    got = _outcomes(Engine(jobs=1), math.sqrt, [4.0, -1.0, 9.0])
    assert got[0] == (2.0, None) and got[2] == (3.0, None)
    assert got[1][0] is None and got[1][1] == "ValueError: math domain error"


def test_process_pool_engine_when_dask_is_absent(monkeypatch):
    monkeypatch.setattr(engine, "dask_available", lambda: False)
    eng = Engine(jobs=2)
    assert eng.kind == "processes" and "Dask not installed" in eng.backend
    got = _outcomes(eng, math.sqrt, [4.0, -1.0, 9.0, 16.0])
    assert {i: v for i, (v, _) in got.items()} == {0: 2.0, 1: None, 2: 3.0, 3: 4.0}
    assert got[1][1] == "ValueError: math domain error"


def test_process_pool_engine_retries_a_task_whose_worker_died_once_then_reports_it(monkeypatch):
    monkeypatch.setattr(engine, "dask_available", lambda: False)
    # os._exit(3) kills the worker process: the pool breaks; tried twice, then a failed outcome
    got = _outcomes(Engine(jobs=1 + 1), os._exit, [3])
    assert got[0][0] is None and got[0][1].startswith("worker process died")


def test_scheduler_without_dask_names_the_extra(monkeypatch):
    monkeypatch.setattr(engine, "dask_available", lambda: False)
    with pytest.raises(DdfuseError, match=r"pip install 'ddfuse\[scale\]'"):
        Engine("tcp://127.0.0.1:8786")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line_naming_the_address():
    pytest.importorskip("distributed")
    address = f"tcp://127.0.0.1:{_closed_port()}"
    with pytest.raises(DdfuseError) as e:
        Engine(address, timeout=1.0).__enter__()
    assert str(e.value).startswith(f"--scheduler {address}: no Dask scheduler answered within 1 s")
    assert "\n" not in str(e.value)


@pytest.mark.integration
def test_local_cluster_gives_each_result_and_reports_a_worker_that_died_twice():
    pytest.importorskip("distributed")
    eng = Engine(jobs=2)
    assert eng.kind == "dask-local"
    got = _outcomes(eng, math.sqrt, [4.0, -1.0, 9.0])
    assert got[0] == (2.0, None) and got[2] == (3.0, None)
    assert "math domain error" in got[1][1]
    got = _outcomes(Engine(jobs=2), os._exit, [3])
    assert got[0][0] is None and "KilledWorker" in got[0][1]


def test_mc_with_an_unreachable_scheduler_is_one_line_and_exit_2(capsys):
    pytest.importorskip("distributed")
    from ddfuse.evaluation.cli import main

    address = f"tcp://127.0.0.1:{_closed_port()}"
    assert main(["mc", "husky", "--seeds", "2", "--duration", "20", "--scheduler", address,
                 "--scheduler-timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ddfuse: error: --scheduler {address}: no Dask scheduler answered")
    assert err.count("\n") == 1


def _sweep_numbers(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in ("rtf", "update_ms")} for r in rows]


@pytest.mark.slow
def test_lag_sweep_points_on_worker_processes_give_the_rows_of_the_serial_sweep(monkeypatch):
    from ddfuse.evaluation.lag_sweep import lag_sweep
    from ddfuse.evaluation.shipped import DATA

    monkeypatch.setattr(engine, "dask_available", lambda: False)
    bag, cfg = DATA / "sample_husky.bag", DATA / "sample_husky.yaml"
    serial = lag_sweep(bag, cfg, (0.5, 10.0))
    with Engine(jobs=2) as eng:
        spread = lag_sweep(bag, cfg, (0.5, 10.0), engine=eng)
    assert len(serial) == 5 and _sweep_numbers(spread) == _sweep_numbers(serial)


def _shared_results(eng: Engine, obj, tasks):
    with eng, eng.shared(operator.mul, obj) as sm:
        first = sm.map(tasks)
        return first, sm.map(reversed(tasks))  # the pool or the scattered object reused


def test_shared_map_gives_results_in_the_tasks_order_in_this_process_and_forked():
    tasks = [float(k) for k in range(12)]
    for eng in (Engine(jobs=1), Engine(jobs=2, fork=True)):
        first, second = _shared_results(eng, 2.5, tasks)
        assert first == [2.5 * t for t in tasks], eng.backend
        assert second == [2.5 * t for t in reversed(tasks)], eng.backend
    assert "forked" in Engine(jobs=2, fork=True).backend


def test_a_shared_map_task_that_fails_is_one_line_naming_the_backend():
    with Engine(jobs=2, fork=True) as eng, eng.shared(operator.truediv, 1.0) as sm:
        assert sm.map([2.0, 4.0]) == [0.5, 0.25]
        with pytest.raises(TaskFailed) as e:
            sm.map([2.0, 0.0, 4.0])
    assert "ZeroDivisionError" in str(e.value) and "forked" in str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.integration
def test_shared_map_on_a_local_cluster_scatters_once_and_keeps_the_order():
    pytest.importorskip("distributed")
    tasks = [float(k) for k in range(12)]
    eng = Engine(jobs=2)
    assert eng.kind == "dask-local"
    first, second = _shared_results(eng, 2.5, tasks)
    assert first == [2.5 * t for t in tasks]
    assert second == [2.5 * t for t in reversed(tasks)]
    failed = pytest.raises(TaskFailed, match=r"task 2 of 3 failed on Dask LocalCluster.*"
                           "ZeroDivisionError")
    with Engine(jobs=2) as eng, eng.shared(operator.truediv, 1.0) as sm, failed:
        sm.map([2.0, 0.0, 4.0])


def test_tune_with_an_unreachable_scheduler_is_one_line_and_exit_2_before_reading(capsys):
    pytest.importorskip("distributed")
    from ddfuse.evaluation.cli import main
    from ddfuse.evaluation.shipped import DATA

    address = f"tcp://127.0.0.1:{_closed_port()}"
    assert main(["tune", str(DATA / "sample_husky.bag"), "--scheduler", address,
                 "--scheduler-timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ddfuse: error: --scheduler {address}: no Dask scheduler answered")
    assert err.count("\n") == 1
