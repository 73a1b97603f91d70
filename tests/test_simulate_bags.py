"""Simulated bags: every format reads back with the same messages, through rosbags' AnyReader
and through the project's reader (estimation.bags.read_stream), and matches the simulation."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.measurements import (
    ForwardAccel,
    GpsFix,
    GyroYawRate,
    Heading,
    LandmarkObservation,
    WheelOdometry,
    WheelSpeeds,
)
from ddfuse.evaluation import cli
from ddfuse.evaluation import simulate as sim
from rosbags.highlevel import AnyReader


def plain(msg, skip=("seq",)):
    """A decoded rosbags message as nested tuples of (field, value); arrays as tuples.

    ``seq`` is skipped by default: ROS2 headers have none."""
    if dataclasses.is_dataclass(msg):
        return tuple((f.name, plain(getattr(msg, f.name), skip))
                     for f in dataclasses.fields(msg) if f.name not in skip)
    if isinstance(msg, np.ndarray):
        return tuple(msg.tolist())
    if isinstance(msg, (list, tuple)):
        return tuple(plain(m, skip) for m in msg)
    return msg


def read_all(path: Path, skip=("seq",)) -> dict[str, list]:
    """topic -> [(record time ns, msgtype, plain message)] in bag order."""
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append(
                (ns, conn.msgtype, plain(reader.deserialize(raw, conn.msgtype), skip)))
    return out


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A 40 s husky and seed002 run, each written in all three formats."""
    root = tmp_path_factory.mktemp("simbags")
    out = {}
    for name in ("husky", "seed002"):
        res = sim.simulate(name, seed=5, duration=40.0)
        paths = {}
        for fmt in sim.FORMATS:
            p = root / (f"{name}_{fmt}.bag" if fmt == "ros1" else f"{name}_{fmt}")
            paths[fmt] = sim.write_bag(res, p, fmt)
        out[name] = (res, paths)
    return out


@pytest.mark.parametrize("name", ["husky", "seed002"])
def test_formats_read_back_identically(bags, name):
    res, paths = bags[name]
    decoded = {fmt: read_all(p[0]) for fmt, p in paths.items()}
    ref = decoded["ros1"]
    expected_topics = {"/ground_truth"} | (
        {"/odom", "/imu/data", "/fix", "/ground_truth/fix"} if name == "husky"
        else {"/joint_states", "/landmarks"})
    assert set(ref) == expected_topics
    for fmt in ("ros2", "mcap"):
        assert set(decoded[fmt]) == set(ref)
        for topic in ref:
            assert decoded[fmt][topic] == ref[topic], f"{fmt} {topic}"
    # The landmark type is defined inside every bag, so a reader with no prior knowledge of it
    # decodes it (AnyReader registered it from the bag).
    if name == "seed002":
        assert ref["/landmarks"][0][1] == sim.LANDMARK_MSGTYPE
        assert len(ref["/landmarks"]) == len(res.landmarks.t)


def test_ros1_messages_carry_stamps_sequence_and_true_covariances(bags):
    res, paths = bags["husky"]
    msgs = read_all(paths["ros1"][0], skip=())
    sc = res.scenario
    for topic, lst in msgs.items():
        stamps = [ns for ns, _, _ in lst]
        assert stamps == sorted(stamps), topic
        for k, (ns, _, m) in enumerate(lst):
            hdr = dict(dict(m)["header"])
            stamp = dict(hdr["stamp"])
            assert stamp["sec"] * 10**9 + stamp["nanosec"] == ns  # record time = header stamp
            assert hdr["seq"] == k
    imu = dict(msgs["/imu/data"][0][2])
    assert imu["orientation_covariance"][8] == pytest.approx(sc.imu.heading_std**2)
    assert imu["angular_velocity_covariance"][8] == pytest.approx(sc.imu.gyro_std**2)
    assert imu["linear_acceleration_covariance"][0] == pytest.approx(sc.imu.accel_std**2)
    odom = dict(msgs["/odom"][0][2])
    twist_cov = dict(odom["twist"])["covariance"]
    n = res.noise()["odometry"]
    assert twist_cov[0] == pytest.approx(n["v"] ** 2)
    assert twist_cov[35] == pytest.approx(n["yaw_rate"] ** 2)
    fix = dict(msgs["/fix"][0][2])
    assert fix["position_covariance"][0] == pytest.approx(sc.gps.horizontal_std**2)
    assert fix["position_covariance"][8] == pytest.approx(sc.gps.vertical_std**2)
    assert fix["position_covariance_type"] == 2  # DIAGONAL_KNOWN


def _stream_key(m) -> tuple:
    if isinstance(m, GpsFix):
        return (type(m).__name__, m.t, m.lat, m.lon, m.alt, m.enu, m.cov.tolist())
    return tuple(getattr(m, f.name) for f in dataclasses.fields(m))


@pytest.mark.parametrize("name", ["husky", "seed002"])
def test_project_reader_reads_every_format_alike_and_matches_the_simulation(bags, name):
    res, paths = bags[name]
    streams = {}
    for fmt, (bag, cfg_path, _) in paths.items():
        cfg = load_config(cfg_path)
        s = read_stream(bag, cfg)
        assert not s.rejected, s.rejected
        streams[fmt] = s
    ref = streams["ros1"]
    for fmt in ("ros2", "mcap"):
        assert [_stream_key(m) for m in streams[fmt].measurements] == \
            [_stream_key(m) for m in ref.measurements], fmt
        assert streams[fmt].ground_truth == ref.ground_truth
    t0 = res.t0
    by = {}
    for m in ref.measurements:
        by.setdefault(type(m), []).append(m)
    gt = res.ground_truth
    assert len(ref.ground_truth) == len(gt.t)
    np.testing.assert_allclose([g.t - t0 for g in ref.ground_truth], gt.t, atol=2e-6)
    np.testing.assert_allclose([g.x for g in ref.ground_truth], gt.x, atol=1e-12)
    np.testing.assert_allclose([g.yaw for g in ref.ground_truth], gt.yaw, atol=1e-9)
    if name == "husky":
        assert ref.datum == res.scenario.datum
        odo = by[WheelOdometry]
        np.testing.assert_allclose([m.v for m in odo], res.encoders.v, atol=1e-12)
        np.testing.assert_allclose([m.yaw_rate for m in odo], res.encoders.yaw_rate, atol=1e-12)
        np.testing.assert_allclose([m.t - t0 for m in odo], res.encoders.t, atol=2e-6)
        head = by[Heading]
        # Yaw from the quaternion that also carries roll and pitch noise is the simulated yaw.
        np.testing.assert_allclose(sim.wrap(np.array([m.yaw for m in head]) - res.imu.yaw), 0.0,
                                   atol=1e-9)
        np.testing.assert_allclose([m.yaw_rate for m in by[GyroYawRate]], res.imu.yaw_rate,
                                   atol=1e-12)
        # less gravity's share along the measured attitude's forward axis: R_wb[2, 0] of
        # Rz Ry Rx is -sin(pitch)
        np.testing.assert_allclose([m.accel for m in by[ForwardAccel]],
                                   res.imu.accel[:, 0] + sim.G * np.sin(res.imu.pitch), atol=1e-9)
        fixes = by[GpsFix]
        np.testing.assert_allclose([m.t - t0 for m in fixes], res.gps.t, atol=2e-6)
        np.testing.assert_allclose([m.enu for m in fixes], res.gps.enu, atol=1e-6)
        assert fixes[0].cov[0, 0] == pytest.approx(res.scenario.gps.horizontal_std**2)
    else:
        assert ref.datum is None
        ws = by[WheelSpeeds]
        np.testing.assert_allclose([m.left for m in ws], res.encoders.left, atol=1e-12)
        np.testing.assert_allclose([m.right for m in ws], res.encoders.right, atol=1e-12)
        lms = by[LandmarkObservation]
        lm = res.landmarks
        assert [m.landmark_id for m in lms] == [lm.ids[i] for i in lm.index]
        np.testing.assert_allclose([m.range for m in lms], lm.range, atol=1e-12)
        np.testing.assert_allclose([m.bearing for m in lms], lm.bearing, atol=1e-12)
        assert set(ref.landmarks) == set(lm.ids)
        for i, lid in enumerate(lm.ids):
            assert ref.landmarks[lid] == pytest.approx(tuple(lm.positions[i]), abs=1e-12)


def test_sidecar_paths_and_no_overwrite(tmp_path):
    assert sim.sidecar_paths(tmp_path / "a.bag") == (tmp_path / "a.yaml",
                                                     tmp_path / "a.landmarks.yaml")
    assert sim.sidecar_paths(tmp_path / "dir") == (tmp_path / "dir.yaml",
                                                   tmp_path / "dir.landmarks.yaml")
    res = sim.simulate("seed002", seed=0, duration=10.0)
    (tmp_path / "x.bag").write_text("keep")
    with pytest.raises(FileExistsError):
        sim.write_bag(res, tmp_path / "x.bag")
    assert (tmp_path / "x.bag").read_text() == "keep"
    with pytest.raises(ValueError, match="format"):
        sim.write_bag(res, tmp_path / "y.bag", fmt="ros3")
    # another format of the same stem would replace the first bag's config and map (a seed-1
    # bag then read with seed 2's map: landmark range residuals of 11.7 m against a stated 0.1)
    sim.write_bag(res, tmp_path / "s.bag")
    kept = (tmp_path / "s.landmarks.yaml").read_text(), (tmp_path / "s.yaml").read_text()
    other = sim.simulate("seed002", seed=1, duration=10.0)
    with pytest.raises(FileExistsError, match="s.yaml exists"):
        sim.write_bag(other, tmp_path / "s.mcap", fmt="mcap")
    assert not (tmp_path / "s.mcap").exists()
    assert ((tmp_path / "s.landmarks.yaml").read_text(), (tmp_path / "s.yaml").read_text()) \
        == kept
    assert cli.main(["simulate", "seed002", "--seed", "1", "--duration", "10", "--format", "mcap",
                     "-o", str(tmp_path / "s.mcap")]) == 2


def test_main_writes_bag_config_and_map(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli.main(["simulate", "seed002", "--seed", "2", "--duration", "15", "--format", "mcap",
                     "-o", str(out)]) == 0
    assert (out / "run.mcap").is_file()
    cfg = load_config(tmp_path / "run.yaml")
    assert cfg.of_kind("landmarks")[0].map == tmp_path / "run.landmarks.yaml"
    assert "wrote" in capsys.readouterr().out
    assert cli.main(["simulate", "seed002", "--duration", "15", "-o", str(out)]) == 2  # exists
    assert "exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["simulate", "nope", "-o", str(tmp_path / "z.bag")])


def test_storage_file_is_named_after_the_directory_without_its_extension(tmp_path):
    assert sim.storage_file(tmp_path / "run", "mcap") == tmp_path / "run" / "run.mcap"
    assert sim.storage_file(tmp_path / "h.mcap", "mcap") == tmp_path / "h.mcap" / "h.mcap"
    assert sim.storage_file(tmp_path / "x.db3", "ros2") == tmp_path / "x.db3" / "x.db3"
    assert sim.storage_file(tmp_path / "a.b", "ros2") == tmp_path / "a.b" / "a.b.db3"
    assert sim.storage_file(tmp_path / "x.bag") == tmp_path / "x.bag"


@pytest.mark.parametrize(("fmt", "ext"), [("mcap", ".mcap"), ("ros2", ".db3")])
def test_a_path_with_the_storage_extension_names_the_file_in_the_directory(tmp_path, capsys,
                                                                           fmt, ext):
    """-o h.mcap: the directory h.mcap holds h.mcap (not h.mcap.mcap), stdout names both, the
    config is h.yaml beside it, and ddfuse run reads the bag by the directory and the file."""
    out = tmp_path / f"h{ext}"
    inner = out / f"h{ext}"
    assert cli.main(["simulate", "husky", "--duration", "10", "--format", fmt, "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == sorted([inner.name, "metadata.yaml"])
    # the sidecar where it always was; no staging directory left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, "h.yaml"])
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == [inner.name]
    assert f"wrote {out}{os.sep} (ROS 2 bag directory" in printed
    assert str(inner) in printed and ext + ext not in printed
    assert f"wrote {tmp_path / 'h.yaml'}" in printed
    ates = []
    # by the file too without -c: the directory's config (it was h.mcap/h.yaml: "no config")
    for k, (bag, extra) in enumerate(((out, []), (inner, []))):
        res_dir = tmp_path / f"res{k}"
        assert cli.main(["run", str(bag), *extra, "-o", str(res_dir), "--estimators", "ekf",
                         "--no-report"]) == 0
        m = json.loads((res_dir / "metrics.json").read_text())
        ates.append(m["estimators"]["ekf"]["ate_rmse_m"])
    assert ates[0] is not None and ates[0] == ates[1]


@pytest.mark.parametrize(("fmt", "name"), [("mcap", "m.bag"), ("ros2", "r.bag"),
                                           ("ros1", "x.mcap"), ("mcap", "y.db3")])
def test_an_extension_of_another_format_is_refused(tmp_path, capsys, fmt, name):
    """A name that says another format would be read as that one (an mcap directory called
    m.bag is taken for a ROS 1 bag): one line, exit 2, nothing written."""
    assert cli.main(["simulate", "husky", "--duration", "10", "--format", fmt, "-o",
                     str(tmp_path / name)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{name}: a name ending in" in err
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_long_bag_writes_and_reads(tmp_path):
    """The 2 h scenario as a ROS1 bag: written and read back through the project reader."""
    res = sim.simulate("long", seed=0)
    bag, cfg_path, _ = sim.write_bag(res, tmp_path / "long.bag")
    s = read_stream(bag, load_config(cfg_path))
    # only the scenario's outlier fixes (0.5 %, 20-60 m off) may be rejected: those that jump
    # further than the robot's top speed explains (estimation.robot_limits)
    assert len(s.rejected) == 1, s.rejected
    (topic, reason), n = next(iter(s.rejected.items()))
    assert topic == "/fix" and "robot.max_speed" in reason and 0 < n <= res.gps.outlier.sum()
    assert s.duration == pytest.approx(7200.0, abs=1.0)
    assert sum(isinstance(m, GyroYawRate) for m in s.measurements) == len(res.imu.t)
    assert math.isclose(s.t0, res.t0 + min(res.imu.t[0], res.encoders.t[0], res.gps.t[0]),
                        abs_tol=1e-6)
