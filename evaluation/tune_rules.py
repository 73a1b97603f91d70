"""The values ``ddfuse tune`` sets by a rule beside the likelihood (``evaluation.tune``): a
landmark sensor's correlation time from its sightings' neighbour scatter, the heavy-tailed
speed walk's burst share and an IMU yaw's correlation time measured before the search, and an
odometry input the landmark EKF's likelihood leaves to the slip, from its own samples."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.measurements import Stream
from ddfuse.evaluation.tune_inputs import Scatter, input_series, sample_scatter
from ddfuse.evaluation.tune_params import Param
from ddfuse.evaluation.tune_result import Tuned, TuneResult

if TYPE_CHECKING:
    from ddfuse.evaluation.tune import Problem

CORR_GAP = 1.0  # s: a sighting whose neighbours (same landmark) are this close is scattered


def sighting_scatter(problem: Problem, sensor: str, sigma: float) -> float | None:
    """The correlation time (s) that ``estimation.gps_scatter``'s rule gives for ``sensor``'s
    landmark bearings of standard deviation ``sigma`` (rad): each sighting against the time
    interpolation of the previous and next sightings of the same landmark, both within
    ``CORR_GAP`` s (the robot's motion between them is smooth at that spacing, as a GPS track's
    is between fixes), the miss's robust RMS (1.4826 MAD: a bearing jump where the robot turns
    fast is not scatter); None without 10 such sightings or when the miss is not under
    ``gps_scatter.CORRELATED_SCATTER`` of what white errors of ``sigma`` give."""
    from ddfuse.estimation.gps_scatter import CORRELATED_SCATTER, scatter_correlation_time
    from ddfuse.estimation.measurements import LandmarkObservation

    by: dict[str, list] = {}
    for m in problem.stream.measurements:
        if type(m) is LandmarkObservation and m.sensor == sensor and m.has_bearing:
            by.setdefault(m.landmark_id, []).append(m)
    miss, gaps = [], []
    for ms in by.values():
        t = np.array([m.t for m in ms])
        z = np.unwrap(np.array([m.bearing for m in ms]))
        a, b = t[1:-1] - t[:-2], t[2:] - t[1:-1]
        ok = (a > 0.0) & (b > 0.0) & (a <= CORR_GAP) & (b <= CORR_GAP)
        w = np.where(ok, a / np.where(ok, a + b, 1.0), 0.0)
        miss.append((z[1:-1] - (z[:-2] + w * (z[2:] - z[:-2])))[ok])
        gaps.append(0.5 * (a + b)[ok])
    e = np.concatenate(miss) if miss else np.zeros(0)
    if len(e) < 10:
        return None
    rms = 1.4826 * float(np.median(np.abs(e - np.median(e))))
    if rms >= CORRELATED_SCATTER * math.sqrt(1.5) * sigma:  # gps_scatter's threshold
        return None
    return scatter_correlation_time(rms, sigma, float(np.median(np.concatenate(gaps))))


def held_inputs(params: list[Param], stream: Stream, result: TuneResult
                ) -> dict[int, Scatter]:
    """For the odometry-driven ``ekf_landmark``: each odometry input (wheel speeds, odometry v
    and yaw rate) that ``result`` left 'not informed', by parameter index, with what its own
    samples show (``evaluation.tune_inputs``); where they give its noise, the parameter is
    held there for the search again. The input's noise and the robot's slip are both process
    noise there, so where the slip took the input's effect the search left the input as the
    config had it, beside a slip that already explains the drift: the two counted it twice
    (docs/design/tuning.md). An input the likelihood fixed, in a reported pair or not, keeps
    that."""
    out = {}
    for i, (p, t) in enumerate(zip(params, result.tuned, strict=True)):
        if p.kind in ("wheels", "odometry") and t.status == "not informed":
            out[i] = sample_scatter(input_series(stream, p.sensor, p.noise_key))
            if out[i].sigma is not None:
                p.start, p.held = out[i].sigma, True
    return out


def inputs_outcome(result: TuneResult, held: dict[int, Scatter]) -> None:
    """The outcome of the inputs :func:`held_inputs` looked at: tuned at what their samples
    gave, else the reason they did not, added to why the likelihood left them."""
    for i, sc in held.items():
        t = result.tuned[i]
        if sc.sigma is not None:
            result.tuned[i] = Tuned(t.param, sc.sigma, "tuned", (
                f"{sc.reason}: an odometry input's noise and the robot's slip are both process "
                f"noise of {result.estimator}, which the innovations do not tell apart (the "
                "search left it not informed; evaluation.tune_inputs); held there while the "
                "search fitted the rest again"),
                sc.se_log)
        elif t.status == "not informed":
            t.reason = f"{t.reason}; nor do its own samples: {sc.reason}"


def correlation(problem: Problem, result: TuneResult) -> None:
    """Each landmark sensor's correlation time in ``result``: :func:`sighting_scatter` at the
    bearing sigma the search found, rounded to 0.1 s (0 where the sightings scatter as white
    ones). Set after the search, not in it: the search run again with the new time drives the
    bearing sigma down (the likelihood keeps R in S while the fusion inflates it, so a small R
    fits the bursts' small innovations without the filter following them): measured on
    mrclam1_robot1.bag, 0.0268 -> 0.0022 rad with the time back at 0 after two rounds."""
    for k, t in enumerate(result.tuned):
        p = t.param
        if p.kind != "corr":
            continue
        if not p.key.startswith("sensors.landmarks") and p.noise_key == "correlation_time":
            # a heading sensor's: measured before the search (tune_params)
            result.tuned[k] = _heading_tau(problem, p)
            continue
        if p.noise_key == "burst_share":
            _burst_share(result, k)
            continue
        # with a common part: the independent model's sigma (the first stage's): the rule
        # compares a landmark's own track's scatter with white errors of the sightings' whole
        # sigma; the second stage's own sigma leaves the frame's part out, and at it the rule
        # read the bearings as white on mrclam1_robot1.bag (docs/design/tuning.md, session 22)
        sigma = result.corr_sigma.get(p.sensor) or bearing_sigma(result, p.sensor, "bearing")
        tau = round(sighting_scatter(problem, p.sensor, sigma) or 0.0, 1) if sigma else 0.0
        if tau == p.before:
            result.tuned[k] = Tuned(p, None, "not informed", (
                "the sightings' neighbour scatter at the tuned bearing sigma gives the same "
                "(evaluation.tune_rules.sighting_scatter); left as the config has it"))
            continue
        result.tuned[k] = Tuned(p, tau, "tuned", (
            f"from each landmark's own sightings' neighbour scatter at the tuned bearing sigma "
            f"{sigma:.3g} rad (evaluation.tune_rules.sighting_scatter, gps_scatter's rule); "
            "set after the search, which ran with the config's"))


def _burst_share(result: TuneResult, k: int) -> None:
    """The outcome of the heavy-tailed speed walk's burst share, ``result.tuned[k]``: the
    share measured before the search (``tune_params``), kept where the search tuned both of
    the walk's densities; else the walk stays Gaussian, the burst density put back too (a
    burst without its steady walk, or a share without its burst, is no config)."""
    p = result.tuned[k].param
    tw = {u.param.noise_key: i for i, u in enumerate(result.tuned)
          if u.param.kind == "twist" and u.param.key.startswith("robot.")}
    if all(key in tw and result.tuned[tw[key]].value is not None
           for key in ("speed", "speed_burst")):
        result.tuned[k] = Tuned(p, p.start, "tuned", (
            "the share of the speed's sample-to-sample changes beyond 4 robust sigmas "
            "(evaluation.tune_params.speed_tails); measured before the search, which ran with "
            "it"))
        return
    why = "the speed walk's densities were not both tuned: the walk stays Gaussian"
    result.tuned[k] = Tuned(p, None, "not informed", why)
    if "speed_burst" in tw:
        b = result.tuned[tw["speed_burst"]]
        result.tuned[tw["speed_burst"]] = Tuned(b.param, None, "not informed", why)


def bearing_sigma(result: TuneResult, sensor: str, key: str) -> float | None:
    """The tuned (else the starting) value of ``sensor``'s noise ``key``; None without one."""
    t = next((u for u in result.tuned if u.param.sensor == sensor and
              u.param.noise_key == key), None)
    if t is None:
        return None
    return t.value if t.value is not None else t.param.start


def _heading_tau(problem: Problem, p) -> Tuned:
    """The outcome of IMU yaw correlation time ``p``: what ``evaluation.compass_correlation``
    measured (the search ran with it), or the config's with the reason it was not."""
    from ddfuse.evaluation.compass_correlation import measure

    if p.source == "measured":
        return Tuned(p, p.start, "tuned", (
            "the yaw's error against the gyro's integral, a Gauss-Markov fit "
            "(evaluation.compass_correlation); measured before the search, which ran with it"))
    fit = measure(problem.cfg, problem.stream, p.sensor)
    why = fit.reason if fit is not None else "no gyro to measure it against"
    return Tuned(p, None, "not informed", f"{why}; left as the config has it")


def drifting_heading_caveat(problem: Problem, result: TuneResult) -> None:
    """Say, on each heading-offset walk ``result`` tuned, when the heading sensor's error against
    the gyro's integral wanders faster at long lags than that walk states
    (``compass_correlation.drifts``): the likelihood of the samples one by one fits their
    shortest scale, not the drift over a GPS outage (docs/design/tuning.md, Limits)."""
    from ddfuse.evaluation.compass_correlation import DRIFT_RATIO, drifts, measure

    for t in result.tuned:
        p = t.param
        if p.noise_key != "heading_offset_walk" or t.value is None or \
                t.status == "not informed":
            continue
        fit = measure(problem.cfg, problem.stream, p.sensor)
        if fit is None or not drifts(fit.wander) or t.value * DRIFT_RATIO > fit.wander[1]:
            continue
        short, long_, lag = fit.wander
        note = (f"the yaw's error against the gyro's integral wanders at {long_:.2g} "
                f"rad/sqrt(s) over {lag:.0f} s and at {short:.2g} from one sample to the next, "
                "faster than one walk: the value fits the samples' scale, not the heading's "
                "drift over a GPS outage (docs/design/tuning.md, Limits)")
        t.reason = f"{t.reason}; {note}" if t.reason else note


def correlated_gps_caveat(cfg: Config, result: TuneResult) -> None:
    """Say, on each GPS sigma ``result`` tuned for a sensor whose config states a correlation
    time, that it is not the fixes' stationary sigma: the likelihood takes the innovations as
    white, which the estimators' inflation model does not make them (docs/design/tuning.md,
    Limits)."""
    for t in result.tuned:
        p = t.param
        if p.kind != "gps" or p.noise_key != "horizontal" or t.value is None or \
                t.status == "not informed":
            continue
        tau = cfg.sensor(p.sensor).correlation_time
        if tau > 0.0:
            note = (f"the config states errors correlated over {tau:g} s, which the likelihood "
                    "takes as white innovations: the value fits the fixes' short-term scatter, "
                    "below their stationary sigma (simulated, 30 s: half of it; "
                    "docs/design/tuning.md, Limits)")
            t.reason = f"{t.reason}; {note}" if t.reason else note

