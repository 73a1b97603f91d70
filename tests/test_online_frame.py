"""``ddfuse online``'s header names the frame of its estimates: the landmark map's, the
start pose's or ENU, the same frame as run's report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ddfuse.evaluation import cli, plots
from ddfuse.evaluation.online import online_frame
from ddfuse.evaluation.shipped import config_for

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def _online_header(bag: Path, capsys) -> str:
    assert cli.main(["online", str(bag), "--estimators", "ekf", "--every", "100000"]) == 0
    return capsys.readouterr().out.splitlines()[0]


def test_online_names_the_landmark_maps_frame_on_the_seed002_sample(capsys):
    """The landmark sample has no GPS: the frame is the landmark map's, as run's report says,
    not ENU."""
    head = _online_header(SEED002, capsys)
    assert "ENU" not in head and "east" not in head
    assert "in the landmark map's frame (yaw counter-clockwise from x)" in head


@pytest.mark.slow  # the seed002 test above on 25 min of real data (30 s here)
def test_online_names_the_landmark_maps_frame_on_mrclam(mrclam_bag, capsys):
    """MRCLAM has no GPS: the frame is the landmark map's, as run's report says, not ENU
   ."""
    head = _online_header(mrclam_bag, capsys)
    assert "ENU" not in head and "east" not in head
    assert "in the landmark map's frame (yaw counter-clockwise from x)" in head


def test_online_names_the_start_pose_frame_on_jackal(jackal_bag, capsys):
    head = _online_header(jackal_bag, capsys)
    assert "ENU" not in head and "east" not in head
    assert "in the start-pose frame" in head


def test_online_frame_is_the_reports_frame(mrclam_bag, jackal_bag, husky_bag, seed002_run):
    """online_frame gives plots.frame the facts run records: the same frame as each report."""
    from ddfuse.estimation.config import load_config

    for bag, kind in ((mrclam_bag, "map"), (jackal_bag, "start"), (husky_bag, "enu"),
                      (SEED002, "map")):
        cfg = load_config(config_for(bag, None))
        assert online_frame(bag, cfg)["kind"] == kind, bag
    m = json.loads((seed002_run / "metrics.json").read_text())
    cfg = load_config(config_for(SEED002, None))
    assert online_frame(SEED002, cfg) == plots.frame(m)
