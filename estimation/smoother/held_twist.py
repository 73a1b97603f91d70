"""The held twist: wheel speed, odometry yaw rate and gyro yaw rate held between their samples
(zero-order hold) and integrated into the preintegration since the newest keyframe.

Odometry (``WheelOdometry``, ``WheelSpeeds``) is the mean over the interval since its previous
sample, stamped at the interval's end: held BACKWARD over its period (``FixedLagSmoother``
holds the messages inside it back until it comes). A gyro sample is instantaneous: held
FORWARD. A held sample's error is the same over its whole period T, so its variance enters as
a density var * T (per step of dt: var * T / dt); outside the span it measures, it grows as a
stale sample (``HeldTwist.stale``). With both a gyro and an odometry yaw rate each step
integrates their inverse-variance weighted mean, and their difference over the interval
(gyro - k_w odometry) is kept for the gyro-bias factor (``factors.gyro.bias_difference_factor``).

Units: m/s, rad/s, s; variances per sample (unit^2), densities (unit^2 s). Design notes:
docs/design/smoother.md (Held twist).
"""

from __future__ import annotations

import math

from ddfuse.estimation.config import RobotConfig
from ddfuse.estimation.measurements import GyroYawRate, WheelSpeeds
from ddfuse.estimation.smoother.noise import SmootherNoise, twist_walk
from ddfuse.estimation.twist_tails import held_speed_walk
from ddfuse.factors.preintegration import WheelGyroPreintegration
from ddfuse.factors.state import BG, KV, KW

ODOMETRY_WAIT = 0.5  # s: without odometry for this long, go on holding the last sample forward


def compiled_preintegration() -> type[WheelGyroPreintegration]:
    """The compiled preintegration class (``factors.preintegration_jit``), its kernel compiled
    or loaded from numba's cache now rather than in the first timed ``process`` call; the
    Python reference if numba does not import, or if the kernel is not in numba's cache under
    the "reference" cold-cache policy of ``ddfuse run`` (``factors.jitcache.on_cold_cache``:
    the background build compiles it for the next runs; the same estimates to rounding).
    Imported here, not at module level, so that importing the smoother does not load numba."""
    try:
        from ddfuse.factors import preintegration_jit
    except ImportError:
        return WheelGyroPreintegration
    from ddfuse.factors import jitcache

    if jitcache.on_cold_cache() == "reference" and not preintegration_jit.load_cached():
        jitcache.build_in_background(["preintegration"])
        return WheelGyroPreintegration
    preintegration_jit.warm_up()
    return preintegration_jit.WheelGyroPreintegrationJit


class HeldTwist:
    """The held (v, w) samples and the preintegration (``pim``) of the keyframe interval open
    since the newest keyframe, integrated up to ``last_t`` (s)."""

    def __init__(self, robot: RobotConfig, noise: SmootherNoise,
                 pim_class: type[WheelGyroPreintegration], fixed_bias: float) -> None:
        self.robot, self.noise = robot, noise
        self.compiled = pim_class is not WheelGyroPreintegration
        self.pim = pim_class(bg_lin=fixed_bias, keep_samples=False)
        self.last_t: float | None = None
        # held samples (zero-order hold): value, per-sample variance and density (var * period)
        self.v = self.wo = self.wg = None  # speed, odometry yaw rate, raw gyro yaw rate
        self.v_var = self.wo_var = self.wg_var = 0.0
        self.v_q = self.wo_q = self.wg_q = 0.0
        # each held sample's period (s) and the span it measures the twist over: its period up
        # to its stamp for odometry (held backward); for the gyro (held forward) from its stamp
        # to 1.5 periods past it (a sample that comes a little late does not make it stale)
        self.v_T = self.wo_T = self.wg_T = 0.1
        self.v_span = self.wo_span = self.wg_span = (-math.inf, math.inf)
        self.sample_T: dict[tuple[str, str], float] = {}  # (sensor, quantity) -> its period
        self.sample_t: dict[tuple[str, str], float] = {}  # (sensor, quantity) -> last stamp
        # integrals of the gyro and the odometry yaw rate dt since the newest keyframe while both
        # are held, that time, and the summed noise density of the two rates (see advance)
        self._int_g = self._int_o = self._diff_t = self._diff_qg = self._diff_qo = 0.0
        self._last_vars = (0.0, 0.0)  # the last integrated step's v, w sample variances

    def forget(self) -> None:
        """Drop the held samples (they described the time before a gap; the next ones start
        afresh) and the interval's gyro-odometry difference."""
        self.v = self.wo = self.wg = None
        self._int_g = self._int_o = self._diff_t = 0.0

    def reset_difference(self) -> None:
        """Start a new interval's gyro-odometry difference (at a keyframe)."""
        self._int_g = self._int_o = self._diff_t = 0.0

    def bias_difference(self) -> tuple[float, float, float, float] | None:
        """The interval's mean gyro rate and mean odometry yaw rate (rad/s) and their noise
        sigmas over it (rad/s), or None when the two were never held fresh together."""
        if self._diff_t <= 0.0:
            return None
        T = self._diff_t
        return (self._int_g / T, self._int_o / T, math.sqrt(self._diff_qg / T),
                math.sqrt(self._diff_qo / T))

    def set_odometry(self, m) -> None:
        if isinstance(m, WheelSpeeds):
            self._wheel_speeds(m)
            return
        if m.v is not None:
            self.v, self.v_var, self.v_T = m.v, m.v_var, self._period(m, "v")
            self.v_q, self.v_span = m.v_var * self.v_T, (m.t - self.v_T, m.t)
        if m.yaw_rate is not None:
            self.wo, self.wo_var, self.wo_T = m.yaw_rate, m.yaw_rate_var, self._period(m, "w")
            self.wo_q, self.wo_span = m.yaw_rate_var * self.wo_T, (m.t - self.wo_T, m.t)


    def set_gyro(self, m: GyroYawRate) -> None:
        """Hold gyro sample ``m`` forward, from its stamp to 1.5 periods past it."""
        self.wg, self.wg_var, self.wg_T = m.yaw_rate, m.var, self._period(m, "w")
        self.wg_q, self.wg_span = m.var * self.wg_T, (m.t, m.t + 1.5 * self.wg_T)

    def _period(self, m, quantity: str) -> float:
        """The period of a held sample (s): the time since the same sensor's previous sample of
        this quantity, clipped to [1 ms, 1 s]; its noise density is var * period. After a gap
        (more than twice the previous period) the previous period: the sample describes its
        own control period, not the gap, which ``stale`` accounts for."""
        key = (m.sensor, quantity)
        last = self.sample_t.get(key)
        self.sample_t[key] = m.t
        prev = self.sample_T.get(key)
        if last is not None and m.t - last < 1e-3 and prev is not None:
            # a repeated (or re-ordered) stamp says nothing of the rate; taken as a 1 ms period
            # it made every later period "a gap" and froze the density at 1 ms for the run
            return prev
        if last is None:
            period = 0.1
        else:  # clipped to [1 ms, 1 s] without min/max calls: 1 % of the smoother's time
            d = m.t - last
            period = 1e-3 if d < 1e-3 else 1.0 if d > 1.0 else d
        if prev is not None and period > 2.0 * prev:
            return prev
        self.sample_T[key] = period
        return period

    def stale(self, var: float, period: float, acc: float | None, default: float,
              span: tuple[float, float], a: float, b: float,
              stated: float | None = None) -> tuple[float, float]:
        """What holding a sample over [a, b] outside ``span`` (the time it measures the twist
        over) adds: (density to add to its var * period for this step, (unit)^2 s; its variance
        as a measurement of the twist at b, (unit)^2).

        Outside its span the sample's error e (variance ``var``) no longer averages out with the
        next sample's: it is the same for the whole hold, and the twist itself moves away from
        the sample as a random walk with the acceleration density q (``stated``^2, the config's
        robot.twist_walk; else ``acc``^2 ``period`` from the robot's acceleration limit
        ``acc``; else ``default``^2, as the EKFs' twist densities). Integrated over an age tau
        outside the span, the error is var tau^2 + q tau^3 / 3; a step adds the difference
        between its ends' ages, as a density over the step (before the span for odometry held
        backward over a gap, after it for a sample held forward). Zero inside the span."""
        since, until = span
        if since <= a and b <= until:
            return 0.0, var
        q = twist_walk(acc, default, period, stated)

        def grown(tau: float) -> float:
            return var * tau * tau + q * tau ** 3 / 3.0

        before = grown(max(since - a, 0.0)) - grown(max(since - b, 0.0))
        after = grown(max(b - until, 0.0)) - grown(max(a - until, 0.0))
        return (before + after) / (b - a), var + q * max(b - until, 0.0)

    def _wheel_speeds(self, m: WheelSpeeds) -> None:
        self.v, self.wo, self.v_var, self.wo_var = m.twist(self.robot.wheel_radius,
                                                           self.robot.track_width)
        self.v_T = self._period(m, "v")
        self.v_q, self.v_span = self.v_var * self.v_T, (m.t - self.v_T, m.t)
        self.wo_T = self._period(m, "w")
        self.wo_q, self.wo_span = self.wo_var * self.wo_T, (m.t - self.wo_T, m.t)

    def yaw_rate(self, qg: float, qo: float, vg: float, vo: float
                 ) -> tuple[float, float, float, float, float] | None:
        """The yaw rate to integrate, fusing the gyro and the odometry yaw rate when both are
        held, given their densities ``qg``, ``qo`` and per-sample variances ``vg``, ``vo`` for
        this step: (gyro part rad/s, odometry part rad/s, per-sample variance, density,
        gyro-bias gain). The gyro part carries the bias with that gain, the odometry part the
        odometry's yaw-rate scale (``ddfuse.factors.preintegration``)."""
        wg, wo = self.wg, self.wo
        if wg is not None and wo is not None:
            a = qo / (qo + qg)  # the gyro's weight
            return a * wg, (1.0 - a) * wo, vg * vo / (vg + vo), qg * qo / (qg + qo), a
        if wg is not None:
            return wg, 0.0, vg, qg, 1.0
        if wo is not None:
            return 0.0, wo, vo, qo, 0.0
        return None

    def advance(self, t: float) -> None:
        """Integrate the held (v, w) from the last sample time up to ``t``."""
        a = self.last_t
        dt = t - a
        if dt <= 0.0:
            return
        if self.v is None:
            # No odometry yet: the interval waits for the first sample, which is then held
            # back over it (grown as a stale sample, ``stale``). Moving last_t on instead left
            # the first keyframe interval's motion out of the preintegration: a 0.4 s factor
            # across 1.2 s, which gtsam declared indeterminate.
            return
        sv, so, sg = self.v_span, self.wo_span, self.wg_span
        if sv[0] <= a and t <= sv[1] and so[0] <= a and t <= so[1] and sg[0] <= a and \
                t <= sg[1]:  # every held sample fresh (almost always): no calls
            qv = qo = qg = 0.0
            v_var, vo, vg = self.v_var, self.wo_var, self.wg_var
        else:
            robot, n = self.robot, self.noise
            tw = robot.twist_walk
            qv, v_var = self.stale(self.v_var, self.v_T, robot.max_accel, n.acc, sv, a, t,
                                   held_speed_walk(robot))
            qo, vo = self.stale(self.wo_var, self.wo_T, robot.max_yaw_accel, n.yaw_acc, so,
                                 a, t, tw.get("yaw_rate")) if self.wo is not None else (0.0, 0.0)
            qg, vg = self.stale(self.wg_var, self.wg_T, robot.max_yaw_accel, n.yaw_acc, sg,
                                 a, t, tw.get("yaw_rate")) if self.wg is not None else (0.0, 0.0)
        fresh = qo == qg == 0.0
        yr = self.yaw_rate(self.wg_q + qg, self.wo_q + qo, vg, vo)
        if yr is not None:
            wg, wo, w_var, w_q, gain = yr
            pim = self.pim
            pim.integrate(dt, self.v, wg, (self.v_q + qv) / dt, w_q / dt, gain, wo)
            # The keyframe's v, w rows compare with the last sample itself, not with its share
            # of one integration step: given to the interval in ``frozen`` (a write into the
            # compiled one's array per step cost 1.7 % of the smoother's time)
            self._last_vars = (v_var, w_var)
            # (a stale sample's difference would carry the twist's change, not the bias)
            if 0.0 < gain < 1.0 and fresh:
                # gyro - k_w odometry = bias + noise, independent of the fused mean integrated
                # above: the bias information the fusion would otherwise throw away
                self._int_g += self.wg * dt
                self._int_o += self.wo * dt
                self._diff_t += dt
                self._diff_qg, self._diff_qo = self.wg_q, self.wo_q
        self.last_t = t

    def frozen(self) -> WheelGyroPreintegration:
        """The preintegration as an object with plain float attributes, for code that reads
        many of them (the compiled one keeps them in an array read through properties), its
        ``last_var_v``, ``last_var_w`` the last sample's own variances (``advance``)."""
        f = self.pim.frozen() if self.compiled else self.pim
        if f.n:
            f.last_var_v, f.last_var_w = self._last_vars
        return f

    def partial(self, st) -> tuple[tuple[float, float, float], list[list[float]]]:
        """The open interval's increment at the biases and scales of state ``st`` and its 3x3
        covariance (row lists): ``delta(st, frozen())`` and ``frozen().covariance`` without the
        copy."""
        return self.pim.partial(float(st[BG]), float(st[KV]), float(st[KW]))

    def delta(self, st, pim=None) -> tuple[float, float, float]:
        """The partial preintegrated increment at the biases and scales of state ``st``."""
        pim = self.pim if pim is None else pim
        return pim.delta_at(float(st[BG]), float(st[KV]), float(st[KW]))

