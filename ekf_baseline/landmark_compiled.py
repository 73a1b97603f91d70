"""The known-map landmark EKF's compiled path: its
:class:`~ddfuse.ekf_baseline.compiled.JitKalmanCore` (F's and Q's patterns, the slip), the
odometry-driven prediction and one sighting each run in one kernel of
``ddfuse.ekf_baseline.kalman_jit`` (``lm_predict``, ``lm_sighting``), with what the kernel
defers -- a gate lock-out's recovery or corroboration verdict, a singular S, a landmark at the
body origin -- handed to the Python update on the same arrays. A mixin of
:class:`~ddfuse.ekf_baseline.landmark.LandmarkEkf`; the message flow (odometry intervals,
pending sightings, gaps) stays the Python filter's."""

from __future__ import annotations

import time

import numpy as np
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.estimation.gaps import is_gap
from ddfuse.estimation.measurements import WheelOdometry

__all__ = ["LandmarkKernels", "landmark_core", "warm_up"]

_DEFER = jit.DEFER
# Q's entries: the pose block's upper triangle (landmark_model.odometry_noise_terms' order),
# then its lower off-diagonal entries (kalman_jit_predict._lm_predict fills them)
_Q_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (1, 0), (2, 0), (2, 1))


def landmark_core(x0, P0, log: jit.BufferedLog | None, *, euler: bool = False,
                  slip: tuple[float, float, float] | None = None) -> jit.JitKalmanCore:
    """The JitKalmanCore of a landmark EKF with state (x, y, psi) or, with the odometry scale
    states, (x, y, psi, k_v, k_w): F's pattern in ``_lm_predict``'s order (the pose block's
    nonzeros, then d pose / d (k_v, k_w) and the scales' identity), Q's pose block; ``slip``:
    the robot's (longitudinal, lateral, heading) variance densities, or None."""
    kj = jit.kernels()
    kj.ready("lm_predict", "lm_sighting")
    n = len(x0)
    if n not in (3, 5):
        raise ValueError(f"a landmark EKF's state has 3 or 5 components, got {n}")
    f_pairs = [(0, 0), (0, 2), (1, 1), (1, 2), (2, 2)]
    if n == 5:
        f_pairs += [(0, 3), (0, 4), (1, 3), (1, 4), (2, 4), (3, 3), (4, 4)]
    core = jit.JitKalmanCore(x0, P0, log, state_angles=(2,), kinds=jit.LANDMARK_KINDS,
                             f_pairs=f_pairs, q_pairs=_Q_PAIRS, motion=1 if euler else 0,
                             ks=3 if n == 5 else None, noise=slip or ())
    core.ip[kj.IP_SLIP] = 0 if slip is None else 1
    return core


def warm_up() -> None:
    """``compiled.warm_up`` for the landmark kernels (on a core of their own layout): compiled
    or loaded once per process, the seconds in ``compiled.COLD_COMPILE['landmark']``."""
    if "landmark" in jit.COLD_COMPILE:
        return
    t0 = time.perf_counter()
    kf = landmark_core(np.zeros(5), np.eye(5), jit.BufferedLog())
    row = kf.sensor_row("warm-up", gate=None)
    kf.kj.lm_predict(kf.fp, kf.ip, kf.W, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    kf.kj.lm_sighting(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, 0.0, row, 1.0, 1.0, 1, 1.0, 0.0,
                      1.0, 1.0, 1.0)
    jit.COLD_COMPILE["landmark"] = time.perf_counter() - t0


class LandmarkKernels:
    """LandmarkEkf's compiled path (module docstring)."""

    def _compiled_core(self, x0, P0) -> jit.JitKalmanCore:
        """The core, and the kernels (the prediction's: called by
        ``_OdometryDrivenEkf.predict_to``)."""
        kf = landmark_core(x0, P0, self.log, euler=self.motion == "euler", slip=self._slip)
        self._lm_predict, self._lm_sighting = kf.kj.lm_predict, kf.kj.lm_sighting
        self._rows: dict[str, int] = {}  # sensor -> its row in kf's sensor table
        return kf

    def process(self, m) -> None:
        """The filter's ``process``; compiled, an odometry sample with no sighting waiting, in
        stamp order and after no gap (71 651 of the 79 771 messages of mrclam1_robot1.bag) takes
        the general path's steps without its dispatch (~1 us of the ~3 us a sample cost)."""
        if (self.compiled and m.__class__ is WheelOdometry and not self._pending
                and self._t_odo is not None and m.t > self._t_odo and m.t >= self.newest_t
                and not is_gap(m.t - self.t)):
            self.newest_t = t = m.t  # (in order: Estimator.in_order's bookkeeping)
            self._set_control(t, m.v, m.yaw_rate, m.v_var, m.yaw_rate_var, m.sensor)
            dt = t - self.t
            if dt > 0.0:  # predict_to's compiled branch (tau: set, as t > the last sample's)
                kf = self.kf
                self._lm_predict(kf.fp, kf.ip, kf.W, dt, self.v, self.w, self.v_var,
                                 self.w_var, self.tau)
                self.t = t
            return
        super().process(m)

    def _sighting_compiled(self, m, landmark, fuse: float = 1.0) -> None:
        """Sighting ``m`` of the known ``landmark`` (x, y) m in the kernel, or in Python when
        the kernel defers it; ``fuse`` the factor on R in the fusion (``_measure``'s)."""
        kf = self.kf
        row = self._rows.get(m.sensor)
        if row is None:
            row = self._rows[m.sensor] = kf.sensor_row(m.sensor, gate=self._gate(m.sensor))
        if m.has_bearing:
            args = (m.t, row, landmark[0], landmark[1], 1, m.range, m.bearing, m.range_var,
                    m.bearing_var, fuse)
        else:
            args = (m.t, row, landmark[0], landmark[1], 0, m.range, 0.0, m.range_var, 0.0, fuse)
        sighting = self._lm_sighting
        code = sighting(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, *args)
        if code:
            code = kf.settle(code, sighting, *args)
        if code & _DEFER:
            self._measure(m, landmark, None, fuse=fuse)
