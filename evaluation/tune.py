"""Noise values from the data: maximum likelihood of one EKF's innovations (the prediction-error
method). Pure math and estimator runs; no printing (``ddfuse tune``: evaluation/cli/tune.py).

For values theta (``evaluation.tune_params``: standard deviations and process noise densities,
searched as their natural logs), one run of the tuning estimator over the stream gives every
innovation nu_k and its covariance S_k; the objective is their negative log-likelihood

    L(theta) = sum_k 0.5 (log det S_k + min(nu_k' S_k^-1 nu_k, c_k)),

c_k the chi-square(dim) 0.9999 quantile, the default gate: a gate-rejected innovation costs as
much as one at the gate, so one gross outlier does not set a noise value, and a too small value
gains nothing by having the gate reject what it cannot explain. L is minimised with L-BFGS-B
within bounds (a factor ``BOUND`` either side of the start), its gradient by forward differences
in log space, the runs of a gradient in parallel (a process pool over the cores). The tuning
estimator is the unicycle ``ekf`` (compiled, 0.4 s over rl_husky_gps.bag's 395 s), or
``ekf_landmark`` when the config has landmarks (the unicycle EKF does not fuse them). GPS fixes
of a hold-out are withheld from the runs, so from the fit.

Identifiability: the outer product of the per-innovation gradients (J' J, the Fisher
information's estimate from the scores, J from the same differences) says how much the data
inform each value: a value with under ``MIN_INFORMATION`` (about ``MIN_INFORMATION`` / 2
innovations' worth of information on its log, a standard error of 0.16 on it) at the start is
left at the config's value, said with the reason; at the optimum, pairs whose estimates are
correlated beyond ``PAIR_CORRELATION`` in the inverse are reported, and each value's standard
error. Design and figures: docs/design/tuning.md.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from ddfuse.estimation import chi2
from ddfuse.estimation.config import Config
from ddfuse.estimation.estimator import InnovationLog
from ddfuse.estimation.measurements import Stream
from ddfuse.estimation.runner import run
from ddfuse.evaluation.consistency import InnovationTable, SensorNis, nis_by_sensor
from ddfuse.evaluation.estimators import build
from ddfuse.evaluation.tune_params import Applier, Param, parameters
from scipy.optimize import minimize

GATE_P = 0.9999  # the innovations' NIS is clipped at this chi-square quantile
BOUND = 100.0  # the search stays within start / BOUND .. start * BOUND
STEP = 0.02  # forward-difference step on the log of a value (2 %: gate flips make L rough)
MIN_INFORMATION = 40.0  # Fisher information on a log value below which the data do not inform it
PAIR_CORRELATION = 0.9  # |correlation| of two estimates beyond which the pair is reported
AT_BOUND = 0.01  # a log value this close to a bound is at it
MAX_ITER = 40
MAX_FUN = 30  # objective evaluations (each one run per free value + 1) the search may take
FTOL = 1e-6  # relative change of L at which the search stops


def tuning_estimator(cfg: Config) -> str:
    """The estimator whose innovations are fitted: ``ekf_landmark`` with landmarks, else ``ekf``."""
    return "ekf_landmark" if cfg.of_kind("landmarks") else "ekf"


@dataclass
class Problem:
    """One bag's tuning problem: the config and stream (changed in place by each evaluation),
    the parameters, the estimator and the GPS hold-out spec."""

    cfg: Config
    stream: Stream
    params: list[Param]
    estimator: str
    holdout: str | None = None

    def __post_init__(self) -> None:
        self.applier = Applier(self.cfg, self.stream, self.params)

    def run(self, values: list[float | None]):
        """The tuning estimator run over the stream with ``values``: (estimator, RunResult)."""
        self.applier.apply(values)
        est = build(self.cfg, self.stream, [self.estimator])[self.estimator]
        est.log.innovations = InnovationLog(keep=1 << 40)  # every S kept for the likelihood
        result = run(self.stream, {self.estimator: est}, output_rate=0.2, holdout=self.holdout)
        return est, result

    def terms(self, values: list[float | None]) -> np.ndarray:
        """Each innovation's term of L (module docstring), in log order; a term whose S is not
        positive definite or whose NIS is not finite is 0."""
        est, _ = self.run(values)
        h = est.log.innovations.held_log_det()
        dims = np.array([d for _, _, d in h["groups"]] or [1])[h["group"]]
        clip = np.array([chi2.ppf(GATE_P, int(d)) for d in range(1, 5)])[np.clip(dims, 1, 4) - 1]
        t = 0.5 * (h["log_det"] + np.minimum(h["nis"], clip))
        t[~np.isfinite(t)] = 0.0
        return t


_WORKER: Problem | None = None


def _init_worker(problem: Problem) -> None:
    global _WORKER
    _WORKER = problem


def _worker_terms(values: list[float | None]) -> np.ndarray:
    return _WORKER.terms(values)


class Evaluator:
    """Runs ``Problem.terms`` for many value sets, on ``jobs`` processes (forked: each has the
    stream as read), counting the runs."""

    def __init__(self, problem: Problem, jobs: int) -> None:
        self.problem, self.jobs, self.runs = problem, jobs, 0
        self.pool = None
        if jobs > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            problem.terms([None] * len(problem.params))  # kernels loaded before the fork
            self.runs += 1
            self.pool = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork"),
                                            initializer=_init_worker, initargs=(problem,))

    def many(self, value_sets: list[list[float | None]]) -> list[np.ndarray]:
        self.runs += len(value_sets)
        if self.pool is None:
            return [self.problem.terms(v) for v in value_sets]
        return list(self.pool.map(_worker_terms, value_sets))

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None


@dataclass
class Tuned:
    """One parameter's outcome. ``value`` is the tuned value (SI), or None where it was left as
    the config had it (``status`` 'not informed'); ``status``: 'tuned', 'not informed',
    'at lower bound', 'at upper bound'; ``reason`` in words; ``se_log``: the standard error of
    its log (a relative standard error, to first order), None when not computed."""

    param: Param
    value: float | None
    status: str
    reason: str = ""
    se_log: float | None = None
    information: float | None = None


@dataclass
class TuneResult:
    """What :func:`tune` found: per parameter a :class:`Tuned`, the pairs the data do not tell
    apart (labels and the correlation of their estimates), the objective at the start and the
    end, how many estimator runs it took and how long (s)."""

    estimator: str
    tuned: list[Tuned]
    pairs: list[tuple[str, str, float]] = field(default_factory=list)
    nll_start: float = math.nan
    nll_end: float = math.nan
    innovations: int = 0
    runs: int = 0
    iterations: int = 0
    wall_s: float = 0.0
    message: str = ""

    def values(self) -> list[float | None]:
        return [t.value for t in self.tuned]


def information(base: np.ndarray, bumped: list[np.ndarray], step: float) -> np.ndarray | None:
    """The information on the log values, J' J (n x n), from the innovations' terms of L at the
    values (``base``, (N,)) and with value i's log moved by ``step`` (``bumped[i]``, (N,)):
    J[k, i] = (bumped[i][k] - base[k]) / step. None when a run logged a different number of
    innovations (e.g. a lock-out that one value set triggered)."""
    if any(len(b) != len(base) for b in bumped):
        return None
    J = np.stack([(b - base) / step for b in bumped], axis=1)
    return J.T @ J


def tune(cfg: Config, stream: Stream, *, holdout: str | None = None,
         estimator: str | None = None, jobs: int | None = None,
         start: dict[str, float] | None = None,
         progress: Callable[[str, float], None] | None = None) -> TuneResult:
    """Tune the noise values of ``cfg`` on ``stream`` (module docstring). ``cfg`` and the
    stream's variances are changed while it runs and left as the config had them. ``start``:
    labels or keys of parameters -> the value to start from instead of the config's (tests,
    and the measurements of docs/design/tuning.md start 3x off). ``jobs``: processes (default:
    the cores). ``progress(stage, fraction)`` is called as it goes."""
    t_start = time.perf_counter()
    params = parameters(cfg, stream)
    for p in params:
        if start and (p.key in start or p.label in start):
            p.start = float(start.get(p.key, start.get(p.label)))
    name = estimator or tuning_estimator(cfg)
    problem = Problem(cfg, stream, params, name, holdout)
    jobs = jobs or min(2, os.cpu_count() or 1)
    ev = Evaluator(problem, jobs)
    try:
        return _search(problem, ev, progress, t_start)
    finally:
        ev.close()
        problem.applier.apply([None] * len(params))


def _search(problem: Problem, ev: Evaluator, progress, t_start: float) -> TuneResult:
    params = problem.params
    n = len(params)
    x0 = np.log([p.start for p in params])
    say = progress or (lambda stage, f: None)
    say("information at the start", 0.0)
    runs = ev.many([list(np.exp(x0))] + [list(np.exp(x0 + STEP * e)) for e in np.eye(n)])
    base0 = runs[0]
    info0 = information(base0, runs[1:], STEP)
    free = np.ones(n, bool)
    tuned: list[Tuned | None] = [None] * n
    if info0 is not None:
        for i, p in enumerate(params):
            if info0[i, i] < MIN_INFORMATION:
                free[i] = False
                tuned[i] = Tuned(p, p.before, "not informed",
                                 _uninformed_reason(p, info0[i, i], "at the start"),
                                 information=float(info0[i, i]))
    idx = np.flatnonzero(free)
    fixed_values = [p.before for p in params]  # the config's (None: the messages' / default)
    n_terms = max(len(base0), 1)
    cache: dict[tuple, tuple[float, np.ndarray]] = {}
    last: dict = {}
    it = [0]

    def full(xf: np.ndarray) -> list[float | None]:
        vals = list(fixed_values)
        for k, i in enumerate(idx):
            vals[i] = float(np.exp(xf[k]))
        return vals

    def fun(xf: np.ndarray):
        key = tuple(np.round(xf, 12))
        if key in cache:
            return cache[key]
        sets = [full(xf)] + [full(xf + STEP * e) for e in np.eye(len(idx))]
        res = ev.many(sets)
        f = float(res[0].sum())
        g = np.array([(float(r.sum()) - f) / STEP for r in res[1:]])
        last.update(x=xf.copy(), base=res[0], bumped=res[1:], f=f)
        cache[key] = out = (f / n_terms, g / n_terms)
        return out

    def step_done(_xk) -> None:
        it[0] += 1
        say("maximum likelihood", min(it[0] / MAX_ITER, 0.99))

    lo, hi = x0[idx] - math.log(BOUND), x0[idx] + math.log(BOUND)
    message = "nothing to tune: no value is informed by the data"
    nll0 = float(base0.sum())
    if len(idx):
        say("maximum likelihood", 0.0)
        opt = minimize(fun, x0[idx], jac=True, method="L-BFGS-B",
                       bounds=list(zip(lo, hi, strict=True)), callback=step_done,
                       options={"maxiter": MAX_ITER, "maxfun": MAX_FUN, "ftol": FTOL,
                                "gtol": 1e-6})
        message = str(opt.message)
        xs = opt.x
        if last.get("x") is None or not np.allclose(last["x"], xs):
            fun(xs)
        info = information(last["base"], last["bumped"], STEP)
        cov = np.linalg.pinv(info) if info is not None else None
        for k, i in enumerate(idx):
            p = params[i]
            se = float(math.sqrt(max(cov[k, k], 0.0))) if cov is not None else None
            status, reason = "tuned", ""
            if info is not None and info[k, k] < MIN_INFORMATION:
                # informed at the start, not where the search ended (a value whose effect
                # another one's took over): the data do not fix it, the config's stands
                tuned[i] = Tuned(p, p.before, "not informed",
                                 _uninformed_reason(p, info[k, k], "at the optimum"), se,
                                 float(info[k, k]))
                continue
            if xs[k] - lo[k] < AT_BOUND:
                status, reason = "at lower bound", (f"at the search's lower bound (start / "
                                                    f"{BOUND:g}): the data want it smaller")
            elif hi[k] - xs[k] < AT_BOUND:
                status, reason = "at upper bound", (f"at the search's upper bound (start x "
                                                    f"{BOUND:g}): the data want it larger")
            tuned[i] = Tuned(p, float(np.exp(xs[k])), status, reason, se,
                             float(info[k, k]) if info is not None else None)
        pairs = correlated_pairs(cov, [params[i].label for i in idx]) if cov is not None \
            else []
        nll1 = last["f"]
        iterations = int(opt.nit)
    else:
        pairs, nll1, iterations = [], nll0, 0
    say("maximum likelihood", 1.0)
    return TuneResult(problem.estimator, tuned, pairs, nll0, nll1, len(base0), ev.runs,
                      iterations, time.perf_counter() - t_start, message)


def correlated_pairs(cov: np.ndarray, labels: list[str],
                     threshold: float = PAIR_CORRELATION) -> list[tuple[str, str, float]]:
    """The pairs of estimates whose correlation in ``cov`` (the inverse of the information,
    n x n, in ``labels``' order) is beyond ``threshold`` in magnitude: (label a, label b,
    correlation), the values the data do not tell apart."""
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(d, d)
    return [(labels[a], labels[b], float(corr[a, b])) for a in range(len(labels))
            for b in range(a + 1, len(labels)) if abs(corr[a, b]) > threshold]


def _uninformed_reason(p: Param, info: float, where: str) -> str:
    """Why the data leave ``p`` as it was, in words."""
    what = {"slip": "the motion the robot's twist does not explain",
            "walk": "how the calibration drifts"}.get(p.kind, f"{p.sensor}'s {p.noise_key}")
    return (f"the data do not inform it (information {info:.3g} on its log {where}, under "
            f"{MIN_INFORMATION:g}: too few innovations that depend on {what}: a bag too "
            "short or too static, or no sensor that sees it); left as the config has it")


@dataclass
class Check:
    """One run of an estimator with a set of values: NIS per 'sensor kind' and, with a GPS
    hold-out, its score (m)."""

    nis: dict[str, SensorNis]
    holdout_rmse_m: float | None


def check(cfg: Config, stream: Stream, values: list[float | None], *, estimator: str,
          holdout: str | None = None, params: list[Param] | None = None) -> Check:
    """Run ``estimator`` over ``stream`` with ``values`` for ``params`` (default: the config's
    parameters) and score it: the before / after columns of ``ddfuse tune``'s table. The config
    and stream are left as the config has them."""
    from ddfuse.evaluation.pipeline import score

    params = params if params is not None else parameters(cfg, stream)
    problem = Problem(cfg, stream, params, estimator, holdout)
    try:
        est, result = problem.run(values)
        nis = nis_by_sensor(InnovationTable.from_innovations(est.log.innovations))
        summary = score(result, cfg=cfg) if holdout else None
    finally:
        problem.applier.apply([None] * len(params))
    rmse = summary.estimators[estimator].gps_holdout_rmse_m if summary else None
    return Check(nis, rmse)
