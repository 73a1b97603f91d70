"""Micro benchmark of the factors in ``factors/``: linearize and error cost per factor (µs).

Each factor type is replicated ``n_factors`` times in a ``NonlinearFactorGraph`` over a Values
created from Python (so gtsam does not copy the Values for each callback, unlike inside ISAM2 and
the optimizers; see the design study, pitfall 1). ``graph.linearize(values)`` and
``graph.error(values)`` are timed with ``timeit``; the figure is the minimum over ``repeat``
round-robin runs divided by the number of factors. Reference rows: a trivial 1-key CustomFactor
that reads nothing (the floor of any Python factor) and C++ built-ins. Not a test: timings
depend on the machine and its load.

Run: ``python3 -m ddfuse.evaluation.bench_factors [repeat]``.
"""

from __future__ import annotations

import math
import sys
import timeit

import gtsam
import numpy as np
from ddfuse.factors.gps import gps_factor
from ddfuse.factors.gyro import gyro_factor
from ddfuse.factors.heading import heading_factor
from ddfuse.factors.landmark import (
    range_bearing_factor,
    range_bearing_slam_factor,
    range_factor,
)
from ddfuse.factors.motion import MotionNoise, motion_factor
from ddfuse.factors.preintegration import WheelGyroPreintegration, preintegrated_factor
from ddfuse.factors.wheel import wheel_rates_calib_factor, wheel_rates_factor, wheel_speed_factor

__all__ = ["bench_factors", "bench_preintegration"]

_FLOOR = "custom trivial 1-key (floor)"


def _trivial_factor(key: int) -> gtsam.CustomFactor:
    h = np.zeros((1, 7))
    arr = np.array

    def error(this, values, H):
        if H is not None:
            H[0] = h
        return arr((0.0,))

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [key], error)


def _reads_only_factor(key_i: int, key_j: int) -> gtsam.CustomFactor:
    """2 keys, 7-D: reads both states and returns constant Jacobians; the plumbing cost alone."""
    hi = -np.eye(7)
    hj = np.eye(7)
    e = np.zeros(7)

    def error(this, values, H):
        values.atVector(key_i).tolist()
        values.atVector(key_j).tolist()
        if H is not None:
            H[0] = hi
            H[1] = hj
        return e

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(7), [key_i, key_j], error)


def _pim() -> WheelGyroPreintegration:
    p = WheelGyroPreintegration(0.0)
    for k in range(10):
        p.integrate(0.01, 1.0, 0.2 + 0.01 * k, 0.05**2, 0.01**2)
    return p


def _builders(n: int) -> dict[str, tuple[object, int]]:
    """name -> (function k -> factor, number of keyframes the factors need)."""
    motion_noise = MotionNoise()
    pim = _pim()
    s2 = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    s1 = gtsam.noiseModel.Isotropic.Sigma(1, 0.1)
    s3 = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.01]))
    huber = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), s2)
    prior7 = gtsam.noiseModel.Diagonal.Precisions(np.array([4.0, 4.0, 1e3, 400, 1e4, 0, 0]))
    calib = 10 * n
    lm = 20 * n
    return {
        _FLOOR: (_trivial_factor, n),
        "custom 2-key 7-D, reads only (plumbing)": (lambda k: _reads_only_factor(k, k + 1), n + 1),
        "C++ PriorFactorVector (7-D state)": (
            lambda k: gtsam.PriorFactorVector(k, np.zeros(7), prior7),
            n,
        ),
        "C++ BetweenFactorPose2 (Pose2 keys)": (
            lambda k: gtsam.BetweenFactorPose2(lm + k, lm + k + 1, gtsam.Pose2(1, 0, 0.1), s3),
            n + 1,
        ),
        "C++ PoseTranslationPrior2D (Pose2 key)": (
            lambda k: gtsam.PoseTranslationPrior2D(lm + k, np.array([1.0, 2.0]), s2),
            n,
        ),
        "C++ PoseRotationPrior2D (Pose2 key)": (
            lambda k: gtsam.PoseRotationPrior2D(lm + k, gtsam.Rot2(0.3), s1),
            n,
        ),
        "motion (2 keys, 7-D)": (lambda k: motion_factor(k, k + 1, 0.1, motion_noise), n + 1),
        "preintegrated (2 keys, 7-D)": (lambda k: preintegrated_factor(k, k + 1, pim), n + 1),
        "gyro": (lambda k: gyro_factor(k, 0.1, s1), n),
        "heading": (lambda k: heading_factor(k, 3.1, s1), n),
        "wheel speed": (lambda k: wheel_speed_factor(k, 1.0, s1), n),
        "wheel rates": (lambda k: wheel_rates_factor(k, 9.0, 11.0, 0.1, 0.5, s2), n),
        "wheel rates + calib key": (
            lambda k: wheel_rates_calib_factor(k, calib, 9.0, 11.0, 0.1, 0.5, s2),
            n,
        ),
        "gps": (lambda k: gps_factor(k, 1.0, 2.0, s2), n),
        "gps lever arm + dt_fix, Huber": (
            lambda k: gps_factor(k, 1.0, 2.0, huber, lever_arm=(0.3, 0.1), dt_fix=0.05),
            n,
        ),
        "range+bearing, known landmark": (
            lambda k: range_bearing_factor(k, (10.0, 5.0), 8.0, 0.4, s2),
            n,
        ),
        "range only, known landmark": (lambda k: range_factor(k, (10.0, 5.0), 8.0, s1), n),
        "range+bearing, Point2 landmark key": (
            lambda k: range_bearing_slam_factor(k, lm - 1, 8.0, 0.4, s2),
            n,
        ),
    }


def _values(n_states: int, n_factors: int) -> gtsam.Values:
    v = gtsam.Values()
    rng = np.random.default_rng(0)
    for k in range(n_states):
        v.insert(k, np.array([0.1 * k, 0.05 * k, 0.01 * k, 1.0, 0.1, 0.01, 0.02]))
    v.insert(10 * n_factors, np.array([1.0, 1.0]))
    v.insert(20 * n_factors - 1, gtsam.Point2(10.0, 5.0))
    for k in range(n_states):
        v.insert(20 * n_factors + k, gtsam.Pose2(0.1 * k, rng.normal(), 0.01 * k))
    return v


def bench_factors(repeat: int = 5, n_factors: int = 2000) -> dict[str, dict[str, float]]:
    """Per-factor cost, µs: {factor name: {"linearize_us", "error_us", "linearize_x_floor",
    "error_x_floor"}} for graphs of ``n_factors`` copies of each factor type.

    The factor types are timed round-robin ``repeat`` times and the minimum is kept, so that a
    change of machine load affects all rows alike (the machine is shared and noisy)."""
    values = _values(n_factors + 1, n_factors)
    graphs: dict[str, gtsam.NonlinearFactorGraph] = {}
    for name, (make, _) in _builders(n_factors).items():
        graph = gtsam.NonlinearFactorGraph()
        for k in range(n_factors):
            graph.add(make(k))
        graph.linearize(values)  # warm-up
        graphs[name] = graph
    lin: dict[str, float] = dict.fromkeys(graphs, math.inf)
    err: dict[str, float] = dict.fromkeys(graphs, math.inf)
    for _ in range(repeat):
        for name, graph in graphs.items():
            lin[name] = min(lin[name], timeit.timeit(lambda g=graph: g.linearize(values), number=1))
            err[name] = min(err[name], timeit.timeit(lambda g=graph: g.error(values), number=1))
    out = {
        name: {"linearize_us": lin[name] / n_factors * 1e6, "error_us": err[name] / n_factors * 1e6}
        for name in graphs
    }
    floor = out[_FLOOR]
    for row in out.values():
        row["linearize_x_floor"] = row["linearize_us"] / floor["linearize_us"]
        row["error_x_floor"] = row["error_us"] / floor["error_us"]
    return out


def bench_preintegration(repeat: int = 5, n_samples: int = 20000) -> float:
    """µs per ``WheelGyroPreintegration.integrate`` call (minimum of ``repeat``)."""
    dts = [0.01] * n_samples
    ws = [0.3 * math.sin(0.01 * k) for k in range(n_samples)]

    def run():
        p = WheelGyroPreintegration(0.0, keep_samples=False)
        integ = p.integrate
        for dt, w in zip(dts, ws, strict=True):
            integ(dt, 1.0, w, 2.5e-3, 1e-4)

    return min(timeit.repeat(run, number=1, repeat=repeat)) / n_samples * 1e6


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    repeat = int(argv[0]) if argv else 7
    res = bench_factors(repeat=repeat)
    w = max(len(k) for k in res)
    print(f"{'factor':<{w}}  {'linearize µs':>12}  {'x floor':>7}  {'error µs':>9}  {'x floor':>7}")
    for name, r in res.items():
        print(
            f"{name:<{w}}  {r['linearize_us']:12.2f}  {r['linearize_x_floor']:7.2f}  "
            f"{r['error_us']:9.2f}  {r['error_x_floor']:7.2f}"
        )
    print(f"\npreintegration: {bench_preintegration(repeat):.2f} µs per integrate() sample")


if __name__ == "__main__":
    main()
