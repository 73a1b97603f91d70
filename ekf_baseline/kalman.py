"""The Kalman core every filter in ``ekf_baseline`` uses: predict, gated Joseph-form update, and
recovery from a gate lock-out.

API (all arrays are float64 numpy; n = state size, m = measurement size)::

    kf = KalmanCore(x0, P0, log, state_angles=(2,))      # x0 (n,), P0 (n, n), EstimatorLog
    kf.predict(F, Q, x_pred=None)                         # F (n, n), Q (n, n); x_pred = f(x) (n,)
    ok = kf.update(t, sensor, kind, z, hx, H, R,          # z, hx (m,); H (m, n); R (m, m)
                   angles=(0,), gate=0.9999)              # -> True if the update was applied
    n_ok = kf.update_blocks(t, z, hx, H, R, blocks)       # stacked measurements, each gated
                                                          # and logged on its own; blocks are
                                                          # (sensor, kind, start, stop, angles,
                                                          #  gate) -> number accepted
    kf.update_blocks(t, z, hx, H, R, blocks,              # per block, the factor on its R in
                     fuse=(1.0, 150.0))
    kf.last_verdicts                                      # the update (not the gate); then
                                                          # per block: fused?
    kf.x, kf.P                                            # current mean and covariance

* ``predict`` propagates the covariance P <- F P F^T + Q and the mean to ``x_pred`` (the EKF's
  nonlinear f(x), computed by the caller) or, for a linear model, to F x.
* ``update`` forms the innovation y = z - h(x) (components listed in ``angles`` are wrapped to
  [-pi, pi)), its covariance S = H P H^T + R and the NIS y^T S^-1 y. With ``gate`` (the sensor's
  chi-square acceptance probability from its config, None = no gate) the update is rejected when
  NIS > chi2.ppf(gate, m). Every update, accepted or rejected, is appended to ``log.innovations``
  as an :class:`ddfuse.estimation.estimator.Innovation`; a rejection also counts in
  ``log.rejected[(sensor, 'gate')]``. An accepted update applies the gain K = P H^T S^-1 and the
  Joseph form P <- (I - K H) P (I - K H)^T + K R K^T (stays symmetric PSD even with the rounding
  of K), both ``ddfuse.ekf_baseline.joseph``'s, the functions the compiled kernels compile too
  (docs/design/ekf_kernels.md; on a cold numba cache under ``ddfuse run``, ``joseph_numpy``'s
  twins: ``update_functions``); state components in ``state_angles`` are wrapped after every
  predict and update.
* Non-finite z or h(x), or an S that is not positive definite, are rejected with reason
  'nonfinite' / 'singular' and never touch the state.
* ``fuse`` (update_blocks; default None = all 1): per block a factor f >= 1 on its noise in
  the gain and Joseph update only (a time-correlated GPS fix, ``estimation.gps_correlation``);
  the rule: R_ij between rows of accepted blocks a and b becomes sqrt(f_a f_b) R_ij, which within
  a block is exactly f_a R_ij. The gate, the log and a recovery keep R. Then ``last_verdicts``
  says per block whether it was fused.

``robust`` maps a (sensor, kind) to a model that replaces its gate (the EKFs' robust GPS model,
``ddfuse.ekf_baseline.gps_robust``: ``judge(t, y, S, R) -> (verdict, f, outlier)``): a block it
excludes is logged not accepted; one it fuses has its R multiplied by f (with ``fuse``'s
factor); an outlier it fuses down-weighted is logged not accepted all the same and counted as
``(sensor, 'outlier')``; on its RECOVER P is inflated as on a lock-out (below) and the block
fused.

Gate lock-out (docs/design/ekf_gate_lockout.md): when one (sensor, kind) has had at least
``lockout_count`` consecutive gate rejections spanning at least ``lockout_time`` s
(``ddfuse.estimation.lockout``), the core either finds the filter corroborated on the states
that measurement observes by other accepted measurements (the sensor is the outlier: nothing
changes; see ``CORROBORATED_BY``) or recovers: P is inflated by the smallest factor that makes
the innovation ordinary (NIS = m), the measurement applied, and a recovery that does not take
makes the next one wait ``recovery_holdoff`` s, doubling. ``recoveries`` lists (t, sensor,
alpha); each is noted in ``log`` and counted in ``log.rejected[(sensor, 'lockout_recovery')]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import numpy as np
from ddfuse.ekf_baseline import joseph, joseph_numpy
from ddfuse.estimation import chi2
from ddfuse.estimation.config import DEFAULT_LOCKOUT_COUNT, DEFAULT_LOCKOUT_TIME
from ddfuse.estimation.estimator import EstimatorLog, Innovation
from ddfuse.estimation.lockout import (
    DEFAULT_RECOVERY_HOLDOFF,
    gate_streak,
    holdoff_over,
    inflation,
    lockout_due,
)

__all__ = [
    "KalmanCore",
    "chi2_threshold",
    "DEFAULT_LOCKOUT_COUNT",
    "DEFAULT_LOCKOUT_TIME",
    "DEFAULT_RECOVERY_HOLDOFF",
]

_TWO_PI = 2.0 * math.pi
_PI = math.pi

# Measurement kinds whose acceptance during a lock-out of another kind corroborates the filter
# on that kind's states although their H has no column there: position fixes and the heading.
# A track that keeps passing the GPS gate has the heading the filter gives it (the position
# the next fixes see is dead-reckoned along it), so a compass failing its gate meanwhile is
# the outlier (a wrong fixed offset, a magnetic disturbance). By H columns alone, a GPS
# without lever arm or delay never observes the heading: on the sample bag with its GPS delay
# set to 0 and the IMU's heading_offset to 0 (it is 0.35 rad), both EKFs recovered onto the
# compass and ended 2.66 m off (tests/test_compass_corroboration.py). The smoother's compass
# gate uses the same rule.
CORROBORATED_BY = {"heading": frozenset({"gps", "landmark"})}


_cold: list[bool] = []  # the update's entry points were not cached when this process first looked


# each block's factor on R when none is given, shared: apply_update scales R, never fs (not
# made read-only: the compiled entry points are typed for writable arrays)
_ONES = tuple(np.ones(nb) for nb in range(9))


def update_functions() -> tuple[Callable, Callable]:
    """(innovation_cov, apply_update) for a new KalmanCore: ``joseph``'s compiled entry points,
    or, under the "reference" cold-cache policy (``factors.jitcache.on_cold_cache``) in a
    process that found them missing from numba's cache, ``joseph_numpy``'s twins (the same
    estimates to rounding) while the background build compiles them (said on the terminal).
    Under that policy decided once per process, so every filter of a run uses the same
    arithmetic; under "compile" (the library's default) always the compiled ones."""
    from ddfuse.factors.jitcache import on_cold_cache

    if on_cold_cache() == "compile" or (not _cold and joseph.load_cached()):
        return joseph.innovation_cov, joseph.apply_update
    if not _cold:
        from ddfuse.factors.jitcache import build_in_background

        _cold.append(True)
        build_in_background(["joseph"])
    return joseph_numpy.innovation_cov, joseph_numpy.apply_update


@lru_cache(maxsize=256)
def chi2_threshold(prob: float, dof: int) -> float:
    """Chi-square gate threshold: the ``prob`` quantile of chi2 with ``dof`` degrees of freedom.

    Cached per (prob, dof): the quantile costs microseconds, the gate runs per update."""
    return chi2.ppf(prob, dof)


class KalmanCore:
    """Mean ``x`` (n,) and covariance ``P`` (n, n) of a (extended) Kalman filter.

    Units and frames are the caller's; ``state_angles`` lists the indices of angle states (rad)
    that are kept wrapped to [-pi, pi). ``log`` receives innovations, rejections and notes.
    ``lockout_count`` / ``lockout_time`` (s) set the gate lock-out detection and
    ``recovery_holdoff`` (s) the wait before a repeated recovery (module docstring).
    """

    __slots__ = (
        "x", "P", "n", "log", "state_angles", "lockout_count", "lockout_time",
        "recovery_holdoff", "_streak", "_holdoff", "_last_ok", "recoveries", "last_nis",
        "after_inflation", "held_in_recovery", "last_verdicts", "robust", "_innovation_cov",
        "_apply_update",
    )

    def __init__(
        self,
        x0,
        P0,
        log: EstimatorLog | None = None,
        *,
        state_angles: tuple[int, ...] = (),
        lockout_count: int = DEFAULT_LOCKOUT_COUNT,
        lockout_time: float = DEFAULT_LOCKOUT_TIME,
        recovery_holdoff: float = DEFAULT_RECOVERY_HOLDOFF,
    ) -> None:
        self._innovation_cov, self._apply_update = update_functions()
        self.x = np.array(x0, dtype=float).reshape(-1)
        self.n = self.x.shape[0]
        self.P = np.array(P0, dtype=float).reshape(self.n, self.n)
        if not np.allclose(self.P, self.P.T, rtol=0.0, atol=1e-12 * (1.0 + np.abs(self.P).max())):
            raise ValueError("P0 must be symmetric")
        self.log = log if log is not None else EstimatorLog()
        self.state_angles = tuple(state_angles)
        self.lockout_count = int(lockout_count)
        self.lockout_time = float(lockout_time)
        self.recovery_holdoff = float(recovery_holdoff)
        # (sensor, kind) -> (earliest time of the next recovery, hold-off after that one)
        self._holdoff: dict[tuple[str, str], tuple[float, float]] = {}
        # (sensor, kind) -> (time, H, row start, row stop) of its last accepted update
        self._last_ok: dict[tuple[str, str], tuple] = {}
        # (sensor, kind) -> [consecutive gate rejections, time of the first of them]
        self._streak: dict[tuple[str, str], list] = {}
        self.recoveries: list[tuple[float, str, float]] = []
        # called with this core after a recovery's inflation: a filter with redundant states
        # re-ties them there (ddfuse.ekf_baseline.igvc)
        self.after_inflation: Callable[[KalmanCore], None] | None = None
        # states a recovery does not widen (the odometry scales): the smoother's rule
        # (FixedLagSmoother._widen). Widened with the rest, nothing but the motion observes
        # them, so they take up the jump: on a simulated Husky with GPS errors correlated over
        # 30 s, a GPS recovery (x6.6e3) let k_w flip sign, after which every turn locked the
        # odometry's yaw rate out and each recovery inflated more, to x1e12, until P broke.
        self.held_in_recovery: tuple[int, ...] = ()
        self.last_nis = float("nan")
        # per block of the last update given ``fuse``: fused (module docstring)
        self.last_verdicts: tuple[bool, ...] = ()
        # (sensor, kind) -> its robust model (ekf_baseline.gps_robust.EkfRobustGps: judge(t, y,
        # S, R)), which replaces the gate for that measurement
        self.robust: dict = {}
        self._wrap_state()

    # ------------------------------------------------------------------ helpers
    def _wrap_state(self) -> None:
        x = self.x
        for i in self.state_angles:
            x[i] = (x[i] + _PI) % _TWO_PI - _PI

    def _symmetrize(self) -> None:
        P = self.P
        P += P.T
        P *= 0.5

    # ------------------------------------------------------------------ predict
    def predict(self, F: np.ndarray, Q: np.ndarray, x_pred=None) -> None:
        """Time update: P <- F P F^T + Q; x <- ``x_pred`` (nonlinear f(x), n floats) or F x.

        F is the (n, n) transition (Jacobian of f at the prior mean), Q the (n, n) discrete
        process noise covariance of the step."""
        if x_pred is None:
            self.x = F @ self.x
            self._wrap_state()
        else:
            xl = x_pred.tolist() if isinstance(x_pred, np.ndarray) else list(x_pred)
            if len(xl) != self.n:
                raise ValueError(f"x_pred has {len(xl)} components, the state {self.n}")
            for i in self.state_angles:
                xl[i] = (xl[i] + _PI) % _TWO_PI - _PI
            self.x = np.array(xl, dtype=float)
        P = F @ self.P @ F.T
        P += Q
        P += P.T
        P *= 0.5
        self.P = P

    # ------------------------------------------------------------------ update
    def update(
        self,
        t: float,
        sensor: str,
        kind: str,
        z,
        hx,
        H,
        R,
        *,
        angles: tuple[int, ...] = (),
        gate: float | None = None,
    ) -> bool:
        """Measurement update with innovation gate and Joseph-form covariance update.

        ``t`` (s) is the measurement time, ``sensor`` its configured name, ``kind`` the model
        name recorded in the Innovation ('gps', 'v', 'gyro', 'heading', ...). ``z`` and ``hx``
        are the measurement and its prediction h(x), (m,); ``H`` the (m, n) Jacobian of h; ``R``
        the (m, m) measurement covariance. ``angles`` lists the measurement components that are
        angles (their innovation is wrapped). ``gate`` is the chi-square acceptance probability
        (None disables the gate). Returns True when the update was applied."""
        z = np.asarray(z, dtype=float).reshape(-1)
        m = z.shape[0]
        return self.update_blocks(
            t, z, np.asarray(hx, dtype=float).reshape(m),
            np.asarray(H, dtype=float).reshape(m, self.n),
            np.asarray(R, dtype=float).reshape(m, m),
            ((sensor, kind, 0, m, tuple(angles), gate),),
        ) == 1

    def update_blocks(
        self,
        t: float,
        z: np.ndarray,
        hx: np.ndarray,
        H: np.ndarray,
        R: np.ndarray,
        blocks,
        fuse=None,
    ) -> int:
        """One stacked update from several measurements present at the same filter step.

        This is seed 003's piecewise measurement model: ``z``, ``hx`` (m,), ``H`` (m, n) and
        ``R`` (m, m) are assembled from whatever measurements are present. ``blocks`` splits the
        rows by measurement: a sequence of ``(sensor, kind, start, stop, angles, gate)`` with rows
        ``start:stop``, ``angles`` the angle components *relative to start*, ``gate`` the chi-square
        probability or None. Each block is gated on its own (its NIS uses its diagonal block of
        S = H P H^T + R, i.e. the same prior as the others) and logged as its own Innovation;
        the accepted rows are then applied together in one Joseph-form update. Cross-covariance
        between blocks in ``R`` is allowed but dropped with a rejected block. Returns the number
        of accepted blocks. Arrays passed in may be modified. ``fuse``: per block the factor on
        its R in the update (module docstring); then ``last_verdicts`` says which were fused.

        The gain and the Joseph update are ``ddfuse.ekf_baseline.joseph``'s, the functions the
        compiled kernels (``ddfuse.ekf_baseline.kalman_jit``) compile into theirs."""
        y = z - hx
        log = self.log
        for _sensor, _kind, i0, _i1, angles, _gate in blocks:
            for a in angles:
                y[i0 + a] = (y[i0 + a] + _PI) % _TWO_PI - _PI
        H = np.ascontiguousarray(H, dtype=float)
        R = np.ascontiguousarray(R, dtype=float)
        Ut, S = self._innovation_cov(self.P, H, R)
        # gate with python floats: per-block numpy calls would dominate the cost of a step
        yl = y.tolist()
        Sl = S.tolist()
        keep: list[bool] = []
        nis_list: list[float] = []
        recovered = False
        rfac: list[float] | None = None  # per block the robust model's factor on R
        marked: set[int] = set()  # blocks fused down-weighted as outliers: logged not accepted
        for sensor, kind, i0, i1, _angles, gate in blocks:
            nis = _nis_rows(yl, Sl, i0, i1)
            if nis is None or not math.isfinite(nis):
                self._unusable(t, sensor, kind, nis, yl[i0:i1])
                keep.append(False)
                nis_list.append(math.nan)
                continue
            judge = self.robust.get((sensor, kind)) if self.robust else None
            if judge is not None:
                verdict, f, outlier = self._robust(t, judge, sensor, kind, yl, Sl, R, i0, i1)
                self.last_nis = nis
                rejected = verdict == _EXCLUDE
                if not rejected:
                    if verdict == _RB_RECOVER:
                        self._recover(t, sensor, kind, y[i0:i1].copy(), H[i0:i1],
                                      R[i0:i1, i0:i1] * f, robust=True)
                        Ut, S = self._innovation_cov(self.P, H, R)
                        Sl = S.tolist()
                        recovered = True
                    rfac = rfac or [1.0] * len(blocks)
                    rfac[len(keep)] = f
                    if outlier:
                        marked.add(len(keep))
            else:
                verdict = self._judge(t, sensor, kind, nis, gate, i1 - i0, (H, i0, i1))
                if verdict == _RECOVER:
                    self._recover(t, sensor, kind, y[i0:i1].copy(), H[i0:i1], R[i0:i1, i0:i1])
                    Ut, S = self._innovation_cov(self.P, H, R)
                    Sl = S.tolist()  # the blocks after this one are gated with the inflated P too
                    recovered = True
                rejected = verdict == _REJECT
            if rejected:
                log.innovations.append(_FloatInnovation(
                    t, sensor, kind, tuple(yl[i0:i1]), _block_of(Sl, i0, i1), nis, False))
            keep.append(not rejected)
            nis_list.append(nis)
        n_acc = sum(keep)
        if fuse is not None:
            self.last_verdicts = tuple(keep)
        if n_acc == 0:
            return 0
        # the kernels' block table (row start, stop, -, -) and verdicts (0 accepted)
        nb = len(blocks)
        blk = np.array([v for b in blocks for v in (b[2], b[3], 0, 0)], dtype=np.int64)
        rejected = np.array([0 if k else 1 for k in keep], dtype=np.int64)
        if fuse is None and rfac is None:
            fs = _ONES[nb] if nb < len(_ONES) else np.ones(nb)
        else:
            fs = np.ones(nb) if fuse is None else np.array(fuse, dtype=float)
            if rfac is not None:
                fs *= rfac
            R = R.copy()  # apply_update fuses it in place; the caller's may be a constant
        self.P, dx = self._apply_update(self.P, H, np.ascontiguousarray(y, dtype=float), R, Ut, blk,
                                  rejected, fs)
        self.x = self.x + dx
        if self.state_angles:
            self._wrap_state()
        inns = log.innovations
        last_ok = self._last_ok
        for i, ((sensor, kind, i0, i1, _a, _g), k, nis) in enumerate(
                zip(blocks, keep, nis_list, strict=True)):
            if k:
                if recovered:
                    nis = _nis_rows(yl, Sl, i0, i1)
                out = i in marked
                if not out:
                    last_ok[(sensor, kind)] = (t, (H, i0, i1))
                inns.append(_FloatInnovation(t, sensor, kind, tuple(yl[i0:i1]),
                                             _block_of(Sl, i0, i1), nis, not out))
        return n_acc

    # ------------------------------------------------------------------ gate
    def _unusable(self, t: float, sensor: str, kind: str, nis, y) -> None:
        """Count (and note) a block whose NIS cannot be formed: S not positive definite
        ('singular') or a non-finite innovation ('nonfinite')."""
        if nis is None and math.isfinite(sum(y)):
            self.log.rejected[(sensor, "singular")] += 1
            self.log.note(t, f"{sensor}/{kind}: innovation covariance not positive definite")
        else:
            self.log.rejected[(sensor, "nonfinite")] += 1

    def _judge(self, t: float, sensor: str, kind: str, nis: float, gate, m: int, rows) -> int:
        """The gate's verdict on one block with NIS ``nis`` (m dof): _ACCEPT, _REJECT (counted)
        or _RECOVER (a lock-out: the caller inflates P and applies the block). Keeps the
        per-(sensor, kind) rejection streaks; ``rows`` ((H, i0, i1) or sparse rows) give the
        states the block observes, for the corroboration check."""
        self.last_nis = nis
        key = (sensor, kind)
        streak = self._streak.get(key)
        if gate is not None and nis > chi2_threshold(gate, m):
            if streak is None:
                # [consecutive rejections, first of them (s), acceptances since recovery]
                streak = self._streak[key] = [0, t, 0]
            streak[0], streak[1], streak[2] = gate_streak(True, t, streak[0], streak[1],
                                                          streak[2])
            if (
                lockout_due(streak[0], streak[1], t, self.lockout_count, self.lockout_time)
                and self._holdoff_over(t, key, streak)
                and self._lost(t, key, rows, streak)
            ):
                return _RECOVER
            self.log.rejected[(sensor, "gate")] += 1
            return _REJECT
        if streak is not None:
            streak[0], streak[1], streak[2] = gate_streak(False, t, streak[0], streak[1],
                                                          streak[2])
        return _ACCEPT

    def _robust(self, t: float, judge, sensor: str, kind: str, yl: list, Sl: list, R, i0: int,
                i1: int) -> tuple[int, float, bool]:
        """The robust model's verdict on rows i0:i1 (ekf_baseline.gps_robust): (_EXCLUDE,
        _RB_FUSE or _RB_RECOVER, factor on R, outlier?); outliers counted, its notes logged."""
        Rl = R[i0:i1, i0:i1].tolist()
        verdict, f, outlier = judge.judge(t, yl[i0:i1], [r[i0:i1] for r in Sl[i0:i1]], Rl)
        if outlier:
            self.log.rejected[(sensor, "outlier")] += 1
        for tn, text in judge.notes:
            self.log.note(tn, text)
        judge.notes.clear()
        return verdict, f, outlier

    # ------------------------------------------------------------------ recovery
    def _holdoff_over(self, t: float, key: tuple[str, str], streak: list) -> bool:
        """True if a recovery of ``key`` is allowed at ``t``. A previous recovery that 'took'
        (the measurement was accepted ``lockout_count`` times since) starts afresh: the doubling
        hold-off is only for lock-outs that recur without the sensor ever being accepted."""
        ho = self._holdoff.get(key)
        if not holdoff_over(ho is not None, 0.0 if ho is None else ho[0], streak[2],
                            self.lockout_count, t):
            return False
        if ho is not None and streak[2] >= self.lockout_count:
            del self._holdoff[key]
        return True

    def _lost(self, t: float, key: tuple[str, str], rows, streak: list) -> bool:
        """True if a lock-out of ``key`` = (sensor, kind) means the filter is lost; False if
        other accepted measurements corroborate the filter on every state this block observes
        (``rows``: its H rows, (H, i0, i1) of a dense H or sparse)."""
        support = _support(rows)
        covered: set[int] = set()
        by: list[str] = []
        kinds = CORROBORATED_BY.get(key[1], ())
        for other, (tk, rows_k) in self._last_ok.items():
            if other == key or tk < streak[1]:
                continue
            cols = support if other[1] in kinds else _support(rows_k)
            if cols & support:
                covered |= cols
                by.append(f"{other[0]}/{other[1]}")
        if not support <= covered:
            return True
        wait = self._holdoff.get(key, (0.0, self.recovery_holdoff / 2.0))[1] * 2.0
        self._holdoff[key] = (t + wait, wait)
        streak[2] = 0  # acceptances count from this verdict, as from a recovery
        self.log.note(
            t,
            f"{key[0]}/{key[1]}: {streak[0]} consecutive gate rejections over "
            f"{t - streak[1]:.2f} s while {', '.join(sorted(by))} (observing the same states"
            f"{', or position fixes for the heading' if kinds else ''}) "
            f"were accepted: the sensor disagrees with the others, not recovering (checked again "
            f"in {wait:.0f} s)",
        )
        return False

    def _recover(self, t, sensor, kind, y, H, R, robust: bool = False) -> None:
        """Inflate P so that innovation ``y`` (m,) of block (H (m, n), R (m, m)) is ordinary
        (NIS = m). ``robust``: asked by a robust model (its own hold-off and note; counted
        as a recovery all the same)."""
        P = self.P
        alpha, rest = inflation(y, H @ P @ H.T, R)
        held = self.held_in_recovery
        if held:  # P + (alpha - 1) P_ww, w the widened states: still positive definite
            W = P * (alpha - 1.0)
            W[held, :] = 0.0
            W[:, held] = 0.0
            self.P = P + W
        else:
            self.P = P * alpha
        if rest is not None:
            d = np.linalg.pinv(H) @ rest  # minimum-norm state error explaining the innovation
            self.P += np.outer(d, d)
        self._symmetrize()
        if self.after_inflation is not None:
            self.after_inflation(self)
        if robust:
            self.recoveries.append((t, sensor, alpha))
            self.log.rejected[(sensor, "lockout_recovery")] += 1
            self.log.note(t, f"{sensor}/{kind}: covariance inflated x{alpha:.3g}")
            return
        key = (sensor, kind)
        streak = self._streak[key]
        wait = self._holdoff.get(key, (0.0, self.recovery_holdoff / 2.0))[1] * 2.0
        self._holdoff[key] = (t + wait, wait)
        streak[2] = 0
        self.recoveries.append((t, sensor, alpha))
        self.log.rejected[(sensor, "lockout_recovery")] += 1
        self.log.note(
            t,
            f"{sensor}/{kind}: gate lock-out after {streak[0]} rejections over "
            f"{t - streak[1]:.2f} s; covariance inflated x{alpha:.3g} and measurement accepted "
            f"(next recovery of it not before {wait:.0f} s)",
        )
        streak[0] = 0


_ACCEPT, _REJECT, _RECOVER = 0, 1, 2  # verdicts of KalmanCore._judge
# verdicts of a robust model (ekf_baseline.gps_robust: FUSE, EXCLUDE, RECOVER)
_RB_FUSE, _EXCLUDE, _RB_RECOVER = 0, 1, 2


class _FloatInnovation(Innovation):
    """An Innovation that keeps its residual and S as the floats they were computed in (tuples)
    and makes the arrays on first access: an update logs one per block, and two small np.array
    calls would be ~10 % of the cost of a scalar update."""

    __slots__ = ("_y", "_S")

    def __init__(self, t, sensor, kind, y, S, nis, accepted) -> None:  # noqa: D107
        self.t = t
        self.sensor = sensor
        self.kind = kind
        self.nis = nis
        self.accepted = accepted
        self._y = y
        self._S = S

    @property
    def residual(self) -> np.ndarray:
        if not isinstance(self._y, np.ndarray):
            self._y = np.array(self._y, dtype=float)
        return self._y

    @property
    def cov(self) -> np.ndarray:
        if not isinstance(self._S, np.ndarray):
            self._S = np.array(self._S, dtype=float)
        return self._S


def _support(rows) -> set[int]:
    """State indices a block observes: the nonzero columns of rows i0:i1 of a dense H, given as
    (H, i0, i1) (not sliced until needed: this is only asked on a lock-out), or the indices of
    sparse rows (tuples of (index, coefficient))."""
    if isinstance(rows[0], np.ndarray):
        H, i0, i1 = rows
        return set(np.flatnonzero(np.any(H[i0:i1] != 0.0, axis=0)).tolist())
    return {c for row in rows for c, a in row if a != 0.0}


def _block_of(S: list, i0: int, i1: int) -> tuple:
    """Rows and columns i0:i1 of the nested list S, as tuples: the innovation log keeps one per
    update, and tuples of floats drop out of the garbage collector's scans, lists do not."""
    if i1 == i0 + 1:
        return ((S[i0][i0],),)
    return tuple([tuple(r[i0:i1]) for r in S[i0:i1]])


def block_nis(m: int, y0: float, y1: float, s00: float, s01: float, s11: float) -> float:
    """y^T S^-1 y of a block of m = 1 or 2 rows (innovation (y0, y1), S = [[s00, s01],
    [s01, s11]]; y1, s01, s11 unused for m = 1); -1.0 if S is not positive definite. Plain
    floats: the compiled kernels call this same function."""
    if m == 1:
        return y0 * y0 / s00 if s00 > 0.0 else -1.0
    det = s00 * s11 - s01 * s01
    if not (s00 > 0.0 and det > 0.0):
        return -1.0
    return (s11 * y0 * y0 - 2.0 * s01 * y0 * y1 + s00 * y1 * y1) / det


def _nis_rows(y, S, i0: int, i1: int) -> float | None:
    """y^T S^-1 y of rows i0:i1 (python floats: nested lists S); None if that block of S is
    not positive definite."""
    m = i1 - i0
    if m <= 2:
        nis = (block_nis(1, y[i0], 0.0, S[i0][i0], 0.0, 0.0) if m == 1 else
               block_nis(2, y[i0], y[i0 + 1], S[i0][i0], S[i0][i0 + 1], S[i0 + 1][i0 + 1]))
        return None if nis < 0.0 else nis
    return _nis(np.array(y[i0:i1], dtype=float),
                np.array([r[i0:i1] for r in S[i0:i1]], dtype=float))


def _nis(y: np.ndarray, S: np.ndarray) -> float | None:
    """y^T S^-1 y for a symmetric S of more than two rows; None if S is not positive
    definite."""
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    w = _solve_lower(L, y)
    return float(w @ w)


def _solve_lower(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve L w = b for lower-triangular L (small m: plain forward substitution)."""
    m = b.shape[0]
    if m == 1:
        return b / L[0, 0]
    w = np.empty(m)
    for i in range(m):
        w[i] = (b[i] - L[i, :i] @ w[:i]) / L[i, i]
    return w
