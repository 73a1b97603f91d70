"""Harness for the scripts of this directory (imported, not run): simulate a seed exactly as
`ddfuse.evaluation.montecarlo.run_seed` does, run estimators (possibly modified ones) message by
message, and record per-tick states plus the true GPS error.

The project's code is only imported (the repo root is put on sys.path), never modified.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))  # the repo root

from ddfuse.estimation.measurements import GpsFix  # noqa: E402
from ddfuse.evaluation import estimators as registry  # noqa: E402
from ddfuse.evaluation.montecarlo import seed_data  # noqa: E402

RATE = 10.0


def make_seed(scenario: str, seed: int, duration=None):
    """(sim, cfg, stream, pose) as run_seed builds them (the same draws)."""
    sim, cfg, stream, pose, _ = seed_data(scenario, seed, duration)
    return sim, cfg, stream, pose


def build(cfg, stream, pose, names):
    return registry.build(cfg, stream, names, pose=pose)


def feed(stream, ests: dict, rate=RATE, record_gps=False):
    """Feed every measurement; record at each 1/rate tick: t, pose (3), the state vector with
    names, and the pose covariance. Returns {name: dict of arrays}."""
    period = 1.0 / rate
    rec = {n: {"t": [], "pose": [], "state": [], "cov": [], "names": None} for n in ests}
    gpsrec = {n: [] for n in ests}
    t_next = None
    wall = {n: 0.0 for n in ests}
    for m in stream.measurements:
        if t_next is None:
            t_next = math.floor(m.t / period) * period + period
        while m.t >= t_next:
            for n, e in ests.items():
                est = e.estimate()
                if est is None:
                    continue
                r = rec[n]
                r["t"].append(est.t)
                r["pose"].append(est.pose)
                if est.state is not None:
                    r["state"].append(np.asarray(est.state, float).copy())
                    r["names"] = est.state_names
                r["cov"].append(np.asarray(est.pose_cov, float).copy()
                                if est.pose_cov is not None else np.full((3, 3), np.nan))
            t_next += period
        for n, e in ests.items():
            if record_gps and isinstance(m, GpsFix):
                pre = e.estimate()
            c = time.perf_counter()
            e.process(m)
            wall[n] += time.perf_counter() - c
            if record_gps and isinstance(m, GpsFix):
                post = e.estimate()
                if pre is not None and post is not None:
                    gpsrec[n].append((m.t, pre.pose, post.pose, pre.t, post.t))
    for e in ests.values():
        e.finish()
    out = {}
    for n, r in rec.items():
        d = {"t": np.array(r["t"]), "pose": np.array(r["pose"]), "cov": np.array(r["cov"]),
             "names": r["names"], "wall": wall[n]}
        d["state"] = np.array(r["state"]) if r["state"] else None
        d["gps"] = gpsrec[n]
        out[n] = d
    return out, ests


def truth_at(sim, t_abs):
    t_rel = np.clip(np.asarray(t_abs) - sim.t0, 0.0, sim.duration)
    x, y, yaw, _, _ = sim.truth.at(t_rel)
    return np.column_stack([x, y, yaw])


def gps_error_at(sim, t_abs):
    """The true horizontal GPS error (east, north; fix - truth at the sampling time) of the
    simulation, as a function of time (linear interpolation between fixes; at the *sampling*
    time, t_abs - sim.t0)."""
    g = sim.gps
    tt = np.asarray(g.t_measured)
    err = np.asarray(g.enu)[:, :2] - np.asarray(g.true_enu)[:, :2]
    t_rel = np.asarray(t_abs) - sim.t0
    return np.column_stack([np.interp(t_rel, tt, err[:, 0]), np.interp(t_rel, tt, err[:, 1])])


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
