"""A stated frame.datum far from where the robot drives (a mistyped or another site's) is said
once, with the distance to the first fix (``estimation.geodesy.far_datum``)."""

from __future__ import annotations

import bagwriter as bw
import pytest
from ddfuse.estimation import geodesy
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import parse_config_text

T0 = 1700000000.0
SITE = (47.0, 8.0, 400.0)
CFG = """
sensors:
  odometry: [{topic: /odom, use: [v, yaw_rate], noise: {v: 0.02, yaw_rate: 0.02}}]
  gps: [{topic: /fix, noise: {horizontal: 1.0}}]
"""


def _bag(tmp_path):
    recs = []
    for i in range(100):  # 10 s straight east at 1 m/s, a fix every 0.5 s
        t = T0 + 0.1 * i
        recs.append(("/odom", bw.odometry(t, 1.0, 0.0)))
        if i % 5 == 0:
            lat, lon, _ = geodesy.enu_to_geodetic(0.1 * i, 0.0, 0.0, *SITE)
            recs.append(("/fix", bw.navsatfix(t, lat, lon, SITE[2])))
    return bw.write_bag(tmp_path / "d.bag", "ros1", recs)


@pytest.mark.parametrize("datum, far", [
    (None, None),  # the first fix: nothing to say
    ((47.0, 8.0, 400.0), None),
    ((47.5, 8.5, 400.0), None),  # 67 km: a large site, not a mistake
    ((47.0, 0.0001, 400.0), 607),  # a longitude mistyped
])
def test_a_datum_far_from_the_first_fix_is_said_once(tmp_path, datum, far):
    text = CFG + (f"frame: {{datum: [{datum[0]}, {datum[1]}, {datum[2]}]}}\n" if datum else "")
    bs = BagStream(_bag(tmp_path), parse_config_text(text))
    fixes = [m for m in bs if getattr(m, "enu", None) is not None]
    said = [w for w in bs.warnings if "frame.datum" in w]
    assert len(fixes) == 20  # converted exactly, whatever the datum
    if far is None:
        assert said == []
    else:
        (w,) = said
        assert f"topic /fix: the first fix (47.000000, 8.000000) is {far} km from frame.datum" \
            in w and "leave frame.datum out" in w
