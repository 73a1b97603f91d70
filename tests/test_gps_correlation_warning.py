"""The GPS correlation_time rule (``estimation.gps_scatter``) as the run applies it: a warning
when the config's correlation_time disagrees with what the run's fixes' scatter gives."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import load_config
from ddfuse.estimation.gps_scatter import AGREEMENT, fix_scatter
from ddfuse.estimation.runner import GpsTrack
from ddfuse.evaluation.pipeline import gps_correlation_warnings

N, DT, SIGMA = 1000, 0.4, 1.0


def _cfg(tmp_path: Path, tau: float | None, receivers: int = 1):
    p = tmp_path / "c.yaml"
    extra = "" if tau is None else f"\n      correlation_time: {tau}"
    gps = "".join(f"\n    - topic: /fix{k or ''}" + extra for k in range(receivers))
    p.write_text("sensors:\n  odometry:\n    - topic: /odom\n  gps:" + gps + "\n")
    return load_config(p)


def _errors(tau: float | None, seed: int = 7) -> np.ndarray:
    """(N, 2) per-axis errors of std SIGMA: white (tau None) or first-order Gauss-Markov."""
    rng = np.random.default_rng(seed)
    w = SIGMA * rng.standard_normal((N, 2))
    if tau is None:
        return w
    a = math.exp(-DT / tau)
    e = np.zeros((N, 2))
    e[0] = w[0]
    for i in range(1, N):
        e[i] = a * e[i - 1] + math.sqrt(1 - a * a) * w[i]
    return e


def _track(err: np.ndarray, withheld: np.ndarray | None = None) -> GpsTrack:
    """Fixes of a robot driving east at 1 m/s with errors ``err``, stated sigma SIGMA."""
    t = 1000.0 + DT * np.arange(N)
    xy = np.column_stack([DT * np.arange(N), np.zeros(N)]) + err
    cov = np.tile(np.eye(2) * SIGMA**2, (N, 1, 1))
    return GpsTrack(t, xy, cov, np.zeros(N, bool) if withheld is None else withheld)


def test_correlated_fixes_fused_as_white_warn_with_the_value_inspect_suggests(tmp_path):
    track = _track(_errors(30.0))
    sc = fix_scatter(track.t, track.xy, np.full(N, SIGMA**2))
    assert sc.recommended == pytest.approx(30, rel=0.2)
    (w,) = gps_correlation_warnings(_cfg(tmp_path, None), track)
    assert w.startswith(f"/fix: the neighbouring fixes predict a fix to {sc.rms:.2f} m per axis, "
                        f"against 1.22 m for white errors of the stated sigma 1.00 m")
    assert "the fixes are fused as independent" in w
    assert w.endswith(f"set correlation_time: {sc.recommended} under the GPS sensor "
                      "(`ddfuse inspect` suggests the same)")
    # the data's number, whatever the hold-out withholds
    held = np.zeros(N, bool)
    held[::5] = True
    assert gps_correlation_warnings(_cfg(tmp_path, None), _track(_errors(30.0), held)) == [w]


def test_a_value_more_than_the_agreement_off_is_corrected(tmp_path):
    track = _track(_errors(30.0))
    rec = fix_scatter(track.t, track.xy, np.full(N, SIGMA**2)).recommended
    (w,) = gps_correlation_warnings(_cfg(tmp_path, 5), track)
    assert f"but correlation_time is 5 s; set correlation_time: {rec} under" in w
    assert gps_correlation_warnings(_cfg(tmp_path, rec * AGREEMENT * 0.99), track) == []
    assert len(gps_correlation_warnings(_cfg(tmp_path, rec * AGREEMENT * 1.01), track)) == 1
    # white errors with a correlation_time: every fix discounted for nothing
    (w,) = gps_correlation_warnings(_cfg(tmp_path, 30), _track(_errors(None)))
    assert "not correlated over several fixes, but correlation_time is 30 s" in w
    assert w.endswith("set correlation_time: 0 under the GPS sensor")


@pytest.mark.parametrize("tau_true, tau_cfg", [
    (None, None),  # white fixes (the simulated husky, gps-outage, the sample bag)
    (30.0, 30.0),  # modelled
    (30.0, 20.0),  # within the agreement
])
def test_no_warning(tmp_path, tau_true, tau_cfg):
    assert gps_correlation_warnings(_cfg(tmp_path, tau_cfg), _track(_errors(tau_true))) == []


def test_no_advice_without_fixes_or_with_two_receivers(tmp_path):
    track = _track(_errors(30.0))
    assert gps_correlation_warnings(_cfg(tmp_path, None, receivers=2), track) == []
    empty = GpsTrack(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, bool))
    assert gps_correlation_warnings(_cfg(tmp_path, None), empty) == []


def test_noise_free_fixes_give_no_time_and_no_advice(tmp_path):
    """Fixes that miss their neighbours by nothing are correlated beyond any time the scatter
    can give: the config's value is left alone."""
    track = _track(np.zeros((N, 2)))
    sc = fix_scatter(track.t, track.xy, np.full(N, SIGMA**2))
    assert sc.correlated and sc.correlation_time is None and sc.recommended == 0
    assert gps_correlation_warnings(_cfg(tmp_path, 30), track) == []
    assert gps_correlation_warnings(_cfg(tmp_path, None), track) == []


def test_no_advice_where_the_watch_found_the_gps_bursty(tmp_path):
    """Where the GPS disagreed with the odometry in bursts (``GpsWatch.bursty``: 3 episodes or
    more) the neighbour scatter is the bursts', measured against a stated sigma they belie: the
    same fixes that get the advice otherwise get none (the watch's own line names the model)."""
    from ddfuse.estimation.gps_watch import MANY_EPISODES, Episode, GpsWatch

    cfg = _cfg(tmp_path, 30)
    track = _track(_errors(None))
    watch = GpsWatch(cfg)
    watch.episodes = [Episode("/fix", 1000.0 + 50 * k, 1002.0 + 50 * k, 5, 30.0, 10.0)
                      for k in range(MANY_EPISODES - 1)]
    assert len(gps_correlation_warnings(cfg, track, watch)) == 1  # two bursts: not bursty
    watch.episodes.append(Episode("/fix", 1300.0, 1302.0, 5, 30.0, 10.0))
    assert watch.bursty("/fix") and gps_correlation_warnings(cfg, track, watch) == []
