"""How the unicycle EKF starts: the initialisation modes (a known pose, the first ground
truth, a measured heading, dead reckoning aligned onto the GPS track), the prior covariance, an
estimated heading offset's first value, and the record of fused GPS fixes a correlated GPS's
inflation counts from. A mixin of :class:`~ddfuse.ekf_baseline.unicycle.UnicycleEkf` (its
module docstring; docs/design/unicycle_ekf.md, "Initialisation")."""

from __future__ import annotations

import math

import numpy as np
from ddfuse.ekf_baseline.gps_robust import robust_judges
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.estimation.gps_correlation import inflation as gps_inflation
from ddfuse.estimation.heading_survey import rotation_fit
from ddfuse.estimation.measurements import GpsFix, Heading

__all__ = ["UnicycleStart"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi
RATE_STD0 = 1.0  # m/s^2, rad/s^2: the twist's rates' prior sigma (a ground robot's accelerations)
_cos = math.cos
_sin = math.sin


class UnicycleStart:
    """UnicycleEkf's initialisation (module docstring)."""

    def _try_start(self, m) -> bool:
        """Handle a measurement before the filter exists; True if the filter now runs and ``m``
        should be processed normally."""
        mode = self._mode
        if mode == "pose":
            x, y, psi = self._initial_pose
            s0, s2 = self.initial_std
            self._start(m.t, x, y, psi, np.diag((s0 * s0, s0 * s0)), s2 * s2)
            return True
        if mode in ("origin", "align"):
            self._start(m.t, 0.0, 0.0, 0.0, np.diag((1e-6, 1e-6)), 1e-6)
            return True
        if mode == "heading":
            if isinstance(m, Heading):
                info = self._sensor(m.sensor)
                if info.hoff_idx is None and (info.uses is None or "yaw" in info.uses):
                    self._pending_head = (m.yaw - info.hoff, m.var)
            elif isinstance(m, GpsFix) and m.enu is not None and m.status >= 0:
                self._pending_pos = (m.enu[0], m.enu[1], np.asarray(m.cov)[:2, :2])
                self._pending_fix = (m.sensor, m.t)
            if self._pending_head is not None and (self._pending_pos or not self._has_gps):
                px, py, pc = self._pending_pos or (0.0, 0.0, np.diag((1e-6, 1e-6)))
                self._start(m.t, px, py, self._pending_head[0], pc, self._pending_head[1])
                if self._pending_pos is not None:  # the position is that fix's
                    self._fused_fix(*self._pending_fix)
                # the message that completed the initialisation is not fused a second time
                return False
            self.log.rejected[(m.sensor, "before_init")] += 1
            return False
        # ground_truth: wait for the first reference pose
        self.log.rejected[(m.sensor, "before_init")] += 1
        return False

    def _start(self, t: float, x: float, y: float, psi: float, pos_cov, psi_var: float) -> None:
        n = self.n
        x0 = np.zeros(n)
        x0[0], x0[1], x0[2] = x, y, psi
        P0 = np.zeros((n, n))
        if self._lie:  # the position error in the body frame: R(psi)^T C R(psi)
            c, s = _cos(psi), _sin(psi)
            Rt = np.array([[c, s], [-s, c]])
            pos_cov = Rt @ np.asarray(pos_cov, dtype=float) @ Rt.T
        P0[:2, :2] = pos_cov
        P0[2, 2] = psi_var
        P0[3, 3] = self.v_std0**2
        P0[4, 4] = self.w_std0**2
        for i in self._bias_states:
            P0[i, i] = self.bias_std0**2
        for i in self._hoff_states:
            P0[i, i] = _PI * _PI / 3.0  # uniform on the circle until initialised from a Heading
        for _ti, ri, _q2 in self._rates:
            P0[ri, ri] = RATE_STD0 ** 2
        if self._scale:
            self._scale.set_prior(x0, P0)
        if self.compiled:
            self.kf = self._compiled_core(x0, P0)
        else:
            self.kf = KalmanCore(x0, P0, self.log, state_angles=(2, *self._hoff_states),
                                 lockout_count=self._lockout[0], lockout_time=self._lockout[1])
        if self._ks is not None:
            self.kf.held_in_recovery = (self._ks, self._ks + 1)
        self.kf.robust = robust_judges(self._robust)
        self.t = t
        self._t0 = t
        self._k = 0
        self.log.note(t, f"{self.name}: started ({self._mode}) at ({x:.2f}, {y:.2f}, {psi:.3f})")

    def _fused_fix(self, sensor: str, stamp: float) -> None:
        """Record that the fix of GPS ``sensor`` stamped ``stamp`` was fused (or gave the
        initial position): the next fix's inflation counts from it (correlated sensors only)."""
        if self._sensor(sensor).tau > 0.0:
            self._gps_fused[sensor] = stamp

    def _gps_factor(self, m: GpsFix, tau: float, prev: dict | None) -> float:
        """The factor on fix ``m``'s covariance in the fusion (module docstring, "Time-correlated
        GPS errors"): from its sensor's last fused fix or, with ``prev`` (a fixed-rate step's
        sensor -> stamp of its previous fix in the step, updated here), that one."""
        if prev is not None and m.sensor in prev:
            t_last = prev[m.sensor]
        else:
            t_last = self._gps_fused.get(m.sensor, -math.inf)
        if prev is not None:
            prev[m.sensor] = m.t
        return gps_inflation(m.t - t_last, tau)

    def _align(self, t: float) -> None:
        """Rotate/translate the dead-reckoned state onto the GPS track (least squares)."""
        pairs = np.array(self._pairs)
        a = pairs[:, 0:2] - pairs[:, 0:2].mean(axis=0)
        b = pairs[:, 2:4] - pairs[:, 2:4].mean(axis=0)
        saa = float((a * a).sum())
        sbb = float((b * b).sum())
        kf = self.kf
        if saa > 0.25 * sbb:
            th, res = rotation_fit(a, b)
            c, s = _cos(th), _sin(th)
            r2 = float((res * res).sum(axis=1).mean())
            # var(theta) ~ sigma^2 / sum |a_i|^2 for independent position errors of sigma (floored:
            # GPS noise is at least decimetres), plus a floor for DR heading drift over the track
            th_var = max(r2, 0.25**2) / saa + 0.03**2
            dx = kf.x[0] - pairs[:, 0].mean()
            dy = kf.x[1] - pairs[:, 1].mean()
            ex = pairs[:, 2].mean() + c * dx - s * dy
            ny = pairs[:, 3].mean() + s * dx + c * dy
            psi = kf.x[2] + th
            how = f"Kabsch rotation {math.degrees(th):.1f} deg, residual {math.sqrt(r2):.2f} m"
        else:  # no usable dead reckoning: course from the first to the last fix
            th = math.atan2(pairs[-1, 3] - pairs[0, 3], pairs[-1, 2] - pairs[0, 2])
            c, s = _cos(th - kf.x[2]), _sin(th - kf.x[2])
            th_var = 2.0 * pairs[-1, 4] / max(sbb / len(pairs), 1e-9) + 0.03**2
            ex, ny, psi = pairs[-1, 2], pairs[-1, 3], th
            how = "GPS course (no dead reckoning)"
        # rotate the cross-covariances of the pose with the other states, reset the pose block
        n = self.n
        T = np.eye(n)
        T[0, 0], T[0, 1], T[1, 0], T[1, 1] = c, -s, s, c
        P = T @ kf.P @ T.T
        P[:3, :] = 0.0
        P[:, :3] = 0.0
        P[0, 0] = P[1, 1] = pairs[-1, 4]
        P[2, 2] = th_var
        x = kf.x.copy()
        x[0], x[1], x[2] = ex, ny, (psi + _PI) % _TWO_PI - _PI
        kf.x = x
        kf.P = P
        self._aligned = True
        self._pairs = []
        for sensor, stamp in self._pair_fix.items():  # the position is the fixes'
            self._fused_fix(sensor, stamp)
        self._pair_fix = {}
        self.log.note(t, f"{self.name}: heading initialised from GPS ({how}); "
                         f"sigma {math.degrees(math.sqrt(th_var)):.1f} deg")

    def _init_offset(self, t: float, m: Heading, hi: int) -> None:
        """hoff = wrap(z - psi): variance var(psi) + R, covariance -cov(psi, .) with the rest."""
        kf = self.kf
        x = kf.x.copy()
        x[hi] = (m.yaw - x[2] + _PI) % _TWO_PI - _PI
        P = kf.P.copy()
        row = -P[2, :]
        P[hi, :] = row
        P[:, hi] = row
        P[hi, hi] = P[2, 2] + m.var
        kf.x = x
        kf.P = P
        self._hoff_ready.add(hi)
        self.log.note(t, f"{self.name}: heading offset of {m.sensor} initialised to "
                         f"{math.degrees(x[hi]):.1f} deg")
