"""EKF kernels missing from numba's cache (the first run after installing): under the
"reference" policy that ``ddfuse run`` sets, the filters run their Python reference path and a
background process is asked to compile the missing kernels, once per process, said on the
terminal; under the library's default ("compile") they are compiled then and there. The numba
cache itself is not touched: its lookup is replaced by one that finds nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
from ddfuse.ekf_baseline import compiled
from ddfuse.ekf_baseline.igvc import IgvcEkf
from ddfuse.ekf_baseline.unicycle import UnicycleEkf
from ddfuse.estimation.config import load_config
from ddfuse.factors import jitcache

ROOT = Path(__file__).resolve().parents[1]


def _cfg():
    return load_config(ROOT / "data" / "sample_husky.yaml")


@pytest.fixture
def cold(monkeypatch):
    """A process whose kernels are in no cache: nothing warmed up, every lookup a miss; the
    background builds asked for recorded instead of started."""
    asked: list[list[str]] = []
    kj = compiled.kernels()
    monkeypatch.setattr(compiled, "COLD_COMPILE", {})
    monkeypatch.setattr(kj, "load_cached", lambda *names: False)
    monkeypatch.setattr(compiled, "build_in_background", lambda names: asked.append(names))
    was = jitcache.on_cold_cache()
    yield asked
    jitcache.on_cold_cache(was)


def test_reference_policy_runs_the_python_filters_and_asks_for_a_build(cold):
    jitcache.on_cold_cache("reference")
    cfg = _cfg()
    ekf = UnicycleEkf(cfg)
    igvc = IgvcEkf(cfg, datum=(47.0, 8.0, 400.0))
    assert ekf.reference and not ekf.compiled and igvc.reference and not igvc.compiled
    assert cold == [["uni_event", "world_cov"], ["igvc_event"]]


def test_a_fixed_rate_filter_asks_for_its_step_kernel_too(cold):
    jitcache.on_cold_cache("reference")
    cfg = _cfg()
    cfg.ekf.rate = 10.0
    assert UnicycleEkf(cfg).reference
    assert cold == [["uni_event", "world_cov", "uni_stacked"]]


def test_compile_policy_compiles_as_before(cold):
    jitcache.on_cold_cache("compile")
    ekf = UnicycleEkf(_cfg())
    assert ekf.compiled and not ekf.reference and cold == []  # warmed up here (cached)


def test_an_explicit_reference_filter_asks_for_nothing(cold):
    jitcache.on_cold_cache("reference")
    assert UnicycleEkf(_cfg(), reference=True).reference and cold == []


def test_the_background_build_is_started_once_and_said(monkeypatch):
    started, said = [], []
    monkeypatch.setattr(compiled, "_started", set())
    monkeypatch.setattr(compiled.subprocess, "Popen",
                        lambda args, **kw: started.append((args, kw)))
    monkeypatch.setattr(jitcache, "_notice", [said.append])
    compiled.build_in_background(["uni_event", "world_cov"])
    compiled.build_in_background(["uni_event"])
    assert len(started) == 1 and len(said) == 1
    args, kw = started[0]
    assert args[1:] == ["-m", "ddfuse.ekf_baseline.kernel_build", "uni_event", "world_cov"]
    assert kw["start_new_session"]  # outlives the run
    assert "reference filters" in said[0] and "background" in said[0]


def test_unknown_policy_is_refused():
    with pytest.raises(ValueError, match="on_cold_cache"):
        jitcache.on_cold_cache("later")
