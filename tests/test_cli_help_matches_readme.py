"""The command line's --help and the command table of the CLI reference the README links
(docs/cli.md) agree: every estimator and option listed, online's refusals named, run's wall-time
line where the reference says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from ddfuse.evaluation import cli

ROOT = Path(__file__).resolve().parents[1]
CLI_DOC = ROOT / "docs" / "cli.md"  # the README's "Command line" link
SEED002 = ROOT / "data" / "sample_seed002.bag"


def test_run_help_lists_every_estimator_the_parser_accepts(capsys):
    """dr was missing from `run --help`: every name --estimators accepts is listed."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    listed = text.split("--estimators LIST comma-separated: ")[1].split(" (")[0]
    assert [n.strip() for n in listed.split(",")] == list(TRACK_TO_SPEC)
    assert "default: all but dr" in text


def _readme_cell(command: str) -> tuple[str, str]:
    """(synopsis, description) of ``ddfuse COMMAND`` in docs/cli.md's command table."""
    for line in CLI_DOC.read_text().splitlines():
        if line.startswith(f"| `ddfuse {command} ") or line.startswith(f"| `ddfuse {command}`"):
            synopsis, text = line[2:].split("` | ", 1)
            return synopsis, text
    raise AssertionError(f"no {CLI_DOC.name} row for ddfuse {command}")


COMMANDS = ["inspect", "run", "report", "online", "node", "bench", "tune", "fleet", "compare",
            "simulate", "plot-sim", "lag-sweep", "mc"]


def test_the_reference_covers_every_command_of_the_parser(capsys):
    """COMMANDS (the rows checked below) are the parser's commands, and docs/cli.md has a row
    for each."""
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    choices = re.search(r"\{([\w,-]+)\}", capsys.readouterr().out).group(1).split(",")
    assert choices == COMMANDS
    for command in COMMANDS:
        _readme_cell(command)


@pytest.mark.parametrize("command", COMMANDS)
def test_readme_synopsis_has_every_option_of_the_help(command, capsys):
    """The table lacked lag-sweep's -c and online's --reorder-window; every command's row is
    checked (it was six of them)."""
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    usage = " ".join(capsys.readouterr().out.split("\n\n")[0].split())
    options = set(re.findall(r"\[(-[-\w]+)", usage)) - {"-h"}
    synopsis, _ = _readme_cell(command)
    missing = [o for o in options if not re.search(rf"{re.escape(o)}\b", synopsis)]
    assert not missing, (command, missing, synopsis)


def test_readme_says_which_estimators_online_refuses():
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED

    _, text = _readme_cell("online")
    refused = text.split("Not ")[1].split(":")[0]
    assert sorted(re.findall(r"`(\w+)`", refused)) == sorted(ONLINE_TRACKS_REFUSED)


def test_readme_places_the_wall_time_line_where_run_prints_it(tmp_path, capsys):
    """The wall-time split follows the table, the headline follows it, and the last line
    says where the results are."""
    assert cli.main(["run", "-o", str(tmp_path / "o"), "--estimators", "ekf",
                     "--no-report"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    wall = [i for i, s in enumerate(lines) if s.startswith("wall time ")]
    head = [i for i, s in enumerate(lines) if s.startswith("Best: ")]
    assert len(wall) == 1 and len(head) == 1 and wall[0] < head[0]
    assert lines[-1].startswith("results in ")
    _, text = _readme_cell("run")
    assert "`wall time` line, right after the table (before the headline and the last line, " \
        "`results in ...`)" in text
