"""Read ROS1 .bag, ROS2 sqlite3 and MCAP bags into one time-ordered stream of measurements.

``read_stream(bag, cfg)`` reads the topics the config names, converts each message into the
measurement dataclasses of ``ddfuse.estimation.measurements`` (SI units, body frame after the
sensor's mount rotation, time from header stamps), orders them by header stamp, fixes the local
ENU datum and converts GPS fixes. ``open_stream`` / ``BagStream`` do the same while the stream is
iterated, with memory bounded however long the bag is.

Bad input never ends in a traceback: a bag or topic that cannot be used raises ``BagError``
naming the file, topic and field; a single bad message (NaN field, NO_FIX, unusable covariance,
a stamp far from its neighbours, a landmark sighting whose id is not in the map) is dropped and
counted in ``Stream.rejected`` by (topic, reason), and the stream's ``warnings`` say so.

A bag that breaks off (truncated, or damaged past some point) still gives what was read before:
the BagError carries it as ``partial``. A ROS1 bag that rosbags cannot open at all because its
index is missing or damaged (the recorder was killed, the copy was cut) is read from the front
by ``ddfuse.estimation.ros1_scan`` for that. A ROS1 bag with damaged records is read past them:
each is a warning, its lost messages counted in ``rejected`` (``bag_drops.DAMAGED``).

Time faults (docs/design/bag_faults.md): a recording clock that steps back, seen in a bag's write
order (ROS1, ROS2 sqlite3 and MCAP), re-times what follows (``ddfuse.estimation.clock_steps``); an
exact duplicate message is dropped and counted (``ddfuse.estimation.duplicates``); each says so in a
warning.

The parts, each in its module: opening the bag and reading the configured topics' raw messages
(``ddfuse.estimation.bag_reader``), the message converters per sensor kind
(``ddfuse.estimation.converters``), the per-topic stamp check (``ddfuse.estimation.stamp_check``);
this module holds the stamp-ordering stream that ties them together. Their names used by other
modules are importable from here too.
"""

from __future__ import annotations

import heapq
import logging
import math
from array import array
from collections import Counter, deque
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from ddfuse.estimation import geodesy
from ddfuse.estimation.bag_drops import TopicDrops
from ddfuse.estimation.bag_reader import (
    ACCEPTED_TYPES,
    BagMessages,
    Source,
    configured_topics,
    open_reader,
    sources_of,
)
from ddfuse.estimation.clock_steps import ClockSteps
from ddfuse.estimation.config import Config, landmark_maps
from ddfuse.estimation.converters import (
    NULL_ISLAND,
    Reject,
    converter,
    gps_fix,
    slope_cells,
)
from ddfuse.estimation.duplicates import DUPLICATE, Duplicates
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.gaps import gap_warning, is_gap
from ddfuse.estimation.gps_watch import GpsWatch
from ddfuse.estimation.measurements import GpsFix, GroundTruthPose, Stream, truth_at_start
from ddfuse.estimation.robot_limits import RobotLimits
from ddfuse.estimation.stamp_check import STAMP_TOLERANCE, UNSET_STAMP, StampCheck
from ddfuse.estimation.truth_screen import TruthScreen, screen_truth

# The names other modules and tests import from here (their homes are the modules above).
_gps_fix = gps_fix
_sources = sources_of
_StampCheck = StampCheck

__all__ = [
    "ACCEPTED_TYPES", "NULL_ISLAND", "STAMP_TOLERANCE", "UNSET_STAMP", "BagError", "BagStream",
    "Reject", "_StampCheck", "_gps_fix", "_sources", "configured_topics", "converter",
    "open_reader", "open_stream", "read_stream", "slope_cells",
]

log = logging.getLogger(__name__)



class BagStream:
    """The configured topics of a bag as one stream of measurements in header-stamp order,
    decoded while it is iterated: memory stays bounded however long the bag is.

    rosbags yields messages in record (receive) order; header stamps may be a little out of that
    order. A reorder buffer keyed by header stamp holds each measurement until the newest stamp
    is ``reorder_window`` seconds past it (default: the config's ``reorder_window``), then
    passes it on; a measurement that arrives after later-stamped ones were passed on is dropped
    and counted in ``rejected`` under its topic ("arrived ... later than reorder_window"), and a
    warning names the topic; with ``pass_late`` it is passed on at once instead, out of stamp
    order, and counted in ``passed_late`` (the GPS watch, a report on the stream in stamp
    order, does not see it). Each topic's broken stamps are dropped as ``StampCheck`` says.
    Measurements with equal stamps keep the order of a stable sort by (source, record order).

    Known before iterating (``prime`` decodes ahead as far as needed, holding what it read):
    ``t0`` (the first stamp), ``datum`` (the config's, or the first GPS fix's), the first
    ground-truth pose at or after ``t0`` (``first_truth``), ``landmarks``. Known after:
    ``t1``, ``count``, ``type_counts()``, ``rejected``, the ground truth (``truth_arrays()``,
    ``ground_truth``; kept as compact arrays, unless ``keep_truth`` is False), ``decode_s``.

    A bag that breaks off (truncated, damaged past some point; a ROS1 bag without its index is
    read from the front by ``ddfuse.estimation.ros1_scan``) ends the iteration early: ``error`` then
    says why, in one line naming the file. Errors that leave nothing to estimate on (a topic
    absent or of the wrong type, a bag that cannot be read at all) raise BagError, at
    construction or, for those only seen at the end of the bag (every message of a topic
    rejected, a topic whose clock jumps), when the iteration ends."""

    PRIME_SPAN = 30.0  # s of data past t0 that prime() reads ahead looking for the truth

    def __init__(self, bag: str | Path, cfg: Config, *, reorder_window: float | None = None,
                 keep_truth: bool = True, pass_late: bool = False) -> None:
        from time import perf_counter

        t_a = perf_counter()
        self.bag = bag = Path(bag)
        self.source = str(bag)
        self.cfg = cfg
        self.depth = cfg.reorder_window if reorder_window is None else float(reorder_window)
        if not self.depth >= 0.0:
            raise BagError(f"{bag}: reorder window must be >= 0 s, got {self.depth!r}")
        self.tolerance = max(STAMP_TOLERANCE, self.depth)
        self.keep_truth = keep_truth
        # pass a late measurement on at once, out of stamp order, instead of dropping it: for
        # a consumer that decides per estimator what it can still use (OnlineSession)
        self.pass_late = pass_late
        self.datum: tuple[float, float, float] | None = (
            cfg.datum if isinstance(cfg.datum, tuple) else None)
        self.landmarks = landmark_maps(cfg, bag)
        # what was dropped, per topic (``bag_drops``); its counts and warnings are this
        # stream's ``rejected``, ``late``, ``unknown_landmarks`` and ``warnings``
        self.drops = drops = TopicDrops(bag, cfg, self.landmarks, self.depth)
        self.unknown_landmarks = drops.unknown_landmarks
        self.passed_late = drops.passed_late  # topic -> late measurements passed on
        self.rejected = drops.rejected
        self.late = drops.late
        self.warnings = drops.warnings
        self.gaps: list[tuple[float, float]] = []  # (last stamp before, first after), s
        self.screen = RobotLimits(cfg, self.rejected)  # what the robot cannot do: rejected
        self.watch = GpsWatch(cfg)  # GPS against the odometry: disagreements reported
        self._datum_checked = not isinstance(cfg.datum, tuple)  # a stated datum: checked once
        self._topic_of = {sc.name: sc.topic for sc in cfg.sensors}
        self.t0: float | None = None
        self.t1: float | None = None
        self.count = 0
        self._counts: Counter = Counter()  # (sensor, measurement type) -> n
        self.error: str | None = None
        self.decode_s = 0.0
        self._truth = (array("d"), array("d"), array("d"), array("d"))
        self._truth_fixes: list[GpsFix] = []  # truth fixes waiting for the datum
        self._truth_found = False  # a truth pose at or after t0 has been seen
        self.truth_screen: TruthScreen | None = None  # set when the bag has been read to its end
        self._head: deque = deque()
        self._started = False
        self._msgs = BagMessages(bag, cfg, self.landmarks, self.unknown_landmarks)
        wanted = self._msgs.wanted
        self._gps_source = any(w[0] == "gps" for w in wanted)
        self._truth_idx = next((i for i, w in enumerate(wanted) if w[1] == "ground_truth"), -1)
        self._has_truth = self._truth_idx >= 0
        # the recording clock's backward steps (ROS1: read in write order) and the exact
        # duplicates found, made when reading starts
        self.clock_steps: ClockSteps | None = None
        self.duplicates: Duplicates | None = None
        self._gen = self._emitted()
        self.decode_s += perf_counter() - t_a

    # --- what is known ---------------------------------------------------------------------

    @property
    def recorded_span(self) -> float | None:
        """The bag's record-time span from its index (s), known before reading; None when
        there is no index (a bag read from the front)."""
        msgs = self._msgs
        if msgs.scan is not None:
            index = msgs.scan.index
            span = index.span if index is not None else None
            return None if span is None else span[1] - span[0]
        if msgs.reader is None:
            return None
        return max(0.0, (msgs.reader.end_time - msgs.reader.start_time) * 1e-9)

    @property
    def duration(self) -> float:
        return (self.t1 - self.t0) if self.t0 is not None and self.t1 is not None else 0.0

    def fraction(self) -> float:
        """How much of the bag has been read, 0..1."""
        return self._msgs.frac

    def type_counts(self) -> Counter:
        """(sensor, measurement type name) -> measurements passed on so far."""
        return Counter({(s, t.__name__): n for (s, t), n in self._counts.items()})

    def truth_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The ground truth so far: stamps (N,) s and poses (N, 3) (x m, y m, yaw rad; yaw NaN
        for a NavSatFix truth), in stamp order."""
        # the shortest column: a Ctrl-C inside _add_truth leaves the others one longer
        n = min(len(a) for a in self._truth)
        t, x, y, yaw = (np.array(a[:n], float) for a in self._truth)
        return t, np.column_stack([x, y, yaw]) if len(t) else np.zeros((0, 3))

    @property
    def ground_truth(self) -> list[GroundTruthPose]:
        t, pose = self.truth_arrays()
        return [GroundTruthPose(float(ti), float(p[0]), float(p[1]), float(p[2]))
                for ti, p in zip(t, pose, strict=True)]

    def first_truth(self) -> GroundTruthPose | None:
        """The ground-truth pose at t0 (``measurements.truth_at_start``); None without truth.
        Call after ``prime``."""
        return truth_at_start(*self.truth_arrays(), self.t0)

    def prime(self) -> BagStream:
        """Decode ahead until the stream's start, its datum and the first ground truth at or
        after its start are known (what estimators are built from), holding the measurements
        read on the way for the iteration. Returns self."""
        from time import perf_counter

        t_a = perf_counter()
        need_datum = self.datum is None and self._gps_source
        try:
            while True:
                if self.t0 is not None and not (need_datum and self.datum is None):
                    if not self._has_truth or self._truth_found:
                        break
                    if self._head and self._head[-1].t - self.t0 > self.PRIME_SPAN:
                        break
                m = next(self._gen, None)
                if m is None:
                    break
                self._head.append(m)
        finally:
            self.decode_s += perf_counter() - t_a
        return self

    def __iter__(self) -> Iterator:
        if self._started:
            raise RuntimeError("a BagStream can be iterated once")
        self._started = True
        return self._iterate_all()

    def _iterate_all(self) -> Iterator:
        from time import perf_counter as clock

        head = self._head
        while head:
            yield head.popleft()
        if not self.keep_truth:
            self._truth = (array("d"), array("d"), array("d"), array("d"))
        gen = self._gen
        t_a = clock()
        for m in gen:
            self.decode_s += clock() - t_a
            yield m
            t_a = clock()
        self.decode_s += clock() - t_a

    def close(self) -> None:
        self._msgs.close()

    # --- the pipeline: raw messages -> measurements -> stamp check -> reorder -> out -----------
    def _emitted(self) -> Iterator:
        """Every measurement in stamp order (the generator behind iteration and prime)."""
        rejected, offered = self.rejected, self.drops.offered
        checks: dict[int, StampCheck] = {}
        heap: list = []
        push, pop = heapq.heappush, heapq.heappop
        depth, tol = self.depth, self.tolerance
        deserialize = None
        seq = 0
        newest = -math.inf  # the newest stamp pushed
        released = -math.inf  # the stamp of the last measurement passed on
        # the newest stamp when it was: a late one needed a reorder window of this minus its
        # stamp (not the newest at its own admission, which a topic's warm-up may hold back)
        released_newest = -math.inf
        warming: set[int] = set()  # sources still in their stamp check's warm-up
        last_raw, last_msg = None, None
        late_out: deque = deque()  # pass_late: late measurements to pass on now

        def admit(ms: list, j: int, src: Source) -> None:
            """Into the reorder buffer, or dropped as late: measurements of source ``j``."""
            nonlocal seq, newest
            offered[src.topic] += len(ms)
            for m in ms:
                t = m.t
                if t < released:
                    if self.pass_late:
                        self.drops.count_passed_late(src.topic, t, released_newest)
                        late_out.append((t, j, -1, m))
                    else:
                        self.drops.count_late(src.topic, t, released, released_newest)
                    continue
                push(heap, (t, j, seq, m))
                seq += 1
                if t > newest:
                    newest = t

        seen = self.drops.seen  # topic -> messages read (per source reading it, as ``rejected``)
        msgs = self._msgs
        raw_items = msgs.records()
        if msgs.scan is None:
            deserialize = msgs.reader.deserialize
        # write order is known where the file is read from the front (ROS1, ROS2 sqlite3 and
        # MCAP without per-file or per-message compression)
        steps = self.clock_steps = ClockSteps(tol) if msgs.in_write_order else None
        dups = self.duplicates = Duplicates(ros1=msgs.scan is not None or not msgs.reader.is2)
        try:
            for src, rec_ns, raw in raw_items:
                seen[src.topic] += 1
                if dups.seen_before(src.index, src.topic, raw):
                    rejected[(src.topic, DUPLICATE)] += 1
                    continue
                if deserialize is None:
                    deserialize = msgs.store.deserialize_ros1
                try:
                    if src.raw:
                        rec = src.extract(raw)
                    else:
                        # Several sources may share a topic: deserialise each message once.
                        # Compare the bytes object itself (kept alive here), never its id(),
                        # which CPython reuses once the previous message is freed.
                        if raw is not last_raw:
                            last_raw, last_msg = raw, deserialize(raw, src.msgtype)
                        rec = src.extract(last_msg)
                    t_rec = rec[0]
                    if t_rec <= 0.0 and t_rec > -math.inf:  # non-finite: the converters' reason
                        rejected[(src.topic, UNSET_STAMP)] += 1
                        continue
                    if steps is not None:
                        t_new, rt_new = steps.retime(src.topic, t_rec, rec_ns * 1e-9)
                        if steps.shift:
                            rec = (t_new, *rec[1:])
                            rec_ns = round(rt_new * 1e9)
                    out = src.convert(rec)
                except Reject as e:
                    rejected[(src.topic, str(e))] += 1
                    if not e.kept:
                        continue
                    out = e.kept
                except Exception as e:  # a message that fails to decode is one bad message
                    rejected[(src.topic, f"cannot decode message: {type(e).__name__}: {e}")] += 1
                    continue
                rt = rec_ns * 1e-9
                idx = src.index
                chk = checks.get(idx)
                if chk is None:
                    chk = checks[idx] = StampCheck()
                    chk.first_rt = rt
                    warming.add(idx)
                passed = None
                if out:  # one check per message: its measurements share its header stamp
                    chk.n += 1
                    if chk.pending is not None:
                        chk.pending.append((out[0].t, rt, out))
                    elif chk.ok(out[0].t, rt, tol):
                        passed = out
                if warming:
                    for j in list(warming):
                        c = checks[j]
                        if len(c.pending) >= StampCheck.WARMUP or \
                                rt - c.first_rt > StampCheck.WARMUP_S:
                            warming.discard(j)
                            for _, _, ms in c.end_warmup(tol):
                                admit(ms, j, self._source_of(j))
                if passed is not None:
                    admit(passed, idx, src)
                while late_out:
                    m = self._out(late_out.popleft(), late=True)
                    if m is not None:
                        yield m
                if not warming:
                    cut = newest - depth
                    while heap and heap[0][0] < cut:
                        item = pop(heap)
                        released, released_newest = item[0], newest
                        m = self._out(item)
                        if m is not None:
                            yield m
            # the end of the bag: every warm-up ends, the buffer empties
            for j in sorted(warming):
                for _, _, ms in checks[j].end_warmup(tol):
                    admit(ms, j, self._source_of(j))
            while late_out:
                m = self._out(late_out.popleft(), late=True)
                if m is not None:
                    yield m
            while heap:
                item = pop(heap)
                released = item[0]
                m = self._out(item)
                if m is not None:
                    yield m
        finally:
            self.close()
        self._finish(checks)

    def _source_of(self, index: int) -> Source:
        return next(s for s in self._msgs.sources if s.index == index)

    def _out(self, item: tuple, late: bool = False):
        """Finish one measurement leaving the reorder buffer (``late``: passed on out of
        order, ``pass_late``): truth goes to the truth arrays, a GPS fix gets its ENU
        position; returns the measurement to pass on, or None."""
        m = item[3]
        if item[1] == self._truth_idx:
            if type(m) is GpsFix:
                if self.datum is None and not self._gps_source:
                    self.datum = (m.lat, m.lon, m.alt)
                if self.datum is None:
                    self._truth_fixes.append(m)
                else:
                    e, n, _ = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
                    self._add_truth(m.t, e, n, math.nan)
            else:
                self._add_truth(m.t, m.x, m.y, m.yaw)
            return None
        if type(m) is GpsFix:
            if self.datum is None:
                self.datum = (m.lat, m.lon, m.alt)
                self._flush_truth_fixes()
            m.enu = geodesy.geodetic_to_enu(m.lat, m.lon, m.alt, *self.datum)
            m.datum = self.datum
            if not self._datum_checked:
                self._datum_checked = True
                line = geodesy.far_datum(m, self.datum, self._topic_of.get(m.sensor, m.sensor))
                if line:
                    self.warnings.append(f"{self.bag}: {line}")
        ok = self.screen.admit(m)
        if not late:
            self.watch.feed(m, ok)
        if not ok:
            return None
        t = m.t
        if self.t0 is None:
            self.t0 = t
            if len(self._truth[0]) and self._truth[0][-1] >= t - 1e-9:
                self._truth_found = True
        if self.t1 is not None and is_gap(t - self.t1):
            self.gaps.append((self.t1, t))
        if self.t1 is None or t > self.t1:
            self.t1 = t
        self.count += 1
        self._counts[(m.sensor, type(m))] += 1
        return m

    def _warn_time(self) -> None:
        """The warnings of a recording clock that stepped back (``clock_steps``) and of exact
        duplicate messages (``duplicates``), one line each."""
        steps, dups = self.clock_steps, self.duplicates
        line = steps.warning(str(self.bag), self.t0) if steps is not None else None
        if line:
            self.warnings.append(line)
        if dups is not None:
            self.warnings.extend(dups.warnings(str(self.bag), self.drops.seen))

    def _count_damage(self) -> list[str]:
        """The damaged records the reader read past, warned about and their messages counted
        (``TopicDrops.count_damage``); returns the warning lines."""
        lines, lost = self._msgs.damage()
        self.drops.count_damage(lines, lost)
        return lines

    def _add_truth(self, t: float, x: float, y: float, yaw: float) -> None:
        if self._started and not self.keep_truth:
            return
        tt, xx, yy, ww = self._truth
        tt.append(t)
        xx.append(x)
        yy.append(y)
        ww.append(yaw)
        if not self._truth_found and self.t0 is not None and t >= self.t0 - 1e-9:
            self._truth_found = True

    def _screen_truth(self) -> None:
        """Leave out the truth samples no robot can produce (``truth_screen``), with a
        warning."""
        if not self._has_truth:
            return
        t, pose = self.truth_arrays()
        robot = self.cfg.robot
        keep, found = screen_truth(self.cfg.ground_truth_topic or "ground truth", t, pose,
                                   robot.speed_limit, robot.yaw_rate_limit)
        self.truth_screen = found
        line = found.warning(self.t0 or 0.0)
        if line:
            self.warnings.append(f"{self.bag}: {line}")
        if found.dropped:
            self._truth = tuple(array("d", col[keep]) for col in (t, *pose.T))

    def _flush_truth_fixes(self) -> None:
        fixes, self._truth_fixes = self._truth_fixes, []
        if not fixes:
            return
        e, n, _ = geodesy.geodetic_to_enu(np.array([f.lat for f in fixes]),
                                          np.array([f.lon for f in fixes]),
                                          np.array([f.alt for f in fixes]), *self.datum)
        for f, ei, ni in zip(fixes, e, n, strict=True):
            self._add_truth(f.t, float(ei), float(ni), math.nan)

    def _finish(self, checks: dict[int, StampCheck]) -> None:
        """At the end of the bag: the datum from a truth fix if no GPS sensor gave one, the
        counts of what was dropped, the errors that can only be seen now."""
        bag = self.bag
        if self._truth_fixes:
            if self.datum is None:
                f = self._truth_fixes[0]
                self.datum = (f.lat, f.lon, f.alt)
            self._flush_truth_fixes()
        where, what = self._msgs.end()
        damage = self._count_damage()
        try:
            self.drops.check_sources(self._msgs.sources, checks, self.tolerance)
        except BagError as e:
            if where is not None:
                raise BagError(f"{e} (only up to {where} could be read: {what})") from None
            if damage:
                raise BagError(f"{e}; the bag is damaged: {damage[0]}") from None
            raise
        self._warn_time()
        self._screen_truth()
        self.drops.warn_rejected()
        self.watch.finish()
        self.warnings += [f"{bag}: {w}" for w in (*self.screen.warnings(), *self.watch.warnings())]
        if self.gaps:
            self.warnings.append(gap_warning(str(bag), self.gaps, self.t0))
        for (topic, reason), n in sorted(self.rejected.items()):
            log.warning("%s: %s: %d message(s) rejected: %s", bag, topic, n, reason)
        for w in self.warnings:
            log.warning("%s", w)
        if where is not None:
            self.error = (f"{bag}: {what}; read {self._msgs.used} messages up to "
                          f"t={self.t1 if self.t1 is not None else 0.0:.3f} "
                          f"({self.duration:.1f} s of data, {where})")
        elif self._msgs.stopped is not None:
            self.error = f"{bag}: {self._msgs.stopped}"


def open_stream(bag: str | Path, cfg: Config, *, reorder_window: float | None = None,
                keep_truth: bool = True) -> BagStream:
    """A primed BagStream of ``bag`` (see there): its start, datum and initial truth known,
    ready to be run."""
    return BagStream(bag, cfg, reorder_window=reorder_window, keep_truth=keep_truth).prime()


def read_stream(bag: str | Path, cfg: Config, progress: Callable[[float], None] | None = None,
                *, reorder_window: float | None = None) -> Stream:
    """Read the configured topics of ``bag`` into a Stream ordered by header stamp: the whole
    of a BagStream (see there) in memory, for the tests and tools that want a list.

    ``progress``, if given, is called with the fraction of the bag read so far.
    Raises BagError (naming the file, topic and field) when the bag or a topic cannot be used.
    A bag that breaks off (truncated or damaged; a ROS1 bag without a usable index is read from
    the front by ``ddfuse.estimation.ros1_scan``) raises BagError saying so, carrying the stream of
    what could be read as ``partial``."""
    bs = BagStream(bag, cfg, reorder_window=reorder_window)
    measurements = []
    for i, m in enumerate(bs):
        measurements.append(m)
        if progress and i % 2000 == 0:
            progress(bs.fraction())
    stream = Stream(measurements=measurements, ground_truth=bs.ground_truth, datum=bs.datum,
                    landmarks=bs.landmarks, rejected=dict(bs.rejected), source=str(bag),
                    t0=bs.t0 if bs.t0 is not None else 0.0,
                    t1=bs.t1 if bs.t1 is not None else 0.0)
    if bs.error is not None:
        raise BagError(bs.error, partial=stream)
    return stream
