"""What an install puts on the import path: one top-level package, ``ddfuse``, whose
sub-packages are the checkout's folders (``ddfuse.estimation`` is ``estimation/``...) and whose
``ddfuse.data`` ships the sample bags, their configs and landmark map, and data/configs/*.yaml;
the command line finds them there. Before, ``pip install .`` put four generic top-level packages
(``estimation``, ``factors``, ``ekf_baseline``, ``evaluation``) into site-packages, two of
whose names PyPI already has."""

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
from ddfuse.evaluation import shipped
real = Path("rl_husky_gps.bag")
real.write_bytes(b"")
print(shipped.SAMPLE_BAG, shipped.SAMPLE_BAG.is_file())
print(shipped.config_for(shipped.SAMPLE_BAG, None))
print(shipped.config_for(real, None))
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


def test_the_install_has_one_top_level_package(site):
    assert sorted(p.name for p in site.iterdir()) == ["ddfuse"]
    for sub in ("factors", "estimation", "ekf_baseline", "evaluation"):
        shipped = {p.name for p in (site / "ddfuse" / sub).glob("*.py")}
        assert shipped == {p.name for p in (ROOT / sub).glob("*.py")}, sub


def test_the_install_ships_the_data(site):
    data = site / "ddfuse" / "data"
    shipped = sorted(str(p.relative_to(data)) for p in data.rglob("*") if p.is_file())
    assert shipped == sorted(SHIPPED)
    assert 1_000_000 < sum((data / f).stat().st_size for f in SHIPPED) < 1_300_000
    assert not (site / "data").exists()


def test_an_installed_copy_finds_the_sample_and_the_shipped_configs(site, tmp_path):
    r = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True,
                       text=True, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"},
                       timeout=120)
    assert r.returncode == 0, r.stderr
    data = site / "ddfuse" / "data"
    assert r.stdout.splitlines() == [f"{data / 'sample_husky.bag'} True",
                                     str(data / "sample_husky.yaml"),
                                     str(data / "configs" / "rl_husky_gps.yaml")]


def test_a_checkout_uses_its_own_data():
    from ddfuse.evaluation import shipped

    assert shipped.DATA == ROOT / "data"
    assert shipped.SAMPLE_BAG == ROOT / "data" / "sample_husky.bag"
    assert shipped.SAMPLE_BAG.is_file()


VENV_PROBE = """
import importlib.util, sys
import ddfuse
print(ddfuse.__version__)
print(ddfuse.__file__)
print([n for n in ("estimation", "factors", "ekf_baseline", "evaluation", "ddfuse_data")
       if importlib.util.find_spec(n) is not None])
"""


@pytest.mark.slow
@pytest.mark.parametrize("editable", [False, True], ids=["regular", "editable"])
def test_a_fresh_venv_install_exposes_only_ddfuse(tmp_path, editable):
    """``pip install .`` and ``pip install -e .`` in a new virtual environment (no dependencies;
    pip fetches the build backend, setuptools, as any install does): from another directory
    ``import ddfuse`` gives the version and none of the
    checkout's folders is importable as a package of its own. The venv is made without pip
    and this interpreter's pip installs into it (``pip --python``, pip >= 22.3): seeding the
    venv's own pip took 4 s of CPU and is no part of what is tested."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    py = venv / "bin" / "python"
    src = tmp_path / "src"
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        if (ROOT / f).is_file():
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / f, src / f)
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q",
                        "--no-deps",
                        *(["-e"] if editable else []), str(src)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = subprocess.run([str(py), "-c", VENV_PROBE], cwd=elsewhere, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    ver, where, leaked = r.stdout.splitlines()
    assert ver == _project_version()
    assert (Path(where).parent == src / "ddfuse") == editable
    assert leaked == "[]"


def _project_version() -> str:
    import re

    return re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(),
                     re.M).group(1)
