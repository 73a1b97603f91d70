"""estimation.baginfo (what `ddfuse inspect` reports): the facts of the real bags as documented in
../shared/data/README.md, suggested configs that load and read, and the IMU mount found from
gravity and the gyro's correlation with the odometry yaw rate on synthetic bags."""

from __future__ import annotations

import math
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
import yaml
from ddfuse.estimation.baginfo import GRAVITY, bag_info, imu_mount, suggest_config
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config, parse_config
from ddfuse.estimation.frames import rpy_matrix
from ddfuse.estimation.measurements import GpsFix, GyroYawRate, LandmarkObservation, WheelOdometry

T0 = 1_500_000_000.0


def topic(info, name):
    (t,) = [t for t in info.topics if t.topic == name]
    return t


def counts(stream) -> dict[str, int]:
    out: dict[str, int] = {}
    for m in stream.measurements:
        out[type(m).__name__] = out.get(type(m).__name__, 0) + 1
    return out


def write_suggested(info, tmp_path: Path) -> Path:
    p = tmp_path / "suggested.yaml"
    p.write_text(yaml.safe_dump(suggest_config(info), sort_keys=False))
    return p


def correlation(t_a, a, t_b, b) -> float:
    """Correlation of series a with b resampled at a's times."""
    order = np.argsort(t_b)
    ref = np.interp(t_a, np.asarray(t_b)[order], np.asarray(b)[order])
    return float(np.corrcoef(a, ref)[0, 1])


# --------------------------------------------------------------------------------------------
# The real bags
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def husky_info():
    from conftest import shared_bag

    return bag_info(shared_bag("rl_husky_gps.bag"))


@pytest.fixture(scope="module")
def jackal_info():
    from conftest import shared_bag

    return bag_info(shared_bag("rl_jackal.bag"))


def test_husky_topics_counts_rates(husky_info):
    info = husky_info
    got = {t.topic: (t.msgtype, t.count) for t in info.topics}
    assert got == {
        "/husky_velocity_controller/odom": ("nav_msgs/msg/Odometry", 3952),
        "/imu/data": ("sensor_msgs/msg/Imu", 11865),
        "/fix": ("sensor_msgs/msg/NavSatFix", 989),
    }
    for name, hz in (("/husky_velocity_controller/odom", 10.0), ("/imu/data", 30.0),
                     ("/fix", 2.5)):
        t = topic(info, name)
        assert t.rate_hz == pytest.approx(hz, rel=0.02)
        assert t.median_dt == pytest.approx(1.0 / hz, rel=0.05)
        assert t.t1 - t.t0 == pytest.approx(395.0, abs=1.0)
    assert info.duration == pytest.approx(395.0, abs=1.0)
    assert info.t0 == pytest.approx(1432235497.99, abs=0.5)  # header stamps, not record times


def test_husky_imu_is_mounted_y_up(husky_info):
    imu = topic(husky_info, "/imu/data")
    ax, ay, az = imu.accel_mean
    assert ay == pytest.approx(9.79, abs=0.05)
    assert abs(ax) < 0.5 and abs(az) < 0.5
    cx, cy, cz = imu.gyro_corr
    assert cy == pytest.approx(0.86, abs=0.03)
    assert abs(cx) < 0.1 and abs(cz) < 0.1
    assert imu.has_orientation and imu.cov_ok
    assert any("axis y" in n for n in imu.notes)
    mount = imu_mount(imu)
    assert mount == pytest.approx([math.pi / 2, 0.0, 0.0], abs=1e-3)
    up = np.asarray(rpy_matrix(*mount)) @ np.asarray(imu.accel_mean)
    assert up[2] == pytest.approx(9.79, abs=0.05)  # gravity reaction now on body +z


def test_husky_covariance_notes(husky_info):
    fix = topic(husky_info, "/fix")
    assert fix.cov_ok
    assert any("0.64..2.89" in n and "[1]" in n and "0 NO_FIX of 989" in n for n in fix.notes)
    odom = topic(husky_info, "/husky_velocity_controller/odom")
    assert odom.cov_ok and any("0.001" in n and "0.03" in n for n in odom.notes)


def test_husky_suggested_config_reads(husky_info, husky_bag, tmp_path):
    p = write_suggested(husky_info, tmp_path)
    cfg = load_config(p)
    assert {s.kind for s in cfg.sensors} == {"odometry", "imu", "gps"}
    imu = cfg.of_kind("imu")[0]
    assert imu.mount_rpy == pytest.approx((math.pi / 2, 0.0, 0.0), abs=1e-3)
    # a field about level (climbs within 4 deg: speeds 0.04 % over the horizontal): no slope
    assert topic(husky_info, "/imu/data").slope_excess < 1e-3
    assert cfg.of_kind("odometry")[0].slope is None
    s = read_stream(husky_bag, cfg)
    assert counts(s) == {"WheelOdometry": 3952, "Heading": 11865, "GyroYawRate": 11865,
                         "GpsFix": 989}
    assert s.rejected == {}
    assert s.duration == pytest.approx(395.0, abs=1.0)
    # With the suggested mount, the gyro's yaw rate follows the odometry's (README: 0.86).
    gy = [m for m in s.measurements if isinstance(m, GyroYawRate)]
    od = [m for m in s.measurements if isinstance(m, WheelOdometry)]
    c = correlation([m.t for m in gy], [m.yaw_rate for m in gy],
                    [m.t for m in od], [m.yaw_rate for m in od])
    assert c == pytest.approx(0.86, abs=0.03)
    fixes = [m for m in s.measurements if isinstance(m, GpsFix)]
    assert fixes[0].enu == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    north = max(f.enu[1] for f in fixes)
    assert 120.0 < north < 160.0  # "about 140 m north and back"


def test_jackal_facts_and_suggested_config(jackal_info, jackal_bag, tmp_path):
    info = jackal_info
    got = {t.topic: (t.msgtype, t.count) for t in info.topics}
    assert got == {"/jackal_velocity_controller/odom": ("nav_msgs/msg/Odometry", 3060),
                   "/imu/data": ("sensor_msgs/msg/Imu", 3061)}
    for t in info.topics:
        assert t.rate_hz == pytest.approx(50.0, rel=0.02)
        assert t.t1 - t.t0 == pytest.approx(61.0, abs=1.0)
    assert info.duration == pytest.approx(61.0, abs=1.0)
    imu = topic(info, "/imu/data")
    assert imu.accel_mean[2] == pytest.approx(GRAVITY, abs=0.2)  # mounted z up
    assert imu_mount(imu) == [0.0, 0.0, 0.0]
    cfg = load_config(write_suggested(info, tmp_path))
    assert {s.kind for s in cfg.sensors} == {"odometry", "imu"}
    assert cfg.of_kind("imu")[0].mount_rpy == (0.0, 0.0, 0.0)
    # skid steering: the odometry's yaw rate correlates 0.53 with the gyro (Husky: 0.86), so
    # the suggestion takes speed only from it; fused, it took every estimator ~10 m off
    assert max(abs(c) for c in imu.gyro_corr) < 0.8
    assert any("agrees poorly with this gyro" in n for n in imu.notes)
    assert cfg.of_kind("odometry")[0].use == ("v",)
    # climbs of up to 12 deg: the odometry's speed is projected with the IMU's climb
    assert imu.slope_excess == pytest.approx(0.0044, abs=0.0005)
    assert any("at most 11.9 deg" in n and "`slope` below" in n for n in imu.notes)
    assert cfg.of_kind("odometry")[0].slope == "/imu/data"
    s = read_stream(jackal_bag, cfg)
    assert counts(s) == {"WheelOdometry": 3060, "Heading": 3061, "GyroYawRate": 3061}
    assert s.rejected == {}


@pytest.mark.slow
def test_mrclam_facts(mrclam_bag):
    info = bag_info(mrclam_bag)
    got = {t.topic: (t.msgtype, t.count) for t in info.topics}
    assert got == {"/odom": ("nav_msgs/msg/Odometry", 75000),
                   "/landmarks": ("ddfuse_msgs/msg/LandmarkObservation", 4771),
                   "/ground_truth": ("nav_msgs/msg/Odometry", 75000)}
    assert topic(info, "/odom").rate_hz == pytest.approx(50.0, rel=0.02)
    assert info.t0 == pytest.approx(1.5e9, abs=1e-3)
    assert info.duration == pytest.approx(1499.98, abs=0.01)
    assert any("15 landmark ids" in n for n in topic(info, "/landmarks").notes)
    cfg = suggest_config(info)
    assert cfg["ground_truth"] == {"topic": "/ground_truth"}
    assert cfg["initial_pose"] == "ground_truth"
    assert Path(cfg["sensors"]["landmarks"][0]["map"]) == mrclam_bag.with_suffix(
        ".landmarks.yaml").resolve()


@pytest.mark.slow
def test_mrclam_suggested_config_reads(mrclam_bag, tmp_path):
    cfg = load_config(write_suggested(bag_info(mrclam_bag), tmp_path))
    s = read_stream(mrclam_bag, cfg)
    assert counts(s) == {"WheelOdometry": 75000, "LandmarkObservation": 4771}
    # 75000 truth messages less the resampled Vicon yaw's spins (estimation.truth_screen)
    assert len(s.ground_truth) == 75000 - 30 and len(s.landmarks) == 15
    assert s.rejected == {}
    lm = [m for m in s.measurements if isinstance(m, LandmarkObservation)]
    assert len({(m.t, m.landmark_id, m.range, m.bearing) for m in lm}) == 4771


# --------------------------------------------------------------------------------------------
# Synthetic bags: IMU mount detection
# --------------------------------------------------------------------------------------------

# name -> (sensor axis carrying +yaw rate as (axis, sign), specific force direction)
MOUNTS = {
    "z_up": ((2, +1.0), (0.0, 0.0, 1.0)),
    "z_down": ((2, -1.0), (0.0, 0.0, -1.0)),
    "y_up": ((1, +1.0), (0.0, 1.0, 0.0)),
    "y_down": ((1, -1.0), (0.0, -1.0, 0.0)),
    "x_up": ((0, +1.0), (1.0, 0.0, 0.0)),
}


def _mounted_imu_bag(tmp_path: Path, fmt: str, mount: str, with_odometry: bool = True,
                     n: int = 600) -> tuple[Path, np.ndarray, np.ndarray]:
    """Odometry at 10 Hz and an IMU at 30 Hz whose sensor frame is mounted as named; the
    yaw rate is 0.5 sin(0.7 t) (plus a little noise on every gyro axis)."""
    rng = np.random.default_rng(11)
    (axis, sign), up = MOUNTS[mount]
    recs = []
    t_imu = T0 + np.arange(n) / 30.0
    w_true = 0.5 * np.sin(0.7 * (t_imu - T0))
    for t, w in zip(t_imu, w_true, strict=True):
        gyro = rng.normal(0.0, 0.01, 3)
        gyro[axis] += sign * w
        acc = GRAVITY * np.asarray(up) + rng.normal(0.0, 0.05, 3)
        recs.append(("/imu", bw.imu(float(t), angvel=gyro, accel=acc,
                                    wcov=bw.diag(1e-4, 1e-4, 1e-4),
                                    acov=bw.diag(0.01, 0.01, 0.01))))
    if with_odometry:
        cov = bw.diag(1e-3, 1, 1, 1, 1, 0.03)
        for k in range(n // 3):
            t = T0 + k / 10.0
            recs.append(("/odom", bw.odometry(t, 0.5, 0.5 * math.sin(0.7 * (t - T0)),
                                              twist_cov=cov)))
    recs.sort(key=lambda r: r[1].stamp)
    bag = bw.write_bag(bw.bag_path(tmp_path, mount, fmt), fmt, recs)
    return bag, t_imu, w_true


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
@pytest.mark.parametrize("mount", list(MOUNTS))
def test_imu_mount_from_gravity_and_gyro(tmp_path, fmt, mount):
    bag, t_imu, w_true = _mounted_imu_bag(tmp_path, fmt, mount)
    info = bag_info(bag)
    imu = topic(info, "/imu")
    (axis, sign), up = MOUNTS[mount]
    assert imu.accel_mean == pytest.approx(tuple(GRAVITY * np.asarray(up)), abs=0.05)
    assert abs(imu.gyro_corr[axis]) > 0.95
    assert np.sign(imu.gyro_corr[axis]) == sign
    rpy = imu_mount(imu)
    r = np.asarray(rpy_matrix(*rpy))
    assert r @ np.asarray(up) == pytest.approx([0.0, 0.0, 1.0], abs=1e-3)
    if mount == "z_up":
        assert rpy == [0.0, 0.0, 0.0]
    # End to end: the suggested config's mount gives the yaw rate with the right sign.
    cfg = parse_config(suggest_config(info))
    s = read_stream(bag, cfg)
    gy = [m.yaw_rate for m in s.measurements if isinstance(m, GyroYawRate)]
    assert len(gy) == len(t_imu)
    assert np.max(np.abs(np.asarray(gy) - w_true)) < 0.06


@pytest.mark.parametrize("mount", ["y_up", "z_down"])
def test_imu_mount_from_gravity_alone(tmp_path, mount):
    bag, _, _ = _mounted_imu_bag(tmp_path, "ros1", mount, with_odometry=False)
    imu = topic(bag_info(bag), "/imu")
    assert imu.gyro_corr is None
    r = np.asarray(rpy_matrix(*imu_mount(imu)))
    assert r @ np.asarray(MOUNTS[mount][1]) == pytest.approx([0.0, 0.0, 1.0], abs=1e-3)


def test_imu_mount_does_not_guess_without_gravity(tmp_path):
    recs = [("/imu", bw.imu(T0 + i / 30, accel=(0.1, -0.2, 0.3), wcov=bw.diag(1, 1, 1)))
            for i in range(60)]
    bag = bw.write_bag(bw.bag_path(tmp_path, "free", "ros1"), "ros1", recs)
    assert imu_mount(topic(bag_info(bag), "/imu")) == [0.0, 0.0, 0.0]


# --------------------------------------------------------------------------------------------
# Synthetic bags: topic facts
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", bw.FORMATS)
def test_bag_info_facts_on_a_synthetic_bag(tmp_path, fmt):
    recs = []
    # 20 Hz odometry for 10 s with three stamps swapped against their neighbour
    stamps = [T0 + 0.05 * i for i in range(201)]
    for i in (50, 100, 150):
        stamps[i], stamps[i + 1] = stamps[i + 1], stamps[i]
    cov = bw.diag(1e-3, 1, 1, 1, 1, 0.0)  # zero yaw-rate variance: covariance not usable
    recs += [("/odom", bw.odometry(t, 1.0, 0.1, twist_cov=cov), T0 + 0.05 * i)
             for i, t in enumerate(stamps)]
    recs += [("/fix", bw.navsatfix(T0 + 0.5 * i, 42.0, -71.0, status=-1 if i < 2 else 0),
              T0 + 0.5 * i) for i in range(21)]
    recs += [("/ground_truth", bw.pose_stamped(T0 + 0.1 * i, i, 0.0), T0 + 0.1 * i)
             for i in range(101)]
    recs += [("/chatter", bw.Msg("std_msgs/msg/String", T0,
                                 lambda s: s.types["std_msgs/msg/String"](data="hi")),
              T0 + 1.0 * i) for i in range(4)]
    recs.sort(key=lambda r: r[2])
    bag = bw.write_bag(bw.bag_path(tmp_path, "facts", fmt), fmt, recs)
    info = bag_info(bag)
    assert {t.topic: t.count for t in info.topics} == {"/odom": 201, "/fix": 21,
                                                      "/ground_truth": 101, "/chatter": 4}
    odom = topic(info, "/odom")
    assert odom.rate_hz == pytest.approx(20.0, rel=1e-6)
    assert odom.median_dt == pytest.approx(0.05, rel=1e-6)
    assert odom.out_of_order == 3
    assert not odom.cov_ok
    fix = topic(info, "/fix")
    assert fix.rate_hz == pytest.approx(2.0, rel=1e-6)
    assert any("2 NO_FIX of 21" in n for n in fix.notes)
    chatter = topic(info, "/chatter")
    assert chatter.msgtype == "std_msgs/msg/String" and math.isnan(chatter.rate_hz)
    assert info.t0 == pytest.approx(T0, abs=1e-6) and info.duration == pytest.approx(10.0)
    cfg = suggest_config(info)
    assert cfg["ground_truth"] == {"topic": "/ground_truth"}
    assert "noise" in cfg["sensors"]["odometry"][0]  # the bag's covariance is not usable
    s = read_stream(bag, parse_config(cfg))
    assert counts(s) == {"WheelOdometry": 201, "GpsFix": 19}
    assert len(s.ground_truth) == 101
    assert sum(s.rejected.values()) == 2  # the two NO_FIX


def test_inspect_prints_a_loadable_config(tmp_path, capsys):
    from ddfuse.evaluation.cli import main

    bag, _, _ = _mounted_imu_bag(tmp_path, "ros1", "y_up", n=300)
    assert main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/imu" in out and "sensor_msgs/Imu" in out and "/odom" in out
    p = tmp_path / "from_cli.yaml"
    p.write_text(out)  # the facts are YAML comments: `ddfuse inspect BAG > from_cli.yaml`
    cfg = load_config(p)
    assert cfg.of_kind("imu")[0].mount_rpy == pytest.approx((math.pi / 2, 0.0, 0.0), abs=1e-3)
    s = read_stream(bag, cfg)
    assert counts(s) == {"GyroYawRate": 300, "Heading": 300, "WheelOdometry": 100}


@pytest.mark.parametrize("with_pose", [True, False])
def test_suggested_truth_is_a_pose_and_only_a_pose_gives_the_initial_pose(tmp_path, with_pose,
                                                                          capsys):
    """The simulator writes /ground_truth (Odometry) and /ground_truth/fix (NavSatFix). The
    suggestion took the last truth topic in name order, the fix, with initial_pose:
    ground_truth, and the run started every estimator at heading 0 with a 0.3 deg sigma (true
    heading 90 deg): NEES 23-81. A fix alone is truth for scoring, not a start pose."""
    from ddfuse.estimation.errors import ConfigError
    from ddfuse.estimation.runner import initial_pose

    recs = [("/odom", bw.odometry(T0 + 0.1 * i, 1.0, 0.0), T0 + 0.1 * i) for i in range(50)]
    recs += [("/ground_truth/fix", bw.navsatfix(T0 + 0.2 * i, 42.0 + 1e-6 * i, -71.0),
              T0 + 0.2 * i) for i in range(25)]
    if with_pose:
        recs += [("/ground_truth", bw.pose_stamped(T0 + 0.1 * i, 0.1 * i, 0.0, math.pi / 2),
                  T0 + 0.1 * i) for i in range(50)]
    recs.sort(key=lambda r: r[2])
    bag = bw.write_bag(bw.bag_path(tmp_path, "truths", "ros1"), "ros1", recs)
    cfg = suggest_config(bag_info(bag))
    if with_pose:
        assert cfg["ground_truth"] == {"topic": "/ground_truth"}
        assert cfg["initial_pose"] == "ground_truth"
        s = read_stream(bag, parse_config(cfg))
        assert initial_pose(cfg["initial_pose"], s)[2] == pytest.approx(math.pi / 2)
        return
    assert cfg["ground_truth"] == {"topic": "/ground_truth/fix"}
    assert "initial_pose" not in cfg
    # asked for anyway: a one-line error naming the key, not heading 0
    cfg["frame"] = {"datum": [42.0, -71.0, 0.0]}
    s = read_stream(bag, parse_config(cfg))
    with pytest.raises(ConfigError, match=r"initial_pose: ground_truth: the ground truth has "
                                          r"no heading"):
        initial_pose("ground_truth", s)
    p = tmp_path / "fix_truth.yaml"
    p.write_text(yaml.safe_dump({**cfg, "initial_pose": "ground_truth"}))
    from ddfuse.evaluation.cli import main

    assert main(["run", str(bag), "-c", str(p), "-o", str(tmp_path / "out"),
                 "--estimators", "ekf", "--no-report"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ddfuse: error: ") and "no heading" in err and "\n" not in err


def _fix_records(err_east_north: np.ndarray, sigma: float, dt: float = 0.4) -> list[tuple]:
    """NavSatFix records of a robot driving east at 1 m/s with these position errors (m)."""
    lat0, lon0 = 47.0, 8.0
    m_per_deg_lat = 111_200.0
    m_per_deg_lon = m_per_deg_lat * math.cos(math.radians(lat0))
    cov = (sigma**2, 0, 0, 0, sigma**2, 0, 0, 0, 4 * sigma**2)
    return [(T0 + dt * i, 0, lat0 + en[1] / m_per_deg_lat,
             lon0 + (dt * i + en[0]) / m_per_deg_lon, 400.0, cov, 2)
            for i, en in enumerate(err_east_north)]


def test_fix_scatter_tells_white_gps_errors_from_correlated_ones():
    from ddfuse.estimation.baginfo import fix_scatter
    from ddfuse.estimation.gps_scatter import scatter_correlation_time

    rng = np.random.default_rng(7)
    n, sigma = 1000, 1.0
    white = fix_scatter(_fix_records(sigma * rng.standard_normal((n, 2)), sigma))
    assert abs(white.rms - math.sqrt(1.5) * sigma) < 0.1  # 1.22 m; 3 % spread at n = 1000
    assert not white.correlated and white.recommended == 0
    assert "correlated" not in white.describe()
    # Gauss-Markov errors of the same sigma, correlation time 30 s (the husky-multipath model)
    a = math.exp(-0.4 / 30.0)
    e = np.zeros((n, 2))
    e[0] = sigma * rng.standard_normal(2)
    for i in range(1, n):
        e[i] = a * e[i - 1] + math.sqrt(1 - a * a) * sigma * rng.standard_normal(2)
    gm = fix_scatter(_fix_records(e, sigma))
    assert gm.correlated and "the errors are correlated in time" in gm.describe()
    # the correlation time those neighbours give back (the scatter's 2000 misses: ~5 %)
    assert gm.correlation_time == pytest.approx(30.0, rel=0.2)
    assert gm.recommended == round(gm.correlation_time)
    assert f"correlation_time: {gm.recommended}" in gm.describe()
    assert fix_scatter(_fix_records(e[:9], sigma)) is None  # too few to say
    # the model's own miss, exactly: sigma^2 (1 - rho)(3 - rho) / 2
    assert scatter_correlation_time(math.sqrt((1 - a) * (3 - a) / 2), 1.0, 0.4) == \
        pytest.approx(30.0, rel=1e-9)
    assert scatter_correlation_time(1.3, 1.0, 0.4) is None  # white errors miss by 1.22 sigma


def test_the_husky_gps_errors_are_found_correlated(husky_bag):
    """../shared/data/README.md: the midpoint of the two neighbouring fixes predicts a fix to
    about 0.16 m (0.11 per axis), far below the stated sigma of 0.8-1.7 m."""
    fix = topic(bag_info(husky_bag), "/fix")
    (note,) = [n for n in fix.notes if "neighbouring fixes" in n]
    assert 0.08 <= fix.scatter.rms <= 0.16 and "the errors are correlated in time" in note
    # stated sigma 0.80 m, fixes every 0.4 s: a Gauss-Markov error of 19.1 s, suggested as 19
    assert fix.scatter.correlation_time == pytest.approx(19.07, abs=0.01)
    assert fix.scatter.recommended == 19 and "correlation_time: 19" in note
