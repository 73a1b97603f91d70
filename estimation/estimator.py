"""The interface that every estimator (each EKF, the smoother) implements, and what it reports.

An estimator consumes one measurement at a time in time order (``process``), gives its current
estimate on demand (``estimate``), and keeps a record of every innovation or residual it used
and every measurement it rejected, so that NIS and gate statistics can be computed afterwards.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from array import array
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from ddfuse.estimation.interrupts import deliver, held_signals
from ddfuse.estimation.measurements import Measurement


def wrap_angle(a: float) -> float:
    """Wrap an angle to [-pi, pi), rad."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(slots=True)
class Estimate:
    """An estimator's belief at time ``t``.

    ``pose`` is (x, y, yaw) in the local frame (m, m, rad) and ``pose_cov`` its 3x3 covariance in
    the same world-frame coordinates (x, y, yaw), so that every estimator can be plotted alike.
    ``state``/``state_cov`` hold the estimator's full state vector and covariance, with
    ``state_names`` naming each component (e.g. ('x', 'y', 'yaw', 'v', 'yaw_rate')).

    ``pose_error`` names the coordinates in which the estimator's Gaussian describes the pose
    error (``POSE_ERRORS``; the NEES is scored in them, ``ddfuse.evaluation.metrics.nees_series``):
    ``'world'``, e = (x, y, yaw)_true - pose (yaw wrapped), with covariance ``pose_cov``;
    ``'se2'``, SE(2) exponential coordinates of the body-frame error, X_true = X_hat Exp(xi),
    xi = (rho_x m, rho_y m, theta rad) = Log(X_hat^-1 X_true), with covariance
    A^-1 pose_cov A^-T, A = blockdiag(R(yaw), 1): ``pose_cov`` (and ``state_cov``) are then
    that covariance mapped to the world frame to first order (A P_xi A^T)."""

    t: float
    pose: tuple[float, float, float]
    pose_cov: np.ndarray  # (3, 3)
    state: np.ndarray | None = None  # (n,)
    state_cov: np.ndarray | None = None  # (n, n)
    state_names: tuple[str, ...] = ()
    pose_error: str = "world"


POSE_ERRORS = ("world", "se2")  # Estimate.pose_error / Estimator.pose_error


NIS_BAND_P = 0.95  # two-sided probability of the chi-square band NIS values are judged against
_BANDS: dict[int, tuple[float, float]] = {}


def nis_band(dim: int) -> tuple[float, float]:
    """The two-sided ``NIS_BAND_P`` chi-square band of one NIS value of dimension ``dim``."""
    b = _BANDS.get(dim)
    if b is None:
        from ddfuse.estimation import chi2

        a = (1.0 - NIS_BAND_P) / 2.0
        b = _BANDS[dim] = (chi2.ppf(a, dim), chi2.ppf(1.0 - a, dim))
    return b


@dataclass(slots=True)
class Innovation:
    """One measurement update: the innovation (EKF) or residual (smoother) and its covariance.

    ``residual`` is z - h(x) with angles wrapped, shape (m,); ``cov`` is its covariance S, (m, m).
    ``nis`` is residual^T S^-1 residual. ``accepted`` is False when the gate rejected it.
    ``kind`` names the measurement model ('gps', 'heading', 'gyro', 'v', 'landmark', ...)."""

    t: float
    sensor: str
    kind: str
    residual: np.ndarray
    cov: np.ndarray
    nis: float
    accepted: bool = True


class InnovationView:
    """One entry of an :class:`InnovationLog`, read from its columns (the fields of
    :class:`Innovation`, plus ``dim``). ``accepted`` can be set (the smoother's GPS gate decides
    after logging). ``residual`` and ``cov`` are None once the entry has been folded into the
    log's summary (only the most recent entries keep them; see InnovationLog)."""

    __slots__ = ("_log", "_i")

    def __init__(self, log: InnovationLog, i: int) -> None:
        self._log, self._i = log, i

    def _k(self) -> int:
        k = self._i - self._log._n_folded
        if k < 0:
            raise IndexError(f"innovation {self._i} has been folded into the log's summary")
        return k

    @property
    def t(self) -> float:
        return self._log._t[self._k()]

    @property
    def sensor(self) -> str:
        return self._log._groups[self._log._g[self._k()]][0]

    @property
    def kind(self) -> str:
        return self._log._groups[self._log._g[self._k()]][1]

    @property
    def dim(self) -> int:
        return self._log._groups[self._log._g[self._k()]][2]

    @property
    def nis(self) -> float:
        return self._log._nis[self._k()]

    @property
    def accepted(self) -> bool:
        return bool(self._log._acc[self._k()])

    @accepted.setter
    def accepted(self, value: bool) -> None:
        self._log._acc[self._k()] = 1 if value else 0

    @property
    def residual(self) -> np.ndarray:
        log, k = self._log, self._k()
        a = log._roff[k]
        return np.array(log._res[a:a + self.dim], dtype=float)

    @property
    def cov(self) -> np.ndarray:
        log, k = self._log, self._k()
        m = self.dim
        a = log._coff[k]
        return np.array(log._cov[a:a + m * m], dtype=float).reshape(m, m)

    def __repr__(self) -> str:
        return (f"InnovationView(t={self.t!r}, sensor={self.sensor!r}, kind={self.kind!r}, "
                f"nis={self.nis!r}, accepted={self.accepted!r})")


def _floats(x) -> list[float]:
    """A residual or covariance (array, tuple, nested tuples, list) as a flat list of floats."""
    if isinstance(x, np.ndarray):
        return x.ravel().tolist()
    if isinstance(x, tuple | list):
        if x and isinstance(x[0], tuple | list | np.ndarray):
            return [float(v) for row in x for v in np.ravel(row)]
        return [float(v) for v in x]
    return [float(x)]


class InnovationLog:
    """Every innovation an estimator logged, in compact columns: a drop-in for the list of
    :class:`Innovation` (``append``, ``len``, indexing, slicing, iteration), whose
    memory does not grow with the length of the run beyond a bound.

    Each entry costs a few dozen bytes (stamp, NIS, a code for (sensor, kind, dimension), the
    gate's verdict, the residual and S flattened) instead of an object and two arrays. The
    most recent ``keep`` to 2 ``keep`` entries are held that way; older ones are *folded*: their
    NIS counts per (sensor, kind, dimension) are added to exact accumulators (count, sum,
    below / above the chi-square band, accepted), and a uniformly thinned subset of them (plus
    every gate-rejected one) stays in a series for plots, itself kept below about ``keep``
    entries by thinning further. So the NIS tables (``evaluation.consistency``) of a run of any
    length are exact; a folded entry can no longer be indexed (IndexError), and iteration and
    slices give the entries still held. ``len`` counts every entry ever logged."""

    KEEP = 32768
    PENDING = 4096

    def __init__(self, keep: int = KEEP) -> None:
        self.keep = max(int(keep), 16)
        self._pending: list = []  # appended, not yet in the columns
        self._groups: list[tuple[str, str, int]] = []  # code -> (sensor, kind, dim)
        self._codes: dict[tuple[str, str, int], int] = {}
        self._t = array("d")
        self._nis = array("d")
        self._g = array("H")
        self._acc = array("B")
        self._roff = array("I")  # offset of each entry's residual in _res
        self._coff = array("I")  # offset of each entry's S (row-major) in _cov
        self._res = array("d")
        self._cov = array("d")
        self._n_folded = 0
        # folded: code -> [count, accepted, finite count, NIS sum, below band, above band,
        # accepted finite count, their NIS sum]
        self.folded: dict[int, list] = {}
        # thinned series of folded entries: t, nis, code, accepted
        self._st, self._snis, self._sg, self._sacc = array("d"), array("d"), array("H"), \
            array("B")
        self._stride = 1

    # --- writing -----------------------------------------------------------------------------

    def append(self, inn) -> None:
        """Log an :class:`Innovation` (or anything with its fields). It is held as it is until
        the next :meth:`compact` (a cheap append on the estimators' hot path); the runner
        compacts between measurements, outside the timed updates, and the log itself does
        when ``PENDING`` entries are waiting."""
        p = self._pending
        p.append(inn)
        if len(p) >= self.PENDING:
            self.compact()

    def add(self, t: float, sensor: str, kind: str, residual, cov, nis: float,
            accepted: bool = True) -> None:
        """Log one innovation (``residual`` (m,) and its covariance ``cov`` (m, m), as arrays,
        tuples or nested tuples)."""
        self.append(Innovation(t, sensor, kind, residual, cov, nis, accepted))

    def extend(self, items) -> None:
        for inn in items:
            self.append(inn)

    def compact(self) -> None:
        """Move the entries appended since the last call into the columns. Ctrl-C or SIGTERM
        arriving meanwhile is held until the columns agree again, then raised (a
        KeyboardInterrupt cutting it in two left columns of different lengths, and the run's
        scoring a traceback: ``ddfuse.estimation.interrupts.held_signals``)."""
        if not self._pending:
            return
        with held_signals() as held:
            self._compact()
        deliver(held)

    def _compact(self) -> None:
        buf = self._pending
        self._pending = []
        codes = self._codes
        res, cov = self._res, self._cov
        roff, coff, gcol = self._roff, self._coff, self._g
        for inn in buf:
            y = getattr(inn, "_y", None)  # the EKF fast path's float tuples, not yet arrays
            if y is not None:
                S = inn._S
            else:
                y, S = inn.residual, inn.cov
            if type(y) is not tuple:
                y = _floats(y)
            m = len(y)
            roff.append(len(res))
            res.extend(y)
            coff.append(len(cov))
            if type(S) is tuple and len(S) == m and type(S[0]) is tuple:
                for row in S:
                    cov.extend(row)
            else:
                flat = _floats(S)
                if len(flat) != m * m:
                    raise ValueError(f"innovation covariance has {len(flat)} entries for a "
                                     f"residual of {m}")
                cov.extend(flat)
            key = (inn.sensor, inn.kind, m)
            code = codes.get(key)
            if code is None:
                code = self._code(key)
            gcol.append(code)
        self._t.extend([inn.t for inn in buf])
        self._nis.extend([inn.nis for inn in buf])
        self._acc.extend([1 if inn.accepted else 0 for inn in buf])
        if len(self._t) >= 2 * self.keep:
            self._fold(len(self._t) - self.keep)

    def extend_small(self, t: np.ndarray, nis: np.ndarray, group: np.ndarray,
                     groups: list[tuple[str, str, int]], y: np.ndarray, S: np.ndarray,
                     accepted: np.ndarray) -> None:
        """Log k innovations of dimension 1 or 2 at once, after those appended before, from
        columns (a compiled filter's buffer): ``t``, ``nis`` (k,) float; ``group`` (k,) int,
        each row's index into ``groups`` (sensor, kind, dim) with dim 1 or 2; ``y`` (k, 2)
        the residual (its second column unused where dim is 1); ``S`` (k, 4) the innovation
        covariance row-major (S[0, 0] alone where dim is 1); ``accepted`` (k,) bool. The same
        columns as appending the records one at a time."""
        self.compact()
        k = len(t)
        if k == 0:
            return
        if any(d not in (1, 2) for _, _, d in groups):
            raise ValueError(f"extend_small: dimensions 1 or 2, got "
                             f"{sorted({d for _, _, d in groups})}")
        dims = np.array([d for _, _, d in groups], dtype=np.int64)
        codes = np.array([self._code(key) for key in groups], dtype=np.uint16)[group]
        m = dims[group]
        cols = np.arange(4)
        res = np.asarray(y, dtype=float)[cols[None, :2] < m[:, None]]
        cov = np.asarray(S, dtype=float)[(m[:, None] == 2) | (cols[None, :] == 0)]
        ends = np.cumsum(m)
        self._roff.frombytes((len(self._res) + ends - m).astype(np.uint32).tobytes())
        self._coff.frombytes((len(self._cov) + np.cumsum(m * m) - m * m)
                             .astype(np.uint32).tobytes())
        self._res.frombytes(res.tobytes())
        self._cov.frombytes(cov.tobytes())
        self._g.frombytes(codes.tobytes())
        self._t.frombytes(np.asarray(t, dtype=float).tobytes())
        self._nis.frombytes(np.asarray(nis, dtype=float).tobytes())
        self._acc.frombytes(np.asarray(accepted, dtype=bool).astype(np.uint8).tobytes())
        if len(self._t) >= 2 * self.keep:
            self._fold(len(self._t) - self.keep)

    def _code(self, key: tuple[str, str, int]) -> int:
        code = self._codes.get(key)
        if code is None:
            code = self._codes[key] = len(self._groups)
            self._groups.append(key)
        return code

    def _fold(self, k: int) -> None:
        """Fold the oldest ``k`` held entries into the summary and the thinned series."""
        # copies: the arrays cannot be resized while numpy views of them exist
        t = np.frombuffer(self._t, float, k).copy()
        nis = np.frombuffer(self._nis, float, k).copy()
        g = np.frombuffer(self._g, np.uint16, k).copy()
        acc = np.frombuffer(self._acc, np.uint8, k).copy()
        for code in np.unique(g).tolist():
            sel = g == code
            v = nis[sel]
            fin = v[np.isfinite(v)]
            lo, hi = nis_band(self._groups[code][2])
            a = self.folded.setdefault(code, [0, 0, 0, 0.0, 0, 0, 0, 0.0])
            a[0] += int(sel.sum())
            a[1] += int(acc[sel].sum())
            a[2] += len(fin)
            a[3] += float(fin.sum())
            a[4] += int((fin < lo).sum())
            a[5] += int((fin > hi).sum())
            fa = v[np.isfinite(v) & (acc[sel] != 0)]
            a[6] += len(fa)
            a[7] += float(fa.sum())
        # the thinned series: every stride-th entry (counted over the whole log) and every
        # rejected one
        idx = np.arange(self._n_folded, self._n_folded + k)
        keep = (idx % self._stride == 0) | (acc == 0)
        self._st.extend(t[keep].tolist())
        self._snis.extend(nis[keep].tolist())
        self._sg.extend(g[keep].tolist())
        self._sacc.extend(acc[keep].tolist())
        if len(self._st) > self.keep:
            self._stride *= 2
            st = np.frombuffer(self._st, float)
            sacc = np.frombuffer(self._sacc, np.uint8)
            keep = np.zeros(len(st), bool)
            keep[::2] = True
            keep |= sacc == 0
            if keep.sum() > self.keep:  # mostly rejections: thin those too
                keep = np.zeros(len(st), bool)
                keep[::2] = True
            self._st = array("d", st[keep].tobytes())
            self._snis = array("d", np.frombuffer(self._snis, float)[keep].tobytes())
            self._sg = array("H", np.frombuffer(self._sg, np.uint16)[keep].tobytes())
            self._sacc = array("B", sacc[keep].tobytes())
        r0 = self._roff[k] if k < len(self._roff) else len(self._res)
        c0 = self._coff[k] if k < len(self._coff) else len(self._cov)
        for name in ("_t", "_nis", "_g", "_acc"):
            del getattr(self, name)[:k]
        roff = np.frombuffer(self._roff, np.uint32)[k:] - np.uint32(r0)
        coff = np.frombuffer(self._coff, np.uint32)[k:] - np.uint32(c0)
        self._roff = array("I", roff.tobytes())
        self._coff = array("I", coff.tobytes())
        del self._res[:r0]
        del self._cov[:c0]
        self._n_folded += k

    # --- reading -----------------------------------------------------------------------------

    def __len__(self) -> int:
        return self._n_folded + len(self._t) + len(self._pending)

    def __bool__(self) -> bool:
        return len(self) > 0

    def __getitem__(self, i):
        n = len(self)
        if isinstance(i, slice):
            self.compact()
            return [InnovationView(self, j) for j in range(n)[i] if j >= self._n_folded]
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("innovation index out of range")
        held = self._n_folded + len(self._t)
        if i >= held:  # not compacted yet: the object as appended (its fields can be set)
            return self._pending[i - held]
        if i < self._n_folded:
            raise IndexError(f"innovation {i} has been folded into the log's summary")
        return InnovationView(self, i)

    def __iter__(self):
        self.compact()
        base = self._n_folded
        return (InnovationView(self, base + k) for k in range(len(self._t)))

    def columns(self) -> dict[str, np.ndarray]:
        """The entries for tables and plots, oldest first: the thinned series of folded entries,
        then every held entry: ``t``, ``sensor``, ``kind`` (str), ``nis``, ``dim`` (int),
        ``accepted`` (bool)."""
        self.compact()
        g = np.concatenate([np.frombuffer(self._sg, np.uint16), np.frombuffer(self._g, np.uint16)])
        groups = self._groups
        sensor = np.array([s for s, _, _ in groups] or [""], dtype=str)
        kind = np.array([k for _, k, _ in groups] or [""], dtype=str)
        dim = np.array([d for _, _, d in groups] or [0], dtype=int)
        return {"t": np.concatenate([np.frombuffer(self._st), np.frombuffer(self._t)]),
                "sensor": sensor[g] if len(g) else np.zeros(0, dtype=str),
                "kind": kind[g] if len(g) else np.zeros(0, dtype=str),
                "nis": np.concatenate([np.frombuffer(self._snis), np.frombuffer(self._nis)]),
                "dim": dim[g] if len(g) else np.zeros(0, dtype=int),
                "accepted": np.concatenate([np.frombuffer(self._sacc, np.uint8),
                                            np.frombuffer(self._acc, np.uint8)]).astype(bool)}

    def held_log_det(self) -> dict[str, np.ndarray]:
        """The entries still held (not folded; all of them in a log made with a ``keep`` above
        its length), oldest first, for sums over every innovation (the innovations' likelihood,
        ``ddfuse.evaluation.tune``): ``group`` (N,) int, an index into ``groups`` (a list of
        (sensor, kind, dim)), ``nis`` (N,), ``accepted`` (N,) bool and ``log_det`` (N,), the
        natural log of det S of each entry (-inf / nan where S is not positive definite)."""
        self.compact()
        g = np.frombuffer(self._g, np.uint16).astype(int)
        dim = np.array([d for _, _, d in self._groups] or [0], dtype=int)[g] if len(g) else g
        cov = np.frombuffer(self._cov, float)
        off = np.frombuffer(self._coff, np.uint32).astype(np.int64)
        log_det = np.full(len(g), np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            one = dim == 1
            log_det[one] = np.log(cov[off[one]])
            two = dim == 2
            o = off[two]
            log_det[two] = np.log(cov[o] * cov[o + 3] - cov[o + 1] * cov[o + 2])
            for i in np.flatnonzero(dim > 2).tolist():
                m = int(dim[i])
                sign, ld = np.linalg.slogdet(cov[off[i]:off[i] + m * m].reshape(m, m))
                log_det[i] = ld if sign > 0 else np.nan
        return {"group": g, "groups": list(self._groups), "nis": np.frombuffer(self._nis).copy(),
                "accepted": np.frombuffer(self._acc, np.uint8).astype(bool), "log_det": log_det}

    def folded_by_group(self) -> dict[tuple[str, str, int], list]:
        """(sensor, kind, dim) -> [count, accepted, finite count, NIS sum, below, above] of the
        folded entries (empty until the log first folds)."""
        return {self._groups[c]: list(self.folded[c]) for c in sorted(self.folded)}

    @property
    def nbytes(self) -> int:
        """Bytes held in the columns."""
        self.compact()
        return sum(a.itemsize * len(a) for a in (
            self._t, self._nis, self._g, self._acc, self._roff, self._coff, self._res,
            self._cov, self._st, self._snis, self._sg, self._sacc))


@dataclass
class EstimatorLog:
    """What an estimator used and rejected, for NIS, gate counts and the report.

    ``innovations`` is an :class:`InnovationLog` (compact; bounded memory on long runs)."""

    innovations: InnovationLog = field(default_factory=InnovationLog)
    rejected: Counter = field(default_factory=Counter)  # (sensor, reason) -> count
    messages: list[str] = field(default_factory=list)  # notable events: resets, recoveries

    MAX_MESSAGES = 1000

    def note(self, t: float, text: str) -> None:
        if len(self.messages) < self.MAX_MESSAGES:
            self.messages.append(f"t={t:.3f}: {text}")
        elif len(self.messages) == self.MAX_MESSAGES:
            self.messages.append("... (further notes dropped)")


# s: how much older than the newest processed a stamp may be and still count as in order: a
# nanosecond, ROS's stamp resolution (stamps computed in floating point, e.g. k * period, may
# differ from an equal one in the last bits)
IN_ORDER_TOLERANCE = 1e-9


class LateMeasurement(ValueError):
    """A measurement older than the newest one an estimator has processed, given to an
    estimator that cannot use it that late (``Estimator.late_horizon``): fusing it as current
    would be wrong, so it is refused (docs/design/late_data.md)."""


class Estimator(ABC):
    """Base class for every estimator.

    Subclasses implement ``process`` and ``estimate``. ``finish`` is called once after the last
    measurement (a smoother flushes its window there). Measurements an estimator cannot use
    (ground truth, a sensor type it does not model) are ignored, not rejected.

    Late data: ``late_horizon(m)`` says how far (s) behind the newest stamp processed a
    measurement like ``m`` may come and still be used correctly; 0 for an estimator without
    history (every EKF), which raises ``LateMeasurement`` (a ValueError) for an older one
    (``in_order``) rather than fuse it as current."""

    name: str = "estimator"
    # the coordinates of its pose error, as Estimate.pose_error (the NEES is scored in them)
    pose_error: str = "world"
    # s: the newest stamp processed (in_order); -inf before the first
    newest_t: float = -math.inf

    def __init__(self) -> None:
        self.log = EstimatorLog()

    @abstractmethod
    def process(self, m: Measurement) -> None:
        """Consume one measurement. Measurements arrive in non-decreasing time order, but for
        those up to ``late_horizon(m)`` s late; an older one raises ``LateMeasurement``."""

    def late_horizon(self, m: Measurement) -> float:
        """How late (s behind the newest stamp this estimator has processed) measurement ``m``
        may be and still be used correctly: 0 here, for an estimator that keeps no history
        (it can only fuse a measurement at its current state)."""
        return 0.0

    def in_order(self, m: Measurement) -> None:
        """Record ``m``'s stamp as the newest processed; ``LateMeasurement`` naming the sensor,
        the stamp and the newest stamp when ``m`` is older (it would be fused as current).
        Equal stamps (to ``IN_ORDER_TOLERANCE``) are in order; a NaN stamp is left to the
        caller's checks."""
        t, newest = m.t, self.newest_t
        if t < newest - IN_ORDER_TOLERANCE:
            raise LateMeasurement(
                f"{self.name}: {type(m).__name__} from sensor {m.sensor!r} stamped "
                f"t={t:.6f} s is {newest - t:.3f} s older than the newest measurement it has "
                f"processed (t={newest:.6f} s); it keeps no history to put it in and will not "
                "fuse it as current: feed measurements in stamp order (OnlineSession drops "
                "and counts such a one)")
        if t > newest:
            self.newest_t = t

    @abstractmethod
    def estimate(self) -> Estimate | None:
        """The current estimate, or None before the estimator is initialised."""

    def finish(self) -> None:  # noqa: B027 - optional hook
        """Called once after the last measurement."""

    def final_state(self) -> Estimate | None:
        """After ``finish``: the estimate whose ``state`` and ``state_cov`` describe the
        estimator's whole state at the end of the run (calibration states included), or None
        to use the last output sample's."""
        return None

    @property
    def innovations(self) -> InnovationLog:
        return self.log.innovations

    @property
    def rejected(self) -> Counter:
        return self.log.rejected
