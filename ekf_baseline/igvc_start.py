"""How the IGVC EKF starts: its calibration states, the initial state and covariance (the
redundant pairs tied together), the start from GPS and a heading or the GPS course, and the
re-tying of the pairs after a lock-out recovery. A mixin of
:class:`~ddfuse.ekf_baseline.igvc.IgvcEkf` (its docstrings; docs/design/igvc_ekf.md)."""

from __future__ import annotations

import math

import numpy as np
from ddfuse.ekf_baseline import igvc_jacobians as gen
from ddfuse.ekf_baseline.calibration import ScaleStates
from ddfuse.ekf_baseline.gps_robust import robust_judges
from ddfuse.ekf_baseline.igvc_model import (
    HALF_PI,
    LAT,
    LON,
    PSI,
    THETA,
    VL,
    VR,
    A,
    N,
    V,
    W,
    X,
    Y,
    sphere_radius,
)
from ddfuse.ekf_baseline.kalman import KalmanCore
from ddfuse.estimation import geodesy
from ddfuse.estimation.config import Config
from ddfuse.estimation.gps_course import COURSE_MIN_PSI_SIGMA, GpsCourseStart
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GyroYawRate,
    Heading,
    WheelOdometry,
    WheelSpeeds,
)

# the measurements the filter fuses (those counted as before_init while it waits)
_USED = (GpsFix, WheelOdometry, WheelSpeeds, GyroYawRate, Heading, ForwardAccel)
# s: a fix this long before the first moving odometry sample may start the course's baseline
# (odometry is held over its period), as in the smoother
COURSE_ODOMETRY_WAIT = 0.5

__all__ = ["IgvcStart"]



class IgvcStart:
    """IgvcEkf's initialisation (module docstring)."""

    def _calibration_states(self, cfg: Config) -> None:
        """The states after the seed's 11 (class docstring) and their random-walk densities."""
        names = list(gen.STATE_NAMES)
        walks: dict[int, float] = {}  # state index -> variance per second
        self._bias_idx: dict[str, int] = {}
        self._hoff_idx: dict[str, int] = {}
        ns = self.noise
        # (the reading it corrects, config field, state prefix, its index map, walk key, default)
        for use, field, prefix, idx, walk, default in (
                ("yaw_rate", "gyro_bias", "bg", self._bias_idx, "gyro_bias_walk",
                 ns.gyro_bias_walk),
                ("yaw", "heading_offset", "hoff", self._hoff_idx, "heading_offset_walk",
                 ns.heading_offset_walk)):
            for s in cfg.of_kind("imu") if use == "yaw_rate" else cfg.heading_sensors():
                if use in s.use and getattr(s, field) == "estimate":
                    idx[s.name] = len(names)
                    walks[len(names)] = s.noise.get(walk, default) ** 2
                    names.append(f"{prefix}:{s.name}")
        self._scale = ScaleStates.append_to(cfg, names)
        self._ks = self._scale.index if self._scale else None
        self.state_names = tuple(names)
        self.n = len(names)
        self._walks = walks
        self._hoff_ready: set[int] = set()

    def _init(self, t: float | None, pose, pos_var: float, yaw_var: float) -> None:
        x, y, yaw = (float(v) for v in pose)
        if self.datum is not None:
            lat, lon, _ = geodesy.enu_to_geodetic(x, y, 0.0, *self.datum)
            lat, lon = math.radians(lat), math.radians(lon)
        else:
            # no datum and no GPS: lat/lon are relative to (0, 0) and unobserved
            lat, lon = y / self.radius, x / self.radius
        ns = self.noise
        s0 = np.zeros(N)
        s0[[LAT, LON, THETA, X, Y, PSI]] = lat, lon, HALF_PI - yaw, x, y, yaw
        gp = self._position_noise_map(lat)
        P0 = pos_var * (gp @ gp.T)
        gh = np.zeros((N, 1))
        gh[PSI, 0], gh[THETA, 0] = 1.0, -1.0
        P0 += yaw_var * (gh @ gh.T)
        P0 += np.diag(self._frame_var(lat, 1.0))
        P0[V, V] = ns.init_speed_std ** 2
        P0[W, W] = ns.init_yaw_rate_std ** 2
        P0[A, A] = ns.init_accel_std ** 2
        # the wheel speeds are functions of (v, psi_dot), plus slip: s0 -> T s0 maps them
        T = np.eye(N)
        T[VL, VL] = T[VR, VR] = 0.0
        T[VL, V], T[VL, W], T[VR, V], T[VR, W] = 1.0, -0.5 * self.track, 1.0, 0.5 * self.track
        P0 = T @ P0 @ T.T
        P0[VL, VL] += ns.slip_var
        P0[VR, VR] += ns.slip_var
        # the calibration states: biases about 0, offsets uniform on the circle until the first
        # reading initialises them, scales about 1
        n = self.n
        x0 = np.zeros(n)
        x0[:N] = s0
        Pn = np.zeros((n, n))
        Pn[:N, :N] = P0
        for i in self._bias_idx.values():
            Pn[i, i] = ns.init_bias_std ** 2
        for i in self._hoff_idx.values():
            Pn[i, i] = math.pi * math.pi / 3.0
        if self._scale:
            self._scale.set_prior(x0, Pn)
        # lon is an angle too: wrapped so that crossing the antimeridian does not leave it
        # outside [-pi, pi) (the GPS innovation is wrapped as well)
        angles = (LON, THETA, PSI, *self._hoff_idx.values())
        if self.compiled:
            self.kf = self._compiled_core(x0, Pn, angles)
        else:
            self.kf = KalmanCore(x0, Pn, self.log, state_angles=angles)
        self.kf.after_inflation = self._retie_pairs
        self.kf.robust = robust_judges(self._robust)
        if self._ks is not None:
            self.kf.held_in_recovery = (self._ks, self._ks + 1)
        self.t = t

    def _position_noise_map(self, lat: float) -> np.ndarray:
        """(11, 2) map of an (east, north) position perturbation in metres to the state."""
        g = np.zeros((N, 2))
        g[X, 0] = 1.0
        g[LON, 0] = 1.0 / (self.radius * math.cos(lat))
        g[Y, 1] = 1.0
        g[LAT, 1] = 1.0 / self.radius
        return g

    def _retie_pairs(self, kf: KalmanCore) -> None:
        """Re-tie the redundant pairs (lat, lon) ~ (x, y) and theta ~ pi/2 - psi after a gate
        recovery inflated P (``KalmanCore._recover``).

        Their independent part (the frame noise, ``frame_psd``) is tiny and observed by no
        measurement: the GPS measures lat/lon and reaches x, y only through their correlation.
        The inflation scales it by alpha (x639 on rl_husky_gps.bag at 54 s) along with the
        rest, and what is left of it after the next fixes is then never reduced: x, y
        decorrelated from lat/lon (0.99 -> 0.18 in 20 s) and their sigma grew to 3.5 m for
        200 s while lat/lon held 0.2 m. So the pair differences are pinned back to the frame
        noise of one second, a constraint update c(s) = (x - E, y - N, psi + theta - pi/2)
        with that variance (Joseph form) and no innovation: the means agree to the frame
        mismatch already, only their errors drifted apart."""
        P = kf.P
        lat = float(kf.x[LAT])
        D = np.zeros((3, self.n))
        D[0, X], D[0, LON] = 1.0, -self.radius * math.cos(lat)
        D[1, Y], D[1, LAT] = 1.0, -self.radius
        D[2, PSI] = D[2, THETA] = 1.0
        Rc = np.diag((self.noise.frame_psd, self.noise.frame_psd, self.noise.frame_heading_psd))
        PD = P @ D.T
        K = np.linalg.solve(D @ PD + Rc, PD.T).T
        A = np.eye(self.n) - K @ D
        P_new = A @ P @ A.T + K @ Rc @ K.T
        kf.P = 0.5 * (P_new + P_new.T)

    def _frame_var(self, lat: float, scale: float) -> np.ndarray:
        d = np.zeros(N)
        v = self.noise.frame_psd * scale
        d[LAT] = v / self.radius**2
        d[LON] = v / (self.radius * math.cos(lat)) ** 2
        d[X] = d[Y] = v
        d[THETA] = d[PSI] = self.noise.frame_heading_psd * scale
        return d

    def _try_init_without_pose(self, m) -> bool:
        """Start from GPS (position) plus a heading, or at the origin without GPS. True when a
        GPS-course start replayed the held measurements, ``m`` with them."""
        if not self._has_gps:
            self._init(m.t, self._pose_given or (0.0, 0.0, 0.0),
                       self.noise.init_position_std ** 2, self.noise.init_heading_std ** 2)
            return False
        if isinstance(m, Heading) and m.sensor not in self._hoff_idx and m.source != "pose":
            # a compass with a known offset gives the heading; an estimated offset does not
            self._heading_init = (m.yaw - self._heading_offset(m.sensor), m.var)
        if not isinstance(m, GpsFix) or m.status < 0:
            if self._heading_init is None and self._pose_given is None:
                self._course.add(m)
            return False
        if self.datum is None:
            # the frame the fix's enu is in: a live converter's first fix may have been dropped
            # before it reached this filter, and the next one is then not the datum
            self.datum = m.datum if m.datum is not None else (m.lat, m.lon, m.alt)
            self.radius = sphere_radius(math.radians(self.datum[0]))
        e, n = self._fix_enu(m)
        pos_var = 0.5 * float(m.cov[0, 0] + m.cov[1, 1])
        if self._pose_given is not None:
            self._init(m.t, self._pose_given, self.noise.init_position_std ** 2,
                       self.noise.init_heading_std ** 2)
            return False
        if self._heading_init is not None:
            self._init(m.t, (e, n, self._heading_init[0]), pos_var, self._heading_init[1])
            self._fused_fix(m.sensor, m.t)  # the position is this fix's
            return False
        if m.enu is None:  # a live converter's fix: the course needs it in the local frame
            m.enu = (e, n, 0.0)
        got = self._course.add(m)
        if got is None:
            return False
        # the course's first fix starts the filter; what came after it is replayed, ``m`` (the
        # fix that decided) last. Each held message was counted before_init as it came: the
        # replayed ones are not
        rejected = self.log.rejected
        for b in got.replay:
            key = (b.sensor, "before_init")
            if b is not m and isinstance(b, _USED) and rejected.get(key):
                rejected[key] -= 1
                if not rejected[key]:
                    del rejected[key]
        self._init(got.t, (*got.position, got.heading), got.pos_sigma ** 2, got.psi_sigma ** 2)
        f0 = next(b for b in got.replay if isinstance(b, GpsFix) and b.t == got.t)
        self._fused_fix(f0.sensor, got.t)
        self.log.note(got.t, "heading initialised from the GPS course")
        # the held messages, in stamp order, are processed now: older than m, which came in
        # order, so the stamp-order check starts again with them
        self.newest_t = -math.inf
        for b in got.replay:
            if b is not f0:
                self.process(b)
        return True

    def _course_start(self) -> GpsCourseStart:
        """A fresh GPS-course start (at the beginning, and again after a restart)."""
        return GpsCourseStart.for_config(
            self.cfg, min_psi_sigma=COURSE_MIN_PSI_SIGMA, odometry_wait=COURSE_ODOMETRY_WAIT,
            distance=self.course_distance)

    def _fix_enu(self, m: GpsFix) -> tuple[float, float]:
        if m.enu is not None:
            return m.enu[0], m.enu[1]
        e, n, _ = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
        return e, n

