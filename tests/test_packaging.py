"""A regular install (``pip install .``, not ``-e``) ships the sample bags, their configs and
landmark map, and data/configs/*.yaml as the package ``ddfuse_data``, and the command line
finds them there. Before, only the four code packages were installed: ``ddfuse run`` said
'.../site-packages/data/sample_husky.bag: no such bag', and a real bag found no shipped
config."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ["README.md", "__init__.py", "sample_husky.bag", "sample_husky.yaml",
           "sample_seed002.bag", "sample_seed002.yaml", "sample_seed002.landmarks.yaml",
           "configs/mrclam1_robot1.yaml", "configs/rl_husky_gps.yaml", "configs/rl_jackal.yaml"]

PROBE = """
from pathlib import Path
from evaluation import cli
real = Path("rl_husky_gps.bag")
real.write_bytes(b"")
print(cli.SAMPLE_BAG, cli.SAMPLE_BAG.is_file())
print(cli._config_for(cli.SAMPLE_BAG, None))
print(cli._config_for(real, None))
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """What a regular install puts in site-packages, by setuptools' build_py from pyproject.toml
    on a copy of the checkout's files (as a clean clone has them; no wheel or network needed)."""
    tmp = tmp_path_factory.mktemp("install")
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    src = tmp / "src"
    for f in files:
        if (ROOT / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / f, src / f)
    lib = tmp / "site"
    r = subprocess.run([sys.executable, "-c", "from setuptools import setup; setup()", "-q",
                        "build_py", "--build-lib", str(lib)], cwd=src, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Package would be ignored" not in r.stderr, r.stderr
    return lib


def test_the_install_ships_the_data(site):
    data = site / "ddfuse_data"
    shipped = sorted(str(p.relative_to(data)) for p in data.rglob("*") if p.is_file())
    assert shipped == sorted(SHIPPED)
    assert 1_000_000 < sum((data / f).stat().st_size for f in SHIPPED) < 1_300_000
    assert not (site / "data").exists()


def test_an_installed_copy_finds_the_sample_and_the_shipped_configs(site, tmp_path):
    r = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True,
                       text=True, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"},
                       timeout=120)
    assert r.returncode == 0, r.stderr
    data = site / "ddfuse_data"
    assert r.stdout.splitlines() == [f"{data / 'sample_husky.bag'} True",
                                     str(data / "sample_husky.yaml"),
                                     str(data / "configs" / "rl_husky_gps.yaml")]


def test_a_checkout_uses_its_own_data():
    from evaluation import cli

    assert cli.DATA == ROOT / "data"
    assert cli.SAMPLE_BAG == ROOT / "data" / "sample_husky.bag" and cli.SAMPLE_BAG.is_file()
