"""Seed 002's published simulator and filter, as its code wrote them, with each defect switchable.

Seed 002 (the blog post in ../shared/seeds) reports "an average RMS error of 3.45 units" with 20
landmarks; ddfuse's known-map landmark EKF gets about 0.1 m on the same setup (the
``seed002-blog`` scenario). This module re-implements what the post's code (its run.py,
robotcar.py and kalman_filter.py, 2015) computes, from its equations, so that the figure can be
reproduced and the difference taken apart one defect at a time (docs/results/seed002_blog.md).
It is a reproduction for that comparison, not an estimator: ddfuse's estimator for this sensor
set is ``ekf_baseline.landmark.LandmarkEkf``.

The world (units read as metres, seconds, radians): each 0.1 s step both wheel rim speeds are
drawn uniformly in 5-15 m/s, the body moves by an explicit Euler step (v = (l + r)/2,
w = (r - l)/2, track 2 m); the encoders add N(0, 0.4^2) m/s to each wheel; 20 landmarks lie
uniformly in +-300 m, and after each step the range finder sights every one, range with
N(0, 0.4^2) m and bearing with N(0, 0.4^2) rad. The run lasts 120 s (1200 steps).

The filter as written (``BlogOptions()``, every switch at the code's behaviour):
- ``global_bearing``: the simulated bearing is atan((ly - y)/(lx - x)), the direction of the
  landmark in the world frame folded into (-pi/2, pi/2), while the filter predicts
  atan(...) - theta: the innovation holds the heading estimate itself, and no angle is wrapped.
- ``odometry_heading``: the prediction moves along the heading integrated from the encoders
  alone (the code's theta_odom), not along the filter's heading; that heading is never corrected.
- ``stated_noise``: R = 0.5 I and Q = 0.1 I (the code's values) instead of the simulated
  variances (range and bearing 0.16; the odometry's v and w 0.08 each).
- ``augmented``: 40 landmark states, started at 0 with unit variance and updated by the
  sightings although h uses the true landmark positions; P0's position block
  [[0.16, 1], [1, 0.16]] is not positive definite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STEP_S = 0.1
TRACK_M = 2.0
STEPS = 1200
LANDMARKS = 20
AREA_M = 300.0
NOISE = 0.4  # m/s (each wheel), m (range), rad (bearing): the code's one value for all three


@dataclass(frozen=True)
class BlogOptions:
    """Which of the published code's defects to keep (True: as the code does)."""

    global_bearing: bool = True
    odometry_heading: bool = True
    stated_noise: bool = True
    augmented: bool = True


@dataclass(frozen=True)
class BlogRun:
    """One run: the post's figure ``mean_error_m`` (the mean of the position error's norm over
    the steps, which the post calls the average RMS error) and the RMS of the same errors (m)."""

    mean_error_m: float
    rmse_m: float
    final_error_m: float


def run_blog(seed: int, options: BlogOptions = BlogOptions(), steps: int = STEPS) -> BlogRun:
    """Simulate and filter one run as the published code does, with ``options``' defects."""
    rng = np.random.default_rng(seed)
    marks = rng.uniform(-AREA_M, AREA_M, size=(LANDMARKS, 2))
    wheels = rng.uniform(5.0, 15.0, size=(steps, 2))
    odo_noise = NOISE * rng.standard_normal((steps, 2))
    sight_noise = NOISE * rng.standard_normal((steps, LANDMARKS, 2))

    n = 3 + 2 * LANDMARKS if options.augmented else 3
    x = np.zeros(n)
    p = np.eye(n)
    if options.augmented:
        p[:2, :2] = [[NOISE**2, 1.0], [1.0, NOISE**2]]
    else:
        p[:3, :3] = np.diag([NOISE**2, NOISE**2, 1.0])
    var_vw = NOISE**2 / 2.0, 2.0 * NOISE**2 / TRACK_M**2  # of v and w from the wheel noise
    q = np.diag([0.1, 0.1]) if options.stated_noise else np.diag(var_vw)
    r = 0.5 * np.eye(2) if options.stated_noise else NOISE**2 * np.eye(2)

    true = np.zeros(3)
    theta_odo = 0.0
    err = np.empty(steps)
    for k in range(steps):
        left, right = wheels[k]
        v, w = 0.5 * (left + right), (right - left) / TRACK_M
        true = true + STEP_S * np.array([v * math.cos(true[2]), v * math.sin(true[2]), w])
        lm, rm = left + odo_noise[k, 0], right + odo_noise[k, 1]
        v_o, w_o = 0.5 * (lm + rm), (rm - lm) / TRACK_M
        theta_odo += w_o * STEP_S
        heading = theta_odo if options.odometry_heading else x[2]
        x[:3] += STEP_S * np.array([v_o * math.cos(heading), v_o * math.sin(heading), w_o])
        a = np.eye(n)
        a[0, 2] = -v_o * STEP_S * math.sin(heading)
        a[1, 2] = v_o * STEP_S * math.cos(heading)
        g = np.zeros((n, 2))
        g[:3] = [[-STEP_S * math.cos(heading), 0.0], [-STEP_S * math.sin(heading), 0.0],
                 [0.0, -STEP_S]]
        p = a @ p @ a.T + g @ q @ g.T
        for j, (lx, ly) in enumerate(marks):
            x, p = _sight(x, p, r, true, lx, ly, j, sight_noise[k, j], options)
        err[k] = math.hypot(x[0] - true[0], x[1] - true[1])
    return BlogRun(mean_error_m=float(err.mean()), rmse_m=float(np.sqrt(np.mean(err**2))),
                   final_error_m=float(err[-1]))


def _sight(x, p, r, true, lx, ly, j, noise, options: BlogOptions):
    """One landmark's range/bearing update, as the code does it or corrected."""
    n = len(x)
    rng_true = math.hypot(lx - true[0], ly - true[1])
    dx, dy = x[0] - lx, x[1] - ly
    rng_est = math.hypot(dx, dy)
    if options.global_bearing:
        z_b = math.atan((ly - true[1]) / (lx - true[0])) + noise[1]
        h_b = math.atan(dy / dx) - x[2]
        y_b = z_b - h_b
    else:
        z_b = math.atan2(ly - true[1], lx - true[0]) - true[2] + noise[1]
        h_b = math.atan2(-dy, -dx) - x[2]
        y_b = math.remainder(z_b - h_b, 2.0 * math.pi)
    innov = np.array([rng_true + noise[0] - rng_est, y_b])
    h = np.zeros((2, n))
    ga, gb = dx / rng_est, dy / rng_est
    gc, gd = -dy / rng_est**2, dx / rng_est**2
    h[:, :3] = [[ga, gb, 0.0], [gc, gd, -1.0]]
    if options.augmented:
        h[:, 3 + 2 * j: 5 + 2 * j] = [[-ga, -gb], [-gc, -gd]]
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    return x + k @ innov, (np.eye(n) - k @ h) @ p


def blog_table(seeds: range, options: dict[str, BlogOptions]) -> dict[str, dict[str, float]]:
    """Per named option set: the mean over ``seeds`` of the post's figure and of the RMSE (m),
    and the median and maximum of the post's figure across the seeds."""
    out = {}
    for name, opt in options.items():
        runs = [run_blog(s, opt) for s in seeds]
        figs = np.array([r.mean_error_m for r in runs])
        out[name] = {"mean_error_m": float(figs.mean()), "median_error_m": float(np.median(figs)),
                     "max_error_m": float(figs.max()),
                     "rmse_m": float(np.mean([r.rmse_m for r in runs]))}
    return out
