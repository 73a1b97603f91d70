"""``ddfuse bench``'s process handling: a benchmark child that dies is reported, never waited on."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from ddfuse.estimation.errors import BagError
from ddfuse.evaluation import bench

pytest.importorskip("gtsam")

ROOT = Path(__file__).resolve().parents[1]


def _dies(bag, cfg_path, name, lag, tracks, conn) -> None:
    """A child that ends the way a crash inside a C++ library does: no result, no exception."""
    os._exit(3)


def test_a_benchmark_child_that_dies_is_an_error_naming_the_estimator_and_exit_code(monkeypatch):
    monkeypatch.setattr(bench, "_one", _dies)  # the spawned child imports this module for it
    with pytest.raises(BagError, match=r"benchmark process of ekf ended without a result "
                                       r"\(exit code 3\)"):
        bench.bench_bag(ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml",
                        ["ekf"])


@pytest.mark.parametrize("names, outputs", [(["smoother"], ["smoother"]),
                                            (["smoother_lagged"], ["smoother", "smoother_lagged"])])
def test_a_benchmark_row_names_the_outputs_it_timed(names, outputs):
    r = bench.bench_bag(ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml",
                        names)
    (row,) = r["estimators"]
    assert row["estimator"] == "smoother" and row["outputs"] == outputs
    assert row["error"] is None and row["runtime_s"] > 0


@pytest.mark.slow
def test_the_batch_row_says_its_solve_is_in_finish_not_in_the_latencies(capsys, tmp_path):
    """The batch's work is its whole-run solve in finish(); its update latencies miss it, so
    its row is marked and a footnote gives the solve's time (which dwarfs any update)."""
    import json

    from ddfuse.evaluation.cli import main

    out_json = tmp_path / "bench.json"
    assert main(["bench", str(ROOT / "data" / "sample_husky.bag"), "--estimators", "ekf,batch",
                 "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    rows = {e["estimator"]: e for e in json.loads(out_json.read_text())[0]["estimators"]}
    assert rows["batch"]["offline"] and not rows["ekf"]["offline"]
    batch = rows["batch"]
    assert 1e3 * batch["finish_s"] > batch["update_ms"]["max"]
    assert batch["finish_s"] <= batch["runtime_s"]
    lines = out.splitlines()
    assert any(line.startswith("  batch *") for line in lines)
    assert not any(line.startswith("  ekf *") for line in lines)
    note = next(line for line in lines if line.startswith("  * batch:"))
    assert "finish()" in note and f"{batch['finish_s']:.3f} s" in note
