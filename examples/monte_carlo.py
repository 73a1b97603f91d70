"""Monte Carlo of a simulated scenario: accuracy and consistency over several seeds.

    python examples/monte_carlo.py [SCENARIO] [--seeds 1-3] [--estimators ekf] [--duration 60]

Each seed simulates the scenario (``ddfuse.evaluation.simulate``: truth, wheel odometry, gyro,
GPS with the scenario's noise), writes it as a bag, reads it back as a user's bag and runs the
estimators plus dead reckoning; the table gives per estimator the position RMSE (m) against
the exact simulated truth and the average NEES (ANEES, 3 DOF) with its 95 % chi-square band.
``ddfuse mc`` is the same with more options, a JSON record and plots.
"""

from __future__ import annotations

import argparse

from ddfuse.evaluation.montecarlo import monte_carlo, to_markdown
from ddfuse.evaluation.simulate import SCENARIOS


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="husky", choices=sorted(SCENARIOS))
    ap.add_argument("--seeds", default="1-3", help="first-last, inclusive")
    ap.add_argument("--estimators", default="ekf", help="comma-separated names")
    ap.add_argument("--duration", type=float, default=60.0, help="simulated seconds per seed")
    args = ap.parse_args(argv)
    first, _, last = args.seeds.partition("-")
    seeds = range(int(first), int(last or first) + 1)
    mc = monte_carlo(args.scenario, seeds, args.estimators.split(","), duration=args.duration,
                     jobs=1)
    print(to_markdown(mc))


if __name__ == "__main__":
    main()
