"""Which estimators a config's sensors allow, and what the refusal says."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest
from ddfuse.estimation.config import load_config
from ddfuse.evaluation import estimators as registry

ROOT = Path(__file__).resolve().parents[1]


def test_range_only_landmarks_leave_out_ekf_slam():
    """EKF-SLAM places a new landmark from its first sighting's range and bearing: with range
    alone it rejected every sighting (6584 on seed002) and ran as dead reckoning, unsaid."""
    cfg = load_config(ROOT / "data" / "sample_seed002.yaml")
    assert "ekf_slam" in registry.select(cfg, None)
    lm = cfg.of_kind("landmarks")[0]
    ranged = replace(cfg, sensors=[replace(s, use=("range",)) if s is lm else s
                                   for s in cfg.sensors])
    chosen = registry.select(ranged, None)
    assert "ekf_slam" not in chosen and {"ekf_landmark", "smoother"} <= set(chosen)
    with pytest.raises(ValueError, match="ekf_slam .* needs an odometry or wheels sensor, and "
                                         "landmarks with bearing"):
        registry.select(ranged, ["ekf_slam"])


def test_a_string_of_names_is_read_as_the_cli_reads_it():
    """A bare string was taken letter by letter: from_config(cfg, "ekf") said "--estimators:
    unknown estimator 'e'", quoting a flag the library caller never gave."""
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    assert registry.select(cfg, "ekf") == ["ekf"]
    assert registry.select(cfg, " ekf, smoother_lagged ") == ["ekf", "smoother"]
    assert registry.select(cfg, ("ekf_igvc", "ekf")) == ["ekf_igvc", "ekf"]
    assert list(registry.build(cfg, None, "ekf", pose=(0.0, 0.0, 0.0))) == ["ekf"]
    with pytest.raises(ValueError, match=r"^estimators: expected comma-separated estimator "
                                         r"names, got ' , ' \(None for the default set\)"):
        registry.select(cfg, " , ")


@pytest.mark.parametrize("names, shown", [(2, "int 2"), (b"ekf", "bytes b'ekf'"),
                                          ({"ekf": 1}, "dict {'ekf': 1}")])
def test_names_that_are_not_a_list_are_a_type_error(names, shown):
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    want = (r"^estimators: expected a list of estimator names \(or one string of "
            r"comma-separated names\), got " + re.escape(shown))
    with pytest.raises(TypeError, match=want):
        registry.select(cfg, names)
    with pytest.raises(TypeError, match=r"^estimators: expected estimator names \(strings\), "
                                        r"got int 3 in \['ekf', 3\]"):
        registry.select(cfg, ["ekf", 3])


def test_library_errors_name_the_parameter_not_the_cli_flag():
    cfg = load_config(ROOT / "data" / "sample_husky.yaml")
    with pytest.raises(ValueError, match=r"^estimators: unknown estimator 'kalman' \(known: ekf,"):
        registry.select(cfg, ["ekf", "kalman"])
    with pytest.raises(ValueError, match=r"^estimators: ekf_landmark \(range/bearing EKF .*\) "
                                         r"needs an odometry or wheels sensor, and landmarks, "
                                         r"which the config does not have$"):
        registry.select(cfg, "ekf_landmark")
