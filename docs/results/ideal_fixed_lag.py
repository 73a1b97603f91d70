"""The smoother's lagged output against the ideal fixed-lag estimate, on one simulated seed.

For every ``every``-th keyframe k: Levenberg-Marquardt over every factor of the run whose keys
are all no later than the newest keyframe the smoother had when k left its window (stamps up
to t_k + lag), i.e. the optimum of exactly the data the lagged output has seen. Prints the
RMS position error against the simulation's truth at those keyframes of that optimum, of
ISAM2's lagged output, of the EKF (interpolated to the keyframe stamps) and of the whole-run
batch, and the largest |lagged - ideal| error difference. About 1 min per 400 s seed.

    PYTHONPATH=. python docs/results/ideal_fixed_lag.py husky 8 [every]   # from the repo root

(docs/results/smoother_monte_carlo.md, session 8; the same property on the sample bag is
``tests/test_smoother.py::test_lagged_estimate_is_the_optimum_of_the_data_it_has_left_with``.)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import gtsam
import numpy as np
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.runner import initial_pose, run
from ddfuse.evaluation import estimators as registry
from ddfuse.evaluation.montecarlo import draw_truth
from ddfuse.evaluation.simulate import get_scenario, simulate, write_bag


def main(scenario: str, seed: int, every: int = 20) -> None:
    sc, err0 = draw_truth(get_scenario(scenario, None), seed)
    sim = simulate(sc, seed=seed)
    with tempfile.TemporaryDirectory() as d:
        bag, cfg_path, _ = write_bag(sim, Path(d) / "s.bag")
        cfg = load_config(cfg_path)
        stream = read_stream(bag, cfg)
    pose = initial_pose(cfg.initial_pose, stream)
    pose = (pose[0] + err0[0], pose[1] + err0[1], pose[2] + err0[2])
    lag = cfg.smoother.lag
    names = registry.select(cfg, ["ekf", "smoother", "smoother_lagged", "batch"])
    built = {n: registry.SPECS[n].build(cfg, stream, pose, lag) for n in names}
    runs = run(stream, built, output_rate=10.0).runs
    b = built["batch"]  # keeps every factor of the run, and the stamp of every keyframe
    stamp = {int(b.key(j)): t for j, t in b.all_kf_t.items()}
    graph = b.all_graph
    factors = [graph.at(i) for i in range(graph.size())]
    keyframes = sorted(b.all_kf_t.items(), key=lambda kv: kv[1])
    t_kf = np.array([t for _, t in keyframes])
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(30)
    params.setRelativeErrorTol(1e-8)

    def error(tr, t, truth):
        xy = (np.interp(t, tr.t, tr.pose[:, 0]), np.interp(t, tr.t, tr.pose[:, 1]))
        return float(np.hypot(*(np.array(xy) - truth)))

    rows = []
    for j, t_k in keyframes[5::every]:
        if t_kf[-1] <= t_k + lag:
            break
        t_cut = t_kf[t_kf <= t_k + lag + 1e-9][-1]
        sub, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for f in factors:
            if f is not None and all(stamp.get(int(k), -np.inf) <= t_cut + 1e-9
                                     for k in f.keys()):  # noqa: SIM118 (a gtsam factor)
                sub.add(f)
        for key, t in stamp.items():
            if t <= t_cut + 1e-9:
                values.insert(key, b.all_values.atVector(key))
        x = gtsam.LevenbergMarquardtOptimizer(sub, values, params).optimize().atVector(b.key(j))
        tx, ty, *_ = sim.truth.at(np.atleast_1d(np.clip(t_k - sim.t0, 0.0, sim.duration)))
        truth = np.array([tx[0], ty[0]])
        rows.append((float(np.hypot(*(x[:2] - truth))),
                     *(error(runs[n].trajectory, t_k, truth)
                       for n in ("smoother_lagged", "ekf", "batch"))))
    r = np.array(rows)
    rms = np.sqrt((r ** 2).mean(axis=0))
    print(f"{scenario} seed {seed}: {len(r)} keyframes, RMS ideal {rms[0]:.4f} lagged "
          f"{rms[1]:.4f} ekf {rms[2]:.4f} batch {rms[3]:.4f} m; max |lagged - ideal| "
          f"{np.abs(r[:, 1] - r[:, 0]).max():.4f} m")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), *(int(a) for a in sys.argv[3:4]))
