"""Run two (or more) estimators on one bag and compare their accuracy.

    python examples/compare_estimators.py [BAG CONFIG] [--estimators ekf,smoother]

Without BAG and CONFIG it uses the simulated sample shipped with ddfuse (``ddfuse.data``:
sample_husky.bag and its config). Every estimator reads the same decoded stream; the table
gives, per output (the smoother adds its lagged estimate), the absolute trajectory error (ATE
RMSE, m, against the bag's ground truth in the config's local ENU frame), the yaw RMSE (deg),
the mean pose NEES (3 DOF) and the wall time (s): the numbers ``ddfuse run`` writes to
metrics.json.
"""

from __future__ import annotations

import argparse
from importlib.resources import files

import ddfuse


def compare(bag: str, config: str, names: list[str]) -> dict:
    """Decode ``bag`` with ``config``, run ``names`` on it; {output name: its scores}
    (``ddfuse.evaluation.scores.EstimatorScores``, what metrics.json holds per estimator)."""
    cfg = ddfuse.load_config(config)
    stream = ddfuse.read_bag(bag, cfg)
    result = ddfuse.run(stream, ddfuse.build_estimators(cfg, stream, names))
    return ddfuse.score(result).estimators


def _cell(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main(argv: list[str] | None = None) -> None:
    data = files("ddfuse.data")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", nargs="?", default=str(data / "sample_husky.bag"))
    ap.add_argument("config", nargs="?", default=str(data / "sample_husky.yaml"))
    ap.add_argument("--estimators", default="ekf,smoother", help="comma-separated names")
    args = ap.parse_args(argv)
    scores = compare(args.bag, args.config, args.estimators.split(","))
    print(f"{'estimator':<16} {'ATE m':>8} {'yaw deg':>8} {'NEES':>7} {'time s':>7}")
    for name, s in scores.items():
        print(f"{name:<16} {_cell(s.ate_rmse_m, '8.3f')} {_cell(s.yaw_rmse_deg, '8.2f')} "
              f"{_cell(s.nees_mean, '7.2f')} {_cell(s.runtime_s, '7.2f')}")


if __name__ == "__main__":
    main()
