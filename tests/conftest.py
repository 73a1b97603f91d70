"""Shared test fixtures: the real bags in ../shared/data, skipped with a reason when absent."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("DDFUSE_SHARED_DATA", ROOT.parent / "shared" / "data"))


def shared_bag(name: str) -> Path:
    """Path of a real bag in ../shared/data (or $DDFUSE_SHARED_DATA); skip the test if absent."""
    p = SHARED_DATA / name
    if not p.is_file():
        pytest.skip(f"real bag {name} not found in {SHARED_DATA} (set DDFUSE_SHARED_DATA)")
    return p


@pytest.fixture
def husky_bag() -> Path:
    return shared_bag("rl_husky_gps.bag")


@pytest.fixture
def jackal_bag() -> Path:
    return shared_bag("rl_jackal.bag")


@pytest.fixture
def mrclam_bag() -> Path:
    return shared_bag("mrclam1_robot1.bag")


@pytest.fixture(scope="session")
def sample_husky():
    """(config, decoded stream) of the project's simulated sample data/sample_husky.bag."""
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config

    bag, yaml = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"
    if not bag.is_file():
        pytest.skip("data/sample_husky.bag not present")
    cfg = load_config(yaml)
    return cfg, read_stream(bag, cfg)


@pytest.fixture(scope="session")
def sample_batch(sample_husky):
    """The batch smoother run over data/sample_husky.bag from the true start and finished
    (its whole-run graph and solution); shared read-only by the tests."""
    from ddfuse.estimation.smoother import BatchSmoother

    cfg, stream = sample_husky
    g = stream.ground_truth[0]
    batch = BatchSmoother(cfg, initial_pose=(g.x, g.y, g.yaw))
    for m in stream.measurements:
        batch.process(m)
    batch.finish()
    return batch


@pytest.fixture(scope="session")
def seed002_run(tmp_path_factory) -> Path:
    """Output folder of ``ddfuse run`` on the landmark sample data/sample_seed002.bag (wheel
    speeds with the robot's geometry), ekf_landmark alone; shared read-only by the tests."""
    from ddfuse.evaluation import cli

    out = tmp_path_factory.mktemp("seed002") / "out"
    bag = ROOT / "data" / "sample_seed002.bag"
    assert cli.main(["run", str(bag), "-o", str(out), "--estimators", "ekf_landmark"]) == 0
    return out


@pytest.fixture
def no_plausibility_screen(monkeypatch):
    """The plausibility screen off, for tests whose synthetic messages encode their index in a
    twist or a fix (a yaw rate of i rad/s, a GPS track at 80 m/s): beyond any robot, they would
    be rejected (``ddfuse.estimation.robot_limits``, tested in test_robot_limits.py)."""
    from ddfuse.estimation.robot_limits import RobotLimits

    monkeypatch.setattr(RobotLimits, "admit", lambda self, m: True)


@pytest.fixture
def cold(monkeypatch):
    """A process whose EKF kernels are in no cache: nothing warmed up, every lookup a miss; the
    background builds asked for recorded instead of started (yields that record)."""
    from ddfuse.ekf_baseline import compiled
    from ddfuse.factors import jitcache

    asked: list[list[str]] = []
    kj = compiled.kernels()
    monkeypatch.setattr(compiled, "COLD_COMPILE", {})
    monkeypatch.setattr(kj, "load_cached", lambda *names: False)
    monkeypatch.setattr(compiled, "build_in_background", lambda names: asked.append(names))
    # the update's entry points and the preintegration kernel, if this cache lacks them
    monkeypatch.setattr(jitcache, "build_in_background", lambda names: None)
    was = jitcache.on_cold_cache()
    yield asked
    jitcache.on_cold_cache(was)


@pytest.fixture
def ctrl_c_raises():
    """Ctrl-C as in a terminal: a process started in the background (``cmd &``, nohup, some CI
    runners) or a pytest-xdist worker has SIGINT ignored, and Python then never raises
    KeyboardInterrupt."""
    import signal

    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def pytest_sessionstart(session):
    """Start one background build of every numba kernel before the tests (in the controller
    only: pytest-xdist's workers have ``workerinput``). On a cold cache (a clean clone, as in
    CI) the workers' tests would otherwise each compile the kernels they meet (about a minute
    of CPU per process); with the build running, a test that needs a kernel waits for it or
    compiles it itself, never both (``jitcache.one_compiler``), and the rest of the suite runs
    meanwhile. On a warm cache the build only loads the kernels (~2 s of CPU)."""
    if hasattr(session.config, "workerinput"):
        return
    from ddfuse.factors import jitcache

    if not jitcache.build_running():
        with contextlib.suppress(OSError):  # the tests then compile what they need
            jitcache.start_build(["uni_stacked", "lm_predict", "lm_sighting"])
