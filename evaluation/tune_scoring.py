"""The search of ``ddfuse tune`` (``evaluation.tune``): Fisher scoring on the log values within
a trust region and bounds, Levenberg-Marquardt damped, with the BHHH step beside it; the
per-innovation gradients, the information they give and the pairs of estimates it does not
tell apart. Pure math on arrays; the estimator runs are the caller's (``values_at``,
``derivs_at``)."""

from __future__ import annotations

import numpy as np

PAIR_CORRELATION = 0.9  # |correlation| of two estimates beyond which the pair is reported
AT_BOUND = 0.01  # a log value this close to a bound is at it
MAX_ITER = 12  # iterations of one pass of the search (each 3 + p runs, p the free values)
SHORT = 1.0 / 3.0  # the shortened scoring step, a fraction of the full one
TRUST_START = 1.5  # the first step's largest change of a log value (a factor 4.5)
TRUST_MAX = 3.0  # the trust radius on the log values never grows beyond this
STOP_STEP = 0.01  # the search stops when a step changes no value by more than 1 %
STOP_NLL = 1.0  # ... or no step predicts a decrease of L of this (nats: gate flips
# make L rough by about as much)


def jacobian(base: np.ndarray, bumped: list[np.ndarray], step: float) -> np.ndarray | None:
    """Per innovation, the gradient of its term of L in the log values, J (N x n), from the
    terms at the values (``base``, (N,)) and with value i's log moved by ``step``
    (``bumped[i]``, (N,)): J[k, i] = (bumped[i][k] - base[k]) / step. None when a run logged a
    different number of innovations (e.g. a lock-out that one value set triggered)."""
    if any(len(b) != len(base) for b in bumped):
        return None
    if not bumped:
        return np.zeros((len(base), 0))
    return np.stack([(b - base) / step for b in bumped], axis=1)


def information(base: np.ndarray, bumped: list[np.ndarray], step: float) -> np.ndarray | None:
    """The information on the log values, J' J (n x n; :func:`jacobian`'s J), None where
    :func:`jacobian` is."""
    J = jacobian(base, bumped, step)
    return None if J is None else J.T @ J


def scoring(values_at, derivs_at, x: np.ndarray, f: float, J: np.ndarray,
             F: np.ndarray | None, lo: np.ndarray, hi: np.ndarray, say
             ) -> tuple[np.ndarray, float, np.ndarray, int, str]:
    """Minimise L from log values ``x`` with L = ``f``, the per-innovation gradient ``J``
    (N x n) and the Fisher information's factor ``F`` (N x n, or None) there, within [``lo``,
    ``hi``]. ``values_at(xs)``: L at each of the points xs (run in parallel);
    ``derivs_at(x)``: (J, F) at x (None, None where a run logged other innovations).

    Each iteration takes Levenberg-Marquardt damped steps, (H + mu diag(H)) d = -J' 1:
    scoring (H = F'F, the expected information through the innovations' covariances), a
    third of it, and BHHH (H = J'J, the outer product of the scores); each capped at the
    trust radius and projected onto the bounds. They are run (in parallel) and the lowest L
    taken when it is
    lower than here, then its p derivative runs; else the radius shrinks and mu grows. Scoring
    is the better step where the covariances carry the information (noise values far off: the
    scores' outer product is then inflated by the misfit and BHHH creeps), BHHH where the
    innovations' means do (process noise that moves the estimate). Stops when no step changes
    a value by STOP_STEP (relative), no step predicts a decrease of L of STOP_NLL
    (not on a small accepted decrease: a short BHHH step lowers L a little far from the
    optimum too), or after MAX_ITER iterations. Returns the best point, its L and J, the
    accepted iterations and why it stopped."""
    radius, mu, iterations = TRUST_START, 0.0, 0
    for tried in range(MAX_ITER):
        g = J.sum(axis=0)
        # scoring's step, a third of it (values that share innovations make F'F nearly
        # singular and the full step overshoots along that direction), and BHHH's
        steps = [_step(F.T @ F, g, mu, x, lo, hi, radius)] if F is not None else []
        steps += [x + SHORT * (steps[0] - x)] if steps else []
        steps += [_step(J.T @ J, g, mu, x, lo, hi, radius)]
        # the largest decrease of L a quadratic model predicts at its optimum, 0.5 g' H^-1 g,
        # undamped and uncapped (a radius shrunk by rough L must not read as convergence);
        # the largest of the two models' (pinv of a nearly singular F'F can point across g)
        predicted = max(0.5 * float(g @ np.linalg.pinv(H) @ g) for H in
                        ([F.T @ F] if F is not None else []) + [J.T @ J])
        cands = []
        for xn in steps:
            moved = float(np.max(np.abs(xn - x))) if len(x) else 0.0
            if moved >= STOP_STEP and not any(np.allclose(xn, c) for c, _ in cands):
                cands.append((xn, moved))
        if not cands:
            return x, f, J, iterations, (f"converged: the step changes no value by more than "
                                         f"{100 * STOP_STEP:g} %")
        if predicted < STOP_NLL:
            return x, f, J, iterations, (f"converged: no step would lower L by more than "
                                         f"{predicted:.3g} (under {STOP_NLL:g})")
        fs = values_at([c for c, _ in cands])
        say("maximum likelihood", min((tried + 1) / MAX_ITER, 0.99))
        best = int(np.argmin(fs))
        xn, moved = cands[best]
        Jn, Fn = derivs_at(xn) if fs[best] < f else (None, None)
        if Jn is not None:
            iterations += 1
            x, J, F, f = xn, Jn, Fn, fs[best]
            radius, mu = min(2.0 * max(radius, moved), TRUST_MAX), mu / 4.0
        else:
            radius, mu = 0.25 * max(m for _, m in cands), max(4.0 * mu, 1e-3)
    return x, f, J, iterations, f"stopped after {MAX_ITER} iterations"


def _step(H: np.ndarray, g: np.ndarray, mu: float, x: np.ndarray, lo: np.ndarray,
          hi: np.ndarray, radius: float) -> np.ndarray:
    """The damped step from ``x`` for curvature ``H`` and gradient ``g``: a value at a bound
    that the step pushes further out stays there; the largest change capped at ``radius``;
    the result projected onto [``lo``, ``hi``]."""
    d = _damped_step(H, g, mu)
    out = ((x - lo < AT_BOUND) & (d < 0)) | ((hi - x < AT_BOUND) & (d > 0))
    if out.any():
        keep = ~out
        d = np.zeros_like(d)
        if keep.any():
            d[keep] = _damped_step(H[np.ix_(keep, keep)], g[keep], mu)
    big = float(np.max(np.abs(d))) if len(d) else 0.0
    if big > radius:
        d *= radius / big
    return np.clip(x + d, lo, hi)


def _damped_step(H: np.ndarray, g: np.ndarray, mu: float) -> np.ndarray:
    """The Levenberg-Marquardt step -(H + mu diag(H))^-1 g (pseudo-inverse: a singular H)."""
    A = H + mu * np.diag(np.diag(H))
    return -np.linalg.pinv(A) @ g


def correlated_pairs(cov: np.ndarray, labels: list[str],
                     threshold: float = PAIR_CORRELATION) -> list[tuple[str, str, float]]:
    """The pairs of estimates whose correlation in ``cov`` (the inverse of the information,
    n x n, in ``labels``' order) is beyond ``threshold`` in magnitude: (label a, label b,
    correlation), the values the data do not tell apart."""
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(d, d)
    return [(labels[a], labels[b], float(corr[a, b])) for a in range(len(labels))
            for b in range(a + 1, len(labels)) if abs(corr[a, b]) > threshold]
