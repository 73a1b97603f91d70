"""docs/tools/ekf_loop_replay.py (issue 27's EKF comparator): replayed in one numba loop, the
event kernel's recorded calls end on the filter's own arrays, bit for bit."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("ekf_loop_replay",
                                                  ROOT / "docs" / "tools" / "ekf_loop_replay.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow  # ~10 s of CPU (the loop's compile, the recording's copies): a tool's check
def test_the_replay_ends_on_the_filters_arrays():
    tool = _tool()
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    stream = read_stream(ROOT / "data" / "sample_husky.bag", cfg)
    ekf, calls, resync = tool.record(cfg, stream)
    assert len(calls) > 5000 and 0 in resync and len(resync) < len(calls) / 100
    kj = jit.kernels()
    loop = tool.replay_loop(kj.uni_event)
    _, arr = tool.replay(loop, calls, resync, kj)
    for name in ("W", "sf", "si"):
        assert np.array_equal(arr[name], getattr(ekf.kf, name), equal_nan=True), name
    # without the resyncs the Python steps between calls are missing: the replay ends elsewhere
    _, skipped = tool.replay(loop, calls, {0: resync[0]}, kj)
    assert not np.array_equal(skipped["W"], ekf.kf.W, equal_nan=True)
