"""Config values that loaded without a word, or ended in a bare TypeError/OverflowError (audit
13): each is now a ConfigError naming the key and saying what is wrong."""

from __future__ import annotations

import math

import pytest
from ddfuse.estimation.config import parse_config, parse_config_text
from ddfuse.estimation.errors import ConfigError


def sensor(kind: str, **fields) -> dict:
    return {"sensors": {kind: [fields]}}


ROBOT = {"wheel_radius": 0.1, "track_width": 0.5}
ODOM = {"topic": "/o"}

# (tree, key path the error names, a word the problem must contain)
CASES = [
    # unknown keys of mixed YAML types: sorting them raised TypeError
    ({"sensors": {"odometry": [ODOM], True: [ODOM], "imu2": [ODOM]}}, "sensors.True", "boolean"),
    ({"sensors": {"odometry": [ODOM], 1: "x", "foo": "y"}}, "sensors.1", "unknown key"),
    # noise that was dropped for being falsy
    (sensor("odometry", topic="/o", noise=0), "sensors.odometry[0].noise", "mapping"),
    (sensor("odometry", topic="/o", noise=[]), "sensors.odometry[0].noise", "mapping"),
    # a std whose square is no variance; an integer beyond any float (was OverflowError)
    (sensor("odometry", topic="/o", noise={"v": 1e-200}), "sensors.odometry[0].noise.v",
     "variance"),
    (sensor("odometry", topic="/o", noise={"yaw_rate": 1e200}),
     "sensors.odometry[0].noise.yaw_rate", "variance"),
    (sensor("imu", topic="/i", noise={"gyro_bias_walk": 1e-170}),
     "sensors.imu[0].noise.gyro_bias_walk", "variance"),
    (sensor("gps", topic="/f", noise={"horizontal": 10 ** 400}), "sensors.gps[0].noise.horizontal",
     "finite"),
    # an acceleration limit of 0: a zero process-noise density for the twist (on the sample
    # bag both at 0 took the unicycle EKF's ATE from 0.11 to 1.37 m, its NEES from 2.9 to 379)
    ({**sensor("odometry", **ODOM), "robot": {"max_accel": 0}}, "robot.max_accel", "> 0"),
    ({**sensor("odometry", **ODOM), "robot": {"max_yaw_accel": 0.0}}, "robot.max_yaw_accel",
     "> 0"),
    # geometry in millimetres (a wheel radius of 1e9 ran, only the screen warned)
    ({**sensor("odometry", **ODOM), "robot": {"wheel_radius": 165, "track_width": 0.555}},
     "robot.wheel_radius", "165 mm is 0.165 m"),
    ({**sensor("odometry", **ODOM), "robot": {"wheel_radius": 0.165, "track_width": 555}},
     "robot.track_width", "in metres"),
    ({**sensor("odometry", **ODOM), "robot": {"wheel_radius": 0.165, "track_width": 0.555,
                                              "track_width_std": 1000.0}},
     "robot.track_width_std", "at most robot.track_width (0.555 m)"),
    # process noise no ground robot has (config fuzzing: a twist walk of 1000 took the
    # unicycle EKF's ATE on the sample from 0.12 to 3.3 m with its NEES passing; a slip of 100
    # made the smoother's system indeterminate)
    ({**sensor("odometry", **ODOM), "robot": {"twist_walk": {"speed": 1000.0}}},
     "robot.twist_walk.speed", "at most 100"),
    ({**sensor("odometry", **ODOM), "robot": {"slip": {"heading": 100.0}}},
     "robot.slip.heading", "at most 10"),
    (sensor("gps", topic="/f", lever_arm=[0.3, 1e12]), "sensors.gps[0].lever_arm",
     "within 100 m"),
    # one joint as both wheels
    ({**sensor("wheels", topic="/js", joints=["a", "a"], noise={"speed": 0.1}), "robot": ROBOT},
     "sensors.wheels[0].joints", "twice"),
    # a vertical sigma that was silently ignored
    (sensor("gps", topic="/f", noise={"vertical": 2.0}), "sensors.gps[0].noise.vertical",
     "horizontal"),
    # a start's yaw and a fixed heading offset in degrees (90 ran as 90 rad)
    ({**sensor("odometry", **ODOM), "initial_pose": [0.0, 0.0, 90.0]}, "initial_pose[2]",
     "the yaw is in radians (90 deg would be 1.5708)"),
    (sensor("imu", topic="/i", use=["yaw"], noise={"yaw": 0.02}, heading_offset=20.0),
     "sensors.imu[0].heading_offset", "the offset is in radians"),
    # a mount in degrees
    (sensor("imu", topic="/i", mount={"rpy": [90, 0, 0]}), "sensors.imu[0].mount.rpy[0]",
     "radians"),
    (sensor("odometry", topic="/o", mount={"rpy": [0, 0, -180]}),
     "sensors.odometry[0].mount.rpy[2]", "radians"),
]


@pytest.mark.parametrize(("tree", "key", "word"), CASES,
                         ids=[f"{i}:{c[1]}" for i, c in enumerate(CASES)])
def test_bad_values_are_config_errors_naming_the_key(tree, key, word):
    with pytest.raises(ConfigError) as e:
        parse_config(tree, "robot.yaml")
    msg = str(e.value)
    assert msg.startswith(f"robot.yaml: {key}: "), msg
    assert word in msg and "\n" not in msg


def test_an_unquoted_on_key_in_a_file_is_named():
    """cfgs/mixed_keys.yaml of the audit: ``on`` is YAML 1.1's True."""
    text = "sensors:\n  odometry: [{topic: /odom}]\n  on: [{topic: /x}]\n  imu2: [{topic: /i}]\n"
    with pytest.raises(ConfigError, match=r"^c.yaml: sensors.True: unknown key \(YAML reads"):
        parse_config_text(text, "c.yaml")


@pytest.mark.parametrize("value", [0.0, 1e-150])
def test_a_walk_may_still_be_zero_and_small_values_stay(value):
    cfg = parse_config(sensor("imu", topic="/i", noise={"gyro_bias_walk": value,
                                                         "yaw_rate": 1e-150}))
    assert cfg.sensors[0].noise == {"gyro_bias_walk": value, "yaw_rate": 1e-150}


def test_a_mount_within_two_pi_and_gps_horizontal_with_vertical_load():
    cfg = parse_config({"sensors": {"imu": [{"topic": "/i",
                                             "mount": {"rpy": [-2 * math.pi, math.pi, 0]}}],
                                    "gps": [{"topic": "/f", "noise": {"horizontal": 1.0,
                                                                      "vertical": 3.0}}]},
                        "robot": {"max_accel": 0.5}})
    assert cfg.sensors[0].mount_rpy == (-2 * math.pi, math.pi, 0.0)
    assert cfg.sensors[1].noise == {"horizontal": 1.0, "vertical": 3.0}
    assert cfg.robot.max_accel == 0.5


def test_a_key_given_twice_a_yaml_error_and_a_directory_are_named(tmp_path):
    """A second `sensors:` block silently replaced the first (PyYAML keeps the last); a YAML
    syntax error said "while parsing a flow node" and not where; `-c` naming a directory said
    "config file not found"."""
    from ddfuse.estimation.config import load_config

    twice = tmp_path / "twice.yaml"
    twice.write_text("sensors:\n  gps:\n    - topic: /fix\nsensors:\n  odometry:\n"
                     "    - topic: /odom\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: key 'sensors' given twice "
                                          r"\(lines 1 and 4\)"):
        load_config(twice)
    broken = tmp_path / "broken.yaml"
    broken.write_text("sensors:\n  gps: [{topic: /fix\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: not valid YAML: expected ',' or '}'"
                                          r".* at line 3, column 1"):
        load_config(broken)
    with pytest.raises(ConfigError, match=r": is a directory, not a config file"):
        load_config(tmp_path)
