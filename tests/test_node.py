"""The core of ``ddfuse node`` without ROS: the sample bag's messages, deserialised by rosbags,
fed one by one with their record times as receive times."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from ddfuse.estimation.bags import open_reader
from ddfuse.estimation.config import ConfigError, load_config, parse_config
from ddfuse.estimation.estimate_msgs import FixOut, OdometryOut, TransformOut
from ddfuse.evaluation.diagnostics import OK, STALE
from ddfuse.evaluation.node import DIAGNOSTICS, TF, NodeCore

ROOT = Path(__file__).resolve().parents[1]
BAG, CFG = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"


@pytest.fixture(scope="module")
def cfg():
    return replace(load_config(CFG), initial_pose=None)  # no truth on a robot


@pytest.fixture(scope="module")
def messages(cfg):
    """(topic, rosbags message, record time s) of the sample bag's configured topics."""
    reader = open_reader(BAG)
    topics = set(cfg.topics)
    conns = [c for c in reader.connections if c.topic in topics]
    out = [(c.topic, reader.deserialize(raw, c.msgtype), ns * 1e-9)
           for c, ns, raw in reader.messages(connections=conns)]
    reader.close()
    return out


def _feed(core: NodeCore, messages, diagnostics: list | None = None) -> list:
    pubs = []
    for topic, msg, rt in messages:
        pubs += core.receive(topic, msg, rt)
        if diagnostics is not None:
            d = core.diagnostics(rt)
            if d is not None:
                diagnostics.append((rt, d))
    return pubs


@pytest.fixture(scope="module")
def fed(cfg, messages):
    core = NodeCore(cfg, ["ekf", "smoother"])
    pubs = _feed(core, messages)
    pubs += core.finish()
    return core, pubs


def test_node_publishes_each_estimator_at_its_rate_and_the_tf_of_the_smoother(fed, messages):
    core, pubs = fed
    odom = [p.fields for p in pubs if p.topic == "/ddfuse/ekf/odom"]
    assert all(isinstance(f, OdometryOut) for f in odom)
    assert all(isinstance(p.fields, FixOut) for p in pubs if p.topic.endswith("/fix"))
    span = messages[-1][2] - messages[0][2]
    # 20 Hz of the receive clock, never the same estimate twice
    assert 0.9 * 20 * span < len(odom) <= 20 * span + 2
    stamps = [f.stamp for f in odom]
    assert np.all(np.diff(stamps) > 0)
    tf = [p.fields for p in pubs if p.topic == TF]
    assert core.tf_name == "smoother" and all(isinstance(f, TransformOut) for f in tf)
    assert len(tf) == len([p for p in pubs if p.topic == "/ddfuse/smoother/odom"])
    assert (odom[0].frame_id, odom[0].child_frame_id) == (core.cfg.local_frame,
                                                         core.cfg.base_frame)


def test_lagged_keyframes_are_published_as_they_leave_the_window_stamped_with_their_time(fed):
    core, pubs = fed
    lagged = [(i, p.fields) for i, p in enumerate(pubs)
              if p.topic == "/ddfuse/smoother_lagged/odom"]
    track = core.session.estimators["smoother"].lagged_estimates()
    assert len(lagged) == len(track) > 10
    assert [f.stamp for _, f in lagged] == pytest.approx([track[i].t for i in range(len(track))])
    # published during the run (before finish), each at least a lag behind the newest filtered
    # estimate published before it
    lag = core.cfg.smoother.lag
    first_i, first = lagged[0]
    before = [p.fields.stamp for p in pubs[:first_i] if p.topic == "/ddfuse/smoother/odom"]
    assert before and max(before) - first.stamp >= lag - 0.5


def test_node_final_estimates_match_run_on_the_same_bag(fed, cfg, tmp_path):
    from ddfuse.evaluation.pipeline import run_bag

    core, pubs = fed
    m = run_bag(BAG, cfg, tmp_path, names=["ekf", "smoother"])
    for name in ("ekf", "smoother"):
        last = [p.fields for p in pubs if p.topic == f"/ddfuse/{name}/odom"][-1]
        x, y = m.estimators[name].final_xy
        assert math.hypot(last.position[0] - x, last.position[1] - y) < 0.05, name


def test_write_results_gives_runs_files_for_what_was_fused(cfg, messages, tmp_path):
    core = NodeCore(cfg, ["ekf"], keep_measurements=True)
    _feed(core, messages[: len(messages) // 2])
    core.finish()
    summary = core.write_results(tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert (tmp_path / "ekf.tum").is_file() and not (tmp_path / "INCOMPLETE").exists()
    assert m["estimators"]["ekf"]["final_xy"] == pytest.approx(summary.estimators["ekf"]
                                                               .final_xy)
    assert m["data"]["t1"] == pytest.approx(max(x.t for x in core.measurements))
    with pytest.raises(ValueError, match="no measurement was fused"):
        NodeCore(cfg, ["ekf"], keep_measurements=True).write_results(tmp_path / "none")


def test_a_silent_topic_turns_stale_within_its_timeout(cfg, messages):
    cfg = replace(cfg, node=replace(cfg.node, topic_timeout=1.0, diagnostics_period=5.0))
    core = NodeCore(cfg, ["ekf"])
    t_cut = messages[0][2] + 20.0
    feed = [m for m in messages if m[0] != "/fix" or m[2] < t_cut]
    diags: list = []
    _feed(core, feed[: len(feed) * 2 // 3], diags)

    def fix_status(d):
        return next(s for s in d.fields if s.name == "ddfuse: topic /fix")

    stale = [(rt, fix_status(d)) for rt, d in diags if fix_status(d).level == STALE]
    assert stale, "the GPS topic never turned stale"
    rt, s = stale[0]
    last_fix = max(m[2] for m in feed if m[0] == "/fix")
    # published as soon as it crossed the timeout, not at the next 5 s period
    assert 1.0 < rt - last_fix <= 1.0 + 0.2, (rt, last_fix)
    assert "no message for" in s.message
    others = [x for x in diags[-1][1].fields if x.name.startswith("ddfuse: topic /")
              and x.name != "ddfuse: topic /fix"]
    assert others and all(x.level == OK for x in others)
    assert diags[-1][1].topic == DIAGNOSTICS
    # the estimator goes on with what is left
    est = next(x for x in diags[-1][1].fields if x.name == "ddfuse: estimator ekf")
    assert int(dict(est.values)["updates"]) > 0 and core.session.errors["ekf"] is None


def test_diagnostics_report_latency_and_a_nis_verdict_per_sensor(fed):
    core, _ = fed
    d = core.diagnostics(core.session.newest, force=True)
    est = {s.name: dict(s.values) for s in d.fields}["ddfuse: estimator ekf"]
    assert float(est["latency_p99_ms"]) > 0
    assert any(k.startswith("nis /fix") and v.split()[0] in ("Pass", "Warn", "Fail")
               for k, v in est.items())


def test_a_clock_jump_back_resets_the_session_once_with_one_log_line(cfg, messages, caplog):
    core = NodeCore(cfg, ["ekf"])
    part = messages[: len(messages) // 4]
    with caplog.at_level(logging.WARNING, logger="ddfuse"):
        _feed(core, part)
        before = core.session.latency_ms()["ekf"]["updates"]
        _feed(core, part)  # the same stretch again: the clock went back (a looping bag)
    assert core.resets == 1
    lines = [r for r in caplog.records if "jumped back" in r.getMessage()]
    assert len(lines) == 1
    # a fresh session took the second pass whole: as many updates, nothing dropped as late
    assert core.session.latency_ms()["ekf"]["updates"] == before
    assert not core.session.late


def test_a_wrong_message_type_is_one_clear_error(cfg, messages):
    core = NodeCore(cfg, ["ekf"])
    problem = core.type_problem("/fix", "nav_msgs/Odometry")
    assert problem == (f"topic /fix carries nav_msgs/Odometry, but sensors.gps[0] "
                       f"({cfg.path}) needs sensor_msgs/NavSatFix")
    assert core.type_problem("/fix", "sensor_msgs/NavSatFix") is None
    odom = next(m for t, m, _ in messages if t == "/odom")
    assert core.receive("/fix", odom, messages[0][2]) == []  # never raises
    assert list(core.callback_errors) == [("/fix", "topic /fix: a nav_msgs/Odometry message, "
                                           "but sensors.gps[0] needs sensor_msgs/NavSatFix")]
    d = core.diagnostics(messages[0][2], force=True)
    node = next(s for s in d.fields if s.name == "ddfuse: node")
    assert node.level == 2 and dict(node.values)["callback_errors"] == "1"


def test_node_tf_must_name_a_running_estimator(cfg):
    with pytest.raises(ValueError, match=r"node\.tf: 'ekf_igvc' does not run here"):
        NodeCore(replace(cfg, node=replace(cfg.node, tf="ekf_igvc")), ["ekf"])
    assert NodeCore(replace(cfg, node=replace(cfg.node, tf="none")), ["ekf"]).tf_name is None


@pytest.mark.parametrize("node, key", [({"rate": 0}, "node.rate"), ({"tf": 1}, "node.tf"),
                                       ({"topic_timeout": -1}, "node.topic_timeout"),
                                       ({"period": 1}, "node.period")])
def test_node_config_errors_name_the_key(node, key):
    with pytest.raises(ConfigError, match=rf"^<config>: {key}: "):
        parse_config({"sensors": {"gps": [{"topic": "/fix"}]}, "node": node})


@pytest.mark.integration
def test_node_feeds_the_foxglove_live_view_with_its_session(cfg, messages):
    """``node --foxglove``: the core's on_update hook drives the live view's feed; a real
    WebSocket client gets each estimator's poses, the last one the node's final estimate."""
    pytest.importorskip("foxglove")
    from ddfuse.evaluation.live_view import LiveView, ReplayFeed
    from test_live_view import Client, stamp_s, wait_for

    names = ["ekf", "smoother"]
    view = LiveView(cfg, names, port=0)
    client = Client(view.url)
    try:
        wait_for(lambda: {f"/ddfuse/{n}/pose" for n in names} <= client.subscribed,
                 "the subscriptions")
        wait_for(lambda: {f"/ddfuse/{n}/pose" for n in names} <= set(view.subscribed_topics()),
                 "the server to see them")
        feed = ReplayFeed(view, cfg)
        core = NodeCore(cfg, names, on_update=feed)
        _feed(core, messages)
        core.finish()
        feed.finish(core.session)
        finals = {n: core.session.estimate(n) for n in names}
        wait_for(lambda: all(
            (p := client.last(f"/ddfuse/{n}/pose")) is not None
            and abs(stamp_s(p.timestamp) - finals[n].t) < 1e-6 for n in names),
            "the final poses")
        for n in names:
            poses = client.decoded(f"/ddfuse/{n}/pose")
            assert len(poses) > 100  # the whole drive, rate-limited, not just the end
            last = poses[-1][1]
            assert (last.pose.position.x, last.pose.position.y) == pytest.approx(
                finals[n].pose[:2], abs=1e-6)
    finally:
        client.close()
        view.close()
    assert client.error is None, client.error
