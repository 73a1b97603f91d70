"""`ddfuse inspect` on a bag whose topic carries two message types (two publishers on one topic):
the facts are of the topic's most frequent type, and a note says so; before, a traceback
(ValueError or IndexError in baginfo._summarise, an inhomogeneous array)."""

from __future__ import annotations

from pathlib import Path

import bagwriter as bw
from ddfuse.estimation.baginfo import bag_info
from ddfuse.evaluation.cli import main
from rosbags.rosbag1 import Writer


def _mixed_bag(path: Path, extra_first: bool) -> Path:
    """Odometry on /odom; on /fix, 49 NavSatFix and 30 Odometry messages (its own
    connection: bagwriter.write_bag refuses mixed types)."""
    store = bw.typestore("ros1")
    with Writer(path) as w:
        odom = w.add_connection("/odom", bw.ODOMETRY, typestore=store)
        conns = [w.add_connection("/fix", t, typestore=store)
                 for t in ((bw.ODOMETRY, bw.NAVSATFIX) if extra_first
                           else (bw.NAVSATFIX, bw.ODOMETRY))]
        fix_conn, other_conn = (conns[1], conns[0]) if extra_first else conns
        for k in range(1, 200):
            t = 1_600_000_000.0 + k * 0.05
            o = bw.odometry(t, 1.0)
            w.write(odom, round(t * 1e9), store.serialize_ros1(o.build(store), o.msgtype))
            if k % 4 == 0:
                f = bw.navsatfix(t, 47.0 + 1e-6 * k, 8.0)
                w.write(fix_conn, round(t * 1e9), store.serialize_ros1(f.build(store), f.msgtype))
                if k < 120:
                    w.write(other_conn, round(t * 1e9),
                            store.serialize_ros1(o.build(store), o.msgtype))
    return path


def test_inspect_a_topic_with_two_message_types(tmp_path, capsys):
    for extra_first in (False, True):
        bag = _mixed_bag(tmp_path / f"mixed{int(extra_first)}.bag", extra_first)
        info = {t.topic: t for t in bag_info(bag).topics}
        fix = info["/fix"]
        assert fix.msgtype == bw.NAVSATFIX and fix.count == 49
        assert fix.other_types == {bw.ODOMETRY: 29}
        assert main(["inspect", str(bag)]) == 0
        out, err = capsys.readouterr()
        assert err == ""
        assert ("/fix: carries messages of 2 types: 49 sensor_msgs/NavSatFix and 29 "
                "nav_msgs/Odometry (two publishers on one topic?); these facts are of the "
                "sensor_msgs/NavSatFix messages alone\n") in out
        assert "/fix: var east 1; covariance type [1]; 0 NO_FIX of 49" in out
