"""What lag-sweep scores against (truth, else withheld GPS fixes) and its refusals when there
is nothing to score: before decoding when the config cannot help, after when no fix is held out."""

from __future__ import annotations

from pathlib import Path

import pytest
from ddfuse.evaluation import cli

ROOT = Path(__file__).resolve().parents[1]
SEED002 = ROOT / "data" / "sample_seed002.bag"


def test_lag_sweep_refuses_before_decoding_when_the_config_has_no_truth(tmp_path, capsys):
    """rl_jackal's config names no ground_truth topic: with no --gps-holdout there is nothing
    to score, said in one line, exit 2, before the bag is opened (here it does not even exist)
    rather than after a table of dashes with exit 0."""
    from ddfuse.evaluation.lag_sweep import lag_sweep

    jackal_cfg = ROOT / "data" / "configs" / "rl_jackal.yaml"
    with pytest.raises(ValueError, match="needs ground truth or --gps-holdout") as e:
        lag_sweep(tmp_path / "absent.bag", jackal_cfg)
    assert str(jackal_cfg) in str(e.value) and "names no ground_truth topic" in str(e.value)
    # a hold-out cannot help a config without GPS either
    with pytest.raises(ValueError,
                       match=r"--gps-holdout every:5: .*rl_jackal\.yaml has no gps sensor"):
        lag_sweep(tmp_path / "absent.bag", jackal_cfg, holdout="every:5")
    bag = tmp_path / "jackal.bag"
    bag.write_bytes(b"")
    code = cli.main(["lag-sweep", str(bag), "-c", str(jackal_cfg)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    [line] = err.strip().splitlines()
    assert line.startswith("ddfuse: error: lag-sweep needs ground truth or --gps-holdout")


def test_lag_sweep_refuses_a_hold_out_that_withholds_nothing(husky_bag, capsys):
    """No truth and a window after the data: every RMSE would be '-' under a 'gps_holdout'
    header; it is refused after decoding, before any estimator runs."""
    code = cli.main(["lag-sweep", str(husky_bag), "--lags", "2", "--gps-holdout",
                     "window:1000:2000"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert "--gps-holdout window:1000:2000 withholds none of its 989 GPS fixes" in err


def test_lag_sweep_scores_against_what_the_stream_has():
    """_scored_against on decoded streams: the truth when there is some, else the withheld
    fixes (runner's rule: every K-th from the first), else refused."""
    import numpy as np
    from ddfuse.estimation.config import load_config
    from ddfuse.estimation.measurements import GpsFix, GroundTruthPose, Stream
    from ddfuse.evaluation.lag_sweep import _scored_against

    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    fixes = [GpsFix(t=float(t), lat=42.0, lon=-71.0, alt=0.0, cov=np.eye(3)) for t in range(4)]
    no_truth = Stream(measurements=fixes)
    assert _scored_against(no_truth, "b.bag", cfg, "every:2") == "gps_holdout"
    with pytest.raises(ValueError, match="withholds none of its 4 GPS fixes"):
        _scored_against(no_truth, "b.bag", cfg, "window:10:20")
    with pytest.raises(ValueError, match="b.bag has no ground truth$"):
        _scored_against(no_truth, "b.bag", cfg, None)
    truth = Stream(measurements=fixes, ground_truth=[GroundTruthPose(0.0, 0.0, 0.0, 0.0)])
    assert _scored_against(truth, "b.bag", cfg, None) == "truth"
    assert _scored_against(truth, "b.bag", cfg, "window:10:20") == "truth"
