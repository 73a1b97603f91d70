"""The files written beside a simulated bag: its ddfuse config (true noise) and landmark map.

The config states the simulator's true noise standard deviations (SI) and the NOMINAL robot
geometry with its stated uncertainty; its header comment gives the true values a config cannot
state (the true geometry, the IMU's offset and bias, the GPS latency and error model).
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import yaml
from ddfuse.evaluation.atomic_files import write_text
from ddfuse.evaluation.simulate.simulator import SimResult

SMOOTHER_LAG = 10.0  # s, the smoother lag of the configs written next to simulated bags


def sidecar_paths(path: str | Path) -> tuple[Path, Path]:
    """(config YAML, landmark map YAML) written next to a bag file or bag directory."""
    p = Path(path)
    stem = p.with_suffix("") if p.suffix in (".bag", ".mcap", ".db3") else p
    return stem.parent / (stem.name + ".yaml"), stem.parent / (stem.name + ".landmarks.yaml")


def sim_config(res: SimResult, landmark_map: str | None = None) -> dict:
    """The ddfuse config (as a YAML tree) describing a simulated bag, with the true noise."""
    sc = res.scenario
    noise = res.noise()
    sensors: dict[str, list] = {}
    if sc.encoders.odometry_topic:
        sensors["odometry"] = [{"topic": sc.encoders.odometry_topic, "use": ["v", "yaw_rate"],
                                "noise": noise["odometry"]}]
    if sc.encoders.joint_topic:
        sensors["wheels"] = [{"topic": sc.encoders.joint_topic,
                              "joints": list(sc.encoders.joints), "noise": noise["wheels"]}]
    if sc.imu:
        imu = {"topic": sc.imu.topic, "use": list(sc.imu.use), "noise": noise["imu"]}
        if "yaw" in sc.imu.use:
            imu["heading_offset"] = "estimate"
        imu["gyro_bias"] = "estimate"
        if "yaw" not in sc.imu.use:  # a gyro alone: no orientation noise, no offset walk
            imu["noise"] = {k: v for k, v in noise["imu"].items()
                            if k not in ("yaw", "heading_offset_walk")
                            and (k != "accel" or "accel" in sc.imu.use)}
        sensors["imu"] = [imu]
    if sc.magnetometer:
        m = sc.magnetometer
        sensors["magnetometer"] = [{"topic": m.topic, "noise": noise["magnetometer"],
                                    "declination": m.declination,
                                    "hard_iron": list(m.hard_iron), "heading_offset": 0.0}]
    if sc.gps:
        sensors["gps"] = [{"topic": sc.gps.topic, "noise": noise["gps"], "delay": sc.gps.delay}]
        if sc.gps.correlation_s > 0.0:  # the true error model, as the noise values are
            sensors["gps"][0]["correlation_time"] = sc.gps.correlation_s
        elif sc.gps.urban is not None:  # the open sky's wander; the stated noise stays the
            # receiver's optimistic one (docs/design/urban_gps.md)
            sensors["gps"][0]["correlation_time"] = sc.gps.urban.base_tau_s
    if sc.landmarks:
        if landmark_map is None:
            raise ValueError("a scenario with landmarks needs the landmark map's file name")
        sensors["landmarks"] = [{"topic": sc.landmarks.topic, "map": landmark_map,
                                 "noise": noise["landmarks"]}]
    robot = {"wheel_radius": sc.nominal_geometry.wheel_radius,
             "track_width": sc.nominal_geometry.track_width}
    if sc.geometry_std is not None:
        robot.update(wheel_radius_std=sc.geometry_std.wheel_radius,
                     track_width_std=sc.geometry_std.track_width)
    # the largest accelerations of the simulated motion (the commands are smooth; the
    # unicycle EKF derives its twist random walks from these)
    tr = res.truth
    for key, rate in (("max_accel", tr.v), ("max_yaw_accel", tr.w)):
        a_max = float(np.max(np.abs(np.gradient(rate, tr.dt))))
        if a_max > 0.0:  # a drive without any (a short straight one) states no limit
            robot[key] = a_max
    # what the simulated robot can do: half as much again as the fastest of its motion, rounded
    # up to 0.1 (the plausibility screen, ddfuse.estimation.robot_limits, rejects beyond it)
    for key, rate in (("max_speed", tr.v), ("max_yaw_rate", tr.w)):
        top = float(np.max(np.abs(rate)))
        if top > 0.0:
            robot[key] = math.ceil(15.0 * top) / 10.0
    # the simulated body moves exactly with its twist (the encoders' slip noise is in their
    # counts, not in the motion)
    slip = sc.config_slip or (0.0, 0.0, 0.0)
    robot["slip"] = dict(zip(("longitudinal", "lateral", "heading"), slip, strict=True))
    cfg: dict = {
        "sensors": sensors,
        "robot": robot,
        "ground_truth": {"topic": sc.truth_topic},
    }
    if sc.datum is not None:
        cfg["frame"] = {"datum": list(sc.datum)}
    cfg["initial_pose"] = "ground_truth"
    # a keyframe at every absolute measurement (GPS fix or landmark scan): attached to a rate
    # keyframe instead, a scan is carried there by the keyframe's twist, which one noisy
    # odometry sample ties, and k_w came out biased (seed002, docs/results/smoother_monte_carlo.md)
    cfg["smoother"] = {"lag": SMOOTHER_LAG, "keyframe": "gps", "robust": "huber"}
    cfg["ekf"] = {"rate": "event"}
    return cfg


def truth_comment(res: SimResult, fmt: str) -> str:
    """Header comment with the true values a config cannot state (for evaluation by eye)."""
    sc = res.scenario
    lines = [
        f"ddfuse config for a simulated bag: scenario {sc.name}, seed {res.seed}, "
        f"{sc.duration:g} s.",
        f"Regenerate: ddfuse simulate {sc.name} --seed {res.seed} "
        f"--duration {sc.duration:g} --format {fmt} -o <bag>",
        "Noise values are the simulator's true standard deviations (SI).",
        f"True geometry: wheel_radius {sc.true_geometry.wheel_radius} m, track_width "
        f"{sc.true_geometry.track_width} m (robot: below is the nominal one).",
    ]
    if sc.imu:
        lines.append(f"True IMU heading offset {sc.imu.heading_offset} rad; gyro bias starts at "
                     f"{sc.imu.gyro_bias0} rad/s, random walk {sc.imu.gyro_bias_walk} "
                     "rad/s/sqrt(s).")
    if sc.gps and sc.gps.urban is not None and res.gps.environment is not None:
        g, u, env = sc.gps, sc.gps.urban, res.gps.environment
        counts = [int(np.sum(env == k)) for k in range(4)]  # urban_gps: OPEN .. NLOS
        text = (f"GPS: latency {g.delay} s (fix stamped late), dropouts {g.dropout_prob}; "
                f"urban errors (docs/design/urban_gps.md): of {len(env)} fixes {counts[0]} in "
                f"open sky ({u.open_std:g} m per axis), {counts[1]} in street canyons "
                f"({u.canyon_std:g} m), {counts[2]} in multipath bursts "
                f"({u.burst_range[0]:g}-{u.burst_range[1]:g} m), {counts[3]} NLOS "
                f"({u.nlos_range[0]:g}-{u.nlos_range[1]:g} m); the receiver states "
                f"{g.horizontal_std:g} m throughout, and this config keeps the default GPS model "
                "(the gate); the model recommended for such fixes is gps: {model: dcs}.")
        # long: wrapped (the other lines stay as the committed sample configs have them)
        lines += textwrap.wrap(text, 98, break_on_hyphens=False)
    elif sc.gps:
        g = sc.gps
        lines.append(f"GPS: latency {g.delay} s (fix stamped late), dropouts {g.dropout_prob}, "
                     f"outliers {g.outlier_prob} ({g.outlier_range[0]:g}-{g.outlier_range[1]:g} "
                     f"m), outages {list(g.outages)} s after the start.")
        if g.correlation_s > 0.0:
            lines.append(f"GPS errors are time-correlated: per axis a first-order Gauss-Markov "
                         f"process, correlation time {g.correlation_s:g} s (correlation_time "
                         "below), stationary std as stated below.")
    return "".join(f"# {s}\n" for s in lines)


def write_sidecars(res: SimResult, path: str | Path, fmt: str = "ros1"
                   ) -> tuple[Path, Path | None]:
    """Write the config YAML (and the landmark map YAML) next to the bag at ``path``."""
    cfg_path, map_path = sidecar_paths(path)
    if res.landmarks is not None:
        lm = res.landmarks
        body = {"frame": "local",
                "landmarks": {i: [float(p[0]), float(p[1])] for i, p in zip(lm.ids, lm.positions,
                                                                            strict=True)}}
        write_text(map_path, f"# Simulated landmarks (scenario {res.scenario.name}, seed "
                            f"{res.seed}): id -> [x, y] m in the local frame\n"
                            + yaml.safe_dump(body, sort_keys=False))
    else:
        map_path = None
    cfg = sim_config(res, map_path.name if map_path else None)
    write_text(cfg_path, truth_comment(res, fmt) + yaml.safe_dump(cfg, sort_keys=False))
    return cfg_path, map_path
