"""ddfuse.estimation.config: a full config loads with the right values; every validation error is a
ConfigError that names the file and the key path."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import yaml
from ddfuse.estimation.config import (
    DEFAULT_GATE,
    load_config,
    load_landmark_map,
    parse_config,
    resolve_landmark_maps,
)
from ddfuse.estimation.errors import ConfigError

FULL = """\
sensors:
  odometry:
    - topic: /husky_velocity_controller/odom
      use: [v, yaw_rate]
      noise: {v: 0.05, yaw_rate: 0.04}
  imu:
    - topic: /imu/data
      use: [yaw, yaw_rate, accel]
      mount: {rpy: [1.5708, 0.0, -0.1]}
      noise: {yaw: 0.05, yaw_rate: 0.02, accel: 0.1}
      heading_offset: estimate
      gyro_bias: 0.001
      gate: 0.999
  gps:
    - topic: /fix
      name: antenna
      noise: {horizontal: 1.5}
      lever_arm: [0.2, -0.1]
      gate: off
  wheels:
    - topic: /joint_states
      joints: [left_wheel, right_wheel]
      noise: {speed: 0.1}
  landmarks:
    - topic: /landmarks
      map: maps/some.landmarks.yaml
      noise: {range: 0.1, bearing: 0.05}
robot: {wheel_radius: 0.165, track_width: 0.555}
ground_truth: {topic: /ground_truth}
frame: {datum: [42.3758, -71.1474, 7.3]}
initial_pose: ground_truth
smoother: {lag: 12.5, keyframe: rate, keyframe_rate: 4.0, robust: cauchy, robust_k: 2.0}
ekf: {rate: 20}
reorder_window: 0.75
"""


@pytest.fixture
def full_config(tmp_path) -> Path:
    d = tmp_path / "cfg"
    (d / "maps").mkdir(parents=True)
    (d / "maps" / "some.landmarks.yaml").write_text("landmarks: {a: [1.0, 2.0]}\n")
    p = d / "robot.yaml"
    p.write_text(FULL)
    return p


def test_full_config_values(full_config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative paths resolve against the file, not the cwd
    cfg = load_config(full_config)
    assert cfg.path == full_config
    assert [(s.kind, s.topic, s.name) for s in cfg.sensors] == [
        ("odometry", "/husky_velocity_controller/odom", "/husky_velocity_controller/odom"),
        ("imu", "/imu/data", "/imu/data"),
        ("gps", "/fix", "antenna"),
        ("wheels", "/joint_states", "/joint_states"),
        ("landmarks", "/landmarks", "/landmarks"),
    ]
    odo = cfg.of_kind("odometry")[0]
    assert odo.use == ("v", "yaw_rate") and odo.noise == {"v": 0.05, "yaw_rate": 0.04}
    assert odo.mount_rpy == (0.0, 0.0, 0.0) and odo.gate == DEFAULT_GATE == 0.9999
    imu = cfg.sensor("/imu/data")
    assert imu.use == ("yaw", "yaw_rate", "accel")
    assert imu.mount_rpy == pytest.approx((1.5708, 0.0, -0.1))
    assert imu.noise == {"yaw": 0.05, "yaw_rate": 0.02, "accel": 0.1}
    assert imu.heading_offset == "estimate" and imu.gyro_bias == pytest.approx(0.001)
    assert imu.gate == pytest.approx(0.999)
    gps = cfg.sensor("antenna")
    assert gps.use == ("position",) and gps.noise == {"horizontal": 1.5}
    assert gps.lever_arm == pytest.approx((0.2, -0.1)) and gps.gate is None
    wheels = cfg.of_kind("wheels")[0]
    assert wheels.joints == ("left_wheel", "right_wheel") and wheels.noise == {"speed": 0.1}
    lm = cfg.of_kind("landmarks")[0]
    assert lm.map == full_config.parent / "maps" / "some.landmarks.yaml"
    assert lm.use == ("range", "bearing") and lm.noise == {"range": 0.1, "bearing": 0.05}
    assert (cfg.robot.wheel_radius, cfg.robot.track_width) == (0.165, 0.555)
    assert cfg.ground_truth_topic == "/ground_truth"
    assert cfg.datum == pytest.approx((42.3758, -71.1474, 7.3))
    assert cfg.initial_pose == "ground_truth"
    sm = cfg.smoother
    assert (sm.lag, sm.keyframe, sm.keyframe_rate, sm.robust, sm.robust_k) == (
        12.5, "rate", 4.0, "cauchy", 2.0)
    assert cfg.ekf.rate == 20.0
    assert cfg.reorder_window == 0.75
    assert cfg.topics == ["/husky_velocity_controller/odom", "/imu/data", "/fix",
                          "/joint_states", "/landmarks", "/ground_truth"]
    with pytest.raises(KeyError):
        cfg.sensor("/fix")  # it is called 'antenna'


def test_minimal_config_defaults():
    cfg = parse_config({"sensors": {"gps": {"topic": "/fix"}}})  # a mapping for a 1-list
    (gps,) = cfg.sensors
    assert gps.kind == "gps" and gps.name == "/fix" and gps.use == ("position",)
    assert gps.noise == {} and gps.gate == DEFAULT_GATE and gps.lever_arm == (0.0, 0.0)
    assert cfg.datum == "first_fix" and cfg.initial_pose is None
    assert cfg.ground_truth_topic is None and cfg.topics == ["/fix"]
    assert cfg.robot.wheel_radius is None and cfg.robot.track_width is None
    sm = cfg.smoother
    assert (sm.lag, sm.keyframe, sm.keyframe_rate, sm.robust, sm.robust_k) == (
        10.0, "gps", 2.0, "huber", None)
    assert cfg.ekf.rate == "event" and cfg.reorder_window == 0.5 and cfg.path is None


def test_use_as_a_string_and_other_accepted_forms():
    cfg = parse_config({
        "sensors": {"imu": [{"topic": "/imu", "use": "yaw_rate", "heading_offset": -0.3,
                             "gyro_bias": "estimate", "mount": {}}]},
        "frame": {"datum": "first_fix"}, "initial_pose": [1.0, -2, 0.5], "ekf": {"rate": "event"},
        "reorder_window": 0})
    imu = cfg.sensors[0]
    assert imu.use == ("yaw_rate",) and imu.heading_offset == -0.3
    assert imu.gyro_bias == "estimate" and imu.mount_rpy == (0.0, 0.0, 0.0)
    assert cfg.initial_pose == (1.0, -2.0, 0.5) and cfg.reorder_window == 0.0


def test_two_sensors_on_one_topic_with_names():
    cfg = parse_config({"sensors": {"imu": [
        {"topic": "/imu", "name": "gyro", "use": ["yaw_rate"]},
        {"topic": "/imu", "name": "compass", "use": ["yaw"]}]}})
    assert cfg.sensor("gyro").use == ("yaw_rate",) and cfg.sensor("compass").use == ("yaw",)


# --------------------------------------------------------------------------------------------
# Validation errors: each names its key path
# --------------------------------------------------------------------------------------------

GPS = {"topic": "/fix"}
BASE = {"sensors": {"gps": [GPS]}}


def with_(tree: dict, **top) -> dict:
    t = copy.deepcopy(tree)
    t.update(top)
    return t


def sensor(kind: str, **fields) -> dict:
    return {"sensors": {kind: [fields]}}


WHEELS_OK = {"topic": "/js", "joints": ["l", "r"], "noise": {"speed": 0.1}}
ROBOT = {"wheel_radius": 0.1, "track_width": 0.5}

ERRORS = [
    # unknown keys, at every level
    (with_(BASE, bogus=1), "bogus"),
    ({"sensors": {"lidar": [GPS]}}, "sensors.lidar"),
    (sensor("imu", topic="/imu", mnt={"rpy": [0, 0, 0]}), "sensors.imu[0].mnt"),
    (sensor("gps", topic="/fix", mount={"rpy": [0, 0, 0]}), "sensors.gps[0].mount"),
    (sensor("odometry", topic="/o", joints=["a", "b"]), "sensors.odometry[0].joints"),
    (with_(BASE, smoother={"lagg": 3}), "smoother.lagg"),
    (with_(BASE, robot={"radius": 0.1}), "robot.radius"),
    (with_(BASE, frame={"origin": [0, 0, 0]}), "frame.origin"),
    (with_(BASE, ekf={"rate": 10, "q": 1}), "ekf.q"),
    (with_(BASE, ground_truth={"topic": "/gt", "type": "odom"}), "ground_truth.type"),
    (sensor("imu", topic="/imu", mount={"xyz": [0, 0, 0]}), "sensors.imu[0].mount.xyz"),
    # topics
    (sensor("gps", noise={"horizontal": 1.0}), "sensors.gps[0].topic"),
    ({"sensors": {"imu": [{"topic": "/a", "name": "a"}, {"name": "b"}]}}, "sensors.imu[1].topic"),
    (sensor("gps", topic=""), "sensors.gps[0].topic"),
    (sensor("gps", topic=5), "sensors.gps[0].topic"),
    (with_(BASE, ground_truth={}), "ground_truth.topic"),
    # noise
    (sensor("imu", topic="/i", noise={"yaw_rate": -0.1}), "sensors.imu[0].noise.yaw_rate"),
    (sensor("imu", topic="/i", noise={"yaw_rate": 0}), "sensors.imu[0].noise.yaw_rate"),
    (sensor("imu", topic="/i", noise={"yaw_rate": "big"}), "sensors.imu[0].noise.yaw_rate"),
    (sensor("imu", topic="/i", noise={"yaw_rate": True}), "sensors.imu[0].noise.yaw_rate"),
    (sensor("imu", topic="/i", noise={"yaw_rate": math.nan}), "sensors.imu[0].noise.yaw_rate"),
    (sensor("imu", topic="/i", noise={"yaw": math.inf}), "sensors.imu[0].noise.yaw"),
    (sensor("imu", topic="/i", noise={"yaw": None}), "sensors.imu[0].noise.yaw"),
    (sensor("odometry", topic="/o", noise={"speed": 0.1}), "sensors.odometry[0].noise.speed"),
    (sensor("imu", topic="/i", noise=[0.1]), "sensors.imu[0].noise"),
    # use
    (sensor("odometry", topic="/o", use=["v", "heading"]), "sensors.odometry[0].use"),
    (sensor("odometry", topic="/o", use=[]), "sensors.odometry[0].use"),
    (sensor("gps", topic="/f", use=5), "sensors.gps[0].use"),
    (sensor("imu", topic="/i", use=["position"]), "sensors.imu[0].use"),
    # mount
    (sensor("imu", topic="/i", mount={"rpy": [1.57, 0]}), "sensors.imu[0].mount.rpy"),
    (sensor("imu", topic="/i", mount={"rpy": "y-up"}), "sensors.imu[0].mount.rpy"),
    (sensor("imu", topic="/i", mount={"rpy": [0, "a", 0]}), "sensors.imu[0].mount.rpy[1]"),
    (sensor("imu", topic="/i", mount={"rpy": [0, 0, math.nan]}), "sensors.imu[0].mount.rpy[2]"),
    (sensor("imu", topic="/i", mount=[0, 0, 0]), "sensors.imu[0].mount"),
    # other sensor fields
    (sensor("imu", topic="/i", heading_offset="auto"), "sensors.imu[0].heading_offset"),
    (sensor("imu", topic="/i", gyro_bias="x"), "sensors.imu[0].gyro_bias"),
    (sensor("gps", topic="/f", lever_arm=[1.0]), "sensors.gps[0].lever_arm"),
    (sensor("gps", topic="/f", gate=1.5), "sensors.gps[0].gate"),
    (sensor("gps", topic="/f", gate=1), "sensors.gps[0].gate"),
    (sensor("gps", topic="/f", gate="sometimes"), "sensors.gps[0].gate"),
    (sensor("gps", topic="/f", name=""), "sensors.gps[0].name"),
    # landmarks
    (sensor("landmarks", topic="/lm"), "sensors.landmarks[0].map"),
    (sensor("landmarks", topic="/lm", map="/nowhere/none.yaml"), "sensors.landmarks[0].map"),
    # frame.datum
    (with_(BASE, frame={"datum": [91.0, 0.0, 0.0]}), "frame.datum"),
    (with_(BASE, frame={"datum": [0.0, -180.5, 0.0]}), "frame.datum"),
    (with_(BASE, frame={"datum": [42.0, -71.0]}), "frame.datum"),
    (with_(BASE, frame={"datum": "origin"}), "frame.datum"),
    (with_(BASE, frame={"datum": [42.0, "x", 0.0]}), "frame.datum[1]"),
    # initial_pose
    (with_(BASE, initial_pose="gt"), "initial_pose"),
    (with_(BASE, initial_pose=[1.0, 2.0]), "initial_pose"),
    (with_(BASE, initial_pose="ground_truth"), "initial_pose"),
    (with_(BASE, initial_pose=[0, 0, "north"]), "initial_pose[2]"),
    (with_(BASE, initial_pose={"x": 0}), "initial_pose"),
    # smoother, ekf, reorder_window
    (with_(BASE, smoother={"robust": "tukey"}), "smoother.robust"),
    (with_(BASE, smoother={"robust": True}), "smoother.robust"),
    (with_(BASE, smoother={"keyframe": "time"}), "smoother.keyframe"),
    (with_(BASE, smoother={"lag": 0}), "smoother.lag"),
    (with_(BASE, smoother={"keyframe_rate": -2}), "smoother.keyframe_rate"),
    (with_(BASE, smoother={"robust_k": "big"}), "smoother.robust_k"),
    (with_(BASE, smoother=[10.0]), "smoother"),
    (with_(BASE, ekf={"rate": -5}), "ekf.rate"),
    (with_(BASE, ekf={"rate": "fast"}), "ekf.rate"),
    (with_(BASE, reorder_window=-0.1), "reorder_window"),
    # duplicate names
    ({"sensors": {"imu": [{"topic": "/imu"}, {"topic": "/imu"}]}}, "sensors"),
    ({"sensors": {"odometry": [{"topic": "/o", "name": "a"}],
                  "imu": [{"topic": "/i", "name": "a"}]}}, "sensors"),
    ({"sensors": {"gps": [{"topic": "/x"}], "imu": [{"topic": "/i", "name": "/x"}]}}, "sensors"),
    # wheels
    (with_(sensor("wheels", topic="/js", noise={"speed": 0.1}), robot=ROBOT),
     "sensors.wheels[0].joints"),
    (with_(sensor("wheels", topic="/js", joints=["l"], noise={"speed": 0.1}), robot=ROBOT),
     "sensors.wheels[0].joints"),
    (with_(sensor("wheels", topic="/js", joints=[1, 2], noise={"speed": 0.1}), robot=ROBOT),
     "sensors.wheels[0].joints"),
    (with_(sensor("wheels", topic="/js", joints=["l", "r"]), robot=ROBOT),
     "sensors.wheels[0].noise.speed"),
    (sensor("wheels", **WHEELS_OK), "robot"),
    (with_(sensor("wheels", **WHEELS_OK), robot={"wheel_radius": 0.1}), "robot"),
    (with_(BASE, robot={"wheel_radius": -0.1}), "robot.wheel_radius"),
    (with_(BASE, robot={"track_width": 0}), "robot.track_width"),
    # calibration statements
    (with_(BASE, robot={"wheel_radius_std": 0.01}), "robot.wheel_radius_std"),
    (with_(BASE, robot={"track_width": 0.5, "track_width_std": -0.01}),
     "robot.track_width_std"),
    (with_(BASE, robot={"slip": {"sideways": 0.1}}), "robot.slip.sideways"),
    (with_(BASE, robot={"slip": {"heading": -1}}), "robot.slip.heading"),
    (with_(BASE, robot={"slip": 0.1}), "robot.slip"),
    (with_(BASE, robot={"max_accel": -0.5}), "robot.max_accel"),
    (with_(BASE, robot={"max_yaw_accel": "fast"}), "robot.max_yaw_accel"),
    (with_(BASE, robot={"max_yaw_accel": 1e9}), "robot.max_yaw_accel"),
    (with_(BASE, robot={"max_accel": 100001}), "robot.max_accel"),
    (sensor("gps", topic="/fix", delay=-0.2), "sensors.gps[0].delay"),
    (sensor("gps", topic="/fix", delay="late"), "sensors.gps[0].delay"),
    (sensor("gps", topic="/fix", delay=100), "sensors.gps[0].delay"),  # milliseconds
    (sensor("odometry", topic="/o", delay=0.1), "sensors.odometry[0].delay"),
    (sensor("imu", topic="/i", noise={"gyro_bias_walk": -1e-4}),
     "sensors.imu[0].noise.gyro_bias_walk"),
    (sensor("imu", topic="/i", noise={"yaw": 0.0}), "sensors.imu[0].noise.yaw"),
    # no sensors / wrong shapes
    ({}, "sensors"),
    ({"sensors": {"imu": []}}, "sensors"),
    ({"sensors": {"imu": "/imu"}}, "sensors.imu"),
    ({"sensors": {"imu": None}}, "sensors.imu"),
    ({"sensors": ["/imu"]}, "sensors"),
    ({"sensors": {"imu": ["/imu"]}}, "sensors.imu[0]"),
]


@pytest.mark.parametrize(("tree", "key"), ERRORS, ids=[f"{i}:{c[1]}" for i, c in
                                                       enumerate(ERRORS)])
def test_validation_error_names_key(tree, key, tmp_path):
    with pytest.raises(ConfigError) as e:
        parse_config(tree, "robot.yaml", base=tmp_path)
    msg = str(e.value)
    # "<file>: <key path>: <problem>", the key path exactly (not a longer key that starts alike)
    assert msg.startswith(f"robot.yaml: {key}: "), msg
    assert len(msg) > len(f"robot.yaml: {key}: ") + 5  # and says what is wrong
    assert "\n" not in msg


def test_error_messages_say_what_is_wrong(tmp_path):
    def err(tree):
        with pytest.raises(ConfigError) as e:
            parse_config(tree, "c.yaml", base=tmp_path)
        return str(e.value)

    assert "-0.1" in err(sensor("imu", topic="/i", noise={"yaw_rate": -0.1}))
    assert "'heading'" in err(sensor("odometry", topic="/o", use=["v", "heading"]))
    assert "'/imu'" in err({"sensors": {"imu": [{"topic": "/imu"}, {"topic": "/imu"}]}})
    msg = err(sensor("landmarks", topic="/lm", map="/nowhere/none.yaml"))
    assert "/nowhere/none.yaml" in msg
    msg = err(with_(BASE, smoother={"robust": "tukey"}))
    assert "huber" in msg and "cauchy" in msg and "'tukey'" in msg
    assert "allowed" in err(with_(BASE, bogus=1))
    msg = err(sensor("gps", topic="/fix", delay=200))
    assert "at most 5 s, got 200" in msg and "not milliseconds" in msg
    assert parse_config(sensor("gps", topic="/fix", delay=5.0), "c.yaml",
                        base=tmp_path).sensor("/fix").delay == 5.0


def test_landmark_map_next_to_the_config_then_next_to_the_bag(tmp_path):
    (tmp_path / "m.yaml").write_text("landmarks: {a: [1, 2]}\n")
    cfg = parse_config(sensor("landmarks", topic="/lm", map="m.yaml"), base=tmp_path)
    resolve_landmark_maps(cfg, tmp_path / "elsewhere" / "run.bag")
    assert cfg.sensors[0].map == tmp_path / "m.yaml"
    # a shipped config names the map by the name it has beside its dataset's bag
    cfg = parse_config(sensor("landmarks", topic="/lm", map="m.yaml"), "c.yaml",
                       base=tmp_path / "configs")
    with pytest.raises(ConfigError) as e:
        resolve_landmark_maps(cfg)  # no bag: only next to the config
    assert str(e.value) == (f"c.yaml: sensors.landmarks[0].map: file not found: "
                            f"{tmp_path / 'configs' / 'm.yaml'}")
    with pytest.raises(ConfigError) as e:
        resolve_landmark_maps(cfg, tmp_path / "bags" / "run.bag")
    assert str(tmp_path / "bags" / "m.yaml") in str(e.value)  # both places named
    resolve_landmark_maps(cfg, tmp_path / "run.bag")
    assert cfg.sensors[0].map == tmp_path / "m.yaml"


def test_gate_zero_is_an_error():
    with pytest.raises(ConfigError) as e:
        parse_config(sensor("gps", topic="/f", gate=0), "c.yaml")
    assert "sensors.gps[0].gate" in str(e.value)


def test_gate_off_spellings():
    for g in ("off", False, None):
        assert parse_config(sensor("gps", topic="/f", gate=g)).sensors[0].gate is None
    assert yaml.safe_load("gate: off") == {"gate": False}  # what YAML makes of 'off'


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------

def test_load_config_errors_carry_the_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("sensors:\n  gps:\n    - topic: /fix\n      noise: {horizontal: -1}\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value).startswith(f"{p}: sensors.gps[0].noise.horizontal: ")


@pytest.mark.parametrize("text", ["sensors: [unclosed\n", "sensors:\n  gps:\n\t- topic: x\n",
                                  "a: b: c\n", "{{{{\n", "key: 'unterminated\n"])
def test_invalid_yaml_names_the_file(tmp_path, text):
    p = tmp_path / "broken.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert msg.startswith(str(p)) and "YAML" in msg and "\n" not in msg


def test_missing_config_file(tmp_path):
    p = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(p) in str(e.value)
    with pytest.raises(ConfigError) as e:
        load_config(tmp_path)  # a directory is not a config file
    assert str(tmp_path) in str(e.value)


@pytest.mark.parametrize("text", ["", "# only a comment\n", "- a\n- b\n", "42\n"])
def test_empty_or_non_mapping_file(tmp_path, text):
    p = tmp_path / "odd.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value).startswith(str(p))


def test_binary_config_file_is_a_config_error(tmp_path):
    p = tmp_path / "robot.bag"
    p.write_bytes(b"#ROSBAG V2.0\n\xff\xfe\x00\x01\x89binary")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(p) in str(e.value)


# --------------------------------------------------------------------------------------------
# Landmark maps
# --------------------------------------------------------------------------------------------

def test_landmark_map_loads(tmp_path):
    p = tmp_path / "m.yaml"
    p.write_text("landmarks:\n  6: [1.5, -2]\n  door: [0.0, 3.25]\n")
    assert load_landmark_map(p) == {"6": (1.5, -2.0), "door": (0.0, 3.25)}


@pytest.mark.parametrize(("text", "key"), [
    ("walls: {}\n", "landmarks"),
    ("landmarks: [1, 2]\n", "landmarks"),
    ("- 1\n", "landmarks"),
    ("landmarks:\n  7: [1.0]\n", "landmarks.7"),
    ("landmarks:\n  7: [1.0, north]\n", "landmarks.7[1]"),
])
def test_bad_landmark_map(tmp_path, text, key):
    p = tmp_path / "m.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    assert str(e.value).startswith(f"{p}: {key}: ")


def test_unreadable_landmark_map(tmp_path):
    for p, text in ((tmp_path / "none.yaml", None), (tmp_path / "bad.yaml", "a: [b\n")):
        if text is not None:
            p.write_text(text)
        with pytest.raises(ConfigError) as e:
            load_landmark_map(p)
        assert str(p) in str(e.value)


def test_binary_landmark_map(tmp_path):
    p = tmp_path / "m.yaml"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError) as e:
        load_landmark_map(p)
    assert str(p) in str(e.value)


def test_calibration_statements():
    """GPS delay, random walks of the IMU's calibration (0 allowed: constant), the geometry's
    uncertainty and the odometry scale uncertainties it implies, slip densities."""
    cfg = parse_config({
        "sensors": {"imu": [{"topic": "/i", "noise": {"gyro_bias_walk": 2e-4,
                                                      "heading_offset_walk": 0.0}}],
                    "gps": [{"topic": "/fix", "delay": 0.2}],
                    "odometry": [{"topic": "/o"}]},
        "robot": {"wheel_radius": 0.2, "track_width": 0.5, "wheel_radius_std": 0.004,
                  "track_width_std": 0.015, "slip": {"lateral": 0.0, "heading": 0.01},
                  "max_accel": 0.5, "max_yaw_accel": 0.3},
    })
    assert cfg.of_kind("gps")[0].delay == 0.2
    assert cfg.of_kind("imu")[0].noise == {"gyro_bias_walk": 2e-4, "heading_offset_walk": 0.0}
    sd_v, sd_w, c = cfg.robot.scale_std
    assert sd_v == pytest.approx(0.02) and c == pytest.approx(0.02**2)
    assert sd_w == pytest.approx(math.hypot(0.02, 0.03))
    assert cfg.robot.slip == {"lateral": 0.0, "heading": 0.01}
    assert (cfg.robot.max_accel, cfg.robot.max_yaw_accel) == (0.5, 0.3)
    assert parse_config(BASE).robot.scale_std is None


def test_exponents_without_a_dot_are_numbers(tmp_path):
    """YAML 1.1 (PyYAML's default) loads 1e-4 as a string; the README writes densities so."""
    p = tmp_path / "c.yaml"
    p.write_text("sensors:\n  imu:\n    - topic: /imu\n      use: [yaw_rate]\n"
                 "      noise: {yaw_rate: 2E-2, gyro_bias_walk: 1e-4}\n")
    noise = load_config(p).sensors[0].noise
    assert noise["gyro_bias_walk"] == 1e-4 and noise["yaw_rate"] == 0.02
    p.write_text("sensors:\n  imu:\n    - topic: /imu\n      use: [yaw_rate]\n"
                 "      noise: {yaw_rate: 1e-4x}\n")
    with pytest.raises(ConfigError, match=r"sensors.imu\[0\].noise.yaw_rate: must be a number"):
        load_config(p)


def test_frame_names_default_to_rep105_and_are_checked():
    from ddfuse.estimation.config import ConfigError, parse_config_text

    base = "sensors: {odometry: [{topic: /odom, noise: {v: 0.1, yaw_rate: 0.1}}]}\n"
    cfg = parse_config_text(base, "f.yaml")
    assert (cfg.local_frame, cfg.base_frame) == ("map", "base_link")
    cfg = parse_config_text(base + "frame: {local: odom, base: base_footprint}\n", "f.yaml")
    assert (cfg.local_frame, cfg.base_frame) == ("odom", "base_footprint")
    with pytest.raises(ConfigError, match=r"f\.yaml: frame\.base: a tf2 frame id has no "
                                          r"leading '/'"):
        parse_config_text(base + "frame: {base: /base_link}\n", "f.yaml")
    with pytest.raises(ConfigError, match=r"frame: local and base name the same frame"):
        parse_config_text(base + "frame: {local: a, base: a}\n", "f.yaml")
