"""One estimator failing in a live session (or in `ddfuse online`) is stopped there, as
`runner.run` stops it: its error kept, its last estimate kept, the others go on."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.measurements import GyroYawRate
from ddfuse.estimation.smoother import FixedLagSmoother
from ddfuse.evaluation import cli
from ddfuse.evaluation.online import OnlineSession

ROOT = Path(__file__).resolve().parents[1]
BAG, CFG = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"
T0 = 1700000000.0  # the sample bag's first stamp


class Failing(Estimator):
    """Fails in ``where`` ('process', 'estimate' or 'finish') once it has seen a stamp at or
    after ``at``; broken afterwards (estimate raises KeyError, as the smoother's did)."""

    def __init__(self, where: str, at: float = 0.0) -> None:
        super().__init__()
        self.where, self.at = where, at
        self.calls = 0
        self.t: float | None = None
        self.broken = False

    def process(self, m) -> None:
        self.calls += 1
        if self.where == "process" and m.t >= self.at:
            self.broken = True
            raise RuntimeError("indeterminate system\nnear x6")
        self.t = m.t

    def estimate(self) -> Estimate | None:
        if self.broken:
            raise KeyError(152)
        if self.where == "estimate" and self.t is not None and self.t >= self.at:
            raise ValueError("no estimate")
        return None if self.t is None else Estimate(self.t, (1.0, 2.0, 0.0), np.eye(3))

    def finish(self) -> None:
        if self.where == "finish":
            raise RuntimeError("cannot finish")


@pytest.fixture(scope="module")
def setup():
    cfg = replace(load_config(CFG), initial_pose=None)
    return cfg, read_stream(BAG, cfg).measurements


def _ekf_session(cfg, extra: dict | None = None) -> OnlineSession:
    built = OnlineSession.from_config(cfg, ["ekf"])
    return OnlineSession({**(extra or {}), **built.estimators}, reorder_window=0.5)


def test_an_estimator_that_raises_is_stopped_and_the_others_go_on(setup):
    cfg, meas = setup
    at = T0 + 60.0
    boom = Failing("process", at)
    s = _ekf_session(cfg, {"boom": boom})  # boom first: the EKF after it must miss nothing
    ref = _ekf_session(cfg)
    for m in meas:
        s.push(m)  # never raises
        ref.push(m)
    s.finish()
    ref.finish()
    assert s.errors["ekf"] is None and s.errors["boom"] is not None
    t_fail = next(m.t for m in meas if m.t >= at)
    assert s.errors["boom"] == (f"RuntimeError at t={t_fail:.3f}: indeterminate system\n"
                                "near x6")  # the runner's format
    assert s.stopped_t["boom"] == t_fail
    calls = boom.calls
    assert calls == sum(1 for m in meas if m.t <= t_fail)  # never called after it failed
    assert any(n.startswith(f"t={t_fail:.3f}: stopped: RuntimeError at t=")
               for n in boom.log.messages)
    last = s.estimate("boom")  # its last estimate, taken before the failing update
    assert last is not None and t_fail - 2 * OnlineSession.KEEP_PERIOD < last.t < t_fail
    # the EKF saw every message, as without the failing one
    a, b = s.estimate("ekf"), ref.estimate("ekf")
    assert a.t == b.t and np.array_equal(a.pose, b.pose)
    assert boom.calls == calls


@pytest.mark.parametrize("where", ["estimate", "finish"])
def test_a_failure_in_estimate_or_finish_stops_only_that_estimator(setup, where):
    cfg, meas = setup
    s = _ekf_session(cfg, {"boom": Failing(where, T0 + 30.0)})
    for m in meas:
        if m.t - T0 > 40.0:
            break
        s.push(m)
        s.estimate("boom")
    s.finish()
    err = s.errors["boom"]
    if where == "estimate":
        assert err.startswith("ValueError at t=") and err.endswith(": no estimate")
        assert s.estimate("boom").t < T0 + 30.0 + 0.1
    else:
        assert err == "RuntimeError in finish: cannot finish" and s.stopped_t["boom"] is None
    assert s.errors["ekf"] is None and s.estimate("ekf") is not None


@pytest.mark.slow
def test_a_nan_gyro_sample_does_not_stop_the_session(setup):
    """The reviewer's case: a hand-built GyroYawRate(yaw_rate=nan) pushed at t=60. Before, the
    smoother raised RuntimeError, every later push raised KeyError and the EKF after it in the
    dict missed those messages. Whatever the smoother makes of the NaN, the EKF goes on."""
    cfg, meas = setup
    i = next(i for i, m in enumerate(meas) if m.t - T0 > 60.0)
    bad = GyroYawRate(t=meas[i].t, yaw_rate=float("nan"), var=1e-4, sensor="/imu/data")
    s = OnlineSession.from_config(cfg, ["smoother", "ekf"])
    ref = OnlineSession.from_config(cfg, ["ekf"])
    for m in [*meas[:i], bad, *meas[i:]]:
        s.push(m)
    for m in meas:
        ref.push(m)
    s.finish()
    ref.finish()
    a, b = s.estimate("ekf"), ref.estimate("ekf")
    assert s.errors["ekf"] is None and a.t == b.t and np.allclose(a.pose, b.pose, atol=1e-9)
    sm = s.estimate("smoother")
    assert sm is not None and np.all(np.isfinite(sm.pose))
    if s.errors["smoother"] is not None:
        assert s.errors["smoother"].startswith("RuntimeError at t=") and sm.t <= bad.t


# --- ddfuse online -----------------------------------------------------------------------------

def test_cli_online_reports_a_failed_estimator_in_one_line_and_carries_on(setup, monkeypatch,
                                                                          capsys):
    """Before: a traceback and exit 1. Now: one line (which, when, why), the other estimators
    to the end, exit 0 as `run` (which shows ERROR in the estimator's row)."""
    meas = setup[1]
    at = f"{next(m.t for m in meas if m.t - T0 >= 10.0) - meas[0].t:.2f}"  # s since the first
    process = FixedLagSmoother.process

    def failing(self, m):
        if m.t - T0 >= 10.0:
            raise RuntimeError("smoother: ill-conditioned\n  near x6")
        process(self, m)

    monkeypatch.setattr(FixedLagSmoother, "process", failing)
    code = cli.main(["online", str(BAG), "--estimators", "smoother,ekf", "--every", "50"])
    out, err = capsys.readouterr()
    assert code == 0 and err == ""
    lines = out.splitlines()
    failed = [ln for ln in lines if "failed" in ln]
    assert failed == [f"smoother failed at t={at} s and is stopped (its last estimate is kept, "
                      "the others go on): RuntimeError: smoother: ill-conditioned near x6"]
    assert lines.index(failed[0]) < [i for i, ln in enumerate(lines)
                                     if ln.startswith("t=   50.")][0]
    assert [ln for ln in lines if ln.startswith("t=   50.")][0].startswith(
        "t=   50.00 s  smoother stopped  ekf (")
    final = [ln for ln in lines if ln.endswith("(final)")]
    assert len(final) == 1 and f"stopped at t={at} s" in final[0] and "ekf (" in final[0]
    assert [ln for ln in lines if ln.startswith("  smoother ")][0].endswith(
        f"ERROR: stopped at t={at} s")


def test_cli_online_refuses_the_lagged_smoother_output(capsys):
    """It printed a column labelled 'smoother' holding the filtered output."""
    code = cli.main(["online", str(BAG), "--estimators", "ekf,smoother_lagged"])
    out, err = capsys.readouterr()
    err = err.strip()
    assert code == 2 and out == "" and "\n" not in err
    assert err.startswith("ddfuse: error: --estimators smoother_lagged: not available online: ")
    assert "'ddfuse run' gives it" in err


def test_cli_online_refuses_the_batch():
    """It ran and printed nothing for the batch until the input ended."""
    code = cli.main(["online", str(BAG), "--estimators", "ekf,batch"])
    assert code == 2
    # the library names its parameter, not the CLI's flag
    with pytest.raises(ValueError, match=r"^estimators: batch: not available online: the batch "
                       r"optimises the whole run at once"):
        OnlineSession.from_config(load_config(CFG), ["ekf", "batch"])


def test_from_config_reads_a_string_of_names_as_the_cli_does():
    """``from_config(cfg, "ekf")`` said "--estimators: unknown estimator 'e'"."""
    cfg = replace(load_config(CFG), initial_pose=None)
    assert list(OnlineSession.from_config(cfg, "ekf").estimators) == ["ekf"]
    assert list(OnlineSession.from_config(cfg, "smoother,ekf").estimators) == ["smoother", "ekf"]
    with pytest.raises(ValueError, match=r"^estimators: batch: not available online"):
        OnlineSession.from_config(cfg, "ekf,batch")
    with pytest.raises(TypeError, match=r"^estimators: expected a list of estimator names"):
        OnlineSession.from_config(cfg, 3)


def test_a_stopped_estimator_is_not_answered_with_an_old_pose_for_now(setup):
    """``estimate(name, at=now)`` carries a running estimator's pose to ``now``; a stopped one
    cannot be carried, and past the carry horizon its last pose is refused, naming why,
    instead of being handed to a robot as the pose now."""
    cfg, meas = setup
    s = OnlineSession.from_config(cfg, ["ekf"])
    s.estimators = {"boom": Failing("process", T0 + 20.0), **s.estimators}
    s.errors["boom"], s.update_s["boom"], s.compact_s["boom"] = None, s.update_s["ekf"][:0], []
    s.stopped_t["boom"] = None
    for m in meas:
        if m.t - T0 > 40.0:
            break
        s.push(m)
    now = s.newest
    assert s.errors["boom"] is not None and s.errors["ekf"] is None
    assert s.estimate("ekf", at=now).t == pytest.approx(now)  # carried
    assert s.estimate("boom").t < T0 + 20.0  # its last one, asked for as such
    near = s.estimate("boom").t + 0.5 * s.carry_horizon
    assert s.estimate("boom", at=near).t < T0 + 20.0  # within the horizon: as it is
    with pytest.raises(ValueError, match=r"estimate\('boom', at=.*s older, more than "
                                         r"carry_horizon .* stopped \(RuntimeError at t="):
        s.estimate("boom", at=now)


def test_latency_without_updates_is_not_a_number_and_the_cli_prints_a_dash(setup, capsys):
    cfg, _ = setup
    s = OnlineSession.from_config(cfg, ["ekf"])
    q = s.latency_ms()["ekf"]
    assert q["updates"] == 0 and all(np.isnan(q[k]) for k in ("p50", "p99", "max"))


def test_cli_online_prints_on_its_grid_and_a_heading_sigma_past_180_as_such(capsys,
                                                                             monkeypatch):
    """--every S prints at the first message at or after each t0 + k S (not S after the
    previous print, which loses a message interval each time); a heading sigma over 180 deg
    is printed as >180."""
    from ddfuse.evaluation import online

    pose_cov = np.diag([1.0, 1.0, 4.0 ** 2])
    real = online.OnlineSession.estimate

    def wide(self, name, at=None):
        e = real(self, name, at)
        return e if e is None or e.t - T0 < 50.0 else replace(e, pose_cov=pose_cov)

    monkeypatch.setattr(online.OnlineSession, "estimate", wide)
    assert cli.main(["online", str(BAG), "--estimators", "ekf", "--every", "0.25"]) == 0
    out = capsys.readouterr().out
    t = np.array([float(line.split()[0][2:] or line.split()[1]) for line in out.splitlines()
                  if line.startswith("t=") and "(final)" not in line])
    assert len(t) > 400
    gaps = np.diff(t)
    # the odometry is 10 Hz: each print within 0.1 s after its grid time, never drifting
    assert np.all(t - 0.25 * np.floor(t / 0.25 + 1e-9) < 0.1 + 1e-6)
    assert gaps.mean() == pytest.approx(0.25, abs=0.005)
    assert ">180 deg)" in out and ", 229.2 deg)" not in out


def test_replay_runs_without_full_garbage_collections_and_restores_the_collector(setup):
    """A full collection walks every long-lived object inside whichever update it interrupts
    (74-77 ms on rl_husky_gps.bag, four in a replay, each inside an update or a log
    compaction): replay, as runner.run, freezes what exists, turns automatic collection off
    and collects only young generations between messages, and leaves the collector as it
    found it."""
    import gc

    from ddfuse.evaluation.online import replay

    cfg, _ = setup
    seen, frozen = [], []

    def look(m):
        seen.append(gc.isenabled())
        if not frozen:  # gc.get_freeze_count walks the frozen objects: once
            frozen.append(gc.get_freeze_count())

    s = replay(BAG, cfg, names=["ekf"], print_every=1000.0, observers=(look,))
    assert s.latency_ms()["ekf"]["updates"] > 1000 and len(seen) > 1000
    assert not any(seen) and frozen[0] > 1000
    assert gc.isenabled() and gc.get_freeze_count() == 0
