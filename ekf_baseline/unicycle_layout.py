"""The unicycle EKF's set-up from its config (``ekf_baseline.unicycle``): its process noise, the
state vector's layout (which states follow the pose and twist, and where), the per-sensor
settings looked up once, and how it starts.

State order: x, y (m, local ENU), psi (rad), v (m/s), w (rad/s); then a gyro bias per IMU
estimating one (rad/s), a heading offset per heading sensor estimating one (rad), the odometry
scales k_v, k_w (``ekf_baseline.calibration``) when the config states the geometry's
uncertainty, and the twist's rates acc (m/s^2), yacc (rad/s^2) where ``robot.twist_walk``
states their densities (``TWIST_RATE_KEYS``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from ddfuse.ekf_baseline.calibration import ScaleStates
from ddfuse.ekf_baseline.unicycle_motion import ProcessNoise
from ddfuse.estimation.config import DEFAULT_GATE, HEADING_KINDS, Config

__all__ = ["TWIST_RATE_KEYS", "SensorSlot", "StateLayout", "process_noise", "start_mode"]

# robot.twist_walk's keys of the twist's rates (module docstring), per twist component
TWIST_RATE_KEYS = {"speed": "speed_rate", "yaw_rate": "yaw_rate_rate"}


class SensorSlot:
    """Per-sensor settings looked up once: gate, GPS lever arm, bias/offset handling."""

    __slots__ = ("gate", "lever", "bias_idx", "bias", "hoff_idx", "hoff", "uses", "delay",
                 "row", "use_w", "use_yaw", "tau")

    def __init__(self, gate=DEFAULT_GATE, lever=(0.0, 0.0), uses=None, delay=0.0, tau=0.0):
        self.gate = gate
        self.lever = lever
        self.delay = delay  # s, GPS: the fix is the position this long before its stamp
        self.tau = tau  # s, GPS: correlation time of its errors (0: white)
        self.bias_idx: int | None = None
        self.bias = 0.0  # rad/s, configured gyro bias when not estimated
        self.hoff_idx: int | None = None
        self.hoff = 0.0  # rad, configured heading offset when not estimated
        self.uses = uses  # None: everything the message carries
        self.row: int | None = None  # its row in the compiled core's sensor table
        self.use_w = uses is None or "yaw_rate" in uses  # gyro and heading used
        self.use_yaw = uses is None or "yaw" in uses


def process_noise(cfg: Config, noise: ProcessNoise | None
                  ) -> tuple[ProcessNoise, tuple[float | None, float | None]]:
    """The filter's densities and the acceleration limits (m/s^2, rad/s^2) that set the
    twist's walks per step (``twist_densities``; None: that walk is the density's). Given
    ``noise``, that and no limits; else the defaults with the robot's stated slip and twist
    walk in, and its limits for each twist component whose walk it does not state."""
    if noise is not None:
        return noise, (None, None)
    out = ProcessNoise()
    r = cfg.robot
    if r.slip:  # the robot's stated slip replaces the default densities
        out = replace(out, pos_long=r.slip.get("longitudinal", out.pos_long),
                      pos_lat=r.slip.get("lateral", out.pos_lat),
                      heading=r.slip.get("heading", out.heading))
    tw = r.twist_walk
    if tw:
        out = replace(out, acc=tw.get("speed", out.acc), yaw_acc=tw.get("yaw_rate", out.yaw_acc))
    return out, (None if "speed" in tw else r.max_accel,
                 None if "yaw_rate" in tw else r.max_yaw_accel)


@dataclass(frozen=True)
class StateLayout:
    """Where each state is (module docstring) and the per-sensor settings: ``names`` in state
    order; ``sensors`` by name; ``walks`` the calibration states' random-walk variances per
    second, in state order; ``scale`` the odometry scale states or None; ``w_true`` whether
    state 4 is the true yaw rate (a gyro with scale states) rather than the odometry's;
    ``rates`` per twist rate (twist index, rate index, variance per s); ``f_index`` and
    ``q_index`` the flat positions in the n x n F and Q that the motion terms fill."""

    names: tuple[str, ...]
    sensors: dict[str, SensorSlot]
    walks: tuple[float, ...]
    scale: ScaleStates | None
    w_true: bool
    rates: list[tuple[int, int, float]]
    f_index: np.ndarray
    q_index: np.ndarray

    @property
    def hoff_states(self) -> tuple[int, ...]:
        return tuple(i for i, nm in enumerate(self.names) if nm.startswith("hoff"))

    @property
    def bias_states(self) -> tuple[int, ...]:
        return tuple(i for i, nm in enumerate(self.names) if nm.startswith("bg"))

    @classmethod
    def of(cls, cfg: Config, noise: ProcessNoise, lie: bool) -> StateLayout:
        """The layout ``cfg`` gives, the calibration walks' defaults from ``noise``; ``lie``:
        the pose error in SE(2) coordinates (its rotation fills F's pose block too)."""
        names = ["x", "y", "psi", "v", "w"]
        sensors: dict[str, SensorSlot] = {}
        imus_b = [s for s in cfg.of_kind("imu")
                  if s.gyro_bias == "estimate" and "yaw_rate" in s.use]
        imus_h = [s for s in cfg.heading_sensors() if s.heading_offset == "estimate"]
        for s in cfg.sensors:
            info = SensorSlot(gate=s.gate, lever=tuple(s.lever_arm), uses=set(s.use),
                              delay=s.delay,
                              tau=float(s.correlation_time) if s.kind == "gps" else 0.0)
            if s.kind in HEADING_KINDS:
                if isinstance(s.gyro_bias, float):
                    info.bias = s.gyro_bias
                if isinstance(s.heading_offset, float):
                    info.hoff = s.heading_offset
            sensors[s.name] = info
        # random-walk densities (variance per second) of the calibration states, in state
        # order: the IMU's stated ones (noise.gyro_bias_walk, heading_offset_walk), else the
        # defaults
        walks: list[float] = []
        for s in imus_b:
            sensors[s.name].bias_idx = len(names)
            names.append("bg" if len(imus_b) == 1 else f"bg:{s.name}")
            walks.append(s.noise.get("gyro_bias_walk", noise.gyro_bias) ** 2)
        for s in imus_h:
            sensors[s.name].hoff_idx = len(names)
            names.append("hoff" if len(imus_h) == 1 else f"hoff:{s.name}")
            walks.append(s.noise.get("heading_offset_walk", noise.heading_offset) ** 2)
        # odometry scale states (ddfuse.ekf_baseline.calibration) when the config states the
        # geometry's uncertainty and a sensor gives odometry
        scale = ScaleStates.append_to(cfg, names)
        # with a gyro, state 4 is the true yaw rate, else the odometry's
        w_true = bool(scale) and any("yaw_rate" in s.use for s in cfg.of_kind("imu"))
        if scale:  # states 3, 4 are then the odometry-frame twist
            names[3:5] = ["v_odo", "w" if w_true else "w_odo"]
        rates: list[tuple[int, int, float]] = []
        for ti, nm, comp in ((3, "acc", "speed"), (4, "yacc", "yaw_rate")):
            q = cfg.robot.twist_walk.get(TWIST_RATE_KEYS[comp])
            if q:
                rates.append((ti, len(names), q * q))
                names.append(nm)
        n = len(names)
        fr, fc = [0, 0, 0, 1, 1, 1, 2], [2, 3, 4, 2, 3, 4, 4]
        if scale:  # scaled_step_terms' order: the scale columns of x, y, psi
            kv, kw = scale.index, scale.index + 1
            fr, fc = fr + [0, 0, 1, 1, 2], fc + [kv, kw, kv, kw, kw]
        if lie:  # se2_error_terms: then the pose block's rotation
            fr, fc = fr + [0, 0, 1, 1], fc + [0, 1, 0, 1]
        # the upper and lower triangle of the 5x5 block (unicycle_process_noise's order), then
        # the diagonal of the bias and the offset states
        iu = np.triu_indices(5)
        diag = np.array([i for i, nm in enumerate(names) if nm.startswith("bg")]
                        + [i for i, nm in enumerate(names) if nm.startswith("hoff")], dtype=int)
        q_index = np.ravel_multi_index(
            (np.concatenate([iu[0], iu[1], diag]), np.concatenate([iu[1], iu[0], diag])), (n, n))
        return cls(tuple(names), sensors, tuple(walks), scale, w_true, rates,
                   np.ravel_multi_index((fr, fc), (n, n)), q_index)


def start_mode(cfg: Config, initial_pose: tuple[float, float, float] | None
               ) -> tuple[str, tuple[float, float, float] | None]:
    """How the filter starts, and the initial pose (the given one, else the config's):
    'pose' (a given pose), 'ground_truth' (the first truth sample), 'heading' (position from
    the first fix or the origin, heading measured by a sensor with a known offset), 'align'
    (dead-reckon, then align onto the GPS track) or 'origin'."""
    if initial_pose is None and isinstance(cfg.initial_pose, tuple):
        initial_pose = cfg.initial_pose
    if initial_pose is not None:
        return "pose", initial_pose
    if cfg.initial_pose == "ground_truth":
        return "ground_truth", None
    if any(isinstance(s.heading_offset, float) for s in cfg.heading_sensors()):
        return "heading", None
    return ("align" if cfg.of_kind("gps") else "origin"), None
