"""Compiled (numba) twin of ``ddfuse.factors.preintegration.WheelGyroPreintegration``.

The arithmetic is written once, in ``ddfuse.factors.preintegration.integrate_step``: the
reference class calls it in Python, ``integrate`` below compiles it (``register_jitable``, with
``se2_step_jac`` / ``twist_coeffs`` of ``ddfuse.factors.kinematics``) on the state array.

The running state lives in one float64 array ``s`` (slot indices below, named after the Python
attributes); ``WheelGyroPreintegrationJit`` exposes it under the reference class's attribute
names, so everything but ``integrate`` (``delta_at``, ``predict``, ``covariance``,
``preintegrated_factor`` ...) is the reference's own code.

Why it exists (per-sample cost on the Husky bag): docs/design/preintegration.md
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ddfuse.factors.jitcache import arg_types, compiling, guard_cache, one_compiler
from ddfuse.factors.jitcache import load_cached as _load
from ddfuse.factors.kinematics import se2_step_jac, twist_coeffs
from ddfuse.factors.preintegration import WheelGyroPreintegration, integrate_step
from numba import njit
from numba.extending import register_jitable

__all__ = ["SIGNATURE", "SLOTS", "WheelGyroPreintegrationJit", "integrate", "load_cached", "ready",
           "warm_up"]

_HERE = Path(__file__).resolve().parent
# every file whose code the kernel compiles: numba's cache checks only this file's time stamp
_KERNEL_SOURCES = ("preintegration_jit.py", "preintegration.py", "kinematics.py")


def _guard_cache() -> None:
    """Drop numba's cached kernel when a source it compiles changed (``factors.jitcache``)."""
    guard_cache((_HERE / rel for rel in _KERNEL_SOURCES), _HERE / "__pycache__",
                "preintegration_jit")


_guard_cache()  # before the kernel below is first called (numba loads its cache lazily)

for _f in (twist_coeffs, se2_step_jac, integrate_step):
    register_jitable(_f)

# the reference class's float attributes, in array order ("n" is stored as a float)
SLOTS = tuple(a for a in WheelGyroPreintegration.__slots__ if a not in ("samples", "keep_samples"))
(BG_LIN, KV_LIN, KW_LIN, DX, DY, DPSI, DT_TOTAL, C_XX, C_XY, C_XP, C_YY, C_YP, C_PP, J_X, J_Y,
 J_P, KV_X, KV_Y, KW_X, KW_Y, KW_P, LAST_V, LAST_W_GYRO, LAST_W_ODO, LAST_VAR_V, LAST_VAR_W,
 LAST_GAIN, N) = range(len(SLOTS))
SIZE = len(SLOTS)


@njit(cache=True)
def integrate(s, dt, v, w_gyro, var_v, var_w, gain, w_odo):
    """``WheelGyroPreintegration.integrate`` on the state array ``s`` (SIZE,), in place.

    Arguments and units as there: ``dt`` s, ``v`` m/s, ``w_gyro`` and ``w_odo`` rad/s, ``var_v``
    (m/s)^2, ``var_w`` (rad/s)^2, ``gain`` (share of the gyro bias carried by ``w_gyro``)."""
    (s[DX], s[DY], s[DPSI], s[C_XX], s[C_XY], s[C_XP], s[C_YY], s[C_YP], s[C_PP], s[J_X],
     s[J_Y], s[J_P], s[KV_X], s[KV_Y], s[KW_X], s[KW_Y], s[KW_P]) = integrate_step(
        s[DX], s[DY], s[DPSI], s[C_XX], s[C_XY], s[C_XP], s[C_YY], s[C_YP], s[C_PP], s[J_X],
        s[J_Y], s[J_P], s[KV_X], s[KV_Y], s[KW_X], s[KW_Y], s[KW_P], s[BG_LIN], s[KV_LIN],
        s[KW_LIN], dt, v, w_gyro, var_v, var_w, gain, w_odo)
    s[DT_TOTAL] += dt
    s[LAST_V] = v
    s[LAST_W_GYRO] = w_gyro
    s[LAST_W_ODO] = w_odo
    s[LAST_VAR_V] = var_v
    s[LAST_VAR_W] = var_w
    s[LAST_GAIN] = gain
    s[N] += 1.0


SIGNATURE = "(float64[::1], float64, float64, float64, float64, float64, float64, float64)"
_warm: list[bool] = []


def ready() -> None:
    """Compile the kernel for SIGNATURE, or load it from numba's cache (once per process)."""
    if not _warm:
        with compiling("the smoother's preintegration kernel"), one_compiler("preintegration"):
            integrate.compile(arg_types(SIGNATURE))  # the key a first call caches under
        _warm.append(True)


def load_cached() -> bool:
    """Whether the kernel is ready: loaded from numba's cache where it holds it, never
    compiling."""
    return bool(_warm) or _load(integrate, arg_types(SIGNATURE))


def warm_up() -> None:
    """Compile the kernel (or load it from numba's cache) once per process, so that an
    estimator's first measurement does not pay for it (~1 s cold, ~0.1 s from the cache)."""
    ready()
    integrate(np.zeros(SIZE), 0.1, 1.0, 0.1, 1e-4, 1e-4, 1.0, 0.0)


def _slot(i: int, as_int: bool = False) -> property:
    if as_int:
        return property(lambda self: int(self.s[i]),
                        lambda self, x: self.s.__setitem__(i, float(x)))
    return property(lambda self: float(self.s[i]),
                    lambda self, x: self.s.__setitem__(i, float(x)))


class WheelGyroPreintegrationJit(WheelGyroPreintegration):
    """``WheelGyroPreintegration`` with its state in one array and ``integrate`` compiled.

    Same constructor, attributes and methods; attributes read as Python floats (``n`` an int)."""

    __slots__ = ("s",)

    def __init__(self, bg_lin: float = 0.0, keep_samples: bool = True, kv_lin: float = 1.0,
                 kw_lin: float = 1.0) -> None:
        self.s = np.zeros(SIZE)
        super().__init__(bg_lin, keep_samples, kv_lin, kw_lin)

    def reset(self, bg_lin: float | None = None, kv_lin: float | None = None,
              kw_lin: float | None = None) -> None:
        """As ``WheelGyroPreintegration.reset`` (one array fill instead of 27 assignments)."""
        s = self.s
        keep = s[BG_LIN], s[KV_LIN], s[KW_LIN]
        s[:] = 0.0
        s[BG_LIN] = keep[0] if bg_lin is None else float(bg_lin)
        s[KV_LIN] = keep[1] if kv_lin is None else float(kv_lin)
        s[KW_LIN] = keep[2] if kw_lin is None else float(kw_lin)
        s[LAST_GAIN] = 1.0
        self.samples = []

    def integrate(self, dt: float, v: float, w_gyro: float, var_v: float, var_w: float,
                  gain: float = 1.0, w_odo: float = 0.0) -> None:
        """As ``WheelGyroPreintegration.integrate``, in the compiled kernel."""
        if self.keep_samples:
            self.samples.append((dt, v, w_gyro, var_v, var_w, gain, w_odo))
        integrate(self.s, float(dt), float(v), float(w_gyro), float(var_v), float(var_w),
                  float(gain), float(w_odo))

    def yaw_terms(self) -> tuple[float, float, float, float]:
        """As ``WheelGyroPreintegration.yaw_terms``, from one read of the array."""
        s = self.s.tolist()
        return s[DPSI], s[J_P], s[KW_P], s[C_PP]

    def partial(self, bg: float, kv: float, kw: float) -> tuple[tuple[float, float, float],
                                                                list[list[float]]]:
        """As ``WheelGyroPreintegration.partial``, from one read of the array."""
        s = self.s.tolist()
        db = bg - s[BG_LIN]
        dv = kv - s[KV_LIN]
        dw = kw - s[KW_LIN]
        cxy, cxp, cyp = s[C_XY], s[C_XP], s[C_YP]
        return ((s[DX] + s[J_X] * db + s[KV_X] * dv + s[KW_X] * dw,
                 s[DY] + s[J_Y] * db + s[KV_Y] * dv + s[KW_Y] * dw,
                 s[DPSI] + s[J_P] * db + s[KW_P] * dw),
                [[s[C_XX], cxy, cxp], [cxy, s[C_YY], cyp], [cxp, cyp, s[C_PP]]])

    def frozen(self) -> WheelGyroPreintegration:
        """The current interval as a reference-class object (a copy, plain float attributes):
        for code that reads many attributes (``preintegrated_factor``, ``predict``, ``delta_at``,
        ``covariance``), each of which is an array read through a property here."""
        f = WheelGyroPreintegration.__new__(WheelGyroPreintegration)
        for name, x in zip(SLOTS, self.s.tolist(), strict=True):
            setattr(f, name, x)
        f.n = int(f.n)
        f.keep_samples = False
        f.samples = []
        return f


for _i, _name in enumerate(SLOTS):
    setattr(WheelGyroPreintegrationJit, _name, _slot(_i, as_int=_name == "n"))
