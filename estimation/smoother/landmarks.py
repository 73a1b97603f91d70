"""Landmark fusion: a range/bearing (or range-only) sighting of a mapped landmark as a factor on
the window's keyframe nearest its stamp, from the keyframe pose carried along its twist to the
sighting (``ddfuse.factors.landmark``), gated as in the landmark EKF (``Gating``).

Landmark positions: east/north in m, the map's frame (the config's ``landmark_maps``); range in
m, bearing in rad from the body's x axis. Design notes: docs/design/smoother.md (Landmarks).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from ddfuse.estimation.config import LANDMARK_NOT_IN_MAP, Config, SensorConfig
from ddfuse.estimation.estimator import EstimatorLog, Innovation, wrap_angle
from ddfuse.estimation.landmark_correlation import SightingClock
from ddfuse.estimation.landmark_frames import FrameBearings
from ddfuse.estimation.measurements import LandmarkObservation
from ddfuse.estimation.smoother.gating import RECOVER, REJECT, Gating
from ddfuse.estimation.smoother.noise import gate_radius, robust
from ddfuse.estimation.smoother.window import Window
from ddfuse.factors.kinematics import se2_step_jac
from ddfuse.factors.landmark import range_bearing_factor, range_factor
from ddfuse.factors.state import DIM


class LandmarkFusion:
    """Builds the landmark factors against the known map ``landmarks`` (id -> (east, north))."""

    def __init__(self, cfg: Config, sensors: dict[str, SensorConfig], landmarks: dict,
                 window: Window, gating: Gating, log: EstimatorLog,
                 flush: Callable[[], None]) -> None:
        """``flush``: sends the window's pending factors to gtsam (re-initialising on
        failure), before a lock-out's widening."""
        self.cfg, self.sensors, self.landmarks = cfg, sensors, landmarks
        self.window, self.gating, self.log, self.flush = window, gating, log, flush
        self.clock = SightingClock(cfg)  # a correlated sensor's factor on R (the factor only)
        self.frames = FrameBearings(cfg)  # bearings with an error common to their frame

    def fuse(self, m: LandmarkObservation, k: int, dt: float) -> None:
        """A sighting ``dt`` s after keyframe ``k``: a range/bearing (or range) factor from the
        keyframe pose carried along its twist to the sighting (``ddfuse.factors.landmark``), if it
        passes its sensor's chi-square gate as in the landmark EKF (``Gating.verdict``; a
        delayed one against its own keyframe's marginal). With ``noise.bearing_common``, the
        bearing conditional on the frame's earlier sightings on the same keyframe and offset
        (``estimation.landmark_frames``), in the gate and the factor alike."""
        lm = self.landmarks.get(m.landmark_id)
        if lm is None:
            self.log.rejected[(m.sensor, LANDMARK_NOT_IN_MAP)] += 1
            return
        s = self.sensors[m.sensor]
        # the factor's sigma times sqrt(f) (estimation.landmark_correlation); the gate keeps R
        wide = math.sqrt(self.clock.factor(m))
        window = self.window
        frame = self.frames.terms(m, (k, dt)) if self.frames else None
        if k == window.k and window.kf_state is not None:
            inn = self.innovation(m, lm, dt, window.kf_state, window.newest_marginal(),
                                  frame=frame)
            if inn is not None:
                verdict = self.gating.verdict(m, s, inn[0])
                if verdict == REJECT:
                    return
                if verdict == RECOVER:
                    self.flush()  # as GpsFusion.widen: the keyframe's own factors first
                    again = self.innovation(m, lm, dt, window.kf_state, window.full, log=False,
                                            frame=frame)
                    if again is not None:  # (None: on top of the landmark, nothing to widen)
                        _, y, H, R = again
                        k = self.gating.widen_link(m.sensor, m.t, H, y, R, "sighting")
                        if frame is not None:  # on another keyframe: a frame of its own
                            frame = self.frames.terms(m, (k, dt))
        elif k != window.k and s.gate is not None:
            try:
                inn = self.innovation(m, lm, dt, *window.estimate_of(k), frame=frame)
            except (RuntimeError, IndexError, ValueError):
                inn = None  # not in the smoother yet: ungated
            if inn is not None and inn[0] > gate_radius(s.gate, len(inn[1])) ** 2:
                self.log.rejected[(m.sensor, "gate")] += 1
                self.log.innovations[-1].accepted = False
                return
        if frame is not None:
            sig = (wide * math.sqrt(m.range_var), wide * math.sqrt(frame.bearing_var))
            f = range_bearing_factor(
                window.key(k), lm, m.range, m.bearing, robust(self.cfg, s, sig), dt=dt,
                earlier=[((*ref, zb), w) for (ref, zb), w in zip(frame.earlier, frame.weights,
                                                                  strict=True)])
            self.frames.accepted(m, lm)
        elif m.has_bearing:
            sig = (wide * math.sqrt(m.range_var), wide * math.sqrt(m.bearing_var))
            f = range_bearing_factor(window.key(k), lm, m.range, m.bearing,
                                     robust(self.cfg, s, sig), dt=dt)
        else:
            f = range_factor(window.key(k), lm, m.range,
                             robust(self.cfg, s, (wide * math.sqrt(m.range_var),)), dt=dt)
        window.add(f)
        self.gating.landmark_t = m.t

    def innovation(self, m: LandmarkObservation, lm, dt: float, st: np.ndarray,
                   full: np.ndarray, log: bool = True, frame=None):
        """Range (and bearing) innovation of a sighting ``dt`` s after a keyframe with state
        ``st`` and marginal ``full`` (DIM, DIM), before it is fused: the model of
        ``ddfuse.factors.landmark`` (the pose carried along the keyframe's twist), its covariance
        through the carry's Jacobian on pose and twist. Logged for the NIS unless ``log`` is
        False; ``frame``: its frame's ``FrameTerms`` (the bearing conditional on the earlier
        sightings, ``estimation.landmark_frames``) or None. Returns (nis, y (m,), H (m, DIM),
        R (m, m)), None on top of the landmark."""
        st = st.tolist() if hasattr(st, "tolist") else list(st)
        x, y, psi, j = se2_step_jac(st[0], st[1], st[2], st[3], st[4], dt)
        dx, dy = lm[0] - x, lm[1] - y
        q = dx * dx + dy * dy
        r = math.sqrt(q)
        if r < 1e-6:
            return None  # on top of the landmark: no bearing, and the range Jacobian is undefined
        hp = np.array(((-dx / r, -dy / r, 0.0), (dy / q, -dx / q, -1.0)))
        H = np.zeros((2, DIM))
        H[:, :5] = hp @ np.array(j)
        res = np.array((m.range - r, wrap_angle(m.bearing - math.atan2(dy, dx) + psi)))
        R = np.diag((m.range_var, m.bearing_var))
        if frame is not None:
            for ((lx, ly), zb), w in zip(frame.earlier, frame.weights, strict=True):
                ex, ey = lx - x, ly - y
                qj = max(ex * ex + ey * ey, 1e-12)
                res[1] -= w * wrap_angle(zb - math.atan2(ey, ex) + psi)
                H[1, :5] -= w * (np.array((ey / qj, -ex / qj, -1.0)) @ np.array(j))
            R[1, 1] = frame.bearing_var
        if not m.has_bearing:
            H, res, R = H[:1], res[:1], R[:1, :1]
        cov = H[:, :5] @ full[:5, :5] @ H[:, :5].T + R
        nis = float(res @ np.linalg.solve(cov, res))
        if log:
            self.log.innovations.append(Innovation(m.t, m.sensor, "landmark", res, cov, nis,
                                                   True))
        return nis, res, H, R

