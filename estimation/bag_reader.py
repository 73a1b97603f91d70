"""Opening a bag and reading the raw messages of the topics a config names.

``open_reader`` opens a ROS1 .bag, a ROS2 bag directory or an .mcap/.db3 file with rosbags'
AnyReader. ``configured_topics`` lists (kind, config key, sensor, topic) of a config;
``sources_of`` pairs each with the bag's connection (BagError naming the topic and config key if
it is absent or of a type its kind does not accept, ``ACCEPTED_TYPES``) and with its extractor
(``ddfuse.estimation.rosmsg``: struct extractors on ROS1 bytes where there is one) and converter
(``ddfuse.estimation.converters``). ``BagMessages`` yields (source, record time ns, raw message)
in write order where the storage keeps it: an intact ROS1 bag read from the front with
``ddfuse.estimation.ros1_scan`` (no index loaded), a ROS1 bag whose index is missing or damaged
the same way, a ROS2 sqlite3 or MCAP bag read by ``ddfuse.estimation.ros2_write_order`` (opened
and decoded by AnyReader); every other bag (a ROS2 bag compressed per file or message) through
AnyReader, sorted by record time. Storage that fails part way ends the reading early, saying
why.
Ordering by stamp, stamp checks and the datum are ``ddfuse.estimation.bags``'.
"""

from __future__ import annotations

import logging
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from ddfuse.estimation import ros1_scan, rosmsg
from ddfuse.estimation.config import Config, SensorConfig
from ddfuse.estimation.converters import converter, ground_truth_converter, slope_cells
from ddfuse.estimation.errors import BagError
from ddfuse.estimation.ros2_write_order import WriteOrder

__all__ = ["ACCEPTED_TYPES", "BagMessages", "Source", "configured_topics", "make_source",
           "open_reader", "sources_of"]

log = logging.getLogger(__name__)

ACCEPTED_TYPES = {
    "odometry": (rosmsg.ODOMETRY, rosmsg.TWIST_STAMPED),
    "imu": (rosmsg.IMU,),
    "gps": (rosmsg.NAVSATFIX,),
    "wheels": (rosmsg.JOINT_STATE,),
    "landmarks": (rosmsg.LANDMARK,),
    "magnetometer": (rosmsg.MAGNETIC_FIELD,),
    # an orientation without a north reference: an odometry's pose, an IMU's, a pose
    "local_heading": (rosmsg.ODOMETRY, rosmsg.IMU, rosmsg.POSE_STAMPED),
    "ground_truth": (rosmsg.ODOMETRY, rosmsg.POSE_STAMPED, rosmsg.NAVSATFIX),
}


@dataclass
class Source:
    """One configured topic: how to extract fields and turn them into measurements."""

    topic: str
    key: str  # config key for messages, e.g. 'sensors.imu[0]'
    msgtype: str
    extract: Callable
    convert: Callable[[tuple], list]
    raw: bool  # extract takes raw ROS1 bytes
    index: int = 0  # its place in the config's order (equal stamps keep that order)


def open_reader(bag: Path):
    """An opened AnyReader for a ROS1 bag, a ROS2 bag directory or an .mcap/.db3 file."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"{bag}: no such file or directory")
    path = bag
    if bag.is_file() and bag.suffix in (".mcap", ".db3"):
        path = bag.parent  # rosbags opens ROS2 bags by their directory (with metadata.yaml)
        if not (path / "metadata.yaml").is_file():
            raise BagError(f"{bag}: a ROS2 bag file needs its metadata.yaml beside it")
    elif bag.is_dir() and not (bag / "metadata.yaml").is_file():
        raise BagError(f"{bag}: a directory, but not a ROS2 bag (no metadata.yaml in it); give "
                       "a ROS1 .bag file or a ROS2 bag directory")
    store = get_typestore(Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE)
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError, AssertionError, IndexError) as e:
        # rosbags asserts on a damaged ROS1 index (a garbled IndexData record), which the
        # caller then reads from the front, as one without an index
        raise BagError(f"{bag}: cannot read bag ({type(e).__name__ if not str(e) else e}); "
                       "is it truncated or not a bag?") from None
    return reader


def configured_topics(cfg: Config) -> list[tuple[str, str, SensorConfig | None, str]]:
    """(kind, config key, sensor or None for ground truth, topic) of each configured topic."""
    wanted: list[tuple[str, str, SensorConfig | None, str]] = []
    counters: Counter = Counter()
    for s in cfg.sensors:
        wanted.append((s.kind, f"sensors.{s.kind}[{counters[s.kind]}]", s, s.topic))
        counters[s.kind] += 1
    if cfg.ground_truth_topic:
        wanted.append(("ground_truth", "ground_truth", None, cfg.ground_truth_topic))
    return wanted


def absent_topic(bag: Path, topic: str, key: str, present) -> BagError:
    return BagError(f"{bag}: topic {topic} ({key}.topic) is not in the bag; "
                    f"topics present: {', '.join(sorted(present)) or 'none'}")


def make_source(bag: Path, wanted: tuple, msgtype: str, ros1: bool,
                landmarks: dict | None = None, unknown: Counter | None = None,
                slopes: dict | None = None) -> Source:
    """The source of one configured topic whose messages are of ``msgtype``; ``ros1``: the
    messages come as ROS1 bytes, so the fast struct extractors apply. ``landmarks``,
    ``unknown``: a landmark sensor's map and count of unknown ids; ``slopes``: the config's
    ``slope_cells`` (``converter``)."""
    kind, key, s, topic = wanted
    if msgtype not in ACCEPTED_TYPES[kind]:
        need = " or ".join(rosmsg.short_type(t) for t in ACCEPTED_TYPES[kind])
        raise BagError(f"{bag}: topic {topic} has type {rosmsg.short_type(msgtype)}, "
                       f"but {key} needs {need}")
    fast, slow = rosmsg.EXTRACTORS[msgtype]
    use_raw = fast is not None and ros1
    conv = (converter(kind, s, key, landmarks, unknown, slopes) if s
            else ground_truth_converter(msgtype))
    return Source(topic, key, msgtype, fast if use_raw else slow, conv, use_raw)


def sources_of(cfg: Config, connections, bag: Path, ros1: bool, landmarks: dict | None = None,
               unknown: dict[str, Counter] | None = None) -> list[Source]:
    """The sources of the configured topics, checked against the bag's ``connections`` (each
    with .topic and .msgtype); BagError naming the topic if one is absent or of a wrong type.
    ``landmarks``: the map the sightings' ids are checked against, the ids not in it counted
    in ``unknown[topic]``."""
    conns = {c.topic: c for c in connections}
    out = []
    slopes = slope_cells(cfg)
    for w in configured_topics(cfg):
        topic = w[3]
        if topic not in conns:
            raise absent_topic(bag, topic, w[1], conns)
        out.append(make_source(bag, w, conns[topic].msgtype, ros1, landmarks,
                               None if unknown is None else unknown[topic], slopes))
    return out


def register_definition(store, conn: ros1_scan.Connection, bag: Path) -> str:
    """Register the type of ``conn`` (a ROS1 connection record) in the rosbags ``store``: the
    bag's own definition, as AnyReader does, unless it is damaged (it does not parse, or the
    standard ROS1 Noetic type has the record's md5sum and the bag's definition does not), then
    the standard one. Returns a warning line when the standard one was used, else ''.
    BagError naming the topic when neither can be used."""
    from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

    noetic = get_typestore(Stores.ROS1_NOETIC)
    known = conn.msgtype in noetic.fielddefs
    if not conn.msgdef:  # none in the bag, or dropped by the scanner as damaged
        store.register(noetic.fielddefs)
        return ""
    why = ""
    try:
        types = get_types_from_msg(conn.msgdef, conn.msgtype)
        own = get_typestore(Stores.EMPTY)
        own.register(types)
        if known and conn.md5sum and \
                own.generate_msgdef(conn.msgtype)[1] != conn.md5sum == \
                noetic.generate_msgdef(conn.msgtype)[1]:
            why = "its md5sum is not the record's"
    except TypesysError as e:
        why = "it does not parse"  # rosbags' message quotes the whole text, many lines
        if not known:
            raise BagError(f"{bag}: topic {conn.topic}: cannot use the bag's definition of "
                           f"{rosmsg.short_type(conn.msgtype)} ({e})") from None
    if not why:
        store.register(types)
        return ""
    store.register(noetic.fielddefs)
    return (f"{bag}: topic {conn.topic}: the bag's definition of "
            f"{rosmsg.short_type(conn.msgtype)} is damaged ({why}); the standard one is used")


class BagMessages:
    """The raw messages of a bag's configured topics: an intact ROS1 bag read from the front by
    ``ros1_scan`` (its topics checked against its index first), a ROS1 bag whose index is missing or
    damaged the same way (``indexed`` False), both in write order; a ROS2 sqlite3 or MCAP bag opened
    by rosbags' AnyReader and read in write order (``write_order``), anything else through AnyReader
    in record-time order. ``in_write_order``: the order is the one the recorder wrote, which shows a
    recording clock that stepped back. ``sources``: one ``Source`` per configured topic, ``index``
    its place in the config's order (BagError at construction if one is absent or of a wrong type;
    on a bag without index, when its connection record is read). ``frac``: the share read, 0..1;
    ``stopped``: why reading ended early on damaged storage, else None."""

    def __init__(self, bag: Path, cfg: Config, landmarks: dict | None,
                 unknown: defaultdict[str, Counter]) -> None:
        self.bag = bag
        self.wanted = configured_topics(cfg)
        self.landmarks = landmarks
        self.unknown = unknown  # topic -> ids of its sightings not in the map
        self.reader = None
        self.scan = None
        self.indexed = True  # False: a ROS1 bag read from the front for want of its index
        self.sources: list[Source] = []
        self.frac = 0.0
        self.stopped: str | None = None
        self.made: dict[str, Source] = {}  # config key -> source (bags read by the scanner)
        self.used = 0  # messages read on configured topics (bags read by the scanner)
        self.store = None  # the scanner's typestore, made when reading starts
        self.open_error: BagError | None = None
        self.notes: list[str] = []  # damaged definitions replaced by the standard ones
        self.write_order: WriteOrder | None = None  # a ROS2 bag's storage read in write order
        index = (ros1_scan.read_index(bag) if bag.is_file() and ros1_scan.has_magic(bag)
                 else None)
        if index is not None:
            # An intact ROS1 bag: its topics are checked against the connections of its index,
            # then it is read from the front by the scanner (rosbags' reader would load the
            # index of every message first: 90 MB for a 2 h bag), which reads past a damaged
            # record, counting what it cost from the index's chunk infos.
            self.sources = sources_of(cfg, index.connections, bag, ros1=True,
                                      landmarks=landmarks, unknown=unknown)
            self.scan = ros1_scan.Ros1Scan(bag, index)
        else:
            try:
                self.reader = open_reader(bag)
            except BagError as e:
                if not ros1_scan.has_magic(bag):
                    raise
                log.info("%s; reading it without its index", e)
                self.open_error = e
                self.scan = ros1_scan.Ros1Scan(bag)
                self.indexed = False
            else:
                try:
                    self.sources = sources_of(cfg, self.reader.connections, bag,
                                              not self.reader.is2, landmarks, unknown)
                except BagError:
                    self.reader.close()
                    raise
                if self.reader.is2:
                    self.write_order, why = WriteOrder.of(bag.parent if bag.is_file() else bag)
                    if why:
                        log.info("%s: read in record-time order (%s): a recording clock that "
                                 "stepped back cannot be seen", bag, why)
        for i, src in enumerate(self.sources):
            src.index = i

    @property
    def in_write_order(self) -> bool:
        return self.scan is not None or self.write_order is not None

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
            self.reader = None

    def records(self) -> Iterator[tuple[Source, int, object]]:
        """(source, record time ns, raw message) from the indexed reader or the scanner; stops
        early (setting ``_stopped``) when the storage fails."""
        if self.scan is not None:
            yield from self._unindexed()
            return
        reader = self.reader
        sources = self.sources
        by_topic: dict[str, list[Source]] = defaultdict(list)
        for src in sources:
            by_topic[src.topic].append(src)
        conns = [c for c in reader.connections if c.topic in by_topic]
        start, span = reader.start_time, max(1, reader.end_time - reader.start_time)
        expected = {c.topic: 0 for c in reader.connections}
        for c in reader.connections:
            expected[c.topic] += c.msgcount
        self._read_counts: Counter = Counter()
        read_counts = self._read_counts
        items = (reader.messages(connections=conns) if self.write_order is None
                 else self.write_order.messages(conns))
        try:
            try:
                for i, (conn, rec_ns, raw) in enumerate(items):
                    if i % 2000 == 0:
                        self.frac = (rec_ns - start) / span
                    for src in by_topic[conn.topic]:
                        read_counts[src.key] += 1
                        yield src, rec_ns, raw
            except BagError:
                raise
            except Exception as e:  # rosbags raises many types on damaged storage
                self.stopped = (f"bag is damaged or truncated after "
                                 f"{sum(read_counts.values())} messages "
                                 f"({type(e).__name__}: {e})")
                return
            short = [(s.topic, read_counts[s.key], expected[s.topic]) for s in sources
                     if read_counts[s.key] < expected[s.topic]]
            if short:
                topic, got, want = short[0]
                self.stopped = (f"bag is damaged: topic {topic} has {want} messages in its "
                                 f"index but only {got} could be read")
        finally:
            self.frac = 1.0
            self.close()

    def _unindexed(self) -> Iterator[tuple[Source, int, bytes]]:
        """The scanner's messages on configured topics. Sources are made at their topic's first
        connection record; messages are decoded as on the indexed path (struct extractors on
        the ROS1 bytes where rosmsg has one, else rosbags' deserialiser with the types that the
        bag's own connection records define, as AnyReader does for ROS1 bags)."""
        from rosbags.typesys import Stores, get_typestore

        bag, scan = self.bag, self.scan
        by_topic: dict[str, list[tuple]] = defaultdict(list)
        for w in self.wanted:
            by_topic[w[3]].append(w)
        made: dict[str, Source] = {s.key: s for s in self.sources}  # config key -> source
        self.made = made
        routes: dict[int, list[Source]] = {}  # connection id -> the sources it feeds
        store = self.store = get_typestore(Stores.EMPTY)
        order = {w[1]: i for i, w in enumerate(self.wanted)}
        self.used = 0  # messages read on configured topics

        def route(conn: ros1_scan.Connection, w: tuple) -> Source:
            src = made.get(w[1])
            if src is None:
                src = made[w[1]] = make_source(bag, w, conn.msgtype, ros1=True,
                                               landmarks=self.landmarks,
                                               unknown=self.unknown[conn.topic])
                src.index = order[w[1]]
                self.sources.append(src)
            elif src.msgtype != conn.msgtype:
                raise BagError(f"{bag}: topic {conn.topic} has messages of two types, "
                               f"{rosmsg.short_type(src.msgtype)} and "
                               f"{rosmsg.short_type(conn.msgtype)}")
            if not src.raw and conn.msgtype not in store.fielddefs:
                note = register_definition(store, conn, bag)
                if note:
                    self.notes.append(note)
            return src

        st = scan.status
        try:
            for i, item in enumerate(scan):
                if type(item) is ros1_scan.Connection:
                    routes[item.id] = [route(item, w) for w in by_topic.get(item.topic, ())]
                    continue
                if i % 2000 == 0:
                    self.frac = st.offset / max(1, st.file_size)
                srcs = routes[item.conn.id]
                if srcs:
                    self.used += 1
                for src in srcs:
                    yield src, item.time_ns, item.data
        except ros1_scan.ScanError as e:
            if self.indexed:
                raise BagError(f"{bag}: cannot read bag ({e})") from None
            raise BagError(f"{self.open_error}; reading it without the index fails too: "
                           f"{e}") from None
        finally:
            self.frac = 1.0

    def damage(self) -> tuple[list[str], Counter]:
        """The damaged records of a ROS1 bag read by the scanner: one line each (naming the
        file, the byte and record, what was damaged, how many messages it cost), and the
        messages lost per configured topic (connection ids resolved through the connections
        read; those of topics not configured are left out)."""
        if self.scan is None:
            return [], Counter()
        lines, lost = list(self.notes), Counter()
        topics = {s.topic for s in self.sources}
        for d in self.scan.status.damage:
            lines.append(f"{self.bag}: {d.line()}")
            for cid, n in (d.lost or {}).items():
                conn = self.scan.connections.get(cid)
                if conn is not None and conn.topic in topics:
                    lost[conn.topic] += n
        return lines, lost

    def end(self) -> tuple[str | None, str | None]:
        """At the end of the bag: (what cut a bag read without its index short, at which byte),
        both None for an indexed bag (whose damage, if any, is in ``stopped``). BagError when a
        bag without index gave nothing usable: no complete message, a configured topic absent
        from what could be read, no message of the configured topics."""
        bag = self.bag
        where = what = None
        if self.scan is not None and self.indexed:
            st = self.scan.status
            if st.reason:
                self.stopped = (f"bag is damaged or truncated after {st.messages} messages "
                                f"({st.reason})")
        elif self.scan is not None:
            st = self.scan.status
            what, where = st.unindexed_end()
            if not st.messages:
                raise BagError(f"{bag}: {what}; no complete message before {where}")
            missing = [w for w in self.wanted if w[1] not in self.made]
            if missing:
                kind, key, _, topic = missing[0]
                present = {c.topic for c in self.scan.connections.values()}
                raise BagError(f"{absent_topic(bag, topic, key, present)} (only up to {where} "
                               f"could be read: {what})")
            if not self.used:
                raise BagError(f"{bag}: {what}; no message of the configured topics before "
                               f"{where}")
        return where, what
