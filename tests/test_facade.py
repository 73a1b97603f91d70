"""``import ddfuse``: the notebook facade the README shows, cheap to import, and its version."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from readme import python_block

import ddfuse

ROOT = Path(__file__).resolve().parents[1]


def test_importing_ddfuse_loads_no_estimator_or_plotting_library():
    code = ("import sys, ddfuse; print(ddfuse.__version__); "
            "print(sorted(m for m in ('gtsam', 'numba', 'matplotlib', 'rosbags', "
            "'ddfuse.estimation') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT / "tests").stdout.splitlines()
    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M)
    assert out == [version.group(1), "[]"]


def test_the_facade_names_resolve_to_the_library():
    from ddfuse.estimation.bags import read_stream
    from ddfuse.evaluation.pipeline import score

    assert ddfuse.read_bag is read_stream and ddfuse.score is score
    assert set(ddfuse.__all__) <= set(dir(ddfuse))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ddfuse.nope  # noqa: B018


def test_the_readmes_facade_example_scores_what_ddfuse_run_scores(monkeypatch, tmp_path):
    monkeypatch.chdir(ROOT)
    ns: dict = {}
    exec(compile(python_block(r"The shortest way in, from a notebook", "import ddfuse"),  # noqa: S102
                 "README.md", "exec"), ns)
    smoother = ns["summary"].estimators["smoother"]
    assert smoother.samples > 250 and smoother.ate_rmse_m < 0.5
    assert type(ns["fig"]).__name__ == "Figure"
    from ddfuse.evaluation import cli

    assert cli.main(["run", "-o", str(tmp_path), "--estimators", "ekf,smoother",
                     "--no-report"]) == 0
    ran = ddfuse.load_run(tmp_path).summary.estimators
    for name in ("ekf", "smoother"):
        assert ns["summary"].estimators[name].ate_rmse_m == pytest.approx(
            ran[name].ate_rmse_m, abs=1e-6)
