"""The committed sample data in data/ is exactly what the documented commands generate."""

from __future__ import annotations

import math
import re
import shlex
from pathlib import Path

import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation import cli
from ddfuse.evaluation import simulate as sim
from test_simulate_bags import read_all  # tests/ is on sys.path (no __init__)

DATA = Path(__file__).resolve().parents[1] / "data"


def documented_commands() -> list[list[str]]:
    """The `ddfuse simulate ...` lines of data/README.md, as argv lists."""
    text = (DATA / "README.md").read_text()
    cmds = [shlex.split(m) for m in re.findall(r"^ddfuse simulate (.+)$", text,
                                               flags=re.M)]
    assert cmds, "data/README.md documents no regenerate command"
    return cmds


def test_sample_data_is_small_and_loads():
    files = [p for p in DATA.iterdir() if p.name != "README.md"]
    assert sum(p.stat().st_size for p in files) < 3_000_000
    for cfg in ("sample_husky.yaml", "sample_seed002.yaml"):
        load_config(DATA / cfg)


def _same(a, b) -> bool:
    """Equal messages, floats to 1e-9 relative: numpy and libm builds differ in the last bit of
    a transcendental, and the geodetic conversion amplifies it (with numpy 2.4.6 the husky
    sample regenerates with altitudes 1.9e-9 m and IMU quaternions 1e-12 relative off the
    committed ones), which no estimate can tell apart."""
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


_NUMBER = re.compile(r"-?\d+\.\d+(?:e[-+]?\d+)?")


def _same_text(a: str, b: str) -> bool:
    """The same text, its decimal numbers compared as :func:`_same` compares floats."""
    return (_NUMBER.split(a) == _NUMBER.split(b)
            and _same([float(x) for x in _NUMBER.findall(a)],
                      [float(x) for x in _NUMBER.findall(b)]))


@pytest.mark.slow
@pytest.mark.parametrize("argv", documented_commands(), ids=lambda a: a[0])
def test_regenerated_sample_matches_committed(argv, tmp_path):
    i = argv.index("-o")
    committed = Path(argv[i + 1])
    assert committed.parts[0] == "data"
    committed = DATA.parent / committed
    fresh = tmp_path / committed.name
    assert cli.main(["simulate", *argv[:i + 1], str(fresh), *argv[i + 2:]]) == 0
    assert _same(read_all(fresh, skip=()), read_all(committed, skip=()))
    fresh_cfg, fresh_map = sim.sidecar_paths(fresh)
    cfg, lmap = sim.sidecar_paths(committed)
    assert _same_text(fresh_cfg.read_text(), cfg.read_text())
    assert fresh_map.is_file() == lmap.is_file()
    if lmap.is_file():
        assert _same_text(fresh_map.read_text(), lmap.read_text())
