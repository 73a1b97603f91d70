"""The smoother's window: gtsam's ``IncrementalFixedLagSmoother`` with the keyframes it holds,
the factors and values waiting for its next update, the newest keyframe's estimate and
marginal, and the lagged output (each keyframe as it leaves the window).

Keys: ``Window.key(k)`` is ``x<k>``, one 9-vector state per keyframe (``ddfuse.factors.state``;
``[x, y, psi, v, w, bg, hoff, k_v, k_w]`` in m, m, rad, m/s, rad/s, rad/s, rad, 1, 1, world
frame ENU); keyframe stamps in s of data time. With ``keep_all`` (the batch) every factor,
value and stamp of the run is kept too.
"""

from __future__ import annotations

import gtsam
import numpy as np
from ddfuse.estimation.estimator import Estimate, wrap_angle
from ddfuse.estimation.runner import TrackBuilder
from ddfuse.estimation.smoother.isam2 import RELINEARIZE_SKIP, isam2_params
from ddfuse.factors.state import DIM, KV, NAMES


class Window:
    """The fixed-lag window of ``lag`` s and what waits to enter it."""

    def __init__(self, lag: float, *, keep_all: bool, lagged: bool,
                 relinearize_skip: int = RELINEARIZE_SKIP) -> None:
        self.lag, self.keep_all, self.lagged = lag, keep_all, lagged
        self.track = TrackBuilder()  # lagged output, compact: (t, pose, pose cov) per keyframe
        self.relinearize_skip = relinearize_skip  # ISAM2's (``isam2.relinearize_skip``)
        self.isam = gtsam.IncrementalFixedLagSmoother(self.lag, isam2_params(relinearize_skip))
        self.k = -1  # index of the newest keyframe
        self.kf_t: dict[int, float] = {}  # keyframes in the window
        self.all_kf_t: dict[int, float] = {}  # every keyframe of the run (keep_all only)
        self.kf_state: np.ndarray | None = None  # newest keyframe's estimate
        self.kf_cov: np.ndarray | None = None  # its 3x3 pose marginal (world frame)
        self.full: np.ndarray | None = None  # newest keyframe's (DIM, DIM) marginal
        self.full_k = -1  # the keyframe whose marginal ``full`` is (behind k after a new one)
        self.skip_in_batch: int | None = None  # pending factor the batch leaves out (widen)
        self.pending_graph = gtsam.NonlinearFactorGraph()
        self.pending_values = gtsam.Values()
        self.pending_stamps: dict[int, float] = {}
        self.scale_belief: tuple[np.ndarray, np.ndarray] | None = None  # (k_v, k_w), 2x2 cov
        # (first keyframe index, m^2): position variance outside gtsam from that keyframe on,
        # cumulative (a restart after a gap with nothing measuring the position; add_gauge)
        self.gauge: list[tuple[int, float]] = []
        if keep_all:
            self.all_graph = gtsam.NonlinearFactorGraph()
            self.all_values = gtsam.Values()

    @staticmethod
    def key(k: int) -> int:
        return gtsam.symbol("x", k)

    def add(self, f) -> None:
        self.pending_graph.add(f)

    def new_keyframe(self, t: float, guess: np.ndarray) -> int:
        """A keyframe after the newest at ``t`` with initial value ``guess``; returns its
        index (its factors are the caller's)."""
        j = self.k + 1
        kj = self.key(j)
        self.pending_values.insert(kj, guess)
        self.pending_stamps[kj] = t
        self.kf_t[j] = t
        if self.keep_all:  # only the batch needs every stamp; the window's are in kf_t
            self.all_kf_t[j] = t
        self.k = j
        return j

    def first_keyframe(self, t: float, x0: np.ndarray, cov0: np.ndarray) -> None:
        """A new first keyframe at ``t`` with prior ``x0``, ``cov0`` (DIM, DIM). Keys stay unique
        across re-initialisations (the batch keeps them all)."""
        key = self.key(self.k + 1)
        self.add(gtsam.PriorFactorVector(key, x0, gtsam.noiseModel.Gaussian.Covariance(cov0)))
        self.new_keyframe(t, x0)
        self.kf_state = x0
        self.kf_cov = cov0[:3, :3].copy()
        self.full, self.full_k = cov0, self.k

    def link_keyframe(self, q: np.ndarray, batch_sigma: float | None) -> int:
        """A keyframe at the newest's stamp and value, tied to it by a zero-mean link with
        covariance ``q`` (DIM, DIM): its marginal is the newest's widened by ``q`` (a gate
        lock-out's recovery). The batch ties the two by ``batch_sigma`` instead: the robot did
        not jump, the filter was lost; with ``batch_sigma`` None it keeps ``q`` too (a stated
        start taken for wrong: the whole run cannot leave the start's prior, what comes after
        the link can). Only the new keyframe is output. Returns its index."""
        x, full = self.kf_state, self.full
        i, t = self.k, self.kf_t[self.k]
        j = self.k = i + 1
        if self.keep_all and batch_sigma is not None:
            self.all_graph.add(gtsam.BetweenFactorVector(
                self.key(i), self.key(j), np.zeros(DIM),
                gtsam.noiseModel.Isotropic.Sigma(DIM, batch_sigma)))
            self.skip_in_batch = self.pending_graph.size()
        self.add(gtsam.BetweenFactorVector(self.key(i), self.key(j), np.zeros(DIM),
                                           gtsam.noiseModel.Gaussian.Covariance(q)))
        self.pending_values.insert(self.key(j), np.asarray(x, dtype=float))
        self.pending_stamps[self.key(j)] = t
        del self.kf_t[i]  # the same instant as j: only j is output
        self.kf_t[j] = t
        if self.keep_all:
            del self.all_kf_t[i]
            self.all_kf_t[j] = t
        self.kf_cov = full[:3, :3] + q[:3, :3]
        self.full, self.full_k = full + q, j
        return j

    def newest_marginal(self) -> np.ndarray:
        """The newest keyframe's marginal (DIM, DIM) as far as it is known: gtsam's after an
        update; between a new keyframe and its update the composed pose covariance with the
        previous keyframe's twist and calibration blocks (cross terms with the pose left out)."""
        full = self.full
        if self.full_k == self.k and full is not None and full.shape == (DIM, DIM):
            return full
        out = np.zeros((DIM, DIM))
        if full is not None and full.shape == (DIM, DIM):
            out[3:, 3:] = full[3:, 3:]
        out[:3, :3] = self.kf_cov
        return out

    def flush(self) -> str | None:
        """Send the pending factors and values to gtsam and capture what leaves the window.
        Returns gtsam's error message when the update failed (the pending factors are dropped;
        the caller re-initialises), else None."""
        if self.pending_graph.size() == 0 and self.pending_values.size() == 0:
            return None
        if self.keep_all:
            if self.skip_in_batch is None:
                self.all_graph.push_back(self.pending_graph)
            else:  # the widening link of a lock-out recovery is the smoother's alone
                for f in range(self.pending_graph.size()):
                    if f != self.skip_in_batch:
                        self.all_graph.add(self.pending_graph.at(f))
                self.skip_in_batch = None
            self.all_values.insert(self.pending_values)
        t_max = max(self.pending_stamps.values(), default=self.kf_t[self.k])
        self.capture_leaving(t_max - self.lag)
        try:
            self.isam.update(self.pending_graph, self.pending_values, self.pending_stamps)
        except RuntimeError as e:
            return str(e)
        finally:
            self.pending_graph = gtsam.NonlinearFactorGraph()
            self.pending_values = gtsam.Values()
            self.pending_stamps = {}
        key = self.key(self.k)
        self.kf_state = self.isam.calculateEstimateVector(key)
        full = self.full = self.isam.marginalCovariance(key)
        self.full_k = self.k
        self.kf_cov = full[:3, :3]
        self.scale_belief = (self.kf_state[KV:].copy(), full[KV:, KV:].copy())
        return None

    def estimate_of(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ``k``'s estimate and (DIM, DIM) marginal from gtsam; raises RuntimeError,
        IndexError or ValueError when it is not (or no longer) in the smoother."""
        key = self.key(k)
        return self.isam.calculateEstimateVector(key), self.isam.marginalCovariance(key)

    def capture_leaving(self, t_cut: float, newest: bool = False) -> None:
        """Output the window's keyframes older than ``t_cut`` (s) as lagged estimates and drop
        them from ``kf_t``; the newest keyframe too only when ``newest`` (the run's end)."""
        leaving = [j for j, tj in self.kf_t.items() if tj < t_cut and (newest or j != self.k)]
        for j in sorted(leaving):
            if not self.lagged and j != self.k:  # the newest still gives final_state
                del self.kf_t[j]
                continue
            key = self.key(j)
            try:
                x = self.isam.calculateEstimateVector(key)
                cov = self.with_gauge(j, self.isam.marginalCovariance(key))
            except (RuntimeError, IndexError, ValueError):
                del self.kf_t[j]
                continue
            self.track.append(Estimate(
                self.kf_t[j], (float(x[0]), float(x[1]), wrap_angle(float(x[2]))),
                cov[:3, :3].copy(), x.copy(), cov.copy(), NAMES))
            del self.kf_t[j]

    def add_gauge(self, first: int, var: float) -> None:
        """From keyframe ``first`` on, every output's position carries ``var`` (m^2) more
        variance than gtsam's marginal: an unobserved offset of the whole window, the grown
        uncertainty of a restart after a gap that no sensor measures (docs/design/gaps.md)."""
        self.gauge.append((first, self.gauge_var(first) + var))

    def gauge_var(self, j: int) -> float:
        """The position variance (m^2) keyframe ``j``'s outputs add to gtsam's marginal."""
        return next((v for first, v in reversed(self.gauge) if first <= j), 0.0)

    def gauge_vars(self, js: np.ndarray) -> np.ndarray:
        """``gauge_var`` of each keyframe index in ``js`` (m^2), shape of ``js``."""
        js = np.asarray(js)
        if not self.gauge:
            return np.zeros(js.shape)
        firsts = np.array([first for first, _ in self.gauge])
        var = np.array([0.0] + [v for _, v in self.gauge])
        # the last entry whose first <= j: gauge firsts are appended in increasing order
        return var[np.searchsorted(firsts, js, side="right")]

    def with_gauge(self, j: int, cov: np.ndarray) -> np.ndarray:
        """``cov`` (pose first: x, y) with keyframe ``j``'s gauge variance on x and y (a copy
        when there is one, else ``cov`` itself)."""
        g = self.gauge_var(j) if self.gauge else 0.0
        if g == 0.0:
            return cov
        cov = cov.copy()
        cov[0, 0] += g
        cov[1, 1] += g
        return cov

    def restart(self) -> None:
        """An empty smoother and window (what was pending is dropped)."""
        self.isam = gtsam.IncrementalFixedLagSmoother(self.lag,
                                                      isam2_params(self.relinearize_skip))
        self.kf_t = {}
        self.pending_graph = gtsam.NonlinearFactorGraph()
        self.pending_values = gtsam.Values()
        self.pending_stamps = {}
        self.skip_in_batch = None
