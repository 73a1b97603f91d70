"""A live view of the estimates over the Foxglove WebSocket protocol (``foxglove-sdk``, the
``live`` extra): what ``ddfuse online --foxglove`` and the ROS node serve to Foxglove.

The only module that imports ``foxglove``. Every message is built from
``ddfuse.estimation.estimate_msgs`` (``odometry_of``, ``fix_of``, ``transform_of``,
``yaw_quaternion``): the quaternion, the covariance layout and lat/lon are never derived here.

Channels (``docs/design/live_view.md`` says why these schemas), per estimator NAME:

- ``/ddfuse/NAME/pose``: ``foxglove.PoseInFrame`` in ``cfg.local_frame`` (the 3D panel's arrow);
- ``/ddfuse/NAME/odom``: ``foxglove.Odometry`` (pose and twist with their 6x6 covariances, the
  fields of ``nav_msgs/Odometry``; body frame ``cfg.base_frame``);
- ``/ddfuse/NAME/tf``: ``foxglove.FrameTransform`` from ``cfg.local_frame`` to ``NAME/BASE``
  (``BASE`` = ``cfg.base_frame``; one child frame per estimator, so that they do not fight);
- ``/ddfuse/NAME/covariance``: ``foxglove.SceneUpdate``, one entity ``NAME``: a flat elliptic
  cylinder, the 2-sigma ellipse of the pose's x/y covariance (semi-axes 2 sqrt(eigenvalue),
  the major axis along its eigenvector), centred on the pose;
- ``/ddfuse/NAME/fix``: ``foxglove.LocationFix`` of the position (``fix_of``), when a datum is
  given (the Map panel);
- ``/ddfuse/NAME/scores``: JSON ``{"t", "error_m", "nis", "kind"}`` (the Plot panel): the
  position error against the truth (m) and the NIS of one update (``kind``: its
  ``sensor/kind``), either null;

and ``/ddfuse/gps/fix`` (``foxglove.LocationFix``: every GPS fix given to the estimators, its
own lat/lon and ENU covariance) and ``/ddfuse/ground_truth/pose`` (``foxglove.PoseInFrame``).

Stamps: every message's timestamp and log time are the estimate's (the header-stamp clock).
Rate: each estimator's pose messages, the truth, and each (estimator, update kind)'s scores are
sent at most ``RATE_HZ`` times per second of stamps (a 100 Hz IMU does not flood the socket);
GPS fixes all. A message is encoded only when a client subscribes to its channel.

Serving never breaks estimation: a failing send is logged once (``logging``, this module's
logger) and never raised; a client that leaves is logged once at INFO.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter
from collections.abc import Sequence

import numpy as np
from ddfuse.estimation.config import Config
from ddfuse.estimation.errors import DdfuseError
from ddfuse.estimation.estimate_msgs import (
    FixOut,
    fix_of,
    odometry_of,
    transform_of,
    yaw_quaternion,
)
from ddfuse.estimation.estimator import Estimate
from ddfuse.estimation.measurements import GpsFix
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation.metrics import interpolate_xy

log = logging.getLogger(__name__)

__all__ = ["ELLIPSE_SIGMA", "GPS_TOPIC", "LiveView", "RATE_HZ", "TRUTH_TOPIC", "topic"]

RATE_HZ = 20.0  # at most this many messages per second of stamps per estimator (and per kind)
ELLIPSE_SIGMA = 2.0  # the covariance ellipse's semi-axes in standard deviations
ELLIPSE_HEIGHT = 0.02  # m: the flat cylinder's thickness
GPS_TOPIC = "/ddfuse/gps/fix"
TRUTH_TOPIC = "/ddfuse/ground_truth/pose"
TRUTH_KEY = "ground_truth"
LIVE_EXTRA = "pip install 'ddfuse[live]'"

SCORES_SCHEMA = {
    "title": "ddfuse.Scores",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "header-stamp time, s"},
        "error_m": {"type": ["number", "null"],
                    "description": "position error against the ground truth, m"},
        "nis": {"type": ["number", "null"], "description": "NIS of one update"},
        "kind": {"type": ["string", "null"], "description": "the update's sensor/kind"},
    },
}

# per estimator, in order: the 3D panel's colours (r, g, b)
_PALETTE = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
            (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5))


def topic(name: str, what: str) -> str:
    """The live view's topic ``what`` of estimator ``name``: ``/ddfuse/<name>/<what>``."""
    return f"/ddfuse/{name}/{what}"


def _foxglove():
    """The foxglove-sdk modules; DdfuseError naming the ``live`` extra when it is absent."""
    try:
        import foxglove
        from foxglove import channels, messages
    except ImportError:
        raise DdfuseError("the Foxglove live view needs the foxglove-sdk package: "
                          f"{LIVE_EXTRA}") from None
    return foxglove, channels, messages


def ellipse_axes(cov_xy: np.ndarray, sigma: float = ELLIPSE_SIGMA
                 ) -> tuple[float, float, float] | None:
    """(major semi-axis m, minor semi-axis m, angle of the major axis rad from x) of the
    ``sigma``-sigma ellipse of a 2x2 position covariance (m^2), from its eigen-decomposition;
    None when it is not finite or not positive semi-definite (beyond rounding)."""
    c = np.asarray(cov_xy, dtype=float)
    c = 0.5 * (c + c.T)
    if not np.all(np.isfinite(c)):
        return None
    w, v = np.linalg.eigh(c)  # ascending
    if w[0] < -1e-9 * max(abs(w[1]), 1e-300):
        return None
    w = np.clip(w, 0.0, None)
    major = v[:, 1]
    return (sigma * math.sqrt(w[1]), sigma * math.sqrt(w[0]),
            math.atan2(float(major[1]), float(major[0])))


class RateGate:
    """At most ``rate_hz`` events per second of stamps per key, on average: ``due(key, t)``
    says whether one at ``t`` s goes (and records it when it does): the first at or after each
    ``1 / rate_hz`` step. A stamp before the key's last one (a clock that stepped back) starts
    afresh."""

    def __init__(self, rate_hz: float = RATE_HZ) -> None:
        self.period = 1.0 / rate_hz
        self._last: dict[object, float] = {}

    def peek(self, key, t: float) -> bool:
        """Whether ``due(key, t)`` would be True, recording nothing."""
        last = self._last.get(key)
        return last is None or not (last <= t < last + self.period)

    def due(self, key, t: float) -> bool:
        if not self.peek(key, t):
            return False
        last = self._last.get(key)
        # on the grid last + k period while the events keep up: the first event of each
        # period goes, RATE_HZ on average (from t itself, events every 20 ms gave 1 in 60 ms)
        p = self.period
        self._last[key] = t if last is None or not (last <= t < last + 2.0 * p) else last + p
        return True

    def mark(self, key, t: float) -> None:
        """Record an event at ``t`` that went regardless (a forced one)."""
        self._last[key] = t


class _Listener:
    """Counts the subscriptions per topic; logs, once per client, its first subscription and
    when it leaves (its last channel unsubscribed: a disconnect or a closed panel). Called on
    the server's threads: never raises."""

    def __init__(self) -> None:
        self.topics: Counter = Counter()
        self.total = 0  # subscriptions now, all clients
        self._clients: Counter = Counter()
        self._lock = threading.Lock()

    def on_subscribe(self, client, channel) -> None:
        try:
            with self._lock:
                self.topics[channel.topic] += 1
                self.total += 1
                self._clients[client.id] += 1
                first = self._clients[client.id] == 1
            if first:
                log.info("live view: client %s subscribed (%s)", client.id, channel.topic)
        except Exception:  # noqa: BLE001 - a listener must not raise into the server
            pass

    def on_unsubscribe(self, client, channel) -> None:
        try:
            with self._lock:
                self.topics[channel.topic] -= 1
                self.total -= 1
                self._clients[client.id] -= 1
                left = self._clients[client.id] == 0
            if left:
                log.info("live view: client %s left (disconnected or unsubscribed from every "
                         "channel)", client.id)
        except Exception:  # noqa: BLE001
            pass


class _Estimator:
    """One estimator's channels."""

    __slots__ = ("color", "cov", "fix", "odom", "pose", "scores", "tf")

    def __init__(self, name: str, ctx, ch, json_channel, color) -> None:
        self.pose = ch.PoseInFrameChannel(topic(name, "pose"), context=ctx)
        self.odom = ch.OdometryChannel(topic(name, "odom"), context=ctx)
        self.tf = ch.FrameTransformChannel(topic(name, "tf"), context=ctx)
        self.cov = ch.SceneUpdateChannel(topic(name, "covariance"), context=ctx)
        self.fix = ch.LocationFixChannel(topic(name, "fix"), context=ctx)
        self.scores = json_channel(topic(name, "scores"), schema=SCORES_SCHEMA, context=ctx)
        self.color = color


class LiveView:
    """A Foxglove WebSocket server on ``host``:``port`` (0: a free port; ``port`` then is the
    one bound) serving the estimates of ``names`` (module docstring: topics, schemas, rate).

    DdfuseError when foxglove-sdk is absent (naming the ``live`` extra) or the port cannot be
    bound (naming host and port). After that, no method raises: a failure to send is logged
    once and the estimation goes on. ``close()`` stops the server (also as a context manager).
    """

    def __init__(self, cfg: Config, names: Sequence[str], *, port: int = 8765,
                 host: str = "127.0.0.1") -> None:
        foxglove, ch, msgs = _foxglove()
        self._m = msgs
        self.cfg = cfg
        self.local_frame = cfg.local_frame
        self.base_frame = cfg.base_frame
        self.host = host
        self._gate = RateGate()
        self._failed = False
        self._ctx = foxglove.Context()
        self._listener = _Listener()
        try:
            self._server = foxglove.start_server(
                name="ddfuse", host=host, port=int(port), context=self._ctx,
                server_listener=self._listener)
        except Exception as e:  # FoxgloveError (a RuntimeError): bind failed
            why = str(e).removeprefix("FoxgloveError: ")
            raise DdfuseError(f"Foxglove live view: cannot serve on {host}:{port}: {why} "
                              "(another server on that port? choose another, or 0 for a free "
                              "one)") from None
        self.port = int(self._server.port)
        self._new_channels = lambda n, color: _Estimator(n, self._ctx, ch, foxglove.Channel,
                                                         color)
        self._est: dict[str, _Estimator] = {}
        for n in names:
            self._channels_of(n)
        self._gps = ch.LocationFixChannel(GPS_TOPIC, context=self._ctx)
        self._truth = ch.PoseInFrameChannel(TRUTH_TOPIC, context=self._ctx)

    def _channels_of(self, name: str) -> _Estimator:
        """``name``'s channels, advertised on first use (an estimator not named at the start)."""
        c = self._est.get(name)
        if c is None:
            c = self._est[name] = self._new_channels(name, _PALETTE[len(self._est) %
                                                                    len(_PALETTE)])
        return c

    @property
    def url(self) -> str:
        """The address a Foxglove client opens: ``ws://HOST:PORT``."""
        return f"ws://{self.host}:{self.port}"

    def watched(self) -> bool:
        """Whether any client subscribes to anything now (a feed can skip its work if not)."""
        return self._listener.total > 0

    def subscribed_topics(self) -> list[str]:
        """The topics some client subscribes to now, sorted."""
        with self._listener._lock:
            return sorted(t for t, n in self._listener.topics.items() if n > 0)

    # --- rate --------------------------------------------------------------------------------

    def wants(self, name: str, t: float) -> bool:
        """Whether an estimate of ``name`` stamped ``t`` (s) would be sent now: at most
        ``RATE_HZ`` per second of stamps (a stamp before the last one sent, a clock that
        stepped back, starts afresh). Lets a caller skip computing an estimate that would be
        dropped."""
        return self._gate.peek(name, t)

    # --- what is served ------------------------------------------------------------------------

    def estimate(self, name: str, e: Estimate | None, datum: tuple[float, float, float] | None,
                 *, force: bool = False) -> None:
        """Estimator ``name``'s new estimate ``e`` (None: nothing to show); ``datum`` (lat deg,
        lon deg, alt m) the local frame's origin, or None (then no LocationFix). Sent when
        ``wants(name, e.t)`` or ``force`` (an estimator's final estimate); a name not given at the
        start gets its channels now."""
        if e is None:
            return
        if force:
            self._gate.mark(name, e.t)
        elif not self._gate.due(name, e.t):
            return
        self._guard(self._send_estimate, name, e, datum)

    def fix(self, m: GpsFix) -> None:
        """A GPS fix given to the estimators, on ``/ddfuse/gps/fix``: its own latitude,
        longitude, altitude and ENU covariance (m^2)."""
        self._guard(self._send_fix, m)

    def truth(self, t: float, pose: Sequence[float]) -> None:
        """The ground-truth pose (x m, y m, yaw rad in the local frame; yaw NaN when the truth
        has none: shown as 0) at ``t`` s, on ``/ddfuse/ground_truth/pose``, at most
        ``RATE_HZ`` per second of stamps."""
        if not self._gate.due(TRUTH_KEY, t):
            return
        self._guard(self._send_truth, t, pose)

    def scores(self, name: str, t: float, error_m: float | None, nis: float | None,
               kind: str | None = None) -> None:
        """Estimator ``name``'s position error against the truth (m) and/or the NIS of one
        update (``kind``: which, e.g. ``gps/gps``) at ``t`` s, on ``/ddfuse/NAME/scores``; at
        most ``RATE_HZ`` per second of stamps per (name, kind)."""
        if not self._gate.due((name, kind), t):
            return
        self._guard(self._send_scores, name, t, error_m, nis, kind)

    def close(self) -> None:
        """Stop the server (clients see the connection close). Twice is harmless."""
        server, self._server = getattr(self, "_server", None), None
        if server is None:
            return
        for e in self._est.values():
            for c in (e.pose, e.odom, e.tf, e.cov, e.fix, e.scores):
                self._guard(c.close)
        for c in (self._gps, self._truth):
            self._guard(c.close)
        self._guard(server.stop)

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- building the messages -----------------------------------------------------------------

    def _guard(self, fn, *args) -> None:
        """``fn(*args)``; an exception is logged once per view (never raised)."""
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - serving must never break estimation
            if not self._failed:
                self._failed = True
                log.warning("live view: a message could not be sent (%s: %s); going on, further "
                            "failures are not logged", type(exc).__name__, exc)

    def _stamp(self, t: float):
        """(foxglove Timestamp, log time ns) of ``t`` s."""
        ts = self._m.Timestamp.from_epoch_secs(float(t))
        return ts, ts.sec * 1_000_000_000 + ts.nsec

    def _pose(self, position, orientation):
        m = self._m
        return m.Pose(position=m.Vector3(x=position[0], y=position[1], z=position[2]),
                      orientation=m.Quaternion(x=orientation[0], y=orientation[1],
                                               z=orientation[2], w=orientation[3]))

    def _send_estimate(self, name: str, e: Estimate, datum) -> None:
        ch = self._channels_of(name)
        send = [c.has_sinks() for c in (ch.pose, ch.odom, ch.tf, ch.cov, ch.fix)]
        if not any(send):  # nobody looks: nothing is built
            return
        m = self._m
        ts, ns = self._stamp(e.t)
        # the pose as tf broadcasts it (no covariance: cheaper than odometry_of)
        tr = transform_of(e, self.local_frame, f"{name}/{self.base_frame}")
        pose = self._pose(tr.translation, tr.rotation)
        if send[0]:
            ch.pose.log(m.PoseInFrame(timestamp=ts, frame_id=tr.frame_id, pose=pose),
                        log_time=ns)
        if send[1]:
            o = odometry_of(e, self.local_frame, self.base_frame)
            ch.odom.log(m.Odometry(
                timestamp=ts, frame_id=o.frame_id, body_frame_id=o.child_frame_id,
                pose=self._pose(o.position, o.orientation),
                linear_velocity=m.Vector3(x=o.linear[0], y=o.linear[1], z=o.linear[2]),
                angular_velocity=m.Vector3(x=o.angular[0], y=o.angular[1], z=o.angular[2]),
                pose_covariance=list(o.pose_covariance),
                velocity_covariance=list(o.twist_covariance)), log_time=ns)
        if send[2]:
            ch.tf.log(m.FrameTransform(
                timestamp=ts, parent_frame_id=tr.frame_id, child_frame_id=tr.child_frame_id,
                translation=m.Vector3(x=tr.translation[0], y=tr.translation[1],
                                      z=tr.translation[2]),
                rotation=m.Quaternion(x=tr.rotation[0], y=tr.rotation[1], z=tr.rotation[2],
                                      w=tr.rotation[3])), log_time=ns)
        if send[3]:
            self._send_ellipse(name, ch, e, tr.translation, ts, ns)
        if send[4] and datum is not None:
            ch.fix.log(self._location(fix_of(e, datum, self.base_frame), ts, ch.color),
                       log_time=ns)

    def _send_ellipse(self, name: str, ch: _Estimator, e: Estimate, position, ts, ns) -> None:
        m = self._m
        axes = ellipse_axes(np.asarray(e.pose_cov, dtype=float)[:2, :2])
        if axes is None:  # no covariance to draw: the old ellipse goes
            ch.cov.log(m.SceneUpdate(deletions=[m.SceneEntityDeletion(
                timestamp=ts, type=m.SceneEntityDeletionType.MatchingId, id=name)]),
                log_time=ns)
            return
        a, b, angle = axes
        r, g, bl = ch.color
        cyl = m.CylinderPrimitive(
            pose=self._pose(position, yaw_quaternion(angle)),
            size=m.Vector3(x=2.0 * a, y=2.0 * b, z=ELLIPSE_HEIGHT),
            bottom_scale=1.0, top_scale=1.0, color=m.Color(r=r, g=g, b=bl, a=0.35))
        ch.cov.log(m.SceneUpdate(entities=[m.SceneEntity(
            timestamp=ts, frame_id=self.local_frame, id=name, cylinders=[cyl])]), log_time=ns)

    def _location(self, f: FixOut, ts, color):
        m = self._m
        r, g, b = color
        return m.LocationFix(
            timestamp=ts, frame_id=f.frame_id, latitude=f.latitude, longitude=f.longitude,
            altitude=f.altitude, position_covariance=list(f.position_covariance),
            position_covariance_type=self._covariance_type(f.position_covariance_type),
            color=m.Color(r=r, g=g, b=b, a=1.0))

    def _covariance_type(self, code: int):
        """NavSatFix's covariance type ``code`` (0..3) as foxglove's enum (not built from an
        int)."""
        T = self._m.LocationFixPositionCovarianceType
        return {int(v): v for v in (T.Unknown, T.Approximated, T.DiagonalKnown,
                                    T.Known)}[int(code)]

    def _send_fix(self, m: GpsFix) -> None:
        if not self._gps.has_sinks():
            return
        msgs = self._m
        ts, ns = self._stamp(m.t)
        cov = np.asarray(m.cov, dtype=float).reshape(3, 3)
        self._gps.log(msgs.LocationFix(
            timestamp=ts, frame_id=m.sensor, latitude=float(m.lat), longitude=float(m.lon),
            altitude=float(m.alt), position_covariance=cov.ravel().tolist(),
            position_covariance_type=msgs.LocationFixPositionCovarianceType.Known,
            color=msgs.Color(r=0.0, g=0.0, b=0.0, a=1.0)), log_time=ns)

    def _send_truth(self, t: float, pose) -> None:
        if not self._truth.has_sinks():
            return
        x, y, yaw = (float(v) for v in pose)
        e = Estimate(t=float(t), pose=(x, y, yaw if math.isfinite(yaw) else 0.0),
                     pose_cov=np.zeros((3, 3)))
        o = odometry_of(e, self.local_frame, self.base_frame)
        ts, ns = self._stamp(t)
        self._truth.log(self._m.PoseInFrame(timestamp=ts, frame_id=o.frame_id,
                                            pose=self._pose(o.position, o.orientation)),
                        log_time=ns)

    def _send_scores(self, name: str, t: float, error_m, nis, kind) -> None:
        ch = self._channels_of(name)
        if not ch.scores.has_sinks():
            return
        _, ns = self._stamp(t)

        def num(v):
            return float(v) if v is not None and math.isfinite(v) else None

        ch.scores.log({"t": float(t), "error_m": num(error_m), "nis": num(nis), "kind": kind},
                      log_time=ns)


def read_truth(bag, cfg: Config) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground truth of ``bag`` (stamps (N,) s, poses (N, 3) x m, y m, yaw rad, yaw NaN
    for a NavSatFix truth) read ahead of a replay, which keeps none; None when the config names
    no ground_truth topic, the bag has none, or it cannot be read (the replay says why)."""
    from ddfuse.estimation.bags import BagStream
    from ddfuse.estimation.errors import BagError

    if not cfg.ground_truth_topic:
        return None
    try:
        stream = BagStream(bag, cfg)
        for _ in stream:
            pass
    except BagError:
        return None
    t, pose = stream.truth_arrays()
    return (t, pose) if len(t) else None


class ReplayFeed:
    """Feeds a ``LiveView`` from an ``OnlineSession`` as a bag is replayed into it: called
    after each measurement (``evaluation.online.replay(..., on_update=feed)``), then
    ``finish(session)`` once the session has finished.

    Per measurement ``m``: a GPS fix goes to ``view.fix`` (and gives the datum when the config
    has none: the stream's, ``GpsFix.datum``); the truth samples stamped up to ``m.t`` to
    ``view.truth``; per estimator, at most ``RATE_HZ`` per second of stamps, the session's
    current estimate to ``view.estimate`` and its position error to ``view.scores`` (the
    truth's x/y interpolated at the estimate's stamp, ``evaluation.metrics.interpolate_xy``;
    None outside the truth's span); and the NIS of every update the estimator logged since,
    read from its innovation log (the values the run's NIS tables count, not recomputed).
    ``truth``: ``read_truth``'s arrays, or None. While no client subscribes, only the GPS fixes
    go to the view (which drops them) and nothing is asked of the session; a client that comes
    gets what follows, not the backlog. Never raises: a failure is logged once."""

    def __init__(self, view: LiveView, cfg: Config,
                 truth: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.view = view
        self.datum = cfg.datum if isinstance(cfg.datum, tuple) else None
        self._truth = None
        if truth is not None and len(truth[0]):
            t, pose = (np.asarray(a, dtype=float) for a in truth)
            self._truth = Trajectory(t, pose, np.broadcast_to(math.nan, (len(t), 3, 3)))
        self._ti = 0  # the next truth sample to send
        self._gate = RateGate()
        self._logged: dict[str, int] = {}  # estimator -> innovations already sent
        self._idle = True  # no client was subscribed at the last measurement
        self._failed = False

    def __call__(self, session, m) -> None:
        try:
            self._update(session, m)
        except Exception as exc:  # noqa: BLE001 - serving must never break estimation
            self._fail(exc)

    def finish(self, session) -> None:
        """Every estimator's final estimate (sent whatever the rate) and its last NIS."""
        try:
            for name in session.estimators:
                self._send(session, name)
                self._send_nis(session, name)
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        if not self._failed:
            self._failed = True
            log.warning("live view: feeding it failed (%s: %s); the replay goes on",
                        type(exc).__name__, exc)

    def _update(self, session, m) -> None:
        view = self.view
        if type(m) is GpsFix:
            if self.datum is None:
                self.datum = m.datum
            view.fix(m)
        if not view.watched():  # nobody looks: nothing is asked of the session
            self._idle = True
            return
        tr = self._truth
        if self._idle:  # a client came: from now on, not the backlog
            self._idle = False
            if tr is not None:
                self._ti = int(np.searchsorted(tr.t, m.t, side="left"))
            self._logged = {n: len(est.log.innovations)
                            for n, est in session.estimators.items()}
        if tr is not None:
            i = self._ti
            while i < len(tr.t) and tr.t[i] <= m.t:
                view.truth(float(tr.t[i]), tr.pose[i])
                i += 1
            self._ti = i
        for name in session.estimators:
            if self._gate.due(name, m.t):  # before the estimate: its cost
                self._send(session, name)
            self._send_nis(session, name)

    def _send(self, session, name: str) -> None:
        e = session.estimate(name)
        if e is None:
            return
        self.view.estimate(name, e, self.datum, force=True)  # rate-limited here, on m.t
        if self._truth is not None:
            xy, inside = interpolate_xy(self._truth, np.array([e.t]))
            err = (math.hypot(e.pose[0] - xy[0, 0], e.pose[1] - xy[0, 1]) if inside[0]
                   else None)
            self.view.scores(name, e.t, err, None)

    def _send_nis(self, session, name: str) -> None:
        inn = session.estimators[name].log.innovations
        i, n = self._logged.get(name, 0), len(inn)
        if i > n:  # a new session (the node restarted its estimators): its log from the start
            i = 0
        for k in range(i, n):
            try:
                u = inn[k]
            except IndexError:  # folded into the log's summary meanwhile
                continue
            self.view.scores(name, u.t, None, u.nis, f"{u.sensor}/{u.kind}")
        self._logged[name] = n
