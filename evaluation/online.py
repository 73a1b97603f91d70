"""Online use: feed measurements one at a time, ask for the current estimate at any moment.

``OnlineSession`` is what a live robot uses from Python: call ``push(measurement)`` from each
sensor callback (``estimation.measurements`` dataclasses; ``estimation.live.LiveConverter``
makes them from the ROS messages, checking each topic's stamps against the receive time) and
``estimate(name)`` whenever a pose is needed; ``latency_ms()`` gives per-update latency
percentiles. ``replay`` drives a session from a bag, optionally paced by the header stamps.

The stream semantics are the bag reader's (``ddfuse.estimation.bags.BagStream``):

- Reordering. A session holds each measurement until a newer stamp is ``reorder_window`` s
  past it (``from_config``: the config's ``reorder_window``; the constructor's default 0), then
  passes it on, in stamp order (equal stamps: the config's sensor order, then arrival order).
- Late data (docs/design/late_data.md). A measurement older than one already passed on
  (``released_t``) goes, at once, to each running estimator that can still use it that late
  (``released_t - m.t <= est.late_horizon(m)``: the smoother takes a GPS fix or landmark
  sighting up to its lag late, into the keyframe nearest its stamp), counted in
  ``late_used[name][sensor]``; every other estimator (the EKFs: no history) drops it, counted
  in ``late_dropped[name][sensor]``. One that no estimator takes is also counted in ``late``
  and in ``rejected`` under (its sensor's name, by default the topic; the bag reader's reason
  "arrived after messages stamped up to more than reorder_window (... s) later had been passed
  on; ..."), the first per sensor logged as a warning: no estimator is ever handed a
  measurement older than one it has processed unless it says it can use it. So when the whole
  clock steps back (stamps and receive times alike, which the converter's stamp check cannot
  see), what comes in the next seconds is dropped until the stamps pass the last one passed
  on. A window of 0 passes each measurement
  straight on (no latency), still dropping the older ones. The estimates lag the newest stamp
  by up to the window (``estimate(name, at=t)`` carries one to t on the odometry pushed since,
  the buffer's included); ``flush()`` passes on what is held, ``finish()`` flushes and ends every
  estimator (a ``push`` after it raises RuntimeError). ``replay`` reads through ``BagStream``,
  which already reorders and checks stamps (``reorder_window`` there) and passes a late
  measurement on out of order (``pass_late``), so its session's own window is 0 and the late
  one reaches the session as late; its ``rejected`` then holds the bag reader's other counts
  (by topic) too.
- Isolation, as ``ddfuse.estimation.runner.run``: an estimator that raises (in ``process``,
  ``estimate`` or ``finish``) is stopped there, never called again, its error kept in
  ``errors[name]`` ("RuntimeError at t=...: ...") and noted in its ``log``; ``estimate(name)``
  then gives its last estimate (or None), and the others go on. ``push`` never raises because
  of one estimator. Ctrl-C inside an update stops that estimator too, and propagates.
"""

from __future__ import annotations

import gc
import heapq
import logging
import math
import time
from array import array
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import Config
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.estimator import Estimate, Estimator
from ddfuse.estimation.forecast import MAX_CARRY_S, OdometryTwist, carry
from ddfuse.estimation.interrupts import interrupt_in
from ddfuse.estimation.measurements import Stream
from ddfuse.estimation.runner import broken, initial_pose
from ddfuse.evaluation import estimators as registry

log = logging.getLogger(__name__)

ONLINE_TRACKS_REFUSED = {
    "smoother_lagged": "the lagged output of a keyframe exists only once it leaves the "
                       "smoother's window (its lag behind the newest message), so it cannot be "
                       "shown as the data comes; 'ddfuse run' gives it ('smoother' is the "
                       "filtered output)",
    "batch": "the batch optimises the whole run at once, so it has no estimate until the "
             "input ends; 'ddfuse run' gives it"}


class OnlineSession:
    """Estimators updated message by message through a reorder buffer, each isolated from the
    others' failures, with the wall time of every update recorded (module docstring).

    A stopped estimator's ``estimate`` is the newest of the last one handed out and the one the
    session keeps every ``KEEP_PERIOD`` s of stamps (as ``run`` records 10 per second): at most
    that old, taken before the failing update (its state after that is not trusted).

    ``order``: sensor name -> rank, the order of measurements with equal stamps (the config's
    sensor order, as the bag reader's); unknown sensors after the known ones.
    ``on_stop(name, t, why)`` is called when an estimator is stopped (``t`` the stamp of the
    measurement it failed on, None in ``finish``; ``why`` "Type: message").
    ``twist``: the odometry ``estimate(name, at=...)`` carries an estimate forward on
    (``from_config``: the config's), at most ``carry_horizon`` s (the reorder window plus
    ``ddfuse.estimation.forecast.MAX_CARRY_S`` = 5 s)."""

    KEEP_PERIOD = 0.1  # s

    def __init__(self, estimators: dict[str, Estimator], *, reorder_window: float = 0.0,
                 order: dict[str, int] | None = None,
                 on_stop: Callable[[str, float | None, str], None] | None = None,
                 twist: OdometryTwist | None = None) -> None:
        window = float(reorder_window)
        if not (window >= 0.0 and math.isfinite(window)):
            raise ValueError(f"reorder_window: expected seconds >= 0, got {reorder_window!r}")
        self.estimators = estimators
        self.reorder_window = window
        self.update_s: dict[str, array] = {n: array("f") for n in estimators}  # s, float32
        self.compact_s: dict[str, list[float]] = {n: [] for n in estimators}  # s
        self.errors: dict[str, str | None] = {n: None for n in estimators}
        self.stopped_t: dict[str, float | None] = {}  # name -> stamp it stopped at (None: finish)
        self.rejected: Counter = Counter()  # (sensor, reason) -> measurements dropped
        self.late: Counter = Counter()  # sensor -> too late for every estimator: dropped
        # name -> Counter(sensor -> n): late measurements the estimator used / dropped
        self.late_used: dict[str, Counter] = {n: Counter() for n in estimators}
        self.late_dropped: dict[str, Counter] = {n: Counter() for n in estimators}
        self._warned_late: set[str] = set()  # sensors whose late measurements were warned of
        self.released_t = -math.inf  # the stamp of the last measurement passed on
        self.on_stop = on_stop
        self.input_error: str | None = None  # set by replay when the bag breaks off
        self.input_warnings: list[str] = []  # set by replay: what the bag reader warned of
        self.replayed_s = 0.0  # data seconds replayed
        self.last_t: float | None = None  # set by replay: the last message's s since the first
        self.interrupted: str | None = None  # set by replay(interruptible=True) on Ctrl-C
        self._order = dict(order or {})
        self._twist = twist if twist is not None and twist.usable else None
        # s: the longest carry estimate(at=) makes, the estimators' lag plus some latency;
        # the twist keeps the samples of as long, or a long window's carry would miss some
        self.carry_horizon = window + MAX_CARRY_S
        if self._twist is not None and self._twist.keep < self.carry_horizon:
            self._twist.keep = self.carry_horizon
        self._heap: list = []
        self._seq = 0
        self._newest = -math.inf
        # each estimator's last estimate, kept for when it stops: the last one handed out by
        # estimate(), or taken every KEEP_PERIOD s of stamps, as run() records its output
        self._last: dict[str, Estimate | None] = {n: None for n in estimators}
        self._next_keep = -math.inf
        self.finished = False  # set by finish(): no push after it
        # s: the reorder window a late measurement missed, for what is said of it: the
        # session's own, or (replay) the bag reader's that reorders for it
        self.late_window = window

    @classmethod
    def from_config(cls, cfg: Config, names: list[str] | str | None = None, *,
                    stream: Stream | None = None, lag: float | None = None,
                    reorder_window: float | None = None,
                    on_stop: Callable[[str, float | None, str], None] | None = None,
                    ) -> OnlineSession:
        """Build the named estimators (``names``: a list, or a comma-separated string as
        ``ddfuse.evaluation.estimators.names_list`` reads it; default: all the config allows, except
        the offline batch). ``stream`` supplies the datum, landmark map and truth-based initial
        pose; ``reorder_window`` (s) defaults to the config's. ValueError for 'smoother_lagged'
        and 'batch' (``ONLINE_TRACKS_REFUSED`` says why), for unknown names, and for a config
        with ``initial_pose: ground_truth`` when no ``stream`` is given or it has no ground
        truth (the EKFs would wait for a truth pose that never comes)."""
        names = registry.names_list(names)
        for n in names or ():
            if n in ONLINE_TRACKS_REFUSED:
                raise ValueError(f"estimators: {n}: not available online: "
                                 f"{ONLINE_TRACKS_REFUSED[n]}")
        given = stream is not None
        stream = stream if given else Stream(measurements=[])
        chosen = [n for n in registry.select(cfg, names) if n not in ONLINE_TRACKS_REFUSED]
        pose = initial_pose(cfg.initial_pose, stream)
        if cfg.initial_pose == "ground_truth" and pose is None:
            # the EKFs would wait for a GroundTruthPose that a session is never pushed, and
            # give no estimate and no error: refused here, as LiveConverter refuses it
            why = "the stream given has no ground truth" if given else "no stream= given"
            raise ValueError(f"{cfg.path or 'config'}: initial_pose: ground_truth, but no truth "
                             f"pose to start from ({why}); give initial_pose as [x, y, yaw], "
                             "leave it out (heading from the GPS course or a compass), or pass "
                             "stream= with the run's ground truth")
        order: dict[str, int] = {}
        for i, s in enumerate(cfg.sensors):
            order.setdefault(s.name, i)
        # no lagged track online: its covariances cost the smoother much of its update time
        # (docs/design/performance.md)
        tracks = [t for n in chosen for t in registry.SPECS[n].produces
                  if t not in ONLINE_TRACKS_REFUSED]
        return cls(registry.build(cfg, stream, chosen, lag=lag, pose=pose, tracks=tracks),
                   reorder_window=cfg.reorder_window if reorder_window is None
                   else reorder_window, order=order, on_stop=on_stop,
                   twist=OdometryTwist(cfg))

    # --- feeding ---------------------------------------------------------------------------

    def push(self, m) -> None:
        """Take one measurement: into the reorder buffer, passing on to every running
        estimator what the buffer releases; dropped and counted when older than what was
        already passed on (or with a non-finite stamp). RuntimeError after ``finish()``:
        the estimators have ended (the smoother's state is gone; the EKFs would go on from a
        finished run as if nothing had happened)."""
        if self.finished:
            what = f"{type(m).__name__} at t={m.t!r}" if hasattr(m, "t") else type(m).__name__
            raise RuntimeError(f"OnlineSession ({', '.join(self.estimators) or 'no estimators'})"
                               f" is finished: push({what}) after finish() is refused; build a "
                               "new session to go on")
        t = m.t
        if not (t >= self.released_t and math.isfinite(t)):  # older than what was passed on
            self._late(m)
            return
        if self._twist is not None:
            self._twist.push(m)
        if self.reorder_window == 0.0:
            self.released_t = t
            self._apply(m)
            return
        heapq.heappush(self._heap, (t, self._order.get(m.sensor, len(self._order)),
                                    self._seq, m))
        self._seq += 1
        if t > self._newest:
            self._newest = t
        self._release(self._newest - self.reorder_window)

    def flush(self) -> None:
        """Pass on every measurement the reorder buffer holds."""
        self._release(math.inf)

    def finish(self) -> None:
        """Flush, then end every running estimator (an offline one solves here). Once only:
        a second call does nothing (the estimators are not finished twice), and ``push``
        is refused from then on."""
        if self.finished:
            return
        self.finished = True
        self.flush()
        for name, est in self.estimators.items():
            if self.errors[name] is None:
                try:
                    est.finish()
                except Exception as exc:
                    self._stop(name, None, exc)

    @property
    def pending(self) -> int:
        """Measurements held in the reorder buffer."""
        return len(self._heap)

    def _release(self, cut: float) -> None:
        heap = self._heap
        while heap and heap[0][0] < cut:
            item = heapq.heappop(heap)
            self.released_t = item[0]
            self._apply(item[3])

    def _late(self, m) -> None:
        """A measurement older than the last one passed on: to each running estimator that
        can use it that late, dropped for the others; each counted (module docstring)."""
        sensor = m.sensor
        if not math.isfinite(m.t):
            self.rejected[(sensor, "non-finite stamp")] += 1
            return
        behind = self.released_t - m.t  # s
        takers, dropped = [], []
        for name, est in self.estimators.items():
            if self.errors[name] is None:
                (takers if behind <= est.late_horizon(m) else dropped).append(name)
        for name in dropped:
            self.late_dropped[name][sensor] += 1
        for name in self._feed(m, takers):
            self.late_used[name][sensor] += 1
        if not takers:
            self.late[sensor] += 1
            # the bag reader's text
            self.rejected[(sensor, f"arrived after messages stamped up to more than "
                                   f"reorder_window ({self.late_window:g} s) later had been "
                                   "passed on; raise reorder_window to keep it")] += 1
        if dropped and sensor not in self._warned_late:
            self._warned_late.add(sensor)
            given = f"; used by {', '.join(takers)}" if takers else ""
            log.warning("%s: a measurement stamped %.3f s before the last one passed on came "
                        "after the reorder window (%g s): dropped and counted for %s (later "
                        "than each can use: late_horizon)%s", sensor, behind, self.late_window,
                        ", ".join(dropped), given)

    def _apply(self, m) -> None:
        """One measurement into every running estimator, each isolated from the others."""
        if m.t >= self._next_keep:  # before the update: what a failure inside it leaves
            self._keep(m.t)
        self._feed(m, [n for n in self.estimators if self.errors[n] is None])

    def _feed(self, m, names: list[str]) -> list[str]:
        """``m`` into the estimators ``names``, each timed and isolated from the others;
        returns those that took it without failing."""
        clock = time.perf_counter
        errors = self.errors
        took = []
        busy = None
        try:
            for name in names:
                est = self.estimators[name]
                busy = name
                t0 = clock()
                try:
                    est.process(m)
                except Exception as exc:  # one estimator failing must not stop the others
                    self._stop(name, m.t, exc)
                    continue
                took.append(name)
                s = self.update_s[name]
                t1 = clock()
                s.append(t1 - t0)
                if len(s) % 1000 == 0:
                    # the log's housekeeping: on this thread too, timed on its own
                    est.log.innovations.compact()
                    self.compact_s[name].append(clock() - t1)
            busy = None
        except KeyboardInterrupt:
            if busy is not None:  # inside an update: its state is half-updated
                errors[busy] = f"interrupted (Ctrl-C) inside an update at t={m.t:.3f}"
                self.stopped_t[busy] = m.t
                if self.on_stop is not None:
                    self.on_stop(busy, m.t, "interrupted (Ctrl-C) inside an update")
            raise
        return took

    def _keep(self, t: float) -> None:
        """Keep every running estimator's estimate (the one a failure would leave)."""
        p = self.KEEP_PERIOD
        self._next_keep = self._next_keep + p if self._next_keep + p > t else t + p
        for name, est in self.estimators.items():
            if self.errors[name] is None:
                try:
                    e = est.estimate()
                except Exception as exc:
                    self._stop(name, self.released_t, exc)
                    continue
                if e is not None and self._sound(name, e, self.released_t):
                    self._last[name] = e

    def _stop(self, name: str, t: float | None, exc: Exception) -> None:
        """Stop estimator ``name`` after ``exc`` (at stamp ``t``; None: in finish); its last
        estimate is what was kept before. An ``exc`` that carries a Ctrl-C (one that came
        inside a compiled call: ``interrupts.interrupt_in``) is raised as that interrupt, as
        a plain Ctrl-C there would be, not taken for the estimator's failure."""
        if (ki := interrupt_in(exc)) is not None:
            raise ki from None
        est = self.estimators[name]
        why = f"{type(exc).__name__}: {exc}"
        at = "in finish" if t is None else f"at t={t:.3f}"
        self.errors[name] = f"{type(exc).__name__} {at}: {exc}"
        self.stopped_t[name] = t
        est.log.note(t if t is not None else self.released_t, f"stopped: {self.errors[name]}")
        if self.on_stop is not None:
            self.on_stop(name, t, why)

    # --- results ---------------------------------------------------------------------------

    @property
    def newest(self) -> float:
        """The newest stamp pushed (s; -inf before the first)."""
        return max(self._newest, self.released_t)

    def estimate(self, name: str, at: float | None = None) -> Estimate | None:
        """The current estimate of ``name``; for a stopped estimator, its last one (or None).
        KeyError for a name the session does not run.

        ``at`` (s, the stamps' clock; e.g. ``session.newest``, or the time now on a live
        robot whose stamps are wall-clock): the estimate carried from its own stamp to ``at``
        on the odometry pushed since, the reorder buffer's included
        (``ddfuse.estimation.forecast``): the pose "now" although the estimators lag the newest
        message by up to the reorder window. Its covariance grows with the odometry's noise;
        it has no ``state``. Not carried: a stopped estimator's, a session without
        odometry (built without ``twist``), or ``at`` not after the estimate (-inf, i.e.
        ``newest`` before any push, included: the estimate returned then carries its own,
        later stamp ``t``). ValueError for an ``at`` that is not a time (NaN, +inf, not a
        number), or more than ``carry_horizon`` s (the reorder window plus
        ``ddfuse.estimation.forecast.MAX_CARRY_S`` = 5 s) after the estimate, carried or not (a
        stopped estimator's included): the carry covers the estimators' lag, it does not
        predict, and a stalled feed or a stopped estimator is to be seen, not answered with
        an old pose."""
        if at is not None:
            try:
                t = float(at)
            except (TypeError, ValueError):
                t = math.nan
            # -inf is allowed: it is ``newest`` before the first push, where nothing is
            # carried (no estimate yet, or at not after it)
            if math.isnan(t) or t == math.inf:
                raise ValueError(f"estimate({name!r}, at={at!r}): expected a time in seconds "
                                 "on the stamps' clock")
            at = t
        e = self._estimate(name)
        if at is None or e is None:
            return e
        if self._twist is None or self.errors[name] is not None:
            if at - e.t > self.carry_horizon:  # nothing to carry it with: as stale as it is
                why = (f"stopped ({self.errors[name]})" if self.errors[name] is not None
                       else "no odometry in the session to carry it with")
                raise ValueError(f"estimate({name!r}, at={at:.3f}): its estimate is "
                                 f"{at - e.t:.3f} s older, more than carry_horizon "
                                 f"{self.carry_horizon:g} s, and it cannot be carried: {why}")
            return e
        try:
            return carry(e, self._twist.samples, at, self._twist.q(), self._twist.scale_cov,
                         horizon=self.carry_horizon)
        except ValueError as exc:
            raise ValueError(f"estimate({name!r}, at=...): {exc} (carry_horizon: "
                             f"reorder_window {self.reorder_window:g} s + {MAX_CARRY_S:g} s "
                             "of latency)") from None

    def _estimate(self, name: str) -> Estimate | None:
        est = self.estimators[name]
        if self.errors[name] is not None:
            return self._last[name]
        try:
            e = est.estimate()
        except Exception as exc:
            t = self.released_t if math.isfinite(self.released_t) else math.nan
            self._stop(name, t, exc)
            return self._last[name]
        if e is not None:
            if not self._sound(name, e, self.released_t):
                return self._last[name]
            self._last[name] = e
        return e

    def _sound(self, name: str, e: Estimate, t: float) -> bool:
        """Whether estimate ``e`` is one a filter can give (``runner.broken``); else
        ``name`` is stopped there, as ``run`` stops it."""
        bad = broken(e)
        if bad is None:
            return True
        self._stop(name, t, FloatingPointError(f"numerical breakdown: {bad}"))
        return False

    def late_counts(self) -> dict[str, dict[str, dict[str, int]]]:
        """Per estimator, the late measurements (older than one already passed on) it used and
        dropped, by sensor: ``{name: {"used": {sensor: n}, "dropped": {sensor: n}}}``."""
        return {n: {"used": dict(sorted(self.late_used[n].items())),
                    "dropped": dict(sorted(self.late_dropped[n].items()))}
                for n in self.estimators}

    def latency_ms(self) -> dict[str, dict[str, float]]:
        """Per-estimator update latency p50 / p99 / max, ms (NaN without updates), and outside
        them the innovation log's compaction every 1000 updates: ``compact_max`` ms (NaN
        without one) over ``compactions`` calls."""
        out = {}
        for name, s in self.update_s.items():
            a = np.array(s, float) * 1e3 if s else np.full(1, math.nan)
            c = self.compact_s[name]
            out[name] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                         "max": float(a.max()), "updates": len(s),
                         "compact_max": max(c) * 1e3 if c else math.nan,
                         "compactions": len(c)}
        return out


def replay(bag: str | Path, cfg: Config, *, names: list[str] | None = None,
           realtime: bool = False, print_every: float = 1.0,
           on_print: Callable[[float, dict[str, Estimate | None]], None] | None = None,
           reorder_window: float | None = None, interruptible: bool = False,
           on_stop: Callable[[str, float | None, str], None] | None = None,
           observers: Sequence[Callable[[object], None]] = (),
           on_update: Callable[[OnlineSession, object], None] | None = None) -> OnlineSession:
    """Replay a bag into an OnlineSession, one message at a time, decoding it as it goes
    (``estimation.bags.BagStream``, which reorders by stamp within ``reorder_window`` and drops
    broken stamps; the session itself then passes each measurement straight on). With
    ``realtime`` the messages are paced by their header stamps; ``on_print`` is called with
    (t, estimates) every ``print_every`` seconds of data time (> 0; ValueError otherwise), from
    the first message on; the session's ``last_t`` is the last message's time (s since the
    first), at which the estimates after ``finish`` are final. ``on_stop(name, t, why)`` is
    called when an estimator fails and is stopped (``t`` s since the first message, None in
    its finish); the others go on (the session's ``errors``). The session's ``rejected`` holds
    what the bag reader dropped. A truncated or damaged bag is replayed up to where it breaks
    off; the session's ``input_error`` then says why (BagError if nothing could be read). With
    ``interruptible``, Ctrl-C ends the replay there as the bag's end would, and the session's
    ``interrupted`` says where (the latency figures so far are kept); otherwise it
    propagates. ``observers`` are called with every measurement before the session has it
    (e.g. ``ddfuse.estimation.heading_survey.OffsetRecorder.add``), outside the latency figures;
    ``on_update(session, m)`` after the session has it (e.g. ``evaluation.live_view.ReplayFeed``,
    which reads the estimates and the estimators' logs)."""
    if not (print_every > 0.0 and np.isfinite(print_every)):
        raise ValueError(f"print_every: expected seconds > 0, got {print_every!r}")
    stream = BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=False,
                       pass_late=True).prime()
    t0 = stream.t0 if stream.t0 is not None else 0.0
    stop_hook = None
    if on_stop is not None:
        def stop_hook(name: str, t: float | None, why: str) -> None:
            on_stop(name, None if t is None else t - t0, why)
    session = OnlineSession.from_config(cfg, names, stream=stream, reorder_window=0.0,
                                        on_stop=stop_hook)
    session.late_window = stream.depth
    wall0, next_print = time.perf_counter(), t0
    n = 0
    t_last = None
    # As runner.run does: a full collection walks every long-lived object (libraries, the
    # estimators, their logs) inside whichever update or log compaction it interrupts
    # (docs/design/performance.md); what exists now is frozen, automatic collection is off,
    # and the young generations are collected between messages.
    gc_was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        for m in stream:
            if realtime:
                lead = (m.t - t0) - (time.perf_counter() - wall0)
                if lead > 0:
                    time.sleep(lead)
            for ob in observers:
                ob(m)
            session.push(m)
            n += 1  # counted once fed: Ctrl-C during the pacing sleep left it unfed
            t_last = m.t
            if on_update is not None:
                on_update(session, m)
            if n % 1000 == 0:
                gc.collect(1)
            if on_print is not None and m.t >= next_print:
                on_print(m.t - t0, {k: session.estimate(k) for k in session.estimators})
                # the next grid time t0 + k * print_every after m.t (from m.t itself, each
                # print would lose up to a message interval: 0.1 s asked, 0.12 s printed)
                next_print = t0 + (math.floor((m.t - t0) / print_every) + 1) * print_every
    except KeyboardInterrupt:
        if not interruptible:
            raise
        at = "before the first message" if t_last is None else \
            f"{t_last - t0:.3f} s after the first message"
        session.interrupted = f"interrupted (Ctrl-C) after {n} measurements, {at}"
    finally:
        if gc_was_enabled:
            gc.enable()
        gc.unfreeze()
    if stream.error is not None and not n:
        raise BagError(stream.error)
    session.finish()
    session.rejected.update(stream.rejected)
    session.input_error = stream.error
    session.input_warnings = list(stream.warnings)
    session.replayed_s = stream.duration
    session.last_t = None if t_last is None else t_last - t0
    return session


def online_frame(bag: str | Path, cfg: Config, reorder_window: float | None = None
                 ) -> dict[str, str]:
    """``evaluation.local_frame.frame`` of an online replay of ``bag``: the facts it is named from
    (the datum: the config's or the first GPS fix; the landmark map; the initial pose) as
    ``run`` records them in metrics.json. The bag's start is decoded for the datum (what the
    replay's own stream does before its first message, a few ms)."""
    from ddfuse.evaluation.local_frame import frame

    stream = BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=False).prime()
    try:
        ip = cfg.initial_pose
        facts = {"data": {"datum": list(stream.datum) if stream.datum else None,
                          "landmarks": len(stream.landmarks)},
                 "initial_pose": "first ground-truth pose" if ip == "ground_truth"
                 else list(ip) if ip else None}
    finally:
        stream.close()
    return frame(facts)
