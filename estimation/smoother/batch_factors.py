"""The batch's whole-run graph with its preintegrated and bias-difference factors evaluated
together with numpy instead of one Python ``CustomFactor`` callback each.

Those two factors are one or two Python callbacks per keyframe interval, and every
linearisation and error evaluation of the batch's Levenberg-Marquardt calls them all; here the
same residuals and Jacobians (``factors.preintegration.preintegrated_factor``,
``factors.gyro.bias_difference_factor``, from the constants they recorded when built) are
computed for every interval at once, whitened by each factor's own noise model, and handed to
gtsam as ``JacobianFactor``s: one per interval, the bias-difference row (keyframe j) stacked
under the preintegrated rows (i, j). The other factors (C++ ones, and any other CustomFactor)
stay a ``NonlinearFactorGraph`` that gtsam linearises. ``linearize`` and ``error`` have the
``NonlinearFactorGraph`` contract that ``batch_lm.levenberg_marquardt`` uses.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.preintegration import RECORD_FIELDS
from ddfuse.factors.state import BG, DIM, KV, KW

_F = {name: i for i, name in enumerate(RECORD_FIELDS)}


class VectorisedGraph:
    """``graph`` (the batch's ``all_graph``) with the recorded factors it holds evaluated with
    numpy. ``record``: what ``preintegrated_factor(record=)`` (3-tuples) and
    ``bias_difference_factor(record=)`` (2-tuples) appended. A recorded factor that is not in
    ``graph`` (dropped before it reached the batch) is ignored; one with a noise model other
    than a plain Gaussian (e.g. robust) stays a CustomFactor."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, record: list) -> None:
        preintegrated = [r for r in record if len(r) == 3]
        bias = [r for r in record if len(r) == 2]
        # pybind11 hands back the Python object of a factor that is still referenced, and the
        # records hold them: identity tells the recorded factors in the graph apart
        pre = {id(f): (f, model, c) for f, model, c in preintegrated
               if type(model) in (gtsam.noiseModel.Gaussian, gtsam.noiseModel.Diagonal,
                                  gtsam.noiseModel.Isotropic, gtsam.noiseModel.Unit)}
        bia = {id(f): (f, c) for f, c in bias}
        self.rest = gtsam.NonlinearFactorGraph()
        p_rows, b_rows = [], []
        for n in range(graph.size()):
            f = graph.at(n)
            if id(f) in pre:
                p_rows.append(pre[id(f)])
            elif id(f) in bia:
                b_rows.append(bia[id(f)])
            else:
                self.rest.add(f)
        self.n_vectorised = len(p_rows) + len(b_rows)
        keys_i = [int(f.keys()[0]) for f, _, _ in p_rows]
        keys_j = [int(f.keys()[1]) for f, _, _ in p_rows]
        keys_b = [int(f.keys()[0]) for f, _ in b_rows]
        self.keys = sorted(set(keys_i) | set(keys_j) | set(keys_b))
        index = {k: n for n, k in enumerate(self.keys)}
        self.ii = np.array([index[k] for k in keys_i], dtype=int)
        self.ij = np.array([index[k] for k in keys_j], dtype=int)
        self.ib = np.array([index[k] for k in keys_b], dtype=int)
        self.keys_i, self.keys_j = keys_i, keys_j
        c = np.array([row[2] for row in p_rows], dtype=float).reshape(-1, len(RECORD_FIELDS))
        self.c = {name: c[:, i] for name, i in _F.items()}
        self.r = np.array([model.R() for _, model, _ in p_rows]).reshape(-1, DIM, DIM)
        self.bc = np.array([row[1] for row in b_rows], dtype=float).reshape(-1, 4)
        # the constant parts of the unwhitened Jacobians (the callbacks' hi, hj buffers)
        n_p = len(p_rows)
        hi = np.zeros((n_p, DIM, DIM))
        hi[:, 2, 2] = -1.0
        hi[:, 0, BG], hi[:, 1, BG], hi[:, 2, BG] = -c[:, _F["jx"]], -c[:, _F["jy"]], -c[:, _F["jp"]]
        hi[:, 0, KV], hi[:, 1, KV] = -c[:, _F["vx"]], -c[:, _F["vy"]]
        hi[:, 0, KW], hi[:, 1, KW], hi[:, 2, KW] = -c[:, _F["wx"]], -c[:, _F["wy"]], -c[:, _F["wp"]]
        for r in range(5, DIM):
            hi[:, r, r] = -1.0
        hj = np.broadcast_to(np.eye(DIM), (n_p, DIM, DIM)).copy()
        hj[:, 4, BG] = c[:, _F["zg"]]
        hj[:, 3, KV] = -c[:, _F["zv"]]
        hj[:, 4, KW] = -c[:, _F["zo"]]
        self.hi, self.hj = hi, hj
        # a bias-difference row joins the interval ending at its keyframe (one factor); the
        # others stand alone
        end = {k: m for m, k in enumerate(keys_j)}
        join = np.array([end.get(k, -1) for k in keys_b], dtype=int)
        self.joined = np.full(n_p, -1, dtype=int)  # interval -> its bias row, or -1
        self.joined[join[join >= 0]] = np.flatnonzero(join >= 0)
        self.lone = np.flatnonzero(join < 0)
        self.keys_lone = [keys_b[n] for n in self.lone]
        self.unit = {d: gtsam.noiseModel.Unit.Create(d) for d in (1, DIM, DIM + 1)}

    def _states(self, values: gtsam.Values) -> np.ndarray:
        at = values.atVector
        return np.array([at(k) for k in self.keys]).reshape(-1, DIM)

    def _preintegrated(self, x: np.ndarray, jacobians: bool):
        """Unwhitened residuals (n, 9) and, with ``jacobians``, (H_i, H_j) (n, 9, 9) each."""
        c = self.c
        xi, xj = x[self.ii], x[self.ij]
        db = xi[:, BG] - c["bl"]
        dv = xi[:, KV] - c["kvl"]
        dw = xi[:, KW] - c["kwl"]
        dx = xj[:, 0] - xi[:, 0]
        dy = xj[:, 1] - xi[:, 1]
        cp, sp = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        u0 = cp * dx + sp * dy
        u1 = cp * dy - sp * dx
        e = np.empty((len(db), DIM))
        e[:, 0] = u0 - c["ddx"] - c["jx"] * db - c["vx"] * dv - c["wx"] * dw
        e[:, 1] = u1 - c["ddy"] - c["jy"] * db - c["vy"] * dv - c["wy"] * dw
        e[:, 2] = np.remainder(xj[:, 2] - xi[:, 2] - c["ddp"] - c["jp"] * db - c["wp"] * dw
                               + math.pi, 2.0 * math.pi) - math.pi
        e[:, 3] = xj[:, 3] - xj[:, KV] * c["zv"]
        e[:, 4] = xj[:, 4] + c["zg"] * xj[:, BG] - c["zw"] - xj[:, KW] * c["zo"]
        e[:, 5] = xj[:, BG] - xi[:, BG]
        e[:, 6] = np.remainder(xj[:, 6] - xi[:, 6] + math.pi, 2.0 * math.pi) - math.pi
        e[:, 7] = xj[:, KV] - xi[:, KV]
        e[:, 8] = xj[:, KW] - xi[:, KW]
        if not jacobians:
            return e, None
        hi, hj = self.hi, self.hj
        hi[:, 0, 0], hi[:, 0, 1], hi[:, 0, 2] = -cp, -sp, u1
        hi[:, 1, 0], hi[:, 1, 1], hi[:, 1, 2] = sp, -cp, -u0
        hj[:, 0, 0], hj[:, 0, 1] = cp, sp
        hj[:, 1, 0], hj[:, 1, 1] = -sp, cp
        return e, (hi, hj)

    def _bias(self, x: np.ndarray, jacobians: bool):
        """Whitened residuals (n,) and, with ``jacobians``, their (n, 9) rows (unit model)."""
        zg, zo, vg, vo = self.bc.T
        s = x[self.ib]
        k = s[:, KW]
        r = s[:, BG] + k * zo - zg
        var = vg + k * k * vo
        sd = np.sqrt(var)
        if not jacobians:
            return r / sd, None
        h = np.zeros((len(r), DIM))
        h[:, BG] = 1.0 / sd
        h[:, KW] = zo / sd - r * k * vo / (var * sd)
        return r / sd, h

    def whitened(self, x: np.ndarray):
        """At the states ``x`` (n_keys, 9) in ``keys`` order: the intervals' whitened Jacobians
        ``ai``, ``aj`` (n, 9, 9) and right-hand sides ``b`` (n, 9) (linear rows ``ai dx_i + aj
        dx_j = b``), and the bias rows' whitened Jacobians ``hb`` (m, 9) and residuals ``eb``
        (m,) (rows ``hb dx = -eb``)."""
        e, (hi, hj) = self._preintegrated(x, True)
        b = -(self.r @ e[:, :, None])[:, :, 0]
        eb, hb = self._bias(x, True)
        return self.r @ hi, self.r @ hj, b, hb, eb

    def error_at(self, x: np.ndarray, values: gtsam.Values) -> float:
        """``error`` with the recorded factors' states given: ``x`` (n_keys, 9) in ``keys``
        order, read from ``values``."""
        e, _ = self._preintegrated(x, False)
        w = np.einsum("nab,nb->na", self.r, e)
        eb, _ = self._bias(x, False)
        return 0.5 * float(np.sum(w * w)) + 0.5 * float(np.sum(eb * eb)) + self.rest.error(values)

    def error(self, values: gtsam.Values) -> float:
        """The graph's error at ``values``: half the sum of squared whitened residuals (robust
        losses for the robust factors among the rest), as ``NonlinearFactorGraph.error``."""
        return self.error_at(self._states(values), values)

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The graph linearised at ``values``, as ``NonlinearFactorGraph.linearize``: the rest's
        factors, then one whitened ``JacobianFactor`` per interval (and per lone bias row)."""
        ai, aj, b, hb, eb = self.whitened(self._states(values))
        lin = self.rest.linearize(values)
        push, jf = lin.push_back, gtsam.JacobianFactor
        n_p, has = len(b), self.joined >= 0
        rows = self.joined[has]
        ai10 = np.zeros((n_p, DIM + 1, DIM))
        ai10[:, :DIM] = ai
        aj10 = np.zeros((n_p, DIM + 1, DIM))
        aj10[:, :DIM] = aj
        aj10[has, DIM] = hb[rows]
        b10 = np.zeros((n_p, DIM + 1))
        b10[:, :DIM] = b
        b10[has, DIM] = -eb[rows]
        ki, kj, u9, u10 = self.keys_i, self.keys_j, self.unit[DIM], self.unit[DIM + 1]
        for m, joined in enumerate(has.tolist()):
            if joined:
                push(jf(ki[m], ai10[m], kj[m], aj10[m], b10[m], u10))
            else:
                push(jf(ki[m], ai[m], kj[m], aj[m], b[m], u9))
        for n, k in zip(self.lone.tolist(), self.keys_lone, strict=True):
            push(jf(k, hb[n][None, :], np.array([-eb[n]]), self.unit[1]))
        return lin
