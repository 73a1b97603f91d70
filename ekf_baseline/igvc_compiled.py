"""The IGVC EKF's compiled path: its :class:`~ddfuse.ekf_baseline.compiled.JitKalmanCore`
(F's pattern from the generated model, Q's entries, the random walks), each message packed as
the kernels' arguments, and one event run in the kernels of ``ddfuse.ekf_baseline.kalman_jit``
with what they defer handed to the reference's Python code. A mixin of
:class:`~ddfuse.ekf_baseline.igvc.IgvcEkf`."""

from __future__ import annotations

from ddfuse.ekf_baseline import compiled as jit
from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline.igvc_model import _Q_INDEX, N
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)

__all__ = ["IgvcKernels"]

# the compiled kernels' message types and return bits (ddfuse.ekf_baseline.compiled)
_T_GYRO, _T_HEAD, _T_HEAD_POSE, _T_ACCEL, _T_ODOM, _T_WHEELS, _T_GPS = (
    jit.T_GYRO, jit.T_HEAD, jit.T_HEAD_POSE, jit.T_ACCEL, jit.T_ODOM, jit.T_WHEELS, jit.T_GPS)
_DEFER = jit.DEFER
_REJECTED = jit.REJECTED


class IgvcKernels:
    """IgvcEkf's compiled path (module docstring)."""

    def _compiled_core(self, x0, P0, angles):
        """The JitKalmanCore of this filter (ddfuse.ekf_baseline.compiled): F's pattern from the
        generated model (its ones, its variable entries, the calibration states' identity),
        Q's entries (_Q_INDEX), the random walks."""
        kj = jit.kernels()
        kj.ready("igvc_event")
        self._igvc_event = kj.igvc_event
        n = self.n
        ones, variable = ((gen.EULER_F_ONES, gen.EULER_F_VARIABLE) if self.motion == "euler"
                          else (gen.ICC_F_ONES, gen.ICC_F_VARIABLE))
        f_pairs = [divmod(k, N) for k in ones] + [divmod(k, N) for k in variable]
        f_pairs += [(i, i) for i in range(N, n)]
        ns = self.noise
        self._jrows = {}
        return jit.JitKalmanCore(
            x0, P0, self.log, state_angles=angles, kinds=jit.IGVC_KINDS, f_pairs=f_pairs,
            f_variable=range(len(ones), len(ones) + len(variable)),
            q_pairs=[divmod(int(k), N) for k in _Q_INDEX], walks=list(self._walks.items()),
            motion=0 if self.motion == "euler" else 1, ks=self._ks,
            noise=(ns.position_psd, ns.frame_psd, ns.heading_psd, ns.frame_heading_psd,
                   ns.jerk_psd, ns.yaw_accel_psd, ns.slip_var),
            params={kj.FP_WHEEL_R: self.wheel_radius, kj.FP_TRACK: self.track,
                    kj.FP_RADIUS: self.radius, kj.FP_MAXSTEP: self.max_step})

    def _pack(self, m):
        """The kernels' arguments (typ, sensor row, z0, z1, r0, r1, r01, r10, flags, rf) for
        message ``m``, or None when it needs the Python path: a heading whose offset is not
        initialised yet, a fix without a fix, wheel speeds without a wheel radius, another
        message type. ``rf``: the factor on R in the fusion (``_gps_factor``; a heading sample's
        ``HeadingClock.factor``)."""
        name = m.sensor
        row = self._jrows.get(name)
        if row is None:
            gate, bias, offset, lever, delay = self._info(name)
            row = self._jrows[name] = self.kf.sensor_row(
                name, gate=gate, bias=bias, hoff=offset, lever=lever, delay=delay,
                bias_idx=self._bias_idx.get(name), hoff_idx=self._hoff_idx.get(name))
        cls = m.__class__
        if cls is GyroYawRate:
            return (_T_GYRO, row, m.yaw_rate, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is Heading:
            hf = self._heading_clock.factor(m)
            hi = self._hoff_idx.get(name)
            if hi is not None and hi not in self._hoff_ready:
                return None
            return (_T_HEAD_POSE if m.source == "pose" else _T_HEAD, row, m.yaw, 0.0, m.var,
                    0.0, 0.0, 0.0, 0, hf)
        if cls is ForwardAccel:
            return (_T_ACCEL, row, m.accel, 0.0, m.var, 0.0, 0.0, 0.0, 0, 1.0)
        if cls is WheelOdometry:
            v, w = m.v, m.yaw_rate
            if v is not None and self.bursts is not None:
                return None  # the heavy-tailed speed walk widens the prior in Python first
            return (_T_ODOM, row, 0.0 if v is None else v, 0.0 if w is None else w, m.v_var,
                    m.yaw_rate_var, 0.0, 0.0, (v is not None) | (w is not None) << 1, 1.0)
        if cls is WheelSpeeds and self.wheel_radius is not None:
            return (_T_WHEELS, row, m.left, m.right, m.left_var, m.right_var, 0.0, 0.0, 0, 1.0)
        if cls is GpsFix and m.status >= 0 and self._robust is None:
            (c00, c01, _), (c10, c11, _), _ = m.cov.tolist()
            return (_T_GPS, row, m.lat, m.lon, c00, c11, c01, c10, 0, self._gps_factor(m))
        return None

    def _run_event(self, m, p) -> None:
        """Predict to ``m.t`` and update with ``m`` (packed as ``p``) in one kernel call."""
        kf = self.kf
        t = m.t
        dt = t - self.t
        code = self._igvc_event(kf.fp, kf.ip, kf.W, kf.sf, kf.si, kf.lg, dt, t, *p)
        if code:
            code = kf.settle(code, self._igvc_event, dt, t, *p)
        if dt > 0.0:
            self.t = t
        if code & _DEFER:  # predicted; the update needs Python (lock-out, singular S)
            self._update(m)
        elif self._gps_tau and p[0] == _T_GPS and not code & _REJECTED:
            self._fused_fix(m.sensor, t)  # fused: the next fix's inflation counts from it
