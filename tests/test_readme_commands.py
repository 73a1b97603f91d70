"""Every command the README shows is run here, as written: the two opening commands (pip's part
resolved with --dry-run against this environment, since installing into the running one would
change it under the other tests; the real installs are test_packaging's fresh venvs), the five
steps on a bag named robot.bag, each command name and `--help` it mentions in the text, and the
screenshot script. A README command this file does not know is a failure, not a skip."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import shared_bag
from ddfuse.estimation.config import load_config
from test_cli_help_matches_readme import COMMANDS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BIN = Path(sys.executable).parent  # the environment's console scripts (ddfuse)
FIRST = "pip install -e . && ddfuse run"
SECOND = 'pip install -e ".[test]" && python -m pytest -q -n auto --dist loadfile'
STEPS = "## Your robot in five steps"


def bash_blocks(text: str) -> list[list[str]]:
    """The non-empty lines of each ```bash block."""
    return [[ln.strip() for ln in b.splitlines() if ln.strip()]
            for b in re.findall(r"```bash\n(.*?)```", text, re.S)]


def inline_commands(text: str) -> list[str]:
    """The code spans outside code blocks that start like a command."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    return [s for s in re.findall(r"`([^`\n]+)`", prose)
            if re.match(r"(ddfuse|python|pip|ruff|\.ci/run)( |$)", s)]


def _run(line: str, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    argv = shlex.split(line)
    if argv[0] in ("ddfuse", "python"):
        argv[0] = str(BIN / "ddfuse") if argv[0] == "ddfuse" else sys.executable
    r = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{line}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    return r


def _pip_dry_run(line: str) -> None:
    """``pip install ...`` of the checkout resolved as written (extras included), nothing
    installed."""
    argv = shlex.split(line)
    assert argv[:3] == ["pip", "install", "-e"], line
    spec = argv[3].replace(".", str(ROOT), 1)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "-q", "-e", spec],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"{line}: {r.stderr[-2000:]}"


def test_the_readme_opens_with_the_two_commands():
    """The developers' guide: the README opens with exactly two commands, the first installing
    and running the main job on the embedded sample, the second the tests."""
    text = README.read_text()
    assert text.split("\n", 2)[2].startswith("```bash\n")
    assert bash_blocks(text)[0] == [FIRST, SECOND]


def test_every_command_in_the_readme_is_one_this_file_runs():
    text = README.read_text()
    blocks = bash_blocks(text)
    steps = bash_blocks(text.split(STEPS, 1)[1])[0]
    assert blocks == [[FIRST, SECOND], steps], "a bash block this file does not run"
    for line in steps:
        assert line.startswith(("ddfuse ", "$EDITOR ")), line
    for span in inline_commands(text):
        known = (re.fullmatch(r"ddfuse (\S+)", span) and span.split()[1] in COMMANDS
                 or span in (*FIRST.split(" && "), *SECOND.split(" && "),
                             "ddfuse COMMAND --help", "python docs/tools/report_screenshot.py",
                             "ruff check .", ".ci/run"))
        assert known, f"README command {span!r} is run by no test"


@pytest.mark.slow
def test_the_first_command_runs_the_sample(tmp_path):
    """``pip install -e .`` resolves; ``ddfuse run`` with no argument, in an empty folder,
    runs the embedded sample and writes the report and metrics to ddfuse-out/."""
    pip, run = FIRST.split(" && ")
    _pip_dry_run(pip)
    out = _run(run, tmp_path).stdout
    assert (tmp_path / "ddfuse-out" / "report.html").stat().st_size > 100_000
    assert (tmp_path / "ddfuse-out" / "metrics.json").is_file()
    assert "sample_husky.bag" in out and "smoother" in out


@pytest.mark.slow
def test_the_second_command(tmp_path):
    """The test extra resolves; the pytest command is what CI runs (pip quiet there), and its
    options (pytest-xdist on every core, whole files per worker) run a test file here."""
    pip, tests = SECOND.split(" && ")
    _pip_dry_run(pip)
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert SECOND in [ln.replace("pip install -q ", "pip install ") for ln in ci]  # pip quiet
    r = _run(f"{tests} -p no:cacheprovider tests/test_readme_config_table.py", ROOT)
    assert re.search(r"\b6 passed\b", r.stdout), r.stdout


def test_each_command_named_in_the_text_has_help(capsys):
    """`ddfuse NAME` in the prose, and `ddfuse COMMAND --help` for every command (in this
    process: the console script itself is run by the slow tests above)."""
    from ddfuse.evaluation import cli

    named = {s.split()[1] for s in inline_commands(README.read_text())
             if re.fullmatch(r"ddfuse \S+", s)}
    assert named and named <= set(COMMANDS)
    for command in COMMANDS:
        with pytest.raises(SystemExit) as done:
            cli.main([command, "--help"])
        assert done.value.code == 0 and "usage: ddfuse" in capsys.readouterr().out


def test_what_ci_runs_from_the_readme():
    """`ruff check .` and the regression gate the Development line names are in .ci/run."""
    ci = (ROOT / ".ci" / "run").read_text()
    assert "\nruff check .\n" in ci and "ddfuse compare .ci/baseline/" in ci


def _robot_bag(kind: str, tmp_path: Path) -> None:
    """``tmp_path/robot.bag`` as a user's bag: no config beside it."""
    bag = tmp_path / "robot.bag"
    if kind == "simulated":
        _run("ddfuse simulate husky --duration 60 --seed 3 -o robot.bag", tmp_path)
        (tmp_path / "robot.yaml").unlink()
    else:
        bag.symlink_to(shared_bag(kind))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["simulated", "rl_jackal.bag"])
def test_your_robot_in_five_steps(kind, tmp_path):
    """The block run line by line in one folder; the edit step checks the file the user edits
    is a config that loads. Then: results in out/ and out-tuned/, and the tuned config differs
    from the inspected one in at least one noise value."""
    _robot_bag(kind, tmp_path)
    steps = bash_blocks(README.read_text().split(STEPS, 1)[1])[0]
    for line in steps:
        if line.startswith("$EDITOR "):
            load_config(tmp_path / line.split()[1])
        else:
            _run(line, tmp_path)
    for out in ("out", "out-tuned"):
        assert (tmp_path / out / "metrics.json").is_file()
        assert (tmp_path / out / "report.html").is_file()
    given, tuned = load_config(tmp_path / "robot.yaml"), load_config(tmp_path / "tuned.yaml")
    assert ([s.noise for s in given.sensors] != [s.noise for s in tuned.sensors]
            or given.robot != tuned.robot)


@pytest.mark.integration
def test_the_screenshot_script(tmp_path):
    """docs/tools/report_screenshot.py makes the README's picture: a PNG under 150 kB, 1000 px
    wide, of a run's report (run here without the report's slowest estimator, batch)."""
    pytest.importorskip("websockets")
    from browser import chromium

    chromium()
    from ddfuse.evaluation import cli

    assert cli.main(["run", "-o", str(tmp_path / "run"), "--estimators", "ekf,smoother"]) == 0
    png = tmp_path / "shot.png"
    _run(f"python docs/tools/report_screenshot.py {tmp_path / 'run'} -o {png}", ROOT)
    from PIL import Image

    assert png.stat().st_size < 150_000
    assert Image.open(png).size[0] == 1000
    committed = ROOT / "docs" / "report.png"
    assert committed.stat().st_size < 150_000 and "(docs/report.png)" in README.read_text()


def test_the_readme_stays_short_and_its_links_resolve():
    """Under 12 kB (issue 29; the rest is in docs/), and every file or folder it names
    (docs/..., tests/..., data/, .ci/run, ...) is in the checkout."""
    text = README.read_text()
    assert len(text.encode()) < 12_000
    named = set(re.findall(r"`((?:docs|tests|data|examples|\.ci)/[^`\s]*)`", text))
    named |= set(re.findall(r"\]\(((?:docs)/[^)]+)\)", text))
    assert {"docs/cli.md", "docs/api.md", "docs/methods.md", "docs/specification.md",
            "docs/errata.md", "docs/report.png", "docs/design/fleet.md"} <= named
    assert [p for p in named if not (ROOT / p).exists()] == []
