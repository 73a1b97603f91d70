"""A GPS fix stating an implausibly small covariance is fused with the floor (``min_std``),
counted and warned about; covariances above the floor are untouched."""

from __future__ import annotations

import bagwriter as bw
import numpy as np
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import DEFAULT_GPS_MIN_STD, parse_config_text
from ddfuse.estimation.converters import Reject, converter
from ddfuse.estimation.errors import ConfigError
from ddfuse.estimation.measurements import GpsFix

T0 = 1700000000.0
DATUM = (47.0, 8.0, 400.0)
CFG = """
sensors:
  odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.02, yaw_rate: 0.02}}]
  gps: [{topic: /fix%s}]
frame: {datum: [47.0, 8.0, 400.0]}
"""
REASON = ("stated horizontal covariance below the floor (%g m)^2 (%s); "
          "the fix is used with the floor")
GIVEN = "sensors.gps[0].min_std"
DEFAULT = "the default for NavSatStatus %d; set sensors.gps[0].min_std"


def _convert(extra: str, cov9, cov_type: int = 2, status: int = 0):
    cfg = parse_config_text(CFG % extra)
    s = cfg.of_kind("gps")[0]
    conv = converter("gps", s, "sensors.gps[0]")
    return conv((T0, status, 47.0, 8.0, 400.0, tuple(cov9), cov_type))


def test_the_default_floor_follows_the_fix_status():
    # RTK (GBAS) reaches 1 cm, SBAS tens of cm, an unaugmented fix no better than 0.5 m
    assert DEFAULT_GPS_MIN_STD == {-1: 0.5, 0: 0.5, 1: 0.3, 2: 0.01}
    assert parse_config_text(CFG % "").of_kind("gps")[0].min_std is None
    (rtk,) = _convert("", bw.diag(1e-4, 1e-4, 1e-4), status=2)  # 1 cm from RTK: kept
    assert rtk.cov[0, 0] == 1e-4
    for status, std in ((2, 0.01), (1, 0.3), (0, 0.5)):
        with pytest.raises(Reject) as e:
            _convert("", bw.diag(1e-6, 1e-6, 1e-6), status=status)
        assert str(e.value) == REASON % (std, DEFAULT % status)
        assert e.value.kept[0].cov[0, 0] == pytest.approx(std * std)


def test_a_covariance_below_the_floor_is_raised_to_it_and_counted():
    with pytest.raises(Reject) as e:
        _convert(", min_std: 0.01", bw.diag(1e-12, 1e-12, 1e-12))
    assert str(e.value) == REASON % (0.01, GIVEN)
    (fix,) = e.value.kept  # used all the same
    assert isinstance(fix, GpsFix)
    assert np.allclose(fix.cov[:2, :2], np.eye(2) * 1e-4, rtol=0, atol=1e-16)
    assert fix.cov[2, 2] == 1e-12  # the vertical is not the floor's business


def test_only_the_direction_below_the_floor_is_raised():
    with pytest.raises(Reject) as e:
        _convert(", min_std: 0.5", bw.diag(4.0, 1e-6, 9.0))
    (fix,) = e.value.kept
    assert np.allclose(np.diag(fix.cov), [4.0, 0.25, 9.0])


def test_a_covariance_above_the_floor_is_untouched():
    (fix,) = _convert("", bw.diag(0.64, 0.81, 2.0))
    assert np.array_equal(np.diag(fix.cov), [0.64, 0.81, 2.0])


def test_the_configured_noise_replaces_the_stated_covariance_without_a_floor():
    (fix,) = _convert(", noise: {horizontal: 0.005}", bw.diag(1e-12, 1e-12, 1e-12))
    assert fix.cov[0, 0] == pytest.approx(0.005 ** 2)


@pytest.mark.parametrize("value", [0, -0.1, "x"])
def test_a_bad_min_std_names_the_key(value):
    with pytest.raises(ConfigError, match=r"sensors\.gps\[0\]\.min_std: must be"):
        parse_config_text(CFG % f", min_std: {value}")


def test_the_bag_stream_counts_the_floored_fixes_and_warns(tmp_path):
    recs = []
    for i in range(50):
        t = T0 + 0.4 * i
        lat, lon, _ = geodesy.enu_to_geodetic(0.4 * i, 0.0, 0.0, *DATUM)
        recs.append(("/odom", bw.odometry(t, 1.0, 0.0)))
        recs.append(("/fix", bw.navsatfix(t, lat, lon, DATUM[2],
                                          cov=bw.diag(1e-12, 1e-12, 1e-12), cov_type=2)))
    bag = bw.write_bag(tmp_path / "c.bag", "ros1", recs)
    bs = BagStream(bag, parse_config_text(CFG % ""))
    fixes = [m for m in bs if isinstance(m, GpsFix)]
    assert len(fixes) == 50 and all(f.cov[0, 0] == pytest.approx(0.25) for f in fixes)
    assert bs.rejected[("/fix", REASON % (0.5, DEFAULT % 0))] == 50
    (w,) = [w for w in bs.warnings if "floor" in w]
    assert "topic /fix: 50 of 50 messages" in w and "min_std" in w
