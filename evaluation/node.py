"""The core of ``ddfuse node``, free of any transport: ROS messages in, what to publish out.

A transport (``evaluation.ros1_transport`` for ROS 1; a ROS 2 one would be another such small
module) subscribes to ``NodeCore.topics``, checks each topic's message type once with
``type_problem``, and hands every message to ``receive(topic, msg, received)`` with its receive
time (s, on the clock of the header stamps: ROS time, which is the bag's under ``/use_sim_time``);
it publishes what ``receive``, ``diagnostics`` and ``finish`` return, each a ``Publish`` whose
``fields`` are transport-free message contents (``estimation.estimate_msgs``,
``evaluation.diagnostics.Status``).

Inside: ``estimation.live.LiveConverter`` (stamp checks, duplicates, robot limits) feeding an
``evaluation.online.OnlineSession`` (the reorder buffer, isolation of a failing estimator), as
``ddfuse online`` does. Published:

* every ``1 / node.rate`` s of the receive clock, each estimator's current estimate (stamp: the
  estimate's own time, not now; not again while it has not moved on, e.g. once stopped) as
  ``nav_msgs/Odometry`` on ``/ddfuse/<estimator>/odom`` and, when there is a datum (the
  config's, or the first fix's), ``sensor_msgs/NavSatFix`` on ``/ddfuse/<estimator>/fix``; one
  estimator's pose (``node.tf``) also as the TF local -> base on ``/tf``;
* each of the smoother's keyframes as it leaves the window (stamp: the keyframe's time) on
  ``/ddfuse/smoother_lagged/odom`` (and ``.../fix``), checked at every message;
* diagnostics every ``node.diagnostics_period`` s, and at once when a topic turns stale
  (``evaluation.diagnostics``).

A receive clock that jumps back by more than the converter's stamp tolerance (a simulated
clock restarted, ``rosbag play -l`` looping) resets the converter, the session and the
diagnostics' clocks: one warning, counted in ``resets``; what was estimated before is dropped
(with ``keep_measurements``, the measurements too: ``write_results`` covers the last segment).
A message that the converter refuses (a type its sensor cannot read) is counted in
``callback_errors`` and logged once per topic and error; ``receive`` never raises for a
message.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from ddfuse.estimation import rosmsg
from ddfuse.estimation.bag_reader import ACCEPTED_TYPES, configured_topics
from ddfuse.estimation.config import Config
from ddfuse.estimation.estimate_msgs import fix_of, odometry_of, tf_source, transform_of
from ddfuse.estimation.live import LiveConverter, message_type
from ddfuse.estimation.measurements import Stream
from ddfuse.evaluation.diagnostics import (
    ERROR,
    OK,
    WARN,
    Status,
    TopicClock,
    estimator_statuses,
    topic_statuses,
)
from ddfuse.evaluation.online import OnlineSession

__all__ = ["DIAGNOSTICS", "LAGGED", "NodeCore", "Publish", "TF", "fix_topic", "odom_topic"]

log = logging.getLogger(__name__)

TF = "/tf"
DIAGNOSTICS = "/diagnostics"
LAGGED = "smoother_lagged"  # the lagged track's name (its topics')
HARDWARE_ID = "ddfuse"


def odom_topic(name: str) -> str:
    return f"/ddfuse/{name}/odom"


def fix_topic(name: str) -> str:
    return f"/ddfuse/{name}/fix"


@dataclass(frozen=True, slots=True)
class Publish:
    """One message to publish: ``topic`` and its ``fields`` (an ``OdometryOut``, ``FixOut``,
    ``TransformOut``, or a tuple of diagnostics ``Status``)."""

    topic: str
    fields: object


class NodeCore:
    """What ``ddfuse node`` does between its subscribers and its publishers (module docstring).
    ``names``: the estimators, as ``OnlineSession.from_config`` takes them (default: all the
    config allows online); the smoother's lagged track is produced too. ``now``: the receive
    clock at the start (s), from which a topic that never publishes turns stale (None: the
    first time ``receive`` or ``diagnostics`` is given).
    ``keep_measurements``: keep what is fused, for ``write_results``. ``on_update(session, m)``:
    called after each measurement is pushed (``live_view.ReplayFeed``; it must not raise).
    ``reorder_window`` (s): the converter's and the session's, instead of the config's.
    ValueError for a config ``ddfuse node`` cannot run (``initial_pose: ground_truth``,
    unknown estimators, ``node.tf`` naming an estimator that does not run)."""

    def __init__(self, cfg: Config, names: list[str] | None = None, *, now: float | None = None,
                 keep_measurements: bool = False, reorder_window: float | None = None,
                 on_update: Callable | None = None) -> None:
        self.cfg = cfg
        self.on_update = on_update  # (session, measurement) after each push: the live view
        self.reorder_window = reorder_window
        self.names = names
        self.keep_measurements = keep_measurements
        self.resets = 0
        self.callback_errors: Counter = Counter()  # (topic, error) -> messages
        self._start(now)
        tf = cfg.node.tf
        run = list(self.session.estimators)
        if tf not in (None, "none", *run):
            raise ValueError(f"{cfg.path or 'config'}: node.tf: {tf!r} does not run here "
                             f"(running: {', '.join(run) or 'none'}; or 'none' for no TF)")
        self.tf_name = tf_source(run, tf)

    def _start(self, now: float | None) -> None:
        nc = self.cfg.node
        self.conv = LiveConverter(self.cfg, reorder_window=self.reorder_window)
        self.session = OnlineSession.from_config(self.cfg, self.names, stream=self.conv.stream(),
                                                 reorder_window=self.reorder_window)
        smoother = self.session.estimators.get("smoother")
        if smoother is not None:
            # from_config builds it without its lagged output (the online replay shows none);
            # the node publishes each keyframe as it leaves the window. Nothing processed yet.
            smoother.window.lagged = True
        self.clock = TopicClock(self.conv.topics, nc.topic_timeout, now)
        self.measurements: list = []
        self._next_pub = -math.inf
        self._next_diag = -math.inf
        self._published_t: dict[str, float] = {}
        self._lagged_sent = 0
        self._last_rt: float | None = None
        self._stale: set[str] = set()

    @property
    def topics(self) -> list[str]:
        """The topics to subscribe to: the config's sensor topics."""
        return self.conv.topics

    def type_problem(self, topic: str, msgtype: str) -> str | None:
        """Why messages of ``msgtype`` (either spelling: 'nav_msgs/Odometry') on ``topic``
        cannot be used (one line naming topic, config key and the types), or None."""
        mt = message_type(None, msgtype)
        for kind, key, _, t in configured_topics(self.cfg):
            if t == topic and mt not in ACCEPTED_TYPES[kind]:
                need = " or ".join(rosmsg.short_type(x) for x in ACCEPTED_TYPES[kind])
                return (f"topic {topic} carries {rosmsg.short_type(mt)}, but {key} "
                        f"({self.cfg.path or 'config'}) needs {need}")
        return None

    # --- input -----------------------------------------------------------------------------

    def receive(self, topic: str, msg, received: float, msgtype: str | None = None
                ) -> list[Publish]:
        """Take one message of ``topic`` received at ``received`` (s, the clock of the header
        stamps); returns what is due for publishing now. Never raises for the message; after
        ``finish`` it is ignored."""
        if self.session.finished:
            return []
        if self._last_rt is not None and received < self._last_rt - self.conv.tolerance:
            self.reset(f"the receive clock jumped back by {self._last_rt - received:.3f} s "
                       "(a simulated clock restarted, or a bag played in a loop)", received)
        self._last_rt = received
        self.clock.seen(topic, received)
        try:
            ms = self.conv.convert(topic, msg, msgtype, received=received)
        except ValueError as e:
            self.refuse(topic, str(e))
            return []
        for m in ms:
            self.session.push(m)
            if self.on_update is not None:
                self.on_update(self.session, m)
        if self.keep_measurements:
            self.measurements += ms
        return self.due(received)

    def refuse(self, topic: str, what: str) -> None:
        """Count a message of ``topic`` that could not be taken (``what``: why, one line),
        logged the first time for that topic and reason."""
        self.callback_errors[(topic, what)] += 1
        if self.callback_errors[(topic, what)] == 1:
            log.error("%s: %s; its messages are dropped and counted", topic, what)

    def reset(self, why: str, now: float) -> None:
        """Start again from nothing (a new converter, session and topic clocks), logging
        ``why`` once."""
        self.resets += 1
        log.warning("%s: the estimators are restarted (reset %d); what they had is dropped",
                    why, self.resets)
        self._start(now)

    # --- output ----------------------------------------------------------------------------

    def due(self, now: float) -> list[Publish]:
        """The smoother's keyframes that left its window since the last call, and, when a
        publishing tick of ``node.rate`` has passed at ``now``, each estimator's estimate."""
        out = self._lagged()
        if now >= self._next_pub:
            period = 1.0 / self.cfg.node.rate
            nxt = self._next_pub + period
            self._next_pub = nxt if nxt > now else now + period
            for name in self.session.estimators:
                e = self.session.estimate(name)
                if e is None or self._published_t.get(name) == e.t:
                    continue
                self._published_t[name] = e.t
                out += self._estimate(name, e)
                if name == self.tf_name:
                    out.append(Publish(TF, transform_of(e, self.cfg.local_frame,
                                                        self.cfg.base_frame)))
        return out

    def _estimate(self, name: str, e) -> list[Publish]:
        out = [Publish(odom_topic(name), odometry_of(e, self.cfg.local_frame,
                                                      self.cfg.base_frame))]
        if self.conv.datum is not None:
            out.append(Publish(fix_topic(name), fix_of(e, self.conv.datum,
                                                        self.cfg.base_frame)))
        return out

    def _lagged(self) -> list[Publish]:
        smoother = self.session.estimators.get("smoother")
        track = smoother.lagged_estimates() if smoother is not None else None
        out: list[Publish] = []
        while track is not None and self._lagged_sent < len(track):
            out += self._estimate(LAGGED, track[self._lagged_sent])
            self._lagged_sent += 1
        return out

    @property
    def rejected(self) -> Counter:
        """(topic or sensor, reason) -> measurements dropped, the converter's and the
        session's (a sensor's name is its topic unless the config names it)."""
        return self.conv.rejected + self.session.rejected

    def diagnostics(self, now: float, force: bool = False) -> Publish | None:
        """The diagnostics at ``now`` (receive clock) when ``node.diagnostics_period`` has
        passed since the last, a topic has turned stale since, or ``force``; else None."""
        self.clock.at(now)
        stale = self.clock.stale(now)
        fresh_stale = stale - self._stale
        self._stale = stale
        if not (force or fresh_stale or now >= self._next_diag):
            return None
        self._next_diag = now + self.cfg.node.diagnostics_period
        nc = self.cfg.node
        statuses = topic_statuses(self.clock, now, self.rejected, HARDWARE_ID)
        statuses += estimator_statuses(self.session, self.session.newest, nc.nis_window,
                                       HARDWARE_ID)
        errors = sum(self.callback_errors.values())
        level = ERROR if errors else WARN if self.resets else OK
        msg = (f"{errors} messages refused (the log says why)" if errors
               else f"{self.resets} resets (clock jumps back)" if self.resets else "running")
        values = (("resets", str(self.resets)), ("callback_errors", str(errors)),
                  ("pending", str(self.session.pending)),
                  ("late_dropped", str(sum(self.session.late.values()))))
        values += tuple((f"refused {topic}", what) for topic, what in self.callback_errors)
        statuses.append(Status(level, "ddfuse: node", msg, HARDWARE_ID, values))
        return Publish(DIAGNOSTICS, tuple(statuses))

    def finish(self) -> list[Publish]:
        """End the session (what the reorder buffer holds is passed on, the smoother's window
        leaves as lagged keyframes); returns what is left to publish."""
        self.session.finish()
        self._next_pub = -math.inf
        return self.due(math.inf)

    # --- results ---------------------------------------------------------------------------

    def write_results(self, outdir: str | Path):
        """``ddfuse run``'s results (metrics.json, tracks, run.npz: ``pipeline.write_outputs``)
        for the measurements fused since the start or the last reset (``keep_measurements``),
        the same estimators run on them as ``ddfuse run`` runs them. Returns the RunSummary;
        ValueError when nothing was fused."""
        from ddfuse.estimation.runner import initial_pose, run
        from ddfuse.evaluation import estimators as registry
        from ddfuse.evaluation.pipeline import data_facts, score, write_outputs
        from ddfuse.evaluation.run_files import config_text_of

        if not self.measurements:
            raise ValueError("no measurement was fused: no results to write")
        cfg = self.cfg
        order = {s.name: i for i, s in reversed(list(enumerate(cfg.sensors)))}
        ms = sorted(self.measurements, key=lambda m: (m.t, order.get(m.sensor, len(order))))
        stream = Stream(measurements=ms, datum=self.conv.datum,
                        landmarks=dict(self.conv.landmarks), rejected=dict(self.rejected),
                        source="ddfuse node", t0=ms[0].t, t1=ms[-1].t)
        names = list(self.session.estimators)
        pose = initial_pose(cfg.initial_pose, stream)
        ests = registry.build(cfg, stream, names, pose=pose)
        result = run(stream, ests)
        summary = score(result, 0.0, {n: getattr(e, "pose_error", "world")
                                      for n, e in ests.items()}, cfg=cfg)
        summary = replace(summary, config=str(cfg.path) if cfg.path else None,
                          initial_pose=list(pose) if pose else None, lag_s=cfg.smoother.lag,
                          estimators_run=names, data=data_facts(result, cfg),
                          warnings=self.conv.warnings)
        write_outputs(result, Path(outdir), summary, config_text_of(cfg), cfg=cfg)
        return summary
