"""The unicycle EKF's compiled path: its :class:`~ddfuse.ekf_baseline.compiled.JitKalmanCore`
(F's and Q's patterns, the random walks, the sensor table), each message packed as the
kernels' arguments, and one event or one fixed-rate step run in the kernels of
``ddfuse.ekf_baseline.kalman_jit``, with what they defer handed to the reference's Python
code. A mixin of :class:`~ddfuse.ekf_baseline.unicycle.UnicycleEkf`."""

from __future__ import annotations

import numpy as np
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, Heading, WheelOdometry, WheelSpeeds

__all__ = ["UnicycleKernels"]

# the compiled kernels' message types and return bits (ddfuse.ekf_baseline.compiled)
_T_NONE, _T_GYRO, _T_HEAD, _T_ODOM, _T_GPS, _T_WHEELS = (
    jit.T_NONE, jit.T_GYRO, jit.T_HEAD, jit.T_ODOM, jit.T_GPS, jit.T_WHEELS)
_DEFER = jit.DEFER
_REJECTED = jit.REJECTED


class UnicycleKernels:
    """UnicycleEkf's compiled path (module docstring)."""

    def _compiled_core(self, x0, P0):
        """The JitKalmanCore of this filter (ekf_baseline.compiled): F's pattern (identity plus
        the pose rows of the motion Jacobian), Q's entries, the random walks, the sensors."""
        kj = jit.kernels()
        kj.ready(*jit.UNICYCLE_ENTRIES, *(() if self.rate is None else ("uni_stacked",)))
        self._uni_event, self._uni_stacked = kj.uni_event, kj.uni_stacked
        n = self.n
        # F: rows 0..2 in the order uni_predict fills them (with scale states their columns of
        # x, y, psi next), then the identity of the rest
        f_pairs = [(0, 0), (0, 2), (0, 3), (0, 4), (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (2, 4)]
        ks = self._ks
        if ks is not None:
            f_pairs += [(0, ks), (0, ks + 1), (1, ks), (1, ks + 1), (2, ks + 1)]
        if self._lie:  # the rotation block of the pose error's F (se2_error_terms)
            f_pairs += [(0, 1), (1, 0)]
        f_pairs += [(i, i) for i in range(3, n)]
        upper = [(i, j) for i in range(5) for j in range(i, 5)]  # unicycle_process_noise order
        q_pairs = upper + [(j, i) for i, j in upper if i != j]
        walks = list(zip(self._bias_states + self._hoff_states, self._walks, strict=True))
        r, L = self._wheel
        kf = jit.JitKalmanCore(
            x0, P0, self.log, state_angles=(2, *self._hoff_states),
            lockout_count=self._lockout[0], lockout_time=self._lockout[1], kinds=jit.UNI_KINDS,
            f_pairs=f_pairs, q_pairs=q_pairs, walks=walks, rates=self._rates,
            motion=0 if self.motion == "exact" else 1, ks=self._ks,
            noise=self._noise_floats(),
            params={kj.FP_WHEEL_R: r, kj.FP_TRACK: L})
        kf.ip[kj.IP_LIE] = 1 if self._lie else 0
        kf.ip[kj.IP_WTRUE] = 1 if self._w_true else 0
        for info in self._sensors.values():
            info.row = None  # (re)registered with this core on first use
        return kf

    def _noise_floats(self) -> tuple[float, ...]:
        """The process noise densities in the kernels' order (unicycle_process_noise_terms)."""
        nz = self.noise
        return (nz.acc, nz.yaw_acc, nz.pos_long, nz.pos_lat, nz.heading)

    def _pack(self, m, prev: dict | None = None):
        """The kernels' arguments (typ, sensor row, z0, z1, r0, r1, r01, r10, flags, rf) for
        message ``m``, or None when it needs the Python path: an odometry speed under the
        heavy-tailed walk (``estimation.twist_tails.SpeedBursts.widen`` before its update), a
        heading before the heading is known or before its offset is initialised, a GPS fix
        while aligning or without a position, wheel speeds without the geometry, another
        message type. ``rf``: the factor on R in the fusion (a correlated GPS sensor's fix:
        ``_gps_factor`` with ``prev``; a correlated heading sensor's sample:
        ``HeadingClock.factor``)."""
        info = self._sensors.get(m.sensor) or self._sensor(m.sensor)
        row = info.row
        if row is None:
            row = info.row = self.kf.sensor_row(
                m.sensor, gate=info.gate, bias=info.bias, hoff=info.hoff, lever=info.lever,
                delay=info.delay, bias_idx=info.bias_idx, hoff_idx=info.hoff_idx)
        cls = m.__class__
        if cls is GyroYawRate:
            if not info.use_w:
                return (_T_NONE, row, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1.0)
            return (_T_GYRO, row, m.yaw_rate, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is Heading:
            if not info.use_yaw:
                return (_T_NONE, row, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 1.0)
            hf = self._heading_clock.factor(m)
            if not self._aligned or (info.hoff_idx is not None
                                     and info.hoff_idx not in self._hoff_ready):
                return None
            return (_T_HEAD, row, m.yaw, 0.0, m.var, 0.0, 0.0, 0.0, 0, hf)
        if cls is WheelOdometry:
            v, w = m.v, m.yaw_rate
            if v is not None and self.bursts is not None:
                return None  # the heavy-tailed speed walk widens the prior in Python first
            return (_T_ODOM, row, 0.0 if v is None else v, 0.0 if w is None else w, m.v_var,
                    m.yaw_rate_var, 0.0, 0.0, (v is not None) | (w is not None) << 1, 1.0)
        if cls is GpsFix:
            if m.enu is None or m.status < 0 or not self._aligned or self._robust is not None:
                return None
            (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
            rf = 1.0 if info.tau <= 0.0 else self._gps_factor(m, info.tau, prev)
            return (_T_GPS, row, m.enu[0], m.enu[1], c00, c11, c01, c10, 0, rf)
        if cls is WheelSpeeds and self._wheel[0] is not None and self._wheel[1] is not None:
            return (_T_WHEELS, row, m.left, m.right, m.left_var, m.right_var, 0.0, 0.0, 0, 1.0)
        return None

    def _run_event(self, m, p) -> None:
        """Predict to ``m.t`` and update with ``m`` (packed as ``p``) in one kernel call."""
        kf = self.kf
        t = m.t
        self._gap_steps(t)
        dt = t - self.t
        code = self._uni_event(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, t, *p)
        if code:
            code = kf.settle(code, self._uni_event, dt, t, *p)
        if dt > 0.0:
            self.t = t
        if code & _DEFER:  # predicted; the update needs Python (lock-out, singular S)
            self._apply((m,))
            return
        if self._gps_corr and p[0] == _T_GPS and not code & _REJECTED:
            # fused: the next fix's inflation counts from it
            self._fused_fix(m.sensor, t)
        if self._tw_on:  # what _apply records, for the next prediction's densities
            self._twist_msg(m, self._sensors[m.sensor])

    def _run_stacked(self, ts: float, buf: list, packs: list) -> None:
        """A fixed-rate step at ``ts``: predict and one stacked update in one kernel call."""
        self._gap_steps(ts)
        dt = ts - self.t
        mb = np.array(packs, dtype=float).reshape(-1, 10)
        kf = self.kf
        k = len(packs)
        code = kf.settle(self._uni_stacked(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, ts, mb, k),
                         self._uni_stacked, dt, ts, mb, k)
        if dt > 0.0:
            self.t = ts
        if code & _DEFER:
            self._apply(buf)
            return
        if self._gps_corr:  # the kernel's verdicts on the fixes (flags column: fused)
            for i, p in enumerate(packs):
                if p[0] == _T_GPS and mb[i, 8] == 1.0:
                    self._fused_fix(buf[i].sensor, buf[i].t)
        if self._tw_on:
            sensors = self._sensors
            for m in buf:
                self._twist_msg(m, sensors[m.sensor])
