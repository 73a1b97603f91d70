"""factors.jitcache.compiling: a slow compile is announced on the terminal, a cache load is not."""

from __future__ import annotations

import time

import pytest
from ddfuse.factors import jitcache


@pytest.fixture
def lines(monkeypatch):
    got: list[str] = []
    monkeypatch.setattr(jitcache, "_notice", [got.append])
    monkeypatch.setattr(jitcache, "NOTICE_AFTER_S", 0.05)
    return got


def test_slow_compile_says_what_and_how_long(lines):
    with jitcache.compiling("the EKF kernels uni_event"):
        time.sleep(0.3)
    assert len(lines) == 2
    assert lines[0].startswith("ddfuse: compiling the EKF kernels uni_event (numba")
    assert lines[1].startswith("ddfuse: compiled the EKF kernels uni_event in ")


def test_fast_load_says_nothing(lines):
    with jitcache.compiling("the EKF kernels uni_event"):
        pass
    time.sleep(0.1)  # the timer, had it not been cancelled, would have fired by now
    assert lines == []


def test_an_error_inside_still_stops_the_timer(lines):
    with pytest.raises(ValueError), jitcache.compiling("x"):
        raise ValueError("boom")
    time.sleep(0.1)
    assert lines == []
