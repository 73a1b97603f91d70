"""The truth drive: commanded body speed and yaw rate along a scenario's path, integrated exactly.

Commanded body speed v(t) (m/s) and yaw rate w(t) (rad/s) are turned into wheel angular speeds
through the TRUE wheel radius r and track width L (w_l = (v - w L/2)/r, w_r = (v + w L/2)/r),
held constant over substeps of ``Scenario.substep`` s, and the pose is integrated exactly over
each substep (closed-form SE(2) constant twist), so the truth is exact at any instant, not only
on the grid (``Truth.at``). The local frame is ENU about the datum (x east, y north, yaw from
east, CCW); the robot moves on the tangent plane (up = 0). Every trajectory kind starts from
rest and ends at rest (``TrajectorySpec``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.evaluation.simulate.scenarios import Scenario, TrajectorySpec


@dataclass
class Truth:
    """The exact motion: substep i covers [t[i], t[i] + dt) with constant wheel speeds.

    Arrays have shape (n,) except the pose arrays x, y, yaw, which have n + 1 entries (the pose
    at every substep boundary, the last at the end of the run). yaw is unwrapped (rad)."""

    dt: float  # s
    t: np.ndarray  # s, substep starts
    wheel_left: np.ndarray  # rad/s, true wheel angular speeds
    wheel_right: np.ndarray  # rad/s
    v: np.ndarray  # m/s, body forward speed
    w: np.ndarray  # rad/s, yaw rate
    x: np.ndarray  # m, east
    y: np.ndarray  # m, north
    yaw: np.ndarray  # rad, unwrapped
    angle_left: np.ndarray  # rad, wheel rotation at substep boundaries (n + 1)
    angle_right: np.ndarray  # rad

    @property
    def duration(self) -> float:
        return len(self.t) * self.dt

    def _index(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        i = np.clip(np.floor(t / self.dt).astype(np.int64), 0, len(self.t) - 1)
        return i, t - i * self.dt

    def at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Exact (x m, y m, yaw rad unwrapped, v m/s, w rad/s) at times ``t`` (s, any shape)."""
        i, tau = self._index(t)
        x, y, yaw = se2_step(self.x[i], self.y[i], self.yaw[i], self.v[i], self.w[i], tau)
        return x, y, yaw, self.v[i], self.w[i]

    def wheel_angles(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Wheel rotation (rad, left and right) since t = 0 at times ``t`` (s)."""
        i, tau = self._index(t)
        return (self.angle_left[i] + self.wheel_left[i] * tau,
                self.angle_right[i] + self.wheel_right[i] * tau)

    def accel(self, t) -> np.ndarray:
        """Forward acceleration dv/dt (m/s^2) at ``t``: the central difference of the substep
        speeds, interpolated linearly between substep midpoints (v itself is the midpoint sample
        of a smooth command, so this is its derivative to O(dt^2))."""
        a = np.gradient(self.v, self.dt)
        return np.interp(t, self.t + 0.5 * self.dt, a)


def wrap(a):
    """Wrap angles (rad) to [-pi, pi), the convention of ddfuse.estimation.estimator.wrap_angle."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def se2_step(x, y, yaw, v, w, dt):
    """Exact pose after constant (v m/s, w rad/s) for ``dt`` s from (x, y, yaw); arrays
    broadcast. Uses sin(a)/a = sinc and (1 - cos a)/a = sin(a/2) sinc(a/2), exact at a = 0."""
    a = w * dt
    d = v * dt
    dxb = d * np.sinc(a / np.pi)
    dyb = d * np.sin(0.5 * a) * np.sinc(a / (2.0 * np.pi))
    c, s = np.cos(yaw), np.sin(yaw)
    return x + c * dxb - s * dyb, y + s * dxb + c * dyb, yaw + a


def _smooth_noise(rng: np.random.Generator, t: np.ndarray, corr_time: float, count: int = 1,
                  span: float | None = None) -> list[np.ndarray]:
    """``count`` independent smooth zero-mean, unit-variance Gaussian processes sampled at ``t``
    (s, from 0).

    White noise on a grid of corr_time/8 s is filtered by a Gaussian kernel of std corr_time s
    (normalised to unit L2 norm, so the output variance is one) and interpolated linearly.

    ``span`` (s) makes the processes a function of the seed alone up to ``span``: every process
    first draws the white noise of a grid that reaches ``span``, whatever ``t`` covers, and only
    then does any process draw the grid's extension to a later ``t[-1]``. So the values at any
    time up to ``span`` are the same for every ``t``. With ``span`` None (or ``t[-1]``), the
    draws are those of a grid that just covers ``t``, process after process."""
    h = corr_time / 8.0
    k = np.arange(-32, 33) * h
    kernel = np.exp(-0.5 * (k / corr_time) ** 2)
    kernel /= np.sqrt(np.sum(kernel**2))
    t_end = t[-1] if len(t) else 0.0
    n = int(math.ceil(t_end / h)) + 2  # grid points of the output, the last beyond t_end
    n0 = n if span is None else int(math.ceil(span / h)) + 2
    white = [rng.standard_normal(n0 + len(kernel) - 1) for _ in range(count)]
    if n > n0:
        # Appended after every process's first block, so that the first blocks (and with them
        # the processes up to span) are what a run of length span draws.
        white = [np.concatenate([w, rng.standard_normal(n - n0)]) for w in white]
    out = []
    for w in white:
        g = np.convolve(w, kernel, mode="valid")  # g[i] depends on w[i : i + len(kernel)] only
        out.append(np.interp(t, np.arange(len(g)) * h, g))
    return out


def _ramp(x: np.ndarray) -> np.ndarray:
    """Raised-cosine step: 0 for x <= 0, 1 for x >= 1, C1 in between."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))


def _envelope(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Start from rest and end at rest: ramps of ``ramp`` s at both ends."""
    return _ramp(t / ramp) * _ramp((duration - t) / ramp)


def _periodic_curvature(lengths: list[float], kappas: list[float], smooth: float, ds: float
                        ) -> tuple[np.ndarray, np.ndarray, float]:
    """One period of a piecewise-constant curvature (1/m) over arc length, smoothed by a
    normalised Hann window of ``smooth`` m (circularly, so the smoothing preserves the total
    heading change of every segment). Returns (s grid m, kappa 1/m, period m)."""
    period = float(sum(lengths))
    n = int(round(period / ds))
    h = period / n
    # Cell averages of kappa from the exact heading function H(s) = integral of kappa (piecewise
    # linear), placed at cell centres: the cells then sum to exactly the segments' heading
    # changes, which sampling kappa at grid points would miss by up to h kappa per segment.
    seg_edges = np.cumsum([0.0] + list(lengths))
    heading = np.concatenate([[0.0], np.cumsum(np.multiply(lengths, kappas))])
    kappa = np.diff(np.interp(np.arange(n + 1) * h, seg_edges, heading)) / h
    s = (np.arange(n) + 0.5) * h
    m = max(3, int(round(smooth / h)) | 1)
    win = np.hanning(m + 2)[1:-1]
    win /= win.sum()
    half = m // 2
    padded = np.concatenate([kappa[-half:], kappa, kappa[:half]])
    return s, np.convolve(padded, win, mode="valid"), period


def _stop_profile(t: np.ndarray, sections: list[float], speed: float, ramp: float,
                  stop_time: float, dt: float) -> np.ndarray:
    """Speed (m/s) at substep midpoints ``t`` for repeated stop-to-stop sections of the given
    lengths (m): raised-cosine ramps of ``ramp`` s, cruise at ``speed``, then ``stop_time`` s at
    rest. Each section is scaled so that its substeps cover exactly its length."""
    pieces = []
    for d in sections:
        cruise = (d - speed * ramp) / speed
        if cruise < 0:
            raise ValueError(f"section of {d} m too short for a {ramp} s ramp at {speed} m/s")
        move = 2.0 * ramp + cruise
        n_move = int(math.ceil(move / dt))
        tm = (np.arange(n_move) + 0.5) * dt
        v = speed * _ramp(tm / ramp) * _ramp((move - tm) / ramp)
        v *= d / (v.sum() * dt)
        pieces += [v, np.zeros(int(round(stop_time / dt)))]
    lap = np.concatenate(pieces)
    reps = int(math.ceil(len(t) / len(lap)))
    return np.tile(lap, reps)[: len(t)]


def _substep_midpoints(duration: float, dt: float) -> np.ndarray:
    """Midpoints (s) of the substeps of ``dt`` s that cover ``duration`` s."""
    return (np.arange(int(round(duration / dt))) + 0.5) * dt


def commands(tr: TrajectorySpec, duration: float, dt: float, rng: np.random.Generator,
              drive_duration: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Commanded (v m/s, w rad/s) at the substep midpoints, for ``duration`` s.

    A random drive is drawn for ``drive_duration`` s (default ``duration``) and then cut (or
    extended) to ``duration``: the commands agree with those of a ``drive_duration`` run up to
    min(duration, drive_duration) - tr.ramp s, where the shorter run starts ramping down to rest."""
    tm = _substep_midpoints(duration, dt)
    env = _envelope(tm, duration, tr.ramp)
    if tr.kind == "random":
        # The last midpoint of the drive_duration run, computed as that run computes it, so that
        # the run of drive_duration s itself draws exactly what it would draw without ``span``
        # (the simulated sample bags stay byte-identical).
        base = _substep_midpoints(drive_duration, dt) if drive_duration is not None else tm
        span = float(base[-1]) if len(base) else 0.0
        g_v, g_w = _smooth_noise(rng, tm, tr.corr_time, count=2, span=span)
        v = tr.speed * np.clip(1.0 + tr.speed_rel_std * g_v, 0.2, 1.8) * env
        # Yaw rate scaled by the envelope too, so the robot does not turn on the spot at rest.
        return v, tr.yaw_rate_std * g_w * env
    if tr.kind == "wheel-steps":
        # One (left, right) draw per hold period, row by row, for the whole drive: a shorter run
        # sees the same wheel speeds as the drive it is cut from.
        span = max(duration, drive_duration or 0.0)
        lo, hi = tr.wheel_speeds
        wheels = rng.uniform(lo, hi, size=(int(math.ceil(span / tr.hold)) + 1, 2))
        k = np.minimum((tm / tr.hold).astype(np.int64), len(wheels) - 1)
        left, right = wheels[k, 0], wheels[k, 1]
        return 0.5 * (left + right) * env, (right - left) / tr.track_width * env
    if tr.kind == "figure-eight":
        v = tr.speed * env
        s_grid, kappa, period = _lemniscate_curvature(tr.half_width)
    elif tr.kind == "lawnmower":
        r = tr.spacing / 2.0
        half = tr.leg_length / 2.0
        # Start mid-leg so the circular smoothing does not bend the start.
        s_grid, kappa, period = _periodic_curvature(
            [half, math.pi * r, tr.leg_length, math.pi * r, half],
            [0.0, 1.0 / r, 0.0, -1.0 / r, 0.0], tr.smooth_length, 0.01)
        v = tr.speed * env
    elif tr.kind == "loop-stops":
        a, b = tr.loop_size
        r = tr.corner_radius
        arc = 0.5 * math.pi * r
        lead = 2.0  # m of straight between a stop and the next corner
        lengths = [lead, arc, b - 2 * r, arc, a - 2 * r, arc, b - 2 * r, arc, a - 2 * r - lead]
        kappas = [0.0, 1.0 / r, 0.0, 1.0 / r, 0.0, 1.0 / r, 0.0, 1.0 / r, 0.0]
        s_grid, kappa, period = _periodic_curvature(lengths, kappas, tr.smooth_length, 0.01)
        # Stops at s = 0 and two metres before every later corner: stop-to-stop distances.
        sections = [arc + b - 2 * r, arc + a - 2 * r, arc + b - 2 * r, arc + a - 2 * r]
        v = _stop_profile(tm, sections, tr.speed, tr.ramp, tr.stop_time, dt)
        v = v * _ramp((duration - tm) / tr.ramp)
    else:
        raise ValueError(f"unknown trajectory kind {tr.kind!r}")
    # Arc length at each substep midpoint; w = kappa(s) v keeps the path geometric (exact heading
    # change per segment) whatever the speed profile.
    s_mid = np.cumsum(v) * dt - 0.5 * v * dt
    k = np.interp(np.mod(s_mid, period), s_grid, kappa, period=period)
    return v, k * v


def _lemniscate_curvature(a: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Curvature (1/m) over arc length of the lemniscate of Gerono x = a sin u, y = a/2 sin 2u,
    starting at the crossing heading north-east. Returns (s grid m, kappa, lap length m)."""
    u = np.linspace(0.0, 2.0 * np.pi, 200001)
    dx, dy = a * np.cos(u), a * np.cos(2 * u)
    ddx, ddy = -a * np.sin(u), -2 * a * np.sin(2 * u)
    speed = np.hypot(dx, dy)
    kappa = (dx * ddy - dy * ddx) / speed**3
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(u))])
    return s[:-1], kappa[:-1], float(s[-1])


def integrate_truth(sc: Scenario, v_cmd: np.ndarray, w_cmd: np.ndarray) -> Truth:
    """Wheel speeds from the commands through the TRUE geometry, then the exact pose."""
    dt = sc.substep
    r, L = sc.true_geometry.wheel_radius, sc.true_geometry.track_width
    wl = (v_cmd - 0.5 * L * w_cmd) / r
    wr = (v_cmd + 0.5 * L * w_cmd) / r
    v = 0.5 * r * (wl + wr)
    w = r * (wr - wl) / L
    x0, y0, yaw0 = sc.trajectory.start
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(w * dt)])
    dx, dy, _ = se2_step(0.0, 0.0, yaw[:-1], v, w, dt)
    x = x0 + np.concatenate([[0.0], np.cumsum(dx)])
    y = y0 + np.concatenate([[0.0], np.cumsum(dy)])
    zero = np.zeros(1)
    return Truth(dt=dt, t=np.arange(len(v)) * dt, wheel_left=wl, wheel_right=wr, v=v, w=w,
                 x=x, y=y, yaw=yaw, angle_left=np.concatenate([zero, np.cumsum(wl * dt)]),
                 angle_right=np.concatenate([zero, np.cumsum(wr * dt)]))
