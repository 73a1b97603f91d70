"""Shared by tests/test_sensor_*.py: a simulated bag run with a config variant, each
estimator's error against the simulator's truth (the honest with/without comparisons of
docs/design/sensors.md: same bag, same noise, only the sensor list differs)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import parse_config_text
from ddfuse.estimation.runner import run
from ddfuse.evaluation.estimators import build
from ddfuse.evaluation.simulate import simulate, write_bag


@dataclass
class Errors:
    """One estimator's track against the truth: position RMSE (m), yaw RMSE (rad), mean pose
    NEES (3 dof, NaN without covariance), samples compared."""

    pos_rmse: float
    yaw_rmse: float
    nees: float
    n: int


def sim_bag(tmp: Path, scenario: str, seed: int, duration: float) -> tuple[Path, dict]:
    """The simulated bag and its sidecar config (as a YAML tree)."""
    res = simulate(scenario, seed=seed, duration=duration)
    bag, cfg_path, _ = write_bag(res, tmp / f"{scenario}-{seed}.bag")
    return bag, yaml.safe_load(cfg_path.read_text())


def variant(cfg: dict, **sensors) -> dict:
    """``cfg`` with sensor kinds replaced (a list) or removed (None)."""
    out = copy.deepcopy(cfg)
    for kind, value in sensors.items():
        if value is None:
            out["sensors"].pop(kind, None)
        else:
            out["sensors"][kind] = value
    return out


def errors(bag: Path, cfg_tree: dict, names: list[str], skip: float = 0.0
           ) -> dict[str, Errors]:
    """Run ``names`` on ``bag`` with the config ``cfg_tree``; each track's errors against the
    ground truth after ``skip`` s (interpolated at the track's stamps)."""
    cfg = parse_config_text(yaml.safe_dump(cfg_tree), str(bag.with_suffix(".variant.yaml")),
                            bag.parent)
    stream = read_stream(bag, cfg)
    result = run(stream, build(cfg, stream, names))
    gt = np.array([(g.t, g.x, g.y, g.yaw) for g in stream.ground_truth])
    gyaw = np.unwrap(gt[:, 3])
    out = {}
    for name in names:
        r = result.runs[name]
        assert r.error is None, (name, r.error)
        tr = r.trajectory
        keep = tr.t >= gt[0, 0] + skip
        t, pose, cov = tr.t[keep], tr.pose[keep], tr.cov[keep]
        d = np.stack([pose[:, 0] - np.interp(t, gt[:, 0], gt[:, 1]),
                      pose[:, 1] - np.interp(t, gt[:, 0], gt[:, 2]),
                      np.remainder(pose[:, 2] - np.interp(t, gt[:, 0], gyaw) + math.pi,
                                   2 * math.pi) - math.pi], axis=1)
        nees = (np.mean([float(e @ np.linalg.solve(c, e)) for e, c in zip(d, cov, strict=True)])
                if np.isfinite(cov).all() else math.nan)
        out[name] = Errors(float(np.sqrt(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2))),
                           float(np.sqrt(np.mean(d[:, 2] ** 2))), float(nees), len(t))
    return out
