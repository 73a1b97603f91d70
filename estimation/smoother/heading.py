"""Heading accumulation: the absolute heading samples (compass, IMU yaw) of the open keyframe
interval, each carried back to the newest keyframe by the yaw preintegrated up to it, gated as
in the EKFs, and averaged into one linear measurement of the state (``pending``; a C++ factor at
the next keyframe, ``ddfuse.factors.linear``). Until then the filtered output applies it as one
scalar Kalman update (``with_pending``).

Units: rad, rad^2; the measurement is psi [+ hoff] + J bg + K k_w of the keyframe's 9-vector
state (``ddfuse.factors.state``). Design notes and the variance derivation:
docs/design/smoother.md (Heading).
"""

from __future__ import annotations

import math

import numpy as np
from ddfuse.estimation.config import SensorConfig
from ddfuse.estimation.estimator import EstimatorLog, Innovation, wrap_angle
from ddfuse.estimation.heading_correlation import HeadingClock
from ddfuse.estimation.measurements import Heading
from ddfuse.estimation.smoother.gating import Gating
from ddfuse.estimation.smoother.held_twist import HeldTwist
from ddfuse.estimation.smoother.noise import SmootherNoise, gate_radius, walk_floor
from ddfuse.estimation.smoother.window import Window
from ddfuse.factors.state import BG, DIM, HOFF, KW, PSI


class HeadingAccumulator:
    """The heading samples since the newest keyframe (``n`` of them, all of one sensor), and
    ``latest``, the last heading sample seen (fused or not)."""

    def __init__(self, sensors: dict[str, SensorConfig], noise: SmootherNoise, twist: HeldTwist,
                 window: Window, gating: Gating, log: EstimatorLog, *, est_bias: bool,
                 est_hoff: bool, est_scales: bool, clock: HeadingClock | None = None) -> None:
        """``clock``: the factors of a sensor with time-correlated samples (its
        ``correlation_time``; ``estimation.heading_correlation``), None: white."""
        self.sensors, self.noise, self.log = sensors, noise, log
        self.twist, self.window, self.gating = twist, window, gating
        self.est_bias, self.est_hoff, self.est_scales = est_bias, est_hoff, est_scales
        self.latest: Heading | None = None
        self.clock = clock if clock else None
        # the samples since the newest keyframe: sensor, the first one carried back to the
        # keyframe (rad), the sum of the others' wrapped differences from it, summed variances
        # as fused (each times its clock factor) and as stated (the gate's, the log's)
        self.n = 0
        self._sensor, self._ref, self._sum, self._var = "", 0.0, 0.0, 0.0
        self._var_own = 0.0
        self._jb = self._jk = self._c1 = self._c2 = 0.0
        self._cache = None  # (key, (state, pose cov)) of with_pending
        self._rows = None  # (marginal, its rows as lists, symmetrised pose block): with_pending
        self._gate_terms: tuple | None = None  # the gate's per-keyframe terms (gate)
        self._walk_terms: tuple | None = None  # (marginal, sensor, rad^2/s): ``_walk``

    def add(self, m: Heading) -> bool:
        """Take heading sample ``m`` (the preintegration already advanced to its stamp): False
        when its gate rejected it. A sample of another sensor than the interval's first is
        left out."""
        self.latest = m
        f = 1.0 if self.clock is None else self.clock.factor(m)  # every sample, fused or not
        if self.n == 0 or m.sensor == self._sensor:
            pim = self.twist.pim
            dpsi, j_p, kw_p, c = pim.yaw_terms()
            c += self._walk(m.sensor) * pim.dt_total
            u = m.yaw - dpsi  # carried back to the interval's start
            if not self.gate(m, u, c):
                return False
            if self.n == 0:
                self._sensor, self._ref, self._sum, self._var = m.sensor, u, 0.0, 0.0
                self._var_own = 0.0
                self._jb = self._jk = self._c1 = self._c2 = 0.0
            self._sum += wrap_angle(u - self._ref)
            self._var += m.var * f
            self._var_own += m.var
            # what the carried yaw depends on: the gyro bias and yaw-rate scale (first
            # order), and the yaw noise integrated up to the sample (its index-weighted
            # sum gives the mean's variance, ``pending``)
            self._jb += j_p
            self._jk += kw_p
            self._c1 += c
            self._c2 += self.n * c
            self.n += 1
        return True

    def _walk(self, sensor: str) -> float:
        """rad^2/s: what the preintegrated factor adds to the heading ``sensor`` reads over an
        interval beside the integrated yaw rate: the slip's heading density
        (``preintegrated_factor``'s pose_noise) and, where the sensor's offset is estimated,
        the offset's walk (``offset_walk``). A sample carried to the keyframe carries them
        too, or a compass stated below their share is gated, averaged and widened against
        too small a variance (docs/design/smoother.md, heading samples)."""
        full = self.window.full
        c = self._walk_terms
        if c is None or c[0] is not full or c[1] != sensor:
            q = self.noise.pose_noise[2] ** 2
            s = self.sensors.get(sensor)
            if s is not None and s.heading_offset == "estimate":
                q += self.offset_walk() ** 2
            c = self._walk_terms = (full, sensor, q)
        return c[2]

    def gate(self, m: Heading, u: float, c_pp: float) -> bool:
        """Whether heading sample ``m`` (``u``: its yaw carried back to the newest keyframe,
        ``c_pp`` rad^2 the variance of the yaw preintegrated since it, ``_walk``'s included)
        passes its sensor's chi-square gate, as in the EKFs: against the keyframe's marginal,
        the yaw preintegrated since it and the sample's own variance. A lock-out (a run of
        rejections, ``ddfuse.estimation.lockout``) with GPS fixes or landmark sightings fused since
        it began means the compass is the outlier (a wrong fixed offset, a magnetic
        disturbance): it stays gated out, with a note. Without them the estimate is lost: the
        belief is widened (``Gating.widen_link``) and the sample used."""
        window = self.window
        full = window.full
        c = self._gate_terms
        if c is None or c[0] is not full or c[1] != m.sensor:
            # what the test needs from the newest keyframe, once per update of it (not per
            # sample: 50-100 Hz)
            s = self.sensors.get(m.sensor)
            if s is None or s.gate is None or full is None or full.shape != (DIM, DIM):
                c = (full, m.sensor, 0.0, 0.0, 0.0, math.inf, False)
            else:
                x, use_offset = window.kf_state, s.heading_offset == "estimate"
                if use_offset:
                    pred = float(x[PSI] + x[HOFF])
                    hph = float(full[PSI, PSI] + 2.0 * full[PSI, HOFF] + full[HOFF, HOFF])
                    offset = 0.0
                else:
                    pred, hph = float(x[PSI]), float(full[PSI, PSI])
                    offset = float(s.heading_offset)
                c = (full, m.sensor, pred, hph, offset, gate_radius(s.gate, 1) ** 2,
                     use_offset)
            self._gate_terms = c
        _, _, pred, hph, offset, rad2, use_offset = c
        if rad2 == math.inf:  # no gate for this sensor (or no marginal yet)
            return True
        r = m.var + c_pp
        y = (u - offset - pred + math.pi) % (2.0 * math.pi) - math.pi  # wrap_angle, inlined
        key = (m.sensor, "heading")
        if y * y <= rad2 * (hph + r):
            self.gating.lockout.accepted(key)
            return True
        if self.gating.lockout.rejected(key, m.t):
            count, first = self.gating.lockout.streak(key)
            gating = self.gating
            if max(gating.gps_ok_t, gating.landmark_t) < first:  # lost: recover, use the sample
                H = np.zeros((1, DIM))
                H[0, PSI] = 1.0
                if use_offset:
                    H[0, HOFF] = 1.0
                # the heading is lost, not the calibration: the gyro bias and the offset are
                # held (widened, the offset's prior against its walk made gtsam's Cholesky
                # refuse the window, see walk_floor)
                gating.widen_link(key, m.t, H, np.array([y]), np.array([[r]]),
                                  "heading sample", calibration=False)
                return True
            wait = self.gating.lockout.corroborated(key, m.t)
            self.log.note(m.t, f"{m.sensor}: {count} heading samples in a row failed the gate "
                          f"over {m.t - first:.1f} s while GPS fixes or landmark sightings were "
                          f"fused: the heading disagrees with them, not recovering (checked "
                          f"again in {wait:.0f} s)")
        self.log.rejected[(m.sensor, "gate")] += 1
        return False

    def log_innovation(self, t: float) -> None:
        """The interval's averaged heading measurement (closed at ``t``) against the state
        before it is fused, for the NIS: carried back to the newest keyframe, whose full
        marginal gtsam gave (psi and the offset are strongly anti-correlated: their cross
        term matters, and the logged S had left out all but psi's variance). S takes the
        samples' stated variances, not their correlation factors (as a correlated GPS fix's)."""
        h, z, var = self.pending(own=True)
        full = self.window.newest_marginal()
        res = np.array([wrap_angle(z - float(h @ self.window.kf_state))])
        scov = np.array([[float(h @ full @ h) + var]])
        self.log.innovations.append(Innovation(
            t, self._sensor, "heading", res, scov, float(res[0] ** 2 / scov[0, 0]), True))

    def offset_walk(self) -> float:
        """The heading offset's walk for the interval ending at the next keyframe: at least
        ``walk_floor`` of its marginal sigma at the newest keyframe (an uncertain offset
        against the stated walk's tie is what gtsam's Cholesky refuses)."""
        n = self.noise
        if not self.est_hoff:
            return n.fixed_rw
        # A compass sample informs psi + offset, not the offset: while the heading is
        # uncertain the offset keeps about its prior sigma, and dropping the floor at the first
        # sample made gtsam refuse the pivot (30 of 30 runs stopped with a 0.6 rad initial
        # heading sigma). The floor follows the offset's own marginal instead.
        full = self.window.full
        sigma = (math.sqrt(max(float(full[HOFF, HOFF]), 0.0))
                 if full is not None and full.shape == (DIM, DIM) else n.init_hoff_sigma)
        return max(n.heading_offset_rw, walk_floor(sigma))

    def pending(self, closing=None, own: bool = False) -> tuple[np.ndarray, float, float]:
        """The heading samples since the newest keyframe as one linear measurement h x = z
        (h (DIM,), z rad, variance rad^2) of the newest keyframe's state, or, with
        ``closing`` (the interval's preintegration), of the keyframe that closes it.

        Each sample u_i = yaw_i - dpsi_i is carried back to the keyframe by the preintegrated
        yaw up to it (``add``), which depends on the gyro bias and the yaw-rate scale:
        u_i = psi + [hoff] + J_i (bg - bg_lin) + K_i (k_w - kw_lin) + noise. So the mean
        measures psi + [hoff] + J bg + K k_w, J, K the means of J_i, K_i; at the closing
        keyframe, psi_j = psi + dpsi_T + J_T (bg - bg_lin) + ..., with J - J_T, K - K_T (left
        out, an uncertain bias biases the heading). The variance: the samples' own var / n plus the
        mean's share of the integrated yaw noise (white: c_i = var(dpsi_i), Var(mean_i int_0^t_i) =
        sum_il c_min(i,l) / n^2, and Var(mean_i int_t_i^T) = C_T - sum_il c_max(i,l) / n^2)."""
        terms, z, var = self.terms(closing, own)
        h = np.zeros(DIM)
        for i, c in terms:
            h[i] = c
        return h, z, var

    def terms(self, closing=None, own: bool = False
              ) -> tuple[list[tuple[int, float]], float, float]:
        """``pending``'s measurement with h as its (index, coefficient) pairs in index order
        (psi, then the gyro bias, offset and yaw-rate scale when they are in it): the few
        entries ``with_pending`` works on, without a dense h. The variance is the fused one
        (the samples' variances times their clock factors), or with ``own`` the stated one."""
        s = self.sensors[self._sensor]
        n = self.n
        z = self._ref + self._sum / n
        pim = self.twist.pim if closing is None else closing
        jb, jk = self._jb / n, self._jk / n
        c1, c2 = self._c1, self._c2
        if closing is None:
            carried = ((2 * n - 1) * c1 - 2.0 * c2) / (n * n)
        else:
            z += pim.dpsi
            jb, jk = jb - pim.j_p, jk - pim.kw_p
            carried = (pim.c_pp + self._walk(self._sensor) * pim.dt_total
                       - (2.0 * c2 + c1) / (n * n))
        terms = [(PSI, 1.0)]
        if self.est_bias:
            terms.append((BG, jb))
        if s.heading_offset == "estimate":
            terms.append((HOFF, 1.0))
        else:
            z -= float(s.heading_offset)
        if self.est_bias:
            z += jb * pim.bg_lin
        if self.est_scales:
            terms.append((KW, jk))
            z += jk * pim.kw_lin
        return terms, z, (self._var_own if own else self._var) / (n * n) + max(carried, 0.0)

    def with_pending(self) -> tuple[np.ndarray, np.ndarray]:
        """The newest keyframe's state and 3x3 pose covariance, updated (outside the graph)
        with the heading samples that arrived since it: they become one factor only at the next
        keyframe, but the filtered output should use them now, as the EKFs do. One scalar
        Kalman update with the keyframe's full marginal; the same averaged measurement as that
        factor (``FixedLagSmoother.new_keyframe``)."""
        window = self.window
        st, full = window.kf_state, window.full
        if not self.n or full is None or full.shape != (DIM, DIM):
            return st, window.kf_cov
        # the same until the next heading sample or update: estimate() asks more often
        key = (self.n, window.k, id(st), id(full))
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        rows = self._rows
        if rows is None or rows[0] is not full:
            # the marginal's rows as Python floats and its symmetrised pose block, once per
            # update of the keyframe, not per output sample
            f = full.tolist()
            rows = self._rows = (full, f, [[0.5 * (f[i][j] + f[j][i]) for j in range(3)]
                                           for i in range(3)])
        _, f, sym = rows
        terms, z, var = self.terms()
        # Python floats over h's few non-zeros (psi, offset, bias, scale), only their rows of
        # the marginal: numpy on 9-vectors cost 10-20 us here, per output sample
        x = st.tolist()
        nz = [(i, c) for i, c in terms if c != 0.0]
        if len(nz) == 4:  # psi, bias, offset, scale (the Husky's): one pass, the same sums
            (i0, c0), (i1, c1), (i2, c2), (i3, c3) = nz
            ph = [c0 * a + c1 * b + c2 * c + c3 * d
                  for a, b, c, d in zip(f[i0], f[i1], f[i2], f[i3], strict=True)]
            pred = c0 * x[i0] + c1 * x[i1] + c2 * x[i2] + c3 * x[i3]
            s = 0.0 + c0 * ph[i0] + c1 * ph[i1] + c2 * ph[i2] + c3 * ph[i3] + var
        else:
            i, c = nz[0]
            ph = [c * b for b in f[i]]
            pred = c * x[i]
            for i, c in nz[1:]:
                ph = [a + c * b for a, b in zip(ph, f[i], strict=True)]
                pred += c * x[i]
            s = sum(c * ph[i] for i, c in nz) + var
        g = wrap_angle(z - pred) / s  # innovation over its variance
        x = np.array([xi + pi * g for xi, pi in zip(x, ph, strict=True)])
        p0, p1, p2 = ph[0], ph[1], ph[2]
        (s00, s01, s02), (_, s11, s12), (_, _, s22) = sym
        p01, p02, p12 = s01 - p0 * p1 / s, s02 - p0 * p2 / s, s12 - p1 * p2 / s
        p = np.array(((s00 - p0 * p0 / s, p01, p02), (p01, s11 - p1 * p1 / s, p12),
                      (p02, p12, s22 - p2 * p2 / s)))
        out = (x, p)
        self._cache = (key, out)
        return out

