"""The gate lock-out rule and the recovery's inflation factor (ddfuse.estimation.lockout)."""

from __future__ import annotations

import numpy as np
import pytest
from ddfuse.estimation.lockout import AGREED_RUN, MAX_INFLATION, Lockout, inflation


@pytest.mark.parametrize("seed", range(5))
def test_inflation_makes_the_innovation_ordinary(seed):
    """After widening the state's share of S by alpha, the innovation's NIS is its dof m, and
    no smaller alpha does it (NIS falls monotonically in alpha)."""
    rng = np.random.default_rng(seed)
    m = 2
    L = rng.normal(size=(m, m))
    A = L @ L.T * 0.01 + np.eye(m) * 1e-3
    R = np.diag(rng.uniform(0.5, 2.0, m))
    y = rng.normal(size=m) * 20.0
    alpha, rest = inflation(y, A, R)
    assert rest is None and alpha > 1.0
    assert y @ np.linalg.solve(alpha * A + R, y) == pytest.approx(m, rel=1e-9)
    assert y @ np.linalg.solve(0.99 * alpha * A + R, y) > m


def test_inflation_when_no_scale_is_enough():
    """The state has no variance in a measured direction (A singular there): no alpha makes the
    innovation ordinary, so the caller is told to add the rank-one term from y."""
    A = np.diag([1.0, 0.0])
    R = np.eye(2) * 1e-4
    y = np.array([0.0, 5.0])
    alpha, rest = inflation(y, A, R)
    assert alpha == MAX_INFLATION and rest is not None and np.allclose(rest, y)


def test_ordinary_innovation_needs_no_widening():
    assert inflation(np.array([0.1]), np.eye(1), np.eye(1)) == (1.0, None)


def test_lockout_needs_both_count_and_time():
    """A burst of rejections within less than the lock-out time is not a lock-out, nor are
    fewer than the count however long they span; an acceptance ends the streak."""
    lo = Lockout(count=5, time=1.0, holdoff=10.0)
    assert not any(lo.rejected("gps", 0.01 * i) for i in range(20))  # 20 in 0.19 s
    lo = Lockout(count=5, time=1.0, holdoff=10.0)
    assert [lo.rejected("gps", 2.0 * i) for i in range(5)] == [False] * 4 + [True]
    lo = Lockout(count=5, time=1.0, holdoff=10.0)
    for i in range(4):
        lo.rejected("gps", float(i))
    lo.accepted("gps")
    assert not lo.rejected("gps", 4.0) and lo.streak("gps")[0] == 1


def test_recovery_holdoff_doubles_until_one_takes():
    """A lock-out that recurs before the sensor was accepted ``count`` times waits 10, then
    20 s; once a recovery took (``count`` acceptances), the next lock-out is recovered at once.
    A corroboration verdict holds off the same way."""
    lo = Lockout(count=3, time=0.5, holdoff=10.0)

    def lock(t0):
        return [lo.rejected("gps", t0 + i) for i in range(3)][-1]

    assert lock(0.0)
    assert lo.recovered("gps", 2.0) == 10.0
    assert not lock(3.0)  # 5 s: inside the hold-off
    assert lock(12.0)  # 14 s: past it
    assert lo.recovered("gps", 14.0) == 20.0
    assert not lock(15.0) and not lock(30.0)  # before 34 s
    for _ in range(3):
        lo.accepted("gps")
    assert lock(40.0)  # the recovery took: no hold-off
    assert lo.corroborated("gps", 42.0) == 10.0
    assert not lock(43.0)


def test_agreed_needs_a_run_of_acceptances_and_keeps_it():
    """A model has agreed with the estimate once it was accepted AGREED_RUN times in a row (a
    rejection restarts the count); from then on a lock-out is a lost estimate's, never the
    start's again, whatever follows."""
    lo = Lockout(count=5, time=1.0, holdoff=10.0)
    for _ in range(AGREED_RUN - 1):
        lo.accepted("gps")
    lo.rejected("gps", 0.0)
    for _ in range(AGREED_RUN - 1):
        lo.accepted("gps")
    assert not lo.agreed("gps")
    lo.accepted("gps")
    assert lo.agreed("gps") and not lo.agreed("compass")
    for i in range(10):
        lo.rejected("gps", float(i))
    assert lo.agreed("gps")
