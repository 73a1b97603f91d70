"""The variance inflation for time-correlated GPS fixes (ddfuse.estimation.gps_correlation)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.config import ConfigError, load_config
from ddfuse.estimation.gps_correlation import inflation


def test_inflated_fixes_average_to_the_variance_of_correlated_ones():
    """N fixes of a Gauss-Markov error (sigma 1, tau 30 s, 0.4 s apart), averaged: the variance
    of the mean is what N independent fixes of variance inflation(dt, tau) would give."""
    rng = np.random.default_rng(4)
    tau, dt, n, runs = 30.0, 0.4, 3000, 4000
    rho = math.exp(-dt / tau)
    e = rng.standard_normal(runs)
    total = e.copy()
    for _ in range(n - 1):
        e = rho * e + math.sqrt(1.0 - rho * rho) * rng.standard_normal(runs)
        total += e
    measured = np.var(total / n)
    fused = inflation(dt, tau) / n  # what an estimator reports for N inflated fixes
    # 4000 runs: the sample variance's relative sd is sqrt(2/4000) = 2.2 %; the finite-N
    # (edge) correction is 2 tau / (N dt) ~ 5 % for N dt = 1200 s
    assert measured == pytest.approx(fused, rel=0.12)
    assert inflation(dt, tau) == pytest.approx(150.0, rel=1e-4)  # white would be off by 150x


def test_edges():
    assert inflation(0.4, 0.0) == 1.0  # white
    assert inflation(math.inf, 30.0) == 1.0 == inflation(math.nan, 30.0)  # no previous fix
    assert inflation(60.0, 30.0) == pytest.approx((1 + math.exp(-2)) / (1 - math.exp(-2)))
    assert inflation(1e6, 30.0) == pytest.approx(1.0)  # long apart: independent
    assert math.isfinite(inflation(0.0, 30.0)) and inflation(0.0, 30.0) >= inflation(0.4, 30.0)
    f = [inflation(dt, 30.0) for dt in (0.1, 0.4, 1.0, 10.0, 100.0)]
    assert all(a > b >= 1.0 for a, b in zip(f[:-1], f[1:], strict=True))


@pytest.mark.parametrize("value, why", [(-1.0, "must be >= 0"), ("30 s", "must be a number"),
                                        (float("inf"), "must be finite")])
def test_config_key(tmp_path: Path, value, why):
    p = tmp_path / "c.yaml"
    p.write_text("sensors:\n  gps:\n    - topic: /fix\n      correlation_time: 20.0\n")
    assert load_config(p).sensors[0].correlation_time == 20.0
    p.write_text(f"sensors:\n  gps:\n    - topic: /fix\n      correlation_time: {value!r}\n"
                 .replace("inf", ".inf"))
    with pytest.raises(ConfigError, match=rf"sensors\.gps\[0\]\.correlation_time.*{why}"):
        load_config(p)
    p.write_text("sensors:\n  odometry:\n    - topic: /odom\n      correlation_time: 20.0\n")
    with pytest.raises(ConfigError, match=r"sensors\.odometry\[0\].*correlation_time"):
        load_config(p)
