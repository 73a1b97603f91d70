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
    monkeypatch.setattr(jitcache, "_started", set())
    monkeypatch.setattr(jitcache, "build_running", lambda: False)
    monkeypatch.setattr(jitcache.subprocess, "Popen",
                        lambda args, **kw: started.append((args, kw)))
    monkeypatch.setattr(jitcache, "_notice", [said.append])
    compiled.build_in_background(["uni_event", "world_cov"])
    compiled.build_in_background(["uni_event"])
    jitcache.build_in_background(["joseph"])  # in the default set the first build compiles
    jitcache.build_in_background(["preintegration"])
    assert len(started) == 1 and len(said) == 1
    args, kw = started[0]
    assert args[1:] == ["-m", "ddfuse.ekf_baseline.kernel_build", "uni_event", "world_cov"]
    assert kw["start_new_session"]  # outlives the run
    assert "reference code" in said[0] and "background" in said[0]
    compiled.build_in_background(["uni_stacked"])  # outside the default set: its own build
    assert len(started) == 2 and started[1][0][3:] == ["uni_stacked"] and len(said) == 1


def test_a_deferred_build_starts_when_the_run_is_over_with_every_name_asked(monkeypatch):
    started, said = [], []
    monkeypatch.setattr(jitcache, "_started", set())
    monkeypatch.setattr(jitcache, "build_running", lambda: False)
    monkeypatch.setattr(jitcache.subprocess, "Popen",
                        lambda args, **kw: started.append(args))
    monkeypatch.setattr(jitcache, "_notice", [said.append])
    with jitcache.deferred_build():
        compiled.build_in_background(["uni_event"])
        with jitcache.deferred_build():  # nested: still the outer block's to start
            compiled.build_in_background(["uni_stacked"])
        assert started == []  # nothing beside the run
        assert len(said) == 1 and "when this run has finished" in said[0]
    assert len(started) == 1 and started[0][3:] == ["uni_event", "uni_stacked"]
    with jitcache.deferred_build():  # nothing asked: nothing started
        pass
    assert len(started) == 1


def test_a_deferred_build_is_not_started_when_another_build_runs_by_then(monkeypatch):
    started, running = [], [False]
    monkeypatch.setattr(jitcache, "_started", set())
    monkeypatch.setattr(jitcache, "build_running", lambda: running[0])
    monkeypatch.setattr(jitcache.subprocess, "Popen",
                        lambda args, **kw: started.append(args))
    monkeypatch.setattr(jitcache, "_notice", [lambda line: None])
    with jitcache.deferred_build():
        compiled.build_in_background(["uni_event"])
        running[0] = True  # another run's build took the lock meanwhile
    assert started == []


def test_ddfuse_run_starts_the_build_once_its_results_are_written(monkeypatch, tmp_path):
    from ddfuse.evaluation import cli

    out, started, said = tmp_path / "out", [], []
    monkeypatch.setattr(compiled, "COLD_COMPILE", {})
    monkeypatch.setattr(compiled.kernels(), "load_cached", lambda *names: False)
    monkeypatch.setattr(jitcache, "_started", set())
    monkeypatch.setattr(jitcache, "build_running", lambda: False)
    monkeypatch.setattr(jitcache.subprocess, "Popen", lambda args, **kw: started.append(
        (args, (out / "metrics.json").is_file())))
    monkeypatch.setattr(jitcache, "_notice", [said.append])
    was = jitcache.on_cold_cache()
    assert cli.main(["run", str(ROOT / "data" / "sample_husky.bag"), "-o", str(out),
                     "--no-report", "--estimators", "ekf"]) == 0
    assert jitcache.on_cold_cache() == was
    assert len(started) == 1, started
    args, written = started[0]
    assert written and "uni_event" in args  # after the results, with the filter's kernels
    assert any("when this run has finished" in line for line in said)


@pytest.mark.parametrize("tune", [False, True])
def test_run_defers_the_build_but_run_tune_does_not(monkeypatch, tune):
    import argparse

    from ddfuse.evaluation.cli import run as run_cli

    seen = []
    monkeypatch.setattr(run_cli, "_command", lambda args: seen.append(
        (jitcache._deferred["on"], jitcache.on_cold_cache())) or 0)
    assert run_cli.command(argparse.Namespace(tune=tune)) == 0
    # the tuning's many runs load the kernels as soon as the build has cached them
    assert seen == [(not tune, "reference")]
    assert not jitcache._deferred["on"]


def test_no_second_builder_while_one_holds_the_lock(monkeypatch, tmp_path):
    fcntl = pytest.importorskip("fcntl")
    started, said = [], []
    monkeypatch.setattr(jitcache, "_started", set())
    monkeypatch.setattr(jitcache, "lock_path", lambda: tmp_path / "build.lock")
    monkeypatch.setattr(jitcache.subprocess, "Popen",
                        lambda args, **kw: started.append(args))
    monkeypatch.setattr(jitcache, "_notice", [said.append])
    with open(tmp_path / "build.lock", "a") as held:  # another process's build
        assert not jitcache.build_running()
        fcntl.flock(held, fcntl.LOCK_EX)
        assert jitcache.build_running()  # (flock locks are per open file: this one is held)
        jitcache.build_in_background(["uni_event"])
    assert started == [] and len(said) == 1 and "is compiling" in said[0]


def test_a_cold_update_uses_the_numpy_twins_for_the_whole_process(monkeypatch):
    from ddfuse.ekf_baseline import joseph, joseph_numpy, kalman

    asked = []
    monkeypatch.setattr(kalman, "_cold", [])
    monkeypatch.setattr(joseph, "load_cached", lambda: False)
    monkeypatch.setattr(jitcache, "build_in_background", lambda names: asked.append(names))
    was = jitcache.on_cold_cache()
    try:
        jitcache.on_cold_cache("reference")
        assert kalman.update_functions() == (joseph_numpy.innovation_cov,
                                             joseph_numpy.apply_update)
        monkeypatch.setattr(joseph, "load_cached", lambda: True)  # cached meanwhile
        assert kalman.KalmanCore([0.0], [[1.0]])._apply_update is joseph_numpy.apply_update
        jitcache.on_cold_cache("compile")
        assert kalman.update_functions() == (joseph.innovation_cov, joseph.apply_update)
    finally:
        jitcache.on_cold_cache(was)
    assert asked == [["joseph"]]


def test_a_cold_preintegration_kernel_leaves_the_smoother_on_python(monkeypatch):
    from ddfuse.estimation.smoother.held_twist import compiled_preintegration
    from ddfuse.factors import preintegration_jit
    from ddfuse.factors.preintegration import WheelGyroPreintegration

    asked = []
    monkeypatch.setattr(preintegration_jit, "load_cached", lambda: False)
    monkeypatch.setattr(jitcache, "build_in_background", lambda names: asked.append(names))
    was = jitcache.on_cold_cache()
    try:
        jitcache.on_cold_cache("reference")
        assert compiled_preintegration() is WheelGyroPreintegration
        assert asked == [["preintegration"]]
        jitcache.on_cold_cache("compile")
        assert compiled_preintegration() is preintegration_jit.WheelGyroPreintegrationJit
    finally:
        jitcache.on_cold_cache(was)
    assert asked == [["preintegration"]]


def test_unknown_policy_is_refused():
    with pytest.raises(ValueError, match="on_cold_cache"):
        jitcache.on_cold_cache("later")


def test_the_build_lock_is_per_numba_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "a"))
    a = jitcache.lock_path()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "b"))
    assert jitcache.lock_path() != a  # another cache's build never stands in for this one's
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "a"))
    assert jitcache.lock_path() == a


_READY = """
from ddfuse.factors import preintegration_jit as p
print("importing done", flush=True)
p.ready()
s = p.integrate.stats
print(sum(s.cache_misses.values()), sum(s.cache_hits.values()), flush=True)
"""


def test_processes_on_one_cold_cache_compile_a_kernel_once(monkeypatch, tmp_path):
    """Two processes meeting the same missing kernel: one compiles it, the other waits for it
    and loads it from the cache (a cache miss in one, a hit in the other). Both are released
    together, after both have imported numba, so that without the lock both would compile."""
    import subprocess
    import sys
    import time

    pytest.importorskip("fcntl")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    with jitcache.one_compiler("preintegration"):
        procs = [subprocess.Popen([sys.executable, "-c", _READY], stdout=subprocess.PIPE,
                                  text=True) for _ in range(2)]
        for p in procs:
            assert p.stdout.readline().strip() == "importing done"
        time.sleep(0.3)  # both now at the lock (without it: both compiling)
    counts = sorted(tuple(map(int, p.communicate(timeout=300)[0].split())) for p in procs)
    assert counts == [(0, 1), (1, 0)]  # (misses, hits): one compiled, one loaded


_WAITER = """
import sys, time
from ddfuse.factors import jitcache
jitcache.BUILD_WAIT_S = float(sys.argv[1])
print("started", flush=True)
t0 = time.monotonic()
with jitcache.one_compiler("waiting-test"):
    print(round(time.monotonic() - t0, 2), flush=True)
"""


def _waiter(wait_s: float):
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-c", _WAITER, str(wait_s)], stdout=subprocess.PIPE,
                         text=True)
    assert p.stdout.readline().strip() == "started"
    return p


@pytest.mark.parametrize("holder", ["build", "run"])
def test_a_run_waits_for_another_run_but_not_long_for_the_background_build(
        monkeypatch, tmp_path, holder):
    """The background build compiles at nice 10; a run waiting behind it for a kernel gives up
    after ``BUILD_WAIT_S`` and compiles it itself. Behind another run it waits to the end."""
    import time

    pytest.importorskip("fcntl")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setitem(jitcache._role, "holder", holder)
    with jitcache.one_compiler("waiting-test"):
        p = _waiter(0.2)
        time.sleep(1.2)
        done_while_held = p.poll() is not None
    waited = float(p.communicate(timeout=60)[0])
    if holder == "build":
        assert done_while_held and 0.2 <= waited < 1.2
    else:
        assert not done_while_held and waited >= 1.2


def test_a_kernel_never_cached_is_missed_without_starting_numba(tmp_path, monkeypatch):
    """A kernel whose cache has no index file is reported missing without numba's
    ``load_overload``, which initialises the target context first: that initialisation is
    most of what a first run would spend in numba to find nothing."""
    import importlib.util
    import sys

    src = tmp_path / "cold_kernel_mod.py"
    src.write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n")
    spec = importlib.util.spec_from_file_location("cold_kernel_mod", src)
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "cold_kernel_mod", mod)
    spec.loader.exec_module(mod)
    loads = []
    cache = mod.twice._cache
    real = cache.load_overload
    monkeypatch.setattr(cache, "load_overload", lambda *a: loads.append(a) or real(*a))
    assert not Path(cache._cache_file._index_path).exists()
    assert jitcache.load_cached(mod.twice, "(float64,)") is False
    assert loads == []
    assert mod.twice(1.5) == 3.0  # compiled now, and written to its cache
    assert Path(cache._cache_file._index_path).exists()
