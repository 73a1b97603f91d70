"""``simulate(scenario, seed)``: one run of a scenario, its truth and every sensor's samples.

Deterministic per seed: each part draws from its own random stream, derived from (seed, stream
name), so changing one sensor's settings does not change another's noise.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np
from ddfuse.evaluation.simulate.gps import GpsData, simulate_gps
from ddfuse.evaluation.simulate.motion import Truth, commands, integrate_truth
from ddfuse.evaluation.simulate.scenarios import Scenario, get_scenario, with_duration
from ddfuse.evaluation.simulate.sensors import (
    EncoderData,
    GroundTruthData,
    ImuData,
    LandmarkData,
    MagnetometerData,
    simulate_encoders,
    simulate_ground_truth,
    simulate_imu,
    simulate_landmarks,
    simulate_magnetometer,
)


@dataclass
class SimResult:
    """Everything one run produced. Times are seconds since the start; add ``t0`` for the header
    stamps' absolute seconds."""

    scenario: Scenario
    seed: int
    truth: Truth
    ground_truth: GroundTruthData
    encoders: EncoderData
    imu: ImuData | None = None
    gps: GpsData | None = None
    landmarks: LandmarkData | None = None
    magnetometer: MagnetometerData | None = None
    extras: dict = field(default_factory=dict)

    @property
    def t0(self) -> float:
        return self.scenario.t0_ns * 1e-9

    @property
    def duration(self) -> float:
        return self.scenario.duration

    def noise(self) -> dict[str, dict[str, float]]:
        """The true noise standard deviations by config sensor kind (SI), as the config states
        them. Odometry noise is about the NOMINAL-geometry twist of the true wheel speeds."""
        sc = self.scenario
        r, L = sc.nominal_geometry.wheel_radius, sc.nominal_geometry.track_width
        s = sc.encoders.speed_std
        out: dict[str, dict[str, float]] = {
            # v = r (wl + wr)/2, w = r (wr - wl)/L with independent wheel errors of std s
            "odometry": {"v": r * s / math.sqrt(2.0), "yaw_rate": math.sqrt(2.0) * r * s / L},
            "wheels": {"speed": s},
        }
        if sc.imu:
            # and the random walks of the gyro bias (rad/s/sqrt(s)) and of the heading offset
            # (rad/sqrt(s): none, it is constant)
            out["imu"] = {"yaw": sc.imu.heading_std, "yaw_rate": sc.imu.gyro_std,
                          "accel": sc.imu.accel_std, "gyro_bias_walk": sc.imu.gyro_bias_walk,
                          "heading_offset_walk": 0.0}
        if sc.gps:
            out["gps"] = {"horizontal": sc.gps.horizontal_std, "vertical": sc.gps.vertical_std}
        if sc.magnetometer:
            out["magnetometer"] = {"field": sc.magnetometer.noise_std}
        if sc.landmarks:
            out["landmarks"] = {"range": sc.landmarks.range_std,
                                "bearing": sc.landmarks.bearing_std}
        return out


def _rng(seed: int, stream: str) -> np.random.Generator:
    """An independent generator per (seed, stream name); crc32 is stable across runs."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(stream.encode())]))


def simulate(scenario: str | Scenario, seed: int = 0, duration: float | None = None
             ) -> SimResult:
    """Simulate a named scenario (see SCENARIOS) or a Scenario; deterministic per ``seed``."""
    sc = scenario if isinstance(scenario, Scenario) else get_scenario(scenario, duration)
    if isinstance(scenario, Scenario) and duration is not None:
        sc = with_duration(sc, duration)
    truth = _drive(sc, seed, sc.duration)
    res = SimResult(scenario=sc, seed=seed, truth=truth,
                    ground_truth=simulate_ground_truth(sc, truth),
                    encoders=simulate_encoders(sc, truth, _rng(seed, "encoders")))
    if sc.imu:
        res.imu = simulate_imu(sc, truth, _rng(seed, "imu"))
    if sc.gps:
        if sc.datum is None:
            raise ValueError(f"scenario {sc.name}: GPS needs a datum")
        res.gps = simulate_gps(sc, truth, _rng(seed, "gps"))
    if sc.magnetometer:
        res.magnetometer = simulate_magnetometer(sc, truth, _rng(seed, "magnetometer"))
    if sc.landmarks:
        # A run cut short of its drive keeps the whole drive's map, so that it is the same world
        # (the map is drawn in the path's bounding box, which a shorter path would shrink).
        drive = sc.drive_duration if sc.drive_duration is not None else sc.duration
        map_truth = truth if drive <= sc.duration else _drive(sc, seed, drive)
        res.landmarks = simulate_landmarks(sc, truth, _rng(seed, "landmarks"),
                                       _rng(seed, "landmark_map"), map_truth)
    return res


def _drive(sc: Scenario, seed: int, duration: float) -> Truth:
    """The true motion of ``sc``'s drive for ``seed``, run for ``duration`` s."""
    v_cmd, w_cmd = commands(sc.trajectory, duration, sc.substep, _rng(seed, "trajectory"),
                             sc.drive_duration)
    return integrate_truth(sc, v_cmd, w_cmd)
