"""The Python side of the compiled filter path (kernels: ``ddfuse.ekf_baseline.kalman_jit``).

* :class:`JitKalmanCore` -- a :class:`~ddfuse.ekf_baseline.kalman.KalmanCore` whose state x,
  covariance P, gate streaks, last acceptances and recovery hold-offs live in the arrays the
  kernels update in place. Every KalmanCore method still works on it (x, P are properties over
  those arrays; ``_streak``, ``_last_ok``, ``_holdoff`` are mappings over the sensor table), so
  what the kernels defer -- a gate lock-out's recovery or corroboration verdict, a singular S --
  runs the reference Python code on the same state.
* :class:`BufferedLog` -- an :class:`~estimation.estimator.EstimatorLog` whose innovations the
  kernels write as rows of a numpy buffer; ``log.innovations`` turns the pending rows into
  Innovation records (in order, before anything appended from Python) whenever it is read.
* :func:`warm_up` -- compile (or load from
  numba's on-disk cache) the kernels once per process, outside any timed region.

Numba caches compiled kernels next to ``kalman_jit.py`` (``__pycache__``) and checks only that
file's time stamp. The kernels also compile code from other files (module docstring of
kalman_jit), so :func:`_guard_cache` keeps a hash of all of them and drops the cache when one
changed.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from ddfuse.ekf_baseline.kalman import (
    DEFAULT_LOCKOUT_COUNT,
    DEFAULT_LOCKOUT_TIME,
    KalmanCore,
    _FloatInnovation,
    _support,
    chi2_threshold,
)
from ddfuse.ekf_baseline.kernel_codes import (  # noqa: F401 - re-exported for the filters
    DEFER,
    GROW,
    IGVC_KINDS,
    LANDMARK_KINDS,
    REJECTED,
    T_ACCEL,
    T_GPS,
    T_GYRO,
    T_HEAD,
    T_HEAD_POSE,
    T_NONE,
    T_ODOM,
    T_WHEELS,
    UNI_KINDS,
)
from ddfuse.estimation.estimator import EstimatorLog
from ddfuse.factors import jitcache
from ddfuse.factors.jitcache import guard_cache, on_cold_cache

__all__ = ["BufferedLog", "JitKalmanCore", "kernels", "usable", "warm_up", "COLD_COMPILE"]


_ROOT = Path(__file__).resolve().parents[1]
# every file whose code the kernels compile (kalman_jit's module docstring)
_KERNEL_SOURCES = ("ekf_baseline/kalman_jit.py", "ekf_baseline/kalman_jit_predict.py",
                   "ekf_baseline/kalman_jit_layout.py", "ekf_baseline/kernel_codes.py",
                   "ekf_baseline/unicycle_motion.py",
                   "ekf_baseline/unicycle_measurements.py", "ekf_baseline/igvc_model.py",
                   "ekf_baseline/igvc_measurements.py", "ekf_baseline/igvc_jacobians.py",
                   "ekf_baseline/landmark_model.py",
                   "ekf_baseline/kalman.py", "ekf_baseline/joseph.py", "factors/kinematics.py",
                   "estimation/lockout.py")
_state: dict = {}
# what the unicycle EKF calls; at a fixed rate (``ekf.rate``) also uni_stacked
UNICYCLE_ENTRIES = ("uni_event", "world_cov")
COLD_COMPILE: dict[str, float] = {}  # entry point -> seconds its warm-up took in this process


def _guard_cache() -> None:
    """Drop numba's cached kernels when a source they compile changed (numba checks only the
    time stamp of the file defining each kernel; ``ddfuse.factors.jitcache``)."""
    sources = [_ROOT / rel for rel in _KERNEL_SOURCES]
    for stem in ("kalman_jit", "kalman_jit_predict"):
        guard_cache(sources, _ROOT / "ekf_baseline" / "__pycache__", stem)


def kernels():
    """The kernel module ``ddfuse.ekf_baseline.kalman_jit``, imported once (after the cache guard;
    importing it compiles the kernels or loads them from numba's cache)."""
    mod = _state.get("mod")
    if mod is None:
        _guard_cache()
        from ddfuse.ekf_baseline import kalman_jit as mod
        _state["mod"] = mod
    return mod


_ENTRIES = {"unicycle": UNICYCLE_ENTRIES, "unicycle_stacked": ("uni_stacked",),
            "igvc": ("igvc_event",)}


def usable(*which: str) -> bool:
    """Whether the kernels of ``which`` (``warm_up``'s names) are ready for a filter to use:
    loaded from numba's cache, or compiled now (``warm_up``) unless the cold-cache policy is
    "reference" (``factors.jitcache.on_cold_cache``). Then a kernel missing from the cache
    makes this False (the filter runs its Python reference path), and a background process
    compiles the missing kernels for the next runs (``kernel_build``; said on the terminal)."""
    if on_cold_cache() == "compile" or all(w in COLD_COMPILE for w in which):
        for w in which:
            warm_up(w)
        return True
    kj = kernels()
    missing = [n for w in which for n in _ENTRIES[w] if not kj.load_cached(n)]
    if missing:
        build_in_background(missing)
        return False
    for w in which:
        warm_up(w)  # loaded: runs the tiny input only
    return True


def build_in_background(names: list[str]) -> None:
    """Ask the background build (``factors.jitcache.build_in_background``, once per process) for
    the entry points ``names`` and every kernel of a default run."""
    jitcache.build_in_background(names)


def warm_up(which: str) -> None:
    """Compile or load the kernels of ``which`` ('unicycle', 'unicycle_stacked': its fixed-rate
    step, or 'igvc') once per process, on a
    tiny input, so that the first filter step does not pay for it. The seconds it took are in
    COLD_COMPILE[which] (a cold compile when numba's cache was empty). The landmark EKF's:
    ``ekf_baseline.landmark_compiled.warm_up``."""
    if which in COLD_COMPILE:
        return
    t0 = time.perf_counter()
    kj = kernels()
    n = 11 if which == "igvc" else 5
    core = JitKalmanCore(np.zeros(n), np.eye(n), BufferedLog(), kinds=UNI_KINDS,
                         f_pairs=[(i, i) for i in range(n)], q_pairs=[])
    row = core.sensor_row("warm-up", gate=None)
    args = (core.fp, core.ip, core.W, core.sf, core.si, core.lg, 0.0, 0.0, T_NONE, row,
            0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0, 1.0)
    if which == "igvc":
        kj.ready("igvc_event")
        kj.igvc_event(*args)
    elif which == "unicycle_stacked":
        kj.ready("uni_stacked")
        kj.uni_stacked(core.fp, core.ip, core.W, core.sf, core.si, core.lg, 0.0, 0.0,
                       np.zeros((1, 10)), 0)
    else:
        kj.ready(*UNICYCLE_ENTRIES)
        kj.uni_event(*args)
    COLD_COMPILE[which] = time.perf_counter() - t0


class BufferedLog(EstimatorLog):
    """EstimatorLog whose ``innovations`` may be pending as rows of compiled kernels' buffers.

    Reading ``innovations`` first appends the pending rows of every attached
    :class:`JitKalmanCore` (as :class:`~ekf_baseline.kalman._FloatInnovation`, the records the
    Python path logs) to the underlying container, so the public API and the order of the
    records are those of the Python path. Nothing else of EstimatorLog changes."""

    def __init__(self, *args, **kwargs) -> None:
        self._sources: list[JitKalmanCore] = []
        super().__init__(*args, **kwargs)

    @property
    def innovations(self):
        store = self.__dict__["_innovations"]
        for src in self._sources:
            src.drain_log(store)
        return store

    @innovations.setter
    def innovations(self, value) -> None:
        self.__dict__["_innovations"] = value

    def __getstate__(self):
        # pickled (e.g. sent from a worker process) as a plain log: pending rows written out
        self.innovations  # noqa: B018 - drains the buffers
        state = dict(self.__dict__)
        state["_sources"] = []
        return state


class _CoreLog:
    """What a JitKalmanCore's ``log`` is: the estimator's :class:`BufferedLog` for everything
    but the innovations, whose ``append`` (KalmanCore's Python update code logging a record)
    writes a row into the kernels' buffer behind the rows already there. So the Python path
    keeps the log's order without turning the whole buffer into records in the middle of a
    run (that cost belongs to whoever reads ``log.innovations``). Any other use of
    ``innovations`` (indexing, iteration, len) sees the estimator's list."""

    __slots__ = ("_core", "_log")

    def __init__(self, core, log) -> None:
        self._core = core
        self._log = log

    @property
    def innovations(self):
        return self

    def append(self, inn) -> None:
        self._core.log_record(inn)

    def __getattr__(self, name):  # rejected, messages, note, ...
        return getattr(self._log, name)

    def __getitem__(self, i):
        return self._log.innovations[i]

    def __iter__(self):
        return iter(self._log.innovations)

    def __len__(self) -> int:
        return len(self._log.innovations)


class _StreakView:
    """KalmanCore's [consecutive rejections, time of the first, acceptances since recovery] of
    one (sensor, kind), over the sensor table."""

    __slots__ = ("core", "row", "k")

    def __init__(self, core, row, k):
        self.core, self.row, self.k = core, row, k

    def __getitem__(self, i):
        kj = self.core.kj
        if i == 1:
            return float(self.core.sf[self.row, kj.SF_K + kj.SF_KW * self.k + kj.SK_T0])
        col = kj.SK_CNT if i == 0 else kj.SK_ACC
        return int(self.core.si[self.row, kj.SI_K + kj.SI_KW * self.k + col])

    def __setitem__(self, i, v):
        kj = self.core.kj
        if i == 1:
            self.core.sf[self.row, kj.SF_K + kj.SF_KW * self.k + kj.SK_T0] = v
        else:
            col = kj.SK_CNT if i == 0 else kj.SK_ACC
            self.core.si[self.row, kj.SI_K + kj.SI_KW * self.k + col] = v


class _SlotMap:
    """Base of the mappings (sensor, kind) -> slot state over the sensor table."""

    def __init__(self, core):
        self.core = core

    def _slot(self, key):
        sensor, kind = key
        return self.core.sensor_row(sensor), self.core.kind_code[kind]

    def _cols(self, k):
        kj = self.core.kj
        return kj.SF_K + kj.SF_KW * k, kj.SI_K + kj.SI_KW * k

    def _slots(self):
        core = self.core
        for name, row in core.rows.items():
            for k, kind in enumerate(core.kinds):
                yield (name, kind), row, k


class _StreakMap(_SlotMap):
    """KalmanCore._streak: (sensor, kind) -> [count, first time, acceptances]."""

    def get(self, key, default=None):
        row, k = self._slot(key)
        _, ci = self._cols(k)
        if self.core.si[row, ci + self.core.kj.SK_EXISTS]:
            return _StreakView(self.core, row, k)
        return default

    def __getitem__(self, key):
        v = self.get(key)
        if v is None:
            raise KeyError(key)
        return v

    def __setitem__(self, key, value):
        row, k = self._slot(key)
        _, ci = self._cols(k)
        self.core.si[row, ci + self.core.kj.SK_EXISTS] = 1
        view = _StreakView(self.core, row, k)
        for i in range(3):
            view[i] = value[i]


class _LastOkMap(_SlotMap):
    """KalmanCore._last_ok: (sensor, kind) -> (time, rows) of its last accepted update; rows
    are given back as sparse rows of its observed columns (all _support needs)."""

    def __setitem__(self, key, value):
        row, k = self._slot(key)
        cf, ci = self._cols(k)
        kj = self.core.kj
        t, rows = value
        self.core.sf[row, cf + kj.SK_OKT] = t
        self.core.si[row, ci + kj.SK_OKMASK] = sum(1 << c for c in _support(rows))

    def items(self):
        kj = self.core.kj
        for key, row, k in self._slots():
            cf, ci = self._cols(k)
            t = self.core.sf[row, cf + kj.SK_OKT]
            if not math.isnan(t):
                mask = int(self.core.si[row, ci + kj.SK_OKMASK])
                cols = tuple(((c, 1.0),) for c in range(self.core.n) if mask >> c & 1)
                yield key, (float(t), cols or (((0, 0.0),),))


class _HoldoffMap(_SlotMap):
    """KalmanCore._holdoff: (sensor, kind) -> (earliest next recovery, hold-off) (s)."""

    def get(self, key, default=None):
        row, k = self._slot(key)
        cf, ci = self._cols(k)
        kj = self.core.kj
        if self.core.si[row, ci + kj.SK_HOLD]:
            return (float(self.core.sf[row, cf + kj.SK_HOLD_UNTIL]),
                    float(self.core.sf[row, cf + kj.SK_HOLD_WAIT]))
        return default

    def __getitem__(self, key):
        v = self.get(key)
        if v is None:
            raise KeyError(key)
        return v

    def __contains__(self, key):
        return self.get(key) is not None

    def __setitem__(self, key, value):
        row, k = self._slot(key)
        cf, ci = self._cols(k)
        kj = self.core.kj
        self.core.si[row, ci + kj.SK_HOLD] = 1
        self.core.sf[row, cf + kj.SK_HOLD_UNTIL], self.core.sf[row, cf + kj.SK_HOLD_WAIT] = value

    def __delitem__(self, key):
        row, k = self._slot(key)
        _, ci = self._cols(k)
        self.core.si[row, ci + self.core.kj.SK_HOLD] = 0


class JitKalmanCore(KalmanCore):
    """KalmanCore over the compiled kernels' arrays (module docstring).

    Beyond KalmanCore's arguments: ``kinds`` names the measurement kinds (slots per sensor, in
    the kernels' K_* order); ``f_pairs`` the (row, col) of F's nonzero entries, ``f_values``
    their constant values (entries the kernel fills each step may hold anything);
    ``f_variable`` for each value the model's Jacobian gives (igvc), its entry number in
    f_pairs; ``q_pairs`` the (row, col) of Q's model entries (each once); ``walks`` (state
    index, variance per second) of random-walk states; ``motion`` / ``ks`` / ``noise`` (up to 8
    densities in the kernel's order) and ``params`` (header fields FP_* -> value) as the
    kernels document. Attributes ``fp``, ``ip``, ``W``, ``sf``, ``si``, ``lg`` are the arrays.
    """

    __slots__ = ("kj", "fp", "ip", "W", "sf", "si", "lg", "kinds", "kind_code", "rows",
                 "_names", "_xv", "_Pv", "_logged")

    def __init__(self, x0, P0, log: BufferedLog | None = None, *, state_angles=(),
                 lockout_count: int = DEFAULT_LOCKOUT_COUNT,
                 lockout_time: float = DEFAULT_LOCKOUT_TIME, kinds=(), f_pairs=(),
                 f_values=None, f_variable=(), q_pairs=(), walks=(), rates=(), motion: int = 0,
                 ks: int | None = None, noise=(), params=None, **kwargs) -> None:
        kj = self.kj = kernels()
        x0 = np.array(x0, dtype=float).reshape(-1)
        n = x0.shape[0]
        if len(state_angles) > kj.MAXANG:
            raise ValueError(f"at most {kj.MAXANG} angle states")
        if n > 62:
            raise ValueError("the kernels keep observed columns as 64-bit masks: n <= 62")
        f_pairs = list(f_pairs)
        q_pairs = list(q_pairs)
        walks = list(walks)
        rates = list(rates)
        nf, nq, nw, nv = len(f_pairs), len(q_pairs), len(walks), len(f_variable)
        nr = len(rates)
        # ip: header, then F's pairs, Q's pairs, walk indices, F's variable entry numbers
        nzi = 8 * kj.MAXB + kj.MAXR + 2 * n  # the event kernels' block table and int scratch
        ip = np.zeros(kj.IP_HEADER + nzi + 2 * nf + 2 * nq + nw + nv + 2 * nr, dtype=np.int64)
        ip[kj.IP_OFF_ZI] = kj.IP_HEADER
        o = kj.IP_HEADER + nzi
        ip[kj.IP_OFF_F] = o
        ip[o:o + 2 * nf] = np.array(f_pairs, dtype=np.int64).reshape(-1)
        o += 2 * nf
        ip[kj.IP_OFF_Q] = o
        if nq:
            ip[o:o + 2 * nq] = np.array(q_pairs, dtype=np.int64).reshape(-1)
        o += 2 * nq
        ip[kj.IP_OFF_WALK] = o
        ip[o:o + nw] = [i for i, _ in walks]
        o += nw
        ip[kj.IP_OFF_FVAR] = o
        ip[o:o + nv] = list(f_variable)
        o += nv
        ip[kj.IP_OFF_RATE], ip[kj.IP_NRATE] = o, nr
        ip[o:o + 2 * nr] = [k for i, j, _ in rates for k in (i, j)]
        ip[kj.IP_N], ip[kj.IP_MOTION], ip[kj.IP_NANG] = n, motion, len(state_angles)
        ip[kj.IP_ANG:kj.IP_ANG + len(state_angles)] = state_angles
        ip[kj.IP_LOCKN] = int(lockout_count)
        ip[kj.IP_KS] = -1 if ks is None else ks
        ip[kj.IP_NF], ip[kj.IP_NQ], ip[kj.IP_NWALK], ip[kj.IP_NFVAR] = nf, nq, nw, nv
        # fp: header, x, F values, Q values, walk variances
        fp = np.zeros(kj.FP_X + n + nf + nq + nw + nr)
        fp[kj.FP_LOCKT] = float(lockout_time)
        fp[kj.FP_LASTNIS] = math.nan
        fp[kj.FP_WHEEL_R] = fp[kj.FP_TRACK] = math.nan
        fp[kj.FP_NOISE:kj.FP_NOISE + len(noise)] = noise
        for k, v in (params or {}).items():
            fp[k] = math.nan if v is None else v
        o = kj.FP_X + n
        ip[kj.IP_OFF_FVAL] = o
        fp[o:o + nf] = 1.0 if f_values is None else f_values
        ip[kj.IP_OFF_QVAL] = o + nf
        ip[kj.IP_OFF_WALKV] = o + nf + nq
        fp[o + nf + nq:o + nf + nq + nw] = [w for _, w in walks]
        ip[kj.IP_OFF_RATEV] = o + nf + nq + nw
        fp[o + nf + nq + nw:o + nf + nq + nw + nr] = [q2 for _, _, q2 in rates]
        self.fp, self.ip = fp, ip
        self.W = np.zeros((4 * n + 8 * kj.MAXR, n))
        self._xv = fp[kj.FP_X:kj.FP_X + n]
        self._Pv = self.W[:n]
        self.kinds = tuple(kinds)
        self.kind_code = {k: i for i, k in enumerate(self.kinds)}
        self.rows: dict[str, int] = {}
        self._names: list[str] = []
        self.sf = np.zeros((0, kj.SF_COLS))
        self.si = np.zeros((0, kj.SI_COLS), dtype=np.int64)
        self.lg = np.zeros((4096, kj.LG_COLS))
        ip[kj.IP_LOGCAP] = self.lg.shape[0]
        self._logged = 0
        log = log if log is not None else BufferedLog()
        log._sources.append(self)
        super().__init__(x0, P0, log, state_angles=state_angles, lockout_count=lockout_count,
                         lockout_time=lockout_time, **kwargs)
        self.log = _CoreLog(self, log)
        self._streak = _StreakMap(self)
        self._last_ok = _LastOkMap(self)
        self._holdoff = _HoldoffMap(self)

    # x, P, last_nis live in the kernels' arrays; assigning copies into them
    @property
    def x(self) -> np.ndarray:
        return self._xv

    @x.setter
    def x(self, value) -> None:
        self._xv[:] = value

    @property
    def P(self) -> np.ndarray:
        return self._Pv

    @P.setter
    def P(self, value) -> None:
        self._Pv[:] = value

    @property
    def last_nis(self) -> float:
        return float(self.fp[self.kj.FP_LASTNIS])

    @last_nis.setter
    def last_nis(self, value) -> None:
        self.fp[self.kj.FP_LASTNIS] = value

    def set_noise(self, noise) -> None:
        """Replace the process noise densities (the kernel's order) the kernels read."""
        kj = self.kj
        self.fp[kj.FP_NOISE:kj.FP_NOISE + len(noise)] = noise

    # ------------------------------------------------------------------ sensors
    def sensor_row(self, name: str, *, gate=None, bias: float = 0.0, hoff: float = 0.0,
                   lever=(0.0, 0.0), delay: float = 0.0, bias_idx: int | None = None,
                   hoff_idx: int | None = None) -> int:
        """The sensor table row of sensor ``name``, added with these settings (gate: chi-square
        probability or None; bias rad/s and hoff rad when not estimated; lever arm m, body
        frame; delay s; the indices of its estimated bias / offset states) if new."""
        row = self.rows.get(name)
        if row is not None:
            return row
        kj = self.kj
        row = len(self._names)
        if row >= self.sf.shape[0]:  # grow the tables (rows are only ever added)
            cap = max(8, 2 * self.sf.shape[0])
            sf = np.zeros((cap, kj.SF_COLS))
            si = np.zeros((cap, kj.SI_COLS), dtype=np.int64)
            sf[:row] = self.sf[:row]
            si[:row] = self.si[:row]
            self.sf, self.si = sf, si
        sf, si = self.sf[row], self.si[row]
        sf[:] = 0.0
        si[:] = 0
        sf[kj.SF_THR1] = math.inf if gate is None else chi2_threshold(gate, 1)
        sf[kj.SF_THR2] = math.inf if gate is None else chi2_threshold(gate, 2)
        sf[kj.SF_BIAS], sf[kj.SF_HOFF] = bias, hoff
        sf[kj.SF_LX], sf[kj.SF_LY] = lever
        sf[kj.SF_DELAY] = delay
        for k in range(len(self.kinds)):
            sf[kj.SF_K + kj.SF_KW * k + kj.SK_OKT] = math.nan
        si[kj.SI_BIAS] = -1 if bias_idx is None else bias_idx
        si[kj.SI_HOFF] = -1 if hoff_idx is None else hoff_idx
        self.rows[name] = row
        self._names.append(name)
        return row

    def settle(self, code: int, kernel, *args) -> int:
        """After ``code = kernel(fp, ip, W, sf, si, lg, *args)`` returned nonzero: the kernel
        called again after growing the log for as long as it asks (GROW: it did nothing), its
        gate rejections drained into the log; returns the final code (DEFER: the update is
        left to Python). The first call stays with the caller: on the per-message path this
        method's call costs ~9 % of the EKF's time."""
        while code & GROW:
            self.grow_log()
            code = kernel(self.fp, self.ip, self.W, self.sf, self.si, self.lg, *args)
        if code & REJECTED:
            self.drain_rejections()
        return code

    def drain_rejections(self) -> None:
        """Add the gate rejections the kernels counted to ``log.rejected``."""
        col = self.kj.SI_REJ
        rej = self.si[:, col]
        for row in np.flatnonzero(rej).tolist():
            self.log.rejected[(self._names[row], "gate")] += int(rej[row])
            rej[row] = 0

    # ------------------------------------------------------------------ log
    def grow_log(self) -> None:
        """Double the innovation buffer (the rows in it are kept: turning them into records
        here would put that cost inside the filter's run, reading ``log.innovations`` does)."""
        lg = np.zeros((2 * self.lg.shape[0], self.kj.LG_COLS))
        nrows = int(self.ip[self.kj.IP_LOGN])
        lg[:nrows] = self.lg[:nrows]
        self.lg = lg
        self.ip[self.kj.IP_LOGCAP] = lg.shape[0]

    def log_record(self, inn) -> None:
        """Append Innovation ``inn`` (logged by KalmanCore's Python code) as a buffer row."""
        kj = self.kj
        y = inn._y if isinstance(inn, _FloatInnovation) else inn.residual
        S = inn._S if isinstance(inn, _FloatInnovation) else inn.cov
        y = np.asarray(y, dtype=float).reshape(-1)
        S = np.asarray(S, dtype=float).reshape(len(y), len(y))
        if len(y) > 2:  # (not produced by these filters) out of the buffer's row format
            self.log._log.innovations.append(inn)
            return
        ln = int(self.ip[kj.IP_LOGN])
        if ln >= self.lg.shape[0]:
            self.grow_log()
        row = self.lg[ln]
        row[:] = 0.0
        row[0], row[1] = inn.t, inn.nis
        row[2:2 + len(y)] = y
        row[4] = S[0, 0]
        if len(y) == 2:
            row[5], row[6], row[7] = S[0, 1], S[1, 0], S[1, 1]
        row[8] = self.sensor_row(inn.sensor)
        row[9] = self.kind_code[inn.kind]
        row[10] = len(y)
        row[11] = 1.0 if inn.accepted else 0.0
        self.ip[kj.IP_LOGN] = ln + 1

    def drain_log(self, store) -> None:
        """Append the buffered innovation rows to ``store`` (a list of Innovation) and empty
        the buffer."""
        kj = self.kj
        nrows = int(self.ip[kj.IP_LOGN])
        if nrows == 0:
            return
        names, kinds = self._names, self.kinds
        if hasattr(store, "extend_small"):  # an InnovationLog: the columns as they are
            lg = self.lg[:nrows]
            # (sensor row, kind, dimension) of each row, and the distinct ones
            uniq, group = np.unique(lg[:, 8:11].astype(np.int64), axis=0, return_inverse=True)
            groups = [(names[r], kinds[k], m) for r, k, m in uniq.tolist()]
            store.extend_small(lg[:, 0], lg[:, 1], group.ravel(), groups, lg[:, 2:4], lg[:, 4:8],
                               lg[:, 11] == 1.0)
            self.ip[kj.IP_LOGN] = 0
            return
        for r in self.lg[:nrows].tolist():
            t, nis, y0, y1, s00, s01, s10, s11, row, k, m, acc = r
            if m == 1.0:
                y, S = (y0,), ((s00,),)
            else:
                y, S = (y0, y1), ((s00, s01), (s10, s11))
            store.append(_FloatInnovation(t, names[int(row)], kinds[int(k)], y, S, nis,
                                          acc == 1.0))
        self.ip[kj.IP_LOGN] = 0
