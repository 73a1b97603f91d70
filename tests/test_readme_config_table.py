"""The README's config table names every key the config accepts, and no other: the accepted
keys are read from the validator itself (estimation/config.py), by giving each mapping an
unknown key and reading the "allowed: ..." its error lists, down to the leaves."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import pytest
from ddfuse.estimation.config import SENSOR_KINDS, ConfigError, parse_config

ROOT = Path(__file__).resolve().parents[1]
PROBE = "zz_probe"
MINIMAL = {"sensors": {"odometry": [{"topic": "/odom"}]}}  # the least config that loads


def _unknown_key(tree) -> tuple[str | None, list[str]]:
    """(where, allowed) of the unknown-key error ``tree`` raises, or (None, [])."""
    try:
        parse_config(tree)
    except ConfigError as e:
        m = re.search(r": (\S+): unknown key \(allowed: ([^)]*)\)$", str(e))
        if m:
            return m.group(1).replace("[0]", "[]"), m.group(2).split(", ")
    return None, []


def accepted_keys(place=lambda v: {**MINIMAL, **v}, path: str = "") -> list[str]:
    """Every leaf key the config accepts under ``path`` (a list of mappings, such as a sensor
    kind, as ``kind[]``); ``place(value)`` is a whole config with ``value`` at ``path``. A key
    whose value refuses a mapping with anything but "unknown key" is a leaf."""
    where, keys = _unknown_key(place({PROBE: 1}))
    if where == f"{path}.{PROBE}".lstrip("."):
        element, sub = {}, path
    elif where == f"{path}[].{PROBE}":  # a list of sensors: each needs its topic to go on
        element, sub = {"topic": "/probe"}, f"{path}[]"
        place = (lambda outer: lambda v: outer([v]))(place)
    else:
        return [path]
    return [leaf for k in keys
            for leaf in accepted_keys(_under(place, element, k), f"{sub}.{k}".lstrip("."))]


def _under(place, element: dict, key: str):
    """``place`` for the value of ``key`` in ``element``."""
    return lambda v: place({**element, key: v})


def _expand(key: str) -> list[str]:
    """``sensors.*[].topic`` is every sensor kind's; ``{a,b}`` is a and b."""
    key = key.replace("sensors.*[]", "sensors.{" + ",".join(SENSOR_KINDS) + "}[]")
    parts = re.split(r"\{([^}]*)\}", key)
    alts = [[p] if i % 2 == 0 else [a.strip() for a in p.split(",")]
            for i, p in enumerate(parts)]
    return ["".join(c) for c in itertools.product(*alts)]


def readme_table() -> dict[str, list[str]]:
    """The README's config table: each expanded key -> its row's cells (type, unit, default,
    meaning)."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Config keys", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        assert len(cells) == 5, line
        for key in _expand(cells[0].strip("`")):
            assert key not in rows, f"{key} in two rows"
            rows[key] = cells[1:]
    return rows


def test_the_probe_finds_keys_at_every_level():
    """The walk reaches top-level, nested and per-sensor keys (so an empty or truncated walk
    cannot pass the table test below)."""
    keys = accepted_keys()
    for k in ("reorder_window", "initial_pose", "smoother.lag", "robot.slip.heading",
              "sensors.imu[].noise.gyro_bias_walk", "sensors.gps[].correlation_time",
              "sensors.odometry[].mount.rpy", "node.nis_window"):
        assert k in keys
    assert len(keys) == len(set(keys)) > 60


def test_the_readme_table_has_every_accepted_key_and_no_other():
    table, keys = readme_table(), set(accepted_keys())
    missing = sorted(keys - set(table))
    rejected = sorted(set(table) - keys)
    assert not missing, f"keys the config accepts that README.md's table lacks: {missing}"
    assert not rejected, f"keys README.md's table names that the config rejects: {rejected}"


@pytest.mark.parametrize("key", ["sensors.*[].topic", "robot.{wheel_radius,track_width}_std"])
def test_expand(key):
    assert len(_expand(key)) == {"sensors.*[].topic": len(SENSOR_KINDS)}.get(key, 2)


def test_every_row_says_type_default_and_meaning():
    for key, (typ, _unit, default, meaning) in readme_table().items():
        assert typ and default and meaning, key


def test_a_key_the_table_lacks_would_be_found(monkeypatch):
    """The check fails on a key the validator accepts beyond the table: accepted_keys reads
    the validator, not a list of its own."""
    import ddfuse.estimation.config as config

    original = config._Checker.mapping

    def wider(self, value, key, allowed):
        if key == "ekf":
            allowed = (*allowed, "extra_key")
        return original(self, value, key, allowed)

    monkeypatch.setattr(config._Checker, "mapping", wider)
    assert "ekf.extra_key" in accepted_keys()
    assert "ekf.extra_key" not in readme_table()
