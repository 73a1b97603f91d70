"""``ddfuse run`` on a cold kernel cache feeds the EKFs' Python reference path in a forked side
process (``ddfuse.evaluation.side_run``): the same tracks, scores and logs as one process; a side
process that fails loses nothing (its estimators are fed in the main process after); Ctrl-C
while waiting for it still gives the results of what was fed."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation import pipeline, side_run
from ddfuse.factors import jitcache

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "data" / "sample_husky.bag"
NAMES = ["ekf", "ekf_igvc", "smoother", "smoother_lagged", "dr"]

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")


@pytest.fixture
def reference(cold, monkeypatch):
    """``ddfuse run``'s cold-cache policy on a cache with no EKF kernel, and two CPUs."""
    jitcache.on_cold_cache("reference")
    monkeypatch.setattr(side_run, "cpus", lambda: 2)


def _run(tmp_path, name, side, notes=None):
    out = tmp_path / name
    m = pipeline.run_bag(BAG, load_config(ROOT / "data" / "sample_husky.yaml"), out,
                         names=NAMES, holdout="every:4", side_process=side,
                         notice=None if notes is None else notes.append)
    return m, out


def _endless(process, quick: int = 2000, pause: float = 0.05):
    """``process`` slowed so that the side process cannot end before the Ctrl-C the test sends
    (whichever process the balance leaves longer): its first ``quick`` messages at 1 ms each
    (some track to return), then ``pause`` s each, minutes for the rest of the bag."""
    import time

    calls = [0]

    def slow_process(self, m):
        calls[0] += 1
        time.sleep(1e-3 if calls[0] <= quick else pause)
        process(self, m)

    return slow_process


def _same_outputs(a: Path, b: Path, ma, mb) -> None:
    for track in NAMES:
        assert (a / f"{track}.tum").read_bytes() == (b / f"{track}.tum").read_bytes(), track
    ja, jb = ma.to_json(), mb.to_json()
    for k in ("wall_s", "decode_s"):
        ja.pop(k), jb.pop(k)
    for e in (*ja["estimators"].values(), *jb["estimators"].values()):
        for k in ("runtime_s", "rtf", "update_ms"):
            e.pop(k, None)
    assert json.dumps(ja, sort_keys=True) == json.dumps(jb, sort_keys=True)


def test_the_reference_filters_are_fed_beside_and_give_one_process_results(reference,
                                                                           tmp_path):
    m1, one = _run(tmp_path, "one", False)
    m2, two = _run(tmp_path, "two", True)
    assert m1.wall_s.side_process == [] and m1.wall_s.side_wait is None
    # the two reference filters would make the side process the longer one: ekf_igvc alone
    assert m2.wall_s.side_process == ["ekf_igvc"] and m2.wall_s.side_wait >= 0.0
    _same_outputs(one, two, m1, m2)
    # the tracks keep the estimators' order (the side ones were gathered last)
    assert list(m2.estimators) == list(m1.estimators)
    # the total is the main process's: the side estimators' times overlap its loop
    w = m2.wall_s
    own = sum(v for k, v in w.estimators.items() if k not in w.side_process)
    parts = w.startup + w.decode + w.build + own + w.runner + w.side_wait + w.metrics + w.write
    assert w.total == pytest.approx(parts, abs=1e-3)
    assert w.runner > 0.0
    # the side filters' innovation logs reached the report's data
    with np.load(one / "run.npz") as z1, np.load(two / "run.npz") as z2:
        assert z1.files == z2.files and "innov/ekf_igvc/nis" in z2.files
        for k in z1.files:
            if k.startswith("innov/"):
                assert np.array_equal(z1[k], z2[k], equal_nan=z1[k].dtype.kind == "f"), k


def test_compiled_filters_stay_in_the_main_process(tmp_path):
    m, _ = _run(tmp_path, "warm", True)
    assert m.wall_s.side_process == []


def test_a_failed_side_process_loses_nothing(reference, tmp_path, monkeypatch):
    m1, one = _run(tmp_path, "one", False)
    def dies(w, open_stream, ests, holdout):  # the child, before it feeds anything
        os._exit(3)

    monkeypatch.setattr(side_run, "_child", dies)
    notes: list[str] = []
    m2, two = _run(tmp_path, "two", True, notes)
    assert any("side process feeding ekf_igvc failed (the side process ended (exit "
               "status 3) with no results): they are fed here now" in n for n in notes), notes
    assert m2.wall_s.side_process == []
    _same_outputs(one, two, m1, m2)


def test_ctrl_c_while_waiting_is_passed_to_the_side_process(reference, tmp_path, monkeypatch,
                                                            ctrl_c_raises):
    """The main loop ends first; Ctrl-C while it waits reaches the child, which returns what it
    had fed; the run says it was interrupted and writes the results whole."""
    import threading
    import time

    from ddfuse.ekf_baseline.igvc import IgvcEkf
    from ddfuse.estimation.errors import RunInterrupted

    real_process, real_join = IgvcEkf.process, side_run.SideRun.join

    def join_then_ctrl_c(self):  # Ctrl-C to this process alone, while it waits
        threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()
        return real_join(self)

    monkeypatch.setattr(IgvcEkf, "process", _endless(real_process))
    monkeypatch.setattr(side_run.SideRun, "join", join_then_ctrl_c)
    t0 = time.perf_counter()
    with pytest.raises(RunInterrupted, match=r"^interrupted \(Ctrl-C\) after \d+ measurements"):
        _run(tmp_path, "int", True)
    assert time.perf_counter() - t0 < 20.0
    doc = json.loads((tmp_path / "int" / "metrics.json").read_text())
    assert doc["interrupted"].startswith("interrupted (Ctrl-C) after")
    assert {"ekf", "ekf_igvc", "smoother", "dr"} <= set(doc["estimators"])
    full = doc["messages"]
    ekf_rows = len((tmp_path / "int" / "ekf_igvc.tum").read_text().splitlines())
    dr_rows = len((tmp_path / "int" / "dr.tum").read_text().splitlines())
    assert 0 < ekf_rows < dr_rows, (ekf_rows, dr_rows, full)  # the side stopped part-way


def test_a_signal_another_thread_takes_still_reaches_the_side_process(reference, tmp_path,
                                                                      monkeypatch,
                                                                      ctrl_c_raises):
    """SIGTERM or Ctrl-C sent to the main process alone may be taken by another of its threads
    (a progress bar's): the main thread's handler runs only between Python steps, so a wait
    blocked in a read would sleep through it until the side process had fed the whole bag.
    The main thread here blocks SIGINT, so the kernel hands it to the timer's thread."""
    import threading
    import time

    from ddfuse.ekf_baseline.igvc import IgvcEkf
    from ddfuse.estimation.errors import RunInterrupted

    real_process, real_join = IgvcEkf.process, side_run.SideRun.join

    def join_then_ctrl_c_elsewhere(self):
        # the timer's thread is started before the block: a thread inherits its creator's mask
        threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return real_join(self)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    monkeypatch.setattr(IgvcEkf, "process", _endless(real_process))
    monkeypatch.setattr(side_run.SideRun, "join", join_then_ctrl_c_elsewhere)
    t0 = time.perf_counter()
    with pytest.raises(RunInterrupted, match=r"^interrupted \(Ctrl-C\) after \d+ measurements"):
        _run(tmp_path, "int", True)
    assert time.perf_counter() - t0 < 6.0  # the whole bag at 1 ms per ekf message: ~7 s


def test_in_order_keeps_the_estimators_order_and_lagged_after_their_own():
    runs_a = {"smoother": 1, "smoother_lagged": 2, "batch": 3}
    runs_b = {"ekf_igvc": 4, "ekf": 5}
    got = side_run.in_order(["ekf", "ekf_igvc", "smoother", "batch"], runs_a, runs_b)
    assert list(got) == ["ekf", "ekf_igvc", "smoother", "smoother_lagged", "batch"]


def test_side_names_needs_a_second_cpu_and_keeps_one_in_the_main_process(monkeypatch):
    class E:
        def __init__(self, ref):
            self.reference = ref

    ests = {"ekf": E(True), "smoother": E(False)}
    monkeypatch.setattr(side_run, "cpus", lambda: 2)
    assert side_run.side_names(ests) == ["ekf"]
    assert side_run.side_names({"ekf": E(True)}) == []  # nothing would stay in the main process
    # every one on the reference path: the first stays in the main process
    assert side_run.side_names({"ekf": E(True), "ekf_igvc": E(True)}) == ["ekf_igvc"]
    monkeypatch.setattr(side_run, "cpus", lambda: 1)
    assert side_run.side_names(ests) == []


def test_a_truncated_bag_gives_the_same_part_with_a_side_process(reference, tmp_path):
    """Both processes read the bag to where it breaks off: the same tracks of the part that
    could be read, and the same error, as one process."""
    import shutil

    from ddfuse.estimation.errors import BagError

    data = BAG.read_bytes()
    bag = tmp_path / "cut.bag"
    bag.write_bytes(data[:len(data) * 6 // 10])
    shutil.copy(ROOT / "data" / "sample_husky.yaml", tmp_path / "cut.yaml")
    cfg = load_config(tmp_path / "cut.yaml")
    errors = []
    for name, side in (("one", False), ("two", True)):
        with pytest.raises(BagError) as e:
            pipeline.run_bag(bag, cfg, tmp_path / name, names=NAMES, side_process=side)
        assert e.value.results_written
        errors.append(str(e.value).replace(str(tmp_path / name), "OUT"))
    assert errors[0] == errors[1] and "truncated" in errors[0]
    for track in NAMES:
        one = (tmp_path / "one" / f"{track}.tum").read_bytes()
        assert one and one == (tmp_path / "two" / f"{track}.tum").read_bytes(), track
    doc = json.loads((tmp_path / "two" / "metrics.json").read_text())
    assert doc["wall_s"]["side_process"] == ["ekf_igvc"]
