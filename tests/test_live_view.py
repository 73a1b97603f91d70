"""The Foxglove live view (``evaluation.live_view``) seen by a real WebSocket client (the
``websockets`` package) on 127.0.0.1: the channels and schemas it advertises, and the decoded
messages against the session's own estimates.

The client offers both names of the Foxglove WebSocket protocol: ``foxglove.sdk.v1``, the only
one foxglove-sdk's server accepts (0.30: HTTP 400 for ``foxglove.websocket.v1`` alone), and
``foxglove.websocket.v1``, its former name (the same protocol)."""

from __future__ import annotations

import asyncio
import base64
import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")
websockets = pytest.importorskip("websockets", reason="the websockets package is not installed")
pytest.importorskip("google.protobuf", reason="protobuf (to decode the messages) is absent")

from ddfuse.estimation.config import load_config  # noqa: E402
from ddfuse.estimation.errors import DdfuseError  # noqa: E402
from ddfuse.estimation.estimate_msgs import fix_of, odometry_of  # noqa: E402
from ddfuse.estimation.estimator import Estimate  # noqa: E402
from ddfuse.estimation.measurements import GpsFix  # noqa: E402
from ddfuse.evaluation import cli  # noqa: E402
from ddfuse.evaluation.live_view import (  # noqa: E402
    ELLIPSE_SIGMA,
    GPS_TOPIC,
    RATE_HZ,
    TRUTH_TOPIC,
    LiveView,
    ReplayFeed,
    read_truth,
)
from ddfuse.evaluation.online import replay  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BAG, YAML = ROOT / "data" / "sample_husky.bag", ROOT / "data" / "sample_husky.yaml"
NAMES = ["ekf", "smoother"]
PER_ESTIMATOR = {"pose": "foxglove.PoseInFrame", "odom": "foxglove.Odometry",
                 "tf": "foxglove.FrameTransform", "covariance": "foxglove.SceneUpdate",
                 "fix": "foxglove.LocationFix", "scores": "ddfuse.Scores"}


class Client:
    """A Foxglove WebSocket client in its own thread: subscribes to every channel advertised
    and keeps each binary message frame, decoded on demand by its channel's schema (protobuf
    from the FileDescriptorSet sent in the advertisement, or JSON): ``decoded(topic)``, a list
    of (log time ns, message). (Decoding as they come would hold the GIL against the replay
    feeding the server in the same process.)"""

    def __init__(self, url: str) -> None:
        self.url = url
        self.channels: dict[int, dict] = {}  # channel id -> advertisement
        self.messages: dict[str, list] = {}  # topic -> [(log time ns, payload)]
        self.subscribed: set[str] = set()
        self._sub_topic: dict[int, str] = {}
        self._decoders: dict[int, object] = {}
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.subprotocol: str | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # noqa: BLE001 - reported by the test
            self.error = e

    async def _main(self) -> None:
        async with websockets.connect(self.url, max_size=None, subprotocols=[
                "foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            self.subprotocol = ws.subprotocol
            while not self._stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return
                if isinstance(frame, bytes):
                    self._binary(frame)
                    continue
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    subs = []
                    for ch in msg["channels"]:
                        self.channels[ch["id"]] = ch
                        sub = len(self._sub_topic) + 1
                        self._sub_topic[sub] = ch["topic"]
                        self._decoders[sub] = decoder(ch)
                        subs.append({"id": sub, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                    self.subscribed.update(self._sub_topic.values())

    def _binary(self, frame: bytes) -> None:
        assert frame[0] == 0x01, f"unexpected binary opcode {frame[0]}"
        sub, log_time = struct.unpack_from("<IQ", frame, 1)
        self.messages.setdefault(sub, []).append((log_time, frame[13:]))

    def decoded(self, topic: str) -> list:
        sub = next(k for k, v in self._sub_topic.items() if v == topic)
        dec = self._decoders[sub]
        return [(lt, dec(b)) for lt, b in list(self.messages.get(sub, ()))]

    def count(self, topic: str) -> int:
        """How many messages came on ``topic`` (none decoded: cheap to poll)."""
        sub = next((k for k, v in self._sub_topic.items() if v == topic), None)
        return len(self.messages.get(sub, ()))

    def last(self, topic: str):
        """The last message on ``topic`` decoded, or None."""
        sub = next((k for k, v in self._sub_topic.items() if v == topic), None)
        got = self.messages.get(sub)
        return self._decoders[sub](got[-1][1]) if got else None
    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)


def decoder(ch: dict):
    """A function decoding a message payload of advertised channel ``ch``."""
    if ch["encoding"] == "json":
        return lambda b: json.loads(b)
    assert ch["encoding"] == "protobuf", ch
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
    return cls.FromString


def wait_for(cond, what: str, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)


def stamp_s(ts) -> float:
    return ts.seconds + ts.nanos * 1e-9


@pytest.fixture(scope="module")
def live_replay():
    """The sample bag replayed in-process into a LiveView on a free port, a client subscribed
    to every channel from the start: (client, session, the fixes given, cfg, view). About 20 s
    (the client takes some 40 000 messages): the tests on it are integration tests; the
    default suite has the same checks on a few estimates (test_estimates_decode_...)."""
    cfg = load_config(YAML)
    view = LiveView(cfg, NAMES, port=0)
    client = Client(view.url)
    expected = {f"/ddfuse/{n}/{w}" for n in NAMES for w in PER_ESTIMATOR} | {GPS_TOPIC,
                                                                              TRUTH_TOPIC}
    wait_for(lambda: client.subscribed >= expected, "the subscriptions")
    wait_for(lambda: set(view.subscribed_topics()) >= expected, "the server to see them")
    fixes: list[GpsFix] = []
    feed = ReplayFeed(view, cfg, read_truth(BAG, cfg))
    updates = [0]

    def paced(session, m) -> None:
        # The client's thread shares this process's GIL with the replay, which would outrun
        # it: the server keeps a backlog of 1024 messages per client and drops beyond it. A
        # millisecond every 10 updates lets the client take what was sent, as a client in its
        # own process does (the replay's ~12 000 updates: about 1.2 s).
        feed(session, m)
        updates[0] += 1
        if updates[0] % 10 == 0:
            time.sleep(0.001)

    session = replay(BAG, cfg, names=NAMES, on_update=paced,
                     observers=(lambda m: fixes.append(m) if type(m) is GpsFix else None,))
    feed.finish(session)
    finals = {n: session.estimate(n) for n in NAMES}

    def last_pose_is_final() -> bool:
        last = [client.last(f"/ddfuse/{n}/pose") for n in NAMES]
        return all(p is not None and abs(stamp_s(p.timestamp) - finals[n].t) < 1e-6
                   for p, n in zip(last, NAMES, strict=True))

    wait_for(last_pose_is_final, "the final poses")
    time.sleep(0.3)  # the rest of the final burst (covariance, fix, scores)
    yield client, session, fixes, cfg, view
    client.close()
    view.close()
    assert client.error is None, client.error


@pytest.mark.integration
def test_channels_and_schemas_advertised(live_replay):
    client, *_ = live_replay
    got = {ch["topic"]: ch["schemaName"] for ch in client.channels.values()}
    want = {f"/ddfuse/{n}/{w}": s for n in NAMES for w, s in PER_ESTIMATOR.items()}
    want |= {GPS_TOPIC: "foxglove.LocationFix", TRUTH_TOPIC: "foxglove.PoseInFrame"}
    assert got == want
    enc = {ch["topic"]: ch["encoding"] for ch in client.channels.values()}
    assert enc[f"/ddfuse/{NAMES[0]}/scores"] == "json"
    assert enc[f"/ddfuse/{NAMES[0]}/pose"] == "protobuf"


@pytest.mark.integration
def test_last_pose_and_odometry_equal_the_sessions_final_estimate(live_replay):
    client, session, _, cfg, _ = live_replay
    for n in NAMES:
        e = session.estimate(n)
        o = odometry_of(e, cfg.local_frame, cfg.base_frame)
        log_time, p = client.decoded(f"/ddfuse/{n}/pose")[-1]
        assert p.frame_id == cfg.local_frame
        assert log_time == pytest.approx(e.t * 1e9, abs=1e3)
        pos, q = p.pose.position, p.pose.orientation
        assert np.allclose([pos.x, pos.y, pos.z], o.position, atol=1e-6)
        assert np.allclose([q.x, q.y, q.z, q.w], o.orientation, atol=1e-9)
        poses = client.decoded(f"/ddfuse/{n}/pose")
        span = e.t - stamp_s(poses[0][1].timestamp)
        # RATE_HZ per second of stamps, none lost on the way (a backlog of 1024 per client)
        assert RATE_HZ * span * 0.95 <= len(poses) <= RATE_HZ * span + 2
        _, od = client.decoded(f"/ddfuse/{n}/odom")[-1]
        assert od.body_frame_id == cfg.base_frame
        assert np.allclose(list(od.pose_covariance), o.pose_covariance, rtol=1e-12, atol=0)
        assert np.allclose(list(od.velocity_covariance), o.twist_covariance, rtol=1e-12)
        _, tf = client.decoded(f"/ddfuse/{n}/tf")[-1]
        assert (tf.parent_frame_id, tf.child_frame_id) == (cfg.local_frame,
                                                           f"{n}/{cfg.base_frame}")
        assert (tf.translation.x, tf.translation.y) == pytest.approx(e.pose[:2], abs=1e-6)


@pytest.mark.integration
def test_the_ellipse_axes_match_the_covariance(live_replay):
    client, session, _, cfg, _ = live_replay
    for n in NAMES:
        e = session.estimate(n)
        _, upd = client.decoded(f"/ddfuse/{n}/covariance")[-1]
        (ent,) = upd.entities
        assert (ent.id, ent.frame_id) == (n, cfg.local_frame)
        (cyl,) = ent.cylinders
        a, b = cyl.size.x / 2, cyl.size.y / 2
        q = cyl.pose.orientation
        ang = 2.0 * math.atan2(q.z, q.w)
        r = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        # the semi-axes are ELLIPSE_SIGMA standard deviations along the eigenvectors
        rebuilt = r @ np.diag([a * a, b * b]) @ r.T / ELLIPSE_SIGMA ** 2
        cov = np.asarray(e.pose_cov)[:2, :2]
        assert np.allclose(rebuilt, 0.5 * (cov + cov.T), rtol=1e-6, atol=1e-12)
        assert a >= b > 0.0
        assert (cyl.pose.position.x, cyl.pose.position.y) == pytest.approx(e.pose[:2],
                                                                           abs=1e-6)


@pytest.mark.integration
def test_location_fixes_match_fix_of_and_the_gps_given(live_replay):
    client, session, fixes, cfg, _ = live_replay
    for n in NAMES:
        f = fix_of(session.estimate(n), cfg.datum, cfg.base_frame)
        _, lf = client.decoded(f"/ddfuse/{n}/fix")[-1]
        assert (lf.latitude, lf.longitude) == pytest.approx((f.latitude, f.longitude),
                                                            abs=1e-12)
        assert np.allclose(list(lf.position_covariance), f.position_covariance, rtol=1e-12)
    gps = client.decoded(GPS_TOPIC)
    assert len(gps) == len(fixes) > 100  # every fix given, none rate-limited
    for (_, lf), m in zip(gps, fixes, strict=True):
        assert (lf.latitude, lf.longitude) == (m.lat, m.lon)
        assert stamp_s(lf.timestamp) == pytest.approx(m.t, abs=1e-6)


@pytest.mark.integration
def test_scores_carry_the_logged_nis_and_the_error_against_truth(live_replay):
    client, session, _, _, _ = live_replay
    truth = client.decoded(TRUTH_TOPIC)
    assert len(truth) > 100
    for n in NAMES:
        scores = [m for _, m in client.decoded(f"/ddfuse/{n}/scores")]
        errors = [s["error_m"] for s in scores if s["error_m"] is not None]
        # the sample run's errors are decimetres; a sign of the truth being paired rightly
        assert len(errors) > 100 and 0.0 < float(np.median(errors)) < 2.0
        cols = session.estimators[n].log.innovations.columns()
        logged = {(round(float(t), 9), float(v)) for t, v in zip(cols["t"], cols["nis"],
                                                                   strict=True)}
        sent = [s for s in scores if s["nis"] is not None]
        assert sent and {(round(s["t"], 9), s["nis"]) for s in sent} <= logged
        # every GPS update's NIS (2.5 Hz, under the rate) is sent
        gps_logged = int(np.sum(cols["sensor"] == "gps"))
        assert sum(1 for s in sent if s["kind"].startswith("gps/")) == gps_logged
        # at most RATE_HZ per second of stamps per (estimator, kind), at least one per 50 ms
        # step for the 100 Hz IMU's
        for kind in {s["kind"] for s in sent}:
            t = np.array([s["t"] for s in sent if s["kind"] == kind])
            assert len(t) <= RATE_HZ * (t[-1] - t[0]) + 2
        imu = np.array([s["t"] for s in sent if s["kind"].startswith("imu/")])
        assert len(imu) == 0 or len(imu) >= 0.95 * RATE_HZ * (imu[-1] - imu[0])


def rotated_cov(a: float, b: float, angle: float) -> np.ndarray:
    """A pose covariance whose x/y block has standard deviations a, b along ``angle``."""
    r = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    c = np.eye(3) * 0.01
    c[:2, :2] = r @ np.diag([a * a, b * b]) @ r.T
    return c


def test_estimates_decode_to_the_estimate_msgs_fields_at_most_rate_hz():
    """A few estimates sent at 100 Hz of stamps, one client: at most RATE_HZ arrive, the
    forced last one included; pose, ellipse and LocationFix decode to what estimate_msgs and
    the covariance give; the GPS fix and the scores come as given."""
    cfg = load_config(YAML)
    t0 = 1.7e9
    with LiveView(cfg, ["a"], port=0) as view:
        client = Client(view.url)
        expected = {f"/ddfuse/a/{w}" for w in PER_ESTIMATOR} | {GPS_TOPIC, TRUTH_TOPIC}
        wait_for(lambda: set(view.subscribed_topics()) >= expected, "the subscriptions")
        sent = []
        for k in range(100):  # 1 s of stamps at 100 Hz
            e = Estimate(t0 + k * 0.01, (1.0 + k, -2.0, 0.3 + 0.01 * k),
                         rotated_cov(0.5 + 0.01 * k, 0.2, 0.4 + 0.01 * k))
            view.estimate("a", e, cfg.datum, force=(k == 99))
            sent.append(e)
        fix = GpsFix(t0 + 0.5, 47.4, 8.5, 480.0, np.diag([1.0, 2.0, 4.0]))
        view.fix(fix)
        view.truth(t0 + 0.5, (3.0, 4.0, math.nan))
        view.scores("a", t0 + 0.5, 0.25, None)
        view.scores("a", t0 + 0.5, None, 3.5, "gps/gps")
        wait_for(lambda: client.last("/ddfuse/a/pose") is not None and abs(
            stamp_s(client.last("/ddfuse/a/pose").timestamp) - sent[-1].t) < 1e-6,
            "the last pose")
        time.sleep(0.3)
        poses = client.decoded("/ddfuse/a/pose")
        # stamps 0, 0.05, ..., 0.95 s (20), then the forced 0.99 s
        assert len(poses) == int(RATE_HZ) + 1
        by_t = {round(e.t - t0, 6): e for e in sent}
        for log_time, p in poses:
            e = by_t[round(stamp_s(p.timestamp) - t0, 6)]
            o = odometry_of(e, cfg.local_frame, cfg.base_frame)
            assert log_time == pytest.approx(e.t * 1e9, abs=1e3)
            q = p.pose.orientation
            assert (p.pose.position.x, p.pose.position.y) == pytest.approx(e.pose[:2],
                                                                           abs=1e-9)
            assert [q.x, q.y, q.z, q.w] == pytest.approx(o.orientation, abs=1e-12)
        for _, upd in client.decoded("/ddfuse/a/covariance"):
            (ent,) = upd.entities
            e = by_t[round(stamp_s(ent.timestamp) - t0, 6)]
            (cyl,) = ent.cylinders
            a, b = cyl.size.x / 2, cyl.size.y / 2
            ang = 2.0 * math.atan2(cyl.pose.orientation.z, cyl.pose.orientation.w)
            r = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
            rebuilt = r @ np.diag([a * a, b * b]) @ r.T / ELLIPSE_SIGMA ** 2
            assert np.allclose(rebuilt, e.pose_cov[:2, :2], rtol=1e-9, atol=1e-12)
        for _, lf in client.decoded("/ddfuse/a/fix"):
            e = by_t[round(stamp_s(lf.timestamp) - t0, 6)]
            f = fix_of(e, cfg.datum, cfg.base_frame)
            assert (lf.latitude, lf.longitude, lf.altitude) == (f.latitude, f.longitude,
                                                                f.altitude)
        ((_, g),) = client.decoded(GPS_TOPIC)
        assert (g.latitude, g.longitude, g.altitude) == (47.4, 8.5, 480.0)
        assert list(g.position_covariance) == np.diag([1.0, 2.0, 4.0]).ravel().tolist()
        ((_, tr),) = client.decoded(TRUTH_TOPIC)
        assert (tr.pose.position.x, tr.pose.position.y) == (3.0, 4.0)
        scores = [m for _, m in client.decoded("/ddfuse/a/scores")]
        assert scores == [{"t": t0 + 0.5, "error_m": 0.25, "nis": None, "kind": None},
                          {"t": t0 + 0.5, "error_m": None, "nis": 3.5, "kind": "gps/gps"}]
        client.close()


def test_a_client_that_leaves_breaks_nothing(caplog):
    cfg = load_config(YAML)
    with LiveView(cfg, ["ekf"], port=0) as view:
        client = Client(view.url)
        wait_for(lambda: "/ddfuse/ekf/pose" in view.subscribed_topics(), "the subscription")
        client.close()
        wait_for(lambda: not view.subscribed_topics(), "the client to leave")
        for k in range(50):  # sends after it left: not raised
            view.estimate("ekf", Estimate(k * 0.1, (k, 0.0, 0.0), np.eye(3)), cfg.datum)
    view.close()  # twice: harmless


def test_a_port_in_use_is_one_clear_error(capsys):
    cfg = load_config(YAML)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(DdfuseError, match=f"127.0.0.1:{port}.*in use"):
            LiveView(cfg, ["ekf"], port=port)
        code = cli.main(["online", str(BAG), "--foxglove", str(port)])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f"127.0.0.1:{port}" in lines[0] and "in use" in lines[0], err


def test_without_foxglove_the_error_names_the_live_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove raises ImportError
    with pytest.raises(DdfuseError, match=r"pip install 'ddfuse\[live\]'"):
        LiveView(load_config(YAML), ["ekf"], port=0)


@pytest.mark.integration
def test_online_foxglove_serves_the_replay_until_ctrl_c(tmp_path):
    """``ddfuse online BAG --foxglove 0`` in its own process: a client sees the final pose
    the command prints, and Ctrl-C after the end exits 0."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "ddfuse.evaluation.cli", "online", str(BAG),
                             "--foxglove", "0", "--estimators", "ekf", "--every", "1000"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            # Ctrl-C as a terminal's: a test run in the background inherits
                            # SIGINT ignored, which exec keeps, and the child would not see it
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    client = None
    try:
        line = proc.stderr.readline()
        assert "live view on ws://127.0.0.1:" in line, line
        url = line.split(" on ", 1)[1].split()[0]
        client = Client(url)
        held = proc.stderr.readline()
        assert "still serving" in held, held
        wait_for(lambda: client.last("/ddfuse/ekf/pose"), "a pose")
        # the replay has ended; on a loaded machine the client is still taking its poses:
        # Ctrl-C only once at most the still-serving view's repeat of the final pose (one a
        # second) has come over the last two seconds
        seen: list[tuple[float, int]] = []

        def settled() -> bool:
            now, n = time.monotonic(), client.count("/ddfuse/ekf/pose")
            seen.append((now, n))
            before = [c for t, c in seen if t <= now - 2.0]
            return bool(before) and n - before[-1] <= 3

        wait_for(settled, "the client to have taken every pose", timeout=60)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0
        final = next(ln for ln in out.splitlines() if ln.endswith("(final)"))
        x, y = (float(v) for v in final.split("ekf (")[1].split(",")[:2])
        _, p = client.decoded("/ddfuse/ekf/pose")[-1]
        assert (p.pose.position.x, p.pose.position.y) == pytest.approx((x, y), abs=0.006)
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
