"""Read a ROS1 bag (format 2.0) from the front, record by record, without its index.

rosbags opens a ROS1 bag through the index that the recorder writes when it closes the file
(connection and chunk-info records at the end, found through the bag header's ``index_pos``).
A bag whose recorder was killed has no index (``index_pos`` 0) and a bag cut short in a copy has
an ``index_pos`` that points past its end, so rosbags cannot open either. Their data is still
there, in order (http://wiki.ros.org/Bags/Format/2.0)::

    #ROSBAG V2.0\\n
    bag header record (op 3, padded to 4096 bytes)
    chunk record (op 5): compressed connection (op 7) and message data (op 2) records
    index data records (op 4) of that chunk
    ... more chunks ...
    index: connection records (op 7), chunk info records (op 6)

Every record is ``<header_len u32><header><data_len u32><data>``; a header is a sequence of
``<field_len u32>name=value`` fields, little-endian. A connection record's data is itself such a
field sequence (topic, type, md5sum, message_definition, ...).

``Ros1Scan(path, index)`` iterates over the file's ``Connection``s (the index's first, if given;
else when their record is met, before any message on them) and ``Message``s, in file order. It
stops at the first record that is incomplete (the file ends), without raising, and
``Ros1Scan.status`` then says how far it got. It reads past a damaged record (a flipped byte):
a connection record whose definition is not text is used without it; a chunk with a damaged
record inside is read at the offsets its index data records give; a chunk whose data cannot be
decompressed gives what decompresses before the damage (of LZ4, which has no block checksums,
the records its index data vouch for: ``_trusted_prefix``); an unparseable record is skipped to
the next chunk or chunk index record found by its 'op' field. Each is a ``Damage`` in
``status.damage``, with the messages it cost when the index's chunk infos can count them
(docs/design/bag_faults.md).

Of a chunk cut by the end of the file it still yields the complete records that can be
decompressed from the bytes present: all of them for uncompressed chunks, those in its complete
LZ4 blocks (rosbags writes 64 KiB blocks), none for bz2 unless a whole bz2 block (900 kB of
records at level 9, more than a recorder's usual chunk) is present.

``estimation.bag_reader.BagMessages`` reads every ROS1 bag with the scanner (with its index
when it has a usable one). Messages come in file order, which is write order, not sorted by time
across chunks; the bag stream sorts by header stamp.
"""

from __future__ import annotations

import bz2
import contextlib
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import NamedTuple

import lz4.frame

MAGIC = b"#ROSBAG V2.0\n"
OP_MSGDATA, OP_BAGHEADER, OP_IDXDATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7
# Record headers hold a few short fields (a connection record's header: conn and topic); a
# length beyond this is damage, not a header, and must not make us allocate gigabytes.
MAX_HEADER = 1 << 20  # bytes
_OP_NAMES = {OP_MSGDATA: "message", OP_BAGHEADER: "bag header", OP_IDXDATA: "chunk index",
             OP_CHUNK: "chunk", OP_CHUNK_INFO: "chunk info", OP_CONNECTION: "connection"}

_U32 = struct.Struct("<I")
_TIME = struct.Struct("<II")  # sec, nsec
# The two layouts of a message record's 38-byte header that writers use: the C++ recorder's
# (time, conn, op) and rosbags' / rospy's (op, conn, time). Matched whole, they are read with
# one unpack instead of the general field parser (a third of the scanner's time per message).
_MSG_HLEN = 38
_MSG_TCO = struct.Struct("<9sII9sI8s")  # 'time=' sec nsec, 'conn=' id, 'op=\x02'
_MSG_OCT = struct.Struct("<8s9sI9sII")  # 'op=\x02', 'conn=' id, 'time=' sec nsec
_F_OP, _F_CONN, _F_TIME = b"\x04\0\0\0op=\x02", b"\x09\0\0\0conn=", b"\x0d\0\0\0time="


def normalize_topic(name: str) -> str:
    """A topic name as rosbags normalises it (``rosbags.rosbag1.reader.normalize``): repeated
    and trailing slashes dropped, a leading one kept. Written out here so that reading a ROS1
    bag does not import rosbags' reader (80 ms of start-up); tests compare the two."""
    return ("/" if name[:1] == "/" else "") + "/".join(x for x in name.split("/") if x)


def normalize_msgtype(name: str) -> str:
    """A message type in the ROS2 spelling rosbags gives it
    (``rosbags.typesys.msg.normalize_msgtype``): 'sensor_msgs/Imu' -> 'sensor_msgs/msg/Imu'."""
    path = PurePosixPath(name)
    if path.parent.name not in ("msg", "action"):
        path = path.parent / "msg" / path.name
    return str(path)


class ScanError(Exception):
    """The file cannot be scanned at all: not a ROS1 v2.0 bag, or an encrypted one."""


@dataclass(frozen=True)
class Connection:
    """A connection record: one publisher's topic and message type."""

    id: int  # 'conn' field, the id message records refer to
    topic: str  # normalised as rosbags does ('/a//b/' -> '/a/b')
    msgtype: str  # ROS2 spelling, as rosbags gives it: 'sensor_msgs/msg/Imu'
    md5sum: str
    msgdef: str  # the ROS1 message_definition text (dependent types after '=====' lines)


class Message(NamedTuple):
    """A message data record."""

    conn: Connection
    time_ns: int  # record (receive) time, ns since the epoch; not the header stamp
    data: bytes  # the message in ROS1 serialisation


@dataclass
class Damage:
    """A damaged part of a bag that the scan read past (a flipped byte, a garbled record)."""

    offset: int  # byte in the file of the damaged top-level record
    what: str  # which record and what is wrong with it
    resumed: int | None = None  # byte where reading went on; None: nothing readable after it
    salvaged: int = 0  # messages read from the damaged record all the same
    # connection id -> messages lost, from the index's chunk infos; None: not known (no index)
    lost: Counter | None = None

    def line(self) -> str:
        """One line: where, what, and how many messages it cost."""
        if self.lost is None:
            cost = "an unknown number of messages lost (the bag has no usable index to count them)"
        else:
            cost = f"{sum(self.lost.values())} messages lost"
        if self.salvaged:
            cost += f", {self.salvaged} read from it"
        then = (f"; reading went on at byte {self.resumed}" if self.resumed is not None
                else "; nothing readable after it")
        return f"damaged record at byte {self.offset}: {self.what}: {cost}{then}"


@dataclass
class ScanStatus:
    """How far a scan got. Updated while iterating; final once the iteration ends."""

    file_size: int  # bytes
    offset: int = 0  # bytes from the start of the file read as complete top-level records
    messages: int = 0  # message records yielded (including salvaged ones)
    chunks: int = 0  # complete chunks read
    salvaged: int = 0  # messages yielded from a chunk cut by the end of the file
    reason: str = ""  # why the scan stopped before the end of the file; '' if it did not
    truncated: bool = False  # it stopped because the file ends inside a record
    damage: list[Damage] = field(default_factory=list)  # damaged records read past

    @property
    def complete(self) -> bool:
        """The scan read every record up to the end of the file."""
        return not self.reason

    def unindexed_end(self) -> tuple[str, str]:
        """(what, where) of a bag read without its index, once the scan has ended: why its end
        may be missing data (a scan that reached the end of the file still lacks what the
        recorder buffered) and the byte it was read up to."""
        if self.truncated:
            what = f"bag is truncated: {self.reason}"
        elif self.reason:
            what = f"bag is truncated or damaged: its index is unusable and {self.reason}"
        else:
            what = ("bag is truncated: it has no index (its recorder did not close it), so the "
                    "messages it still buffered may be missing")
        return what, f"byte {self.offset} of {self.file_size}"


class _Incomplete(Exception):
    """The file (or a chunk's data) ends inside a record."""


class _Damaged(Exception):
    """A record that is not what the format allows."""


def _fields(buf: bytes, start: int, end: int) -> dict[str, bytes]:
    """Parse the ``<len u32>name=value`` fields of a header in ``buf[start:end]``."""
    out: dict[str, bytes] = {}
    pos = start
    while pos < end:
        if pos + 4 > end:
            raise _Damaged("header field length runs past the header")
        (n,) = _U32.unpack_from(buf, pos)
        pos += 4
        if pos + n > end:
            raise _Damaged("header field runs past the header")
        eq = buf.find(b"=", pos, pos + n)
        if eq < 0:
            raise _Damaged("header field without '='")
        out[buf[pos:eq].decode("ascii", "replace")] = buf[eq + 1:pos + n]
        pos += n
    return out


def _op(fields: dict[str, bytes]) -> int:
    op = fields.get("op")
    if op is None or len(op) != 1:
        raise _Damaged("record header has no 'op' field")
    return op[0]


def _u32(fields: dict[str, bytes], name: str) -> int:
    v = fields.get(name)
    if v is None or len(v) != 4:
        raise _Damaged(f"record header has no 4-byte {name!r} field")
    return _U32.unpack(v)[0]


def _connection(fields: dict[str, bytes], data: bytes) -> tuple[Connection, str]:
    """A Connection from a connection record's header fields and data, and what of its record
    is damaged ('' if nothing). A message definition or md5sum that is not text (a flipped
    byte) is dropped (''): readers then use the standard definition of the type, and only
    the topic and type are needed to route messages; without those the record is _Damaged."""
    conn = _u32(fields, "conn")
    info = _fields(data, 0, len(data))
    try:
        topic = (info.get("topic") or fields["topic"]).decode()
        msgtype = normalize_msgtype(info["type"].decode())
    except KeyError as e:
        raise _Damaged(f"connection record {conn} has no {e} field") from None
    except UnicodeDecodeError:
        raise _Damaged(f"connection record {conn}: its topic or type is not text") from None
    text, bad = {}, []
    for name in ("md5sum", "message_definition"):
        try:
            text[name] = info.get(name, b"").decode()
        except UnicodeDecodeError as e:
            text[name] = ""
            bad.append(f"its {name} is not text (byte {e.start} of the field)")
    return (Connection(conn, normalize_topic(topic), msgtype, text["md5sum"],
                       text["message_definition"]),
            f"connection record {conn} ({normalize_topic(topic)}): {'; '.join(bad)}"
            if bad else "")


def _decompress_head(compression: str, data: bytes) -> bytes:
    """What decompresses of damaged chunk ``data`` before the decompressor fails, fed to a
    streaming decompressor in slices until it does. bz2 checks each block's CRC, so its head
    is exact. LZ4, as rosbags writes it, has no block checksums: a flipped bit garbles its
    output silently before it fails (records seconds off in time, lengths shifted), so its head
    is to be trusted only as far as ``_trusted_prefix`` checks it against the chunk's index."""
    if compression == "none":
        return data
    if compression == "bz2":
        dec, errors = bz2.BZ2Decompressor(), (RuntimeError, OSError, ValueError, EOFError)
    elif compression == "lz4":
        dec, errors = lz4.frame.LZ4FrameDecompressor(), (RuntimeError, ValueError)
    else:
        return b""
    out = []
    step = 1 << 12 if compression == "lz4" else 1 << 14  # LZ4: a slice under its 64 KiB blocks
    try:
        for i in range(0, len(data), step):
            out.append(dec.decompress(data[i:i + step]))
    except errors:
        pass
    return b"".join(out)


def _trusted_prefix(buf: bytes, entries: list[tuple[int, int, int, int]]) -> int:
    """How many bytes of the head ``buf`` of a damaged LZ4 chunk to read: up to the start of
    the last of the message records that, from the chunk's first on, each stand at the offset
    the chunk's index data ``entries`` (offset, connection, sec, nsec; sorted) give, with that
    connection and time, and end at or before the next one's offset. The record in which the
    damage lies keeps a good header, so the last that checks is left out too; past the damage
    the output is shifted and no record checks (measured: docs/design/bag_faults.md)."""
    starts: list[int] = []
    n = len(buf)
    for k, (off, conn, sec, nsec) in enumerate(entries):
        nxt = entries[k + 1][0] if k + 1 < len(entries) else n
        if off + 8 > n:
            break
        hend = off + 4 + _U32.unpack_from(buf, off)[0]
        if hend + 4 > n:
            break
        try:
            fields = _fields(buf, off + 4, hend)
            ok = (_op(fields) == OP_MSGDATA and _u32(fields, "conn") == conn
                  and fields.get("time") == _TIME.pack(sec, nsec))
        except _Damaged:
            ok = False
        if not ok or hend + 4 + _U32.unpack_from(buf, hend)[0] > min(nxt, n):
            break
        starts.append(off)
    return starts[-1] if starts else 0


def _record_at(f, pos: int, size: int) -> bool:
    """Whether a chunk, chunk index, chunk info or connection record whose data fits in the
    file (``size`` bytes) starts at byte ``pos``; the file position is left unchanged."""
    back = f.tell()
    try:
        f.seek(pos)
        head = f.read(4)
        if len(head) < 4:
            return False
        (hlen,) = _U32.unpack(head)
        if not 8 <= hlen <= 4096:
            return False
        hdr = f.read(hlen)
        raw = f.read(4)
        if len(hdr) < hlen or len(raw) < 4:
            return False
        fields = _fields(hdr, 0, hlen)
        op = _op(fields)
        if op not in (OP_IDXDATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION):
            return False
        if op == OP_CHUNK and not ("compression" in fields and len(fields.get("size", b"")) == 4):
            return False
        return f.tell() + _U32.unpack(raw)[0] <= size
    except _Damaged:
        return False
    finally:
        f.seek(back)


def _find_record(f, start: int, size: int) -> int | None:
    """The byte of the first chunk or chunk index record at or after ``start`` (``_record_at``),
    found by its 'op' field; None if there is none. Read in windows: a bag may be large."""
    window, back = 1 << 20, 128  # bytes; a record header's op field is within 128 bytes
    pos = start
    while pos < size:
        f.seek(max(start, pos - back))
        base = f.tell()
        buf = f.read(window + back)
        hits = sorted(i for needle in (b"\x04\0\0\0op=\x05", b"\x04\0\0\0op=\x04")
                      for i in _all(buf, needle))
        for q in hits:
            for p in range(max(0, q - back), q - 3):
                if base + p >= start and _record_at(f, base + p, size):
                    return base + p
        pos = base + len(buf)
        if len(buf) < window:
            break
    return None


def _chunk_entries(f, size: int) -> list[tuple[int, int, int, int]] | None:
    """The message records that the index data records at the file position list, as
    (offset in the decompressed chunk, connection id, sec, nsec), sorted by offset; None if
    there are none or one is damaged. The file position is left unchanged."""
    back = f.tell()
    entries: list[tuple[int, int, int, int]] = []
    try:
        while _record_at(f, f.tell(), size):
            head = f.read(4)
            hdr = f.read(_U32.unpack(head)[0])
            fields = _fields(hdr, 0, len(hdr))
            data = f.read(_U32.unpack(f.read(4))[0])
            if _op(fields) != OP_IDXDATA:
                break
            if _u32(fields, "ver") != 1 or len(data) % 12:
                return None
            conn = _u32(fields, "conn")
            entries += [(off, conn, sec, nsec)
                        for sec, nsec, off in struct.iter_unpack("<III", data)]
    except _Damaged:
        return None
    finally:
        f.seek(back)
    return sorted(entries) or None


def _chunk_offsets(f, size: int) -> list[int] | None:
    """The message offsets (in the decompressed chunk) that the index data records at the file
    position give, sorted; None if there are none or one is damaged."""
    entries = _chunk_entries(f, size)
    return None if entries is None else [e[0] for e in entries]


def _next_inner_record(buf: bytes, start: int) -> int:
    """The offset of the first message or connection record at or after ``start`` in the
    decompressed chunk ``buf`` whose header parses and whose data ends inside the chunk, found
    by its 'op' field; ``len(buf)`` if there is none."""
    n = len(buf)
    hits = sorted(i for needle in (_F_OP, b"\x04\0\0\0op=\x07") for i in _all(buf, needle, start))
    for q in hits:
        for p in range(q - 4, max(start, q - 128) - 1, -1):
            (hlen,) = _U32.unpack_from(buf, p)
            hend = p + 4 + hlen
            if not (q < hend and hend + 4 <= n):
                continue
            try:
                _op(_fields(buf, p + 4, hend))
            except _Damaged:
                continue
            if hend + 4 + _U32.unpack_from(buf, hend)[0] <= n:
                return p
    return n


def _all(buf: bytes, needle: bytes, start: int = 0) -> Iterator[int]:
    i = buf.find(needle, start)
    while i >= 0:
        yield i
        i = buf.find(needle, i + 1)


def has_magic(path: str | Path) -> bool:
    """Whether ``path`` is a file that starts like a ROS1 v2.0 bag (a file cut inside the first
    line counts: it is a truncated bag, not some other file)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC))
    except OSError:
        return False
    return bool(head) and MAGIC.startswith(head)


@dataclass
class Index:
    """What a ROS1 bag's index holds that a front-to-back reader needs."""

    connections: list[Connection]
    # chunk byte -> connection id -> messages in that chunk (the chunk info records); None when
    # those records cannot be read
    chunk_counts: dict[int, Counter] | None
    # the record times the chunk infos span, (first, last) s; None when they cannot be read
    span: tuple[float, float] | None = None


class Ros1Scan:
    """Iterate over a ROS1 v2.0 bag's connections and messages in file order, without the
    index; see the module docstring. ``status`` tells how far the iteration got."""

    def __init__(self, path: str | Path, index: Index | None = None):
        """``index``: the bag's index (``read_index``), if it has a usable one: its connections
        are yielded first (a damaged chunk may hold the only other copy of a connection
        record) and its chunk infos count what a damaged record costs."""
        self.path = Path(path)
        self.status = ScanStatus(file_size=self.path.stat().st_size)
        self.connections: dict[int, Connection] = {}
        self.index = index
        self.chunk_counts = None if index is None else index.chunk_counts
        self._chunk_pos = 0  # byte of the chunk being read
        self._got: Counter = Counter()  # connection id -> messages read from that chunk
        self._inner: list[tuple[int, str]] = []  # that chunk's damaged records: (offset, why)

    def _stop(self, reason: str, truncated: bool) -> None:
        self.status.reason = reason
        self.status.truncated = truncated

    def __iter__(self) -> Iterator[Connection | Message]:
        st = self.status
        with open(self.path, "rb") as f:
            magic = f.read(len(MAGIC))
            if magic != MAGIC:
                if MAGIC.startswith(magic):
                    self._stop(f"the file ends inside the bag's first line ({len(magic)} bytes)",
                               truncated=True)
                    return
                raise ScanError(f"not a ROS1 bag v2.0 (its first line is {magic[:13]!r})")
            st.offset = len(MAGIC)
            try:
                fields, _, _ = self._record(f, read_data=False)
            except _Incomplete:
                self._stop("the file ends inside the bag header record", truncated=True)
                return
            except _Damaged as e:
                raise ScanError(f"bag header record is damaged ({e})") from None
            if fields is None:
                self._stop("the file ends after the bag's first line", truncated=True)
                return
            if _op(fields) != OP_BAGHEADER:
                raise ScanError("the first record is not a bag header")
            if fields.get("encryptor"):
                raise ScanError("the bag is encrypted "
                                f"({fields['encryptor'].decode(errors='replace')!r})")
            st.offset = f.tell()
            for c in self.index.connections if self.index is not None else ():
                self.connections[c.id] = c
                yield c
            while True:
                pos = f.tell()
                try:
                    fields, data, dlen = self._record(f, read_data=None)
                    if fields is None:
                        return  # end of file exactly between two records
                    op = _op(fields)
                    if op == OP_CHUNK:
                        self._chunk_pos, self._got = pos, Counter()
                        try:
                            yield from self._chunk(fields, data, dlen, f)
                        except _Damaged as e:
                            if not self._read_past(f, pos, f"chunk record: {e}", f.tell()):
                                return
                            continue
                        st.chunks += 1
                    elif op == OP_CONNECTION:
                        # The index repeats every connection; a new one here has no messages.
                        c, bad = _connection(fields, data)
                        if bad:
                            st.damage.append(Damage(pos, bad, f.tell(), lost=Counter()))
                        if c.id not in self.connections:
                            self.connections[c.id] = c
                            yield c
                    elif op not in (OP_IDXDATA, OP_CHUNK_INFO):
                        raise _Damaged(f"unexpected record op {op} outside a chunk")
                except _Incomplete as e:
                    self._stop(f"the file ends inside the record at byte {pos}{e}",
                               truncated=True)
                    return
                except _Damaged as e:
                    self._got = Counter()
                    if not self._read_past(f, pos, f"record header: {e}", None):
                        return
                    continue
                st.offset = f.tell()

    def _read_past(self, f, pos: int, what: str, end: int | None) -> bool:
        """Note the damaged record at byte ``pos`` and move ``f`` to the next record that can
        be read: its stated ``end``, if a record starts there, else the next chunk or chunk
        index record found after ``pos``. False (the scan stops) when there is none."""
        st = self.status
        if end is None or not _record_at(f, end, self.status.file_size):
            end = _find_record(f, pos + 1, st.file_size)
        dmg = Damage(pos, what, end, salvaged=sum(self._got.values()))
        if self.chunk_counts is not None:
            dmg.lost = Counter()
            stop = st.file_size if end is None else end
            for cpos, counts in self.chunk_counts.items():
                if pos <= cpos < stop:
                    dmg.lost.update(counts)
            dmg.lost.subtract(self._got)
            dmg.lost = +dmg.lost
        st.damage.append(dmg)
        if end is None:
            self._stop(f"the record at byte {pos} is damaged ({what}) and no readable record "
                       "follows it", truncated=False)
            return False
        f.seek(end)
        st.offset = end
        return True

    def _record(self, f, read_data: bool | None) -> tuple[dict[str, bytes] | None, bytes, int]:
        """Read the record at the file position: (header fields, data, declared data length).
        ``read_data`` False skips the data, None reads it except for index records (which the
        scan ignores). Returns (None, b'', 0) at the end of the file. A chunk whose data is cut
        by the end of the file is returned with the bytes present, for its caller to salvage."""
        head = f.read(4)
        if not head:
            return None, b"", 0
        if len(head) < 4:
            raise _Incomplete("")
        (hlen,) = _U32.unpack(head)
        if hlen > MAX_HEADER:
            raise _Damaged(f"header length {hlen} bytes")
        hdr = f.read(hlen)
        if len(hdr) < hlen:
            raise _Incomplete("")
        fields = _fields(hdr, 0, hlen)
        op = _op(fields)
        what = f" ({_OP_NAMES.get(op, f'op {op}')} record)"
        raw = f.read(4)
        if len(raw) < 4:
            raise _Incomplete(what)
        (dlen,) = _U32.unpack(raw)
        if read_data is False or (read_data is None and op in (OP_IDXDATA, OP_CHUNK_INFO)):
            end = f.tell() + dlen
            if end > self.status.file_size:
                raise _Incomplete(what)
            f.seek(end)
            return fields, b"", dlen
        # Never ask for more than the file holds: a damaged length can be up to 4 GiB, and
        # read(n) allocates n bytes before it reads.
        data = f.read(min(dlen, self.status.file_size - f.tell()))
        if len(data) < dlen and op != OP_CHUNK:
            raise _Incomplete(what)
        return fields, data, dlen

    def _chunk(self, fields: dict[str, bytes], data: bytes, dlen: int, f
               ) -> Iterator[Connection | Message]:
        """The records of a chunk record with header ``fields`` and (compressed) ``data`` of
        declared length ``dlen``. A chunk cut by the end of the file yields the complete records
        that can be decompressed from the bytes present, then raises _Incomplete saying so."""
        st = self.status
        compression = fields.get("compression", b"").decode("ascii", "replace")
        size = _u32(fields, "size")  # uncompressed bytes
        cut = len(data) < dlen
        try:
            if compression == "none":
                buf = data
            elif compression == "lz4":
                # A cut frame: the streaming decompressor returns every complete block.
                buf = (lz4.frame.LZ4FrameDecompressor().decompress(data) if cut
                       else lz4.frame.decompress(data))
            elif compression == "bz2":
                buf = bz2.BZ2Decompressor().decompress(data) if cut else bz2.decompress(data)
            else:
                raise _Damaged(f"chunk compression {compression!r} is not none, bz2 or lz4")
        except (RuntimeError, OSError, ValueError, EOFError) as e:
            if cut:
                raise _Incomplete(f" (a {compression} chunk with {len(data)} of its {dlen} "
                                  f"bytes, which cannot be decompressed ({e}): its messages "
                                  "are lost)") from None
            # what decompresses before the damage is read (of LZ4 what the chunk's index
            # data vouch for, none without them), then the chunk is reported damaged
            buf = _decompress_head(compression, data)
            if compression == "lz4":
                entries = _chunk_entries(f, self.status.file_size)
                yield from self._chunk_records(buf[:_trusted_prefix(buf, entries or [])])
            else:
                yield from self._chunk_records(buf, resync=True)
            raise _Damaged(f"its {compression} data cannot be decompressed: {e}") from None
        if not cut:
            # held until the chunk is known whole: a damaged record may swallow the ones after it
            items = list(self._chunk_records(buf, resync=True))
            if self._inner:
                (at, why), more = self._inner[0], len(self._inner) - 1
                how = ""
                offsets = _chunk_offsets(f, self.status.file_size)
                if offsets is not None:
                    items = self._at_offsets(buf, items, offsets)
                    how = "; its messages were read at the offsets its index records give"
                yield from items
                raise _Damaged(f"its record at offset {at} in the chunk is damaged ({why})"
                               + (f", and {more} more after it" if more else "") + how)
            yield from items
            if len(buf) != size:  # the records are whole: the size field is what is damaged
                st.damage.append(Damage(self._chunk_pos, f"chunk record: it holds {len(buf)} "
                                        f"bytes, its header says {size}", lost=Counter()))
            return
        # The output of a cut stream is exactly the start of the chunk's records, so every
        # complete record in it is as good as if the chunk were whole.
        before = st.messages
        yield from self._chunk_records(buf[:size])
        got = st.messages - before
        st.salvaged += got
        raise _Incomplete(f" (a {compression} chunk with {len(data)} of its {dlen} bytes: "
                          + (f"{got} messages recovered from it, the rest lost)" if got else
                             "no complete message could be recovered from them)"))

    def _at_offsets(self, buf: bytes, items: list, offsets: list[int]) -> list:
        """The records of the damaged chunk ``buf`` read again at the message ``offsets`` its
        index data records give: the connections of the first reading ``items``, then each
        message record that parses at its offset (the others are lost)."""
        self.status.messages -= sum(self._got.values())
        self._got = Counter()
        inner = self._inner
        out = [c for c in items if type(c) is Connection]
        n = len(buf)
        for off in offsets:
            if off + 8 > n:
                continue
            hend = off + 4 + _U32.unpack_from(buf, off)[0]
            end = hend + 4 + (_U32.unpack_from(buf, hend)[0] if hend + 4 <= n else n)
            if end > n:
                continue
            with contextlib.suppress(_Damaged):
                out += [m for m in self._chunk_records(buf[off:end]) if type(m) is Message]
        self._inner = inner
        return out

    def _chunk_records(self, buf: bytes, resync: bool = False):
        """Yield the connection and message records in the decompressed chunk ``buf`` up to the
        first incomplete one; returns the offset where it stopped. ``resync``: ``buf`` is a
        whole chunk, whose damaged records are noted in ``_inner`` (offset, why) and skipped
        to the next record found by its 'op' field (as a reader using the index would)."""
        st = self.status
        conns = self.connections
        n = len(buf)
        pos = 0
        self._inner = []
        while pos + 4 <= n:
            try:
                (hlen,) = _U32.unpack_from(buf, pos)
                hend = pos + 4 + hlen
                if hend + 4 > n:
                    if not resync:
                        break
                    raise _Damaged("its header runs past the chunk's end")
                (dlen,) = _U32.unpack_from(buf, hend)
                dend = hend + 4 + dlen
                if dend > n:
                    if not resync:
                        break
                    raise _Damaged("its data runs past the chunk's end")
                sec = -1
                if hlen == _MSG_HLEN:
                    ft, sec, nsec, fc, cid, fo = _MSG_TCO.unpack_from(buf, pos + 4)
                    if not (ft == _F_TIME and fc == _F_CONN and fo == _F_OP):
                        fo, fc, cid, ft, sec, nsec = _MSG_OCT.unpack_from(buf, pos + 4)
                        if not (ft == _F_TIME and fc == _F_CONN and fo == _F_OP):
                            sec = -1
                if sec >= 0:  # a message record in one of the usual layouts
                    op = OP_MSGDATA
                else:
                    fields = _fields(buf, pos + 4, hend)
                    op = _op(fields)
                if op == OP_MSGDATA:
                    if sec < 0:
                        cid = _u32(fields, "conn")
                    conn = conns.get(cid)
                    if conn is None:
                        raise _Damaged(f"message on connection {cid}, which has no record "
                                       "before it")
                    if sec < 0:
                        t = fields.get("time")
                        if t is None or len(t) != 8:
                            raise _Damaged("message record has no 8-byte 'time' field")
                        sec, nsec = _TIME.unpack(t)
                    st.messages += 1
                    self._got[cid] += 1
                    yield Message(conn, sec * 1_000_000_000 + nsec, buf[hend + 4:dend])
                elif op == OP_CONNECTION:
                    c, bad = _connection(fields, buf[hend + 4:dend])
                    if bad:
                        st.damage.append(Damage(self._chunk_pos, f"in its chunk, {bad}",
                                                lost=Counter()))
                    if conns.get(c.id) != c:  # writers may repeat a connection in later chunks
                        conns[c.id] = c
                        yield c
                else:
                    raise _Damaged(f"unexpected record op {op} inside a chunk")
            except _Damaged as e:
                if not resync:
                    raise
                self._inner.append((pos, str(e)))
                pos = _next_inner_record(buf, pos + 1)
                continue
            pos = dend
        if resync and pos < n:
            self._inner.append((pos, "a record runs past the chunk's end"))
            pos = n
        return pos


def read_index(path: str | Path) -> Index | None:
    """The connection and chunk info records of an intact ROS1 v2.0 bag's index (at the end of
    the file, at the bag header's ``index_pos``), without reading its chunks or the per-message
    index: what a reader needs to check topics and types before it scans the bag from the
    front, and to count what a damaged chunk costs. None when the bag has no usable index (no
    ``index_pos``, one past the end of the file, or records there that are not connections),
    is encrypted or is not a ROS1 v2.0 bag at all."""
    scan = Ros1Scan(path)
    size = scan.status.file_size
    try:
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                return None
            fields, _, _ = scan._record(f, read_data=False)
            if fields is None or _op(fields) != OP_BAGHEADER or fields.get("encryptor"):
                return None
            index_pos = fields.get("index_pos")
            conn_count = _u32(fields, "conn_count")
            chunk_count = _u32(fields, "chunk_count")
            if index_pos is None or len(index_pos) != 8:
                return None
            (pos,) = struct.unpack("<Q", index_pos)
            if not 0 < pos < size:
                return None
            f.seek(pos)
            out = []
            for _ in range(conn_count):
                fields, data, _ = scan._record(f, read_data=True)
                if fields is None or _op(fields) != OP_CONNECTION:
                    return None
                out.append(_connection(fields, data)[0])  # damage: the scan notes it
            span: list[float] = []
            return Index(out, _chunk_infos(f, scan, chunk_count, span),
                         (min(span), max(span)) if span else None)
    except (OSError, _Incomplete, _Damaged):
        return None


def _chunk_infos(f, scan: Ros1Scan, count: int, span: list[float]) -> dict[int, Counter] | None:
    """The ``count`` chunk info records at the file position: chunk byte -> connection id ->
    messages; None if one is damaged. Each chunk's start and end record time (s) are appended
    to ``span``."""
    out: dict[int, Counter] = {}
    try:
        for _ in range(count):
            fields, data, _ = scan._record(f, read_data=True)
            if fields is None or _op(fields) != OP_CHUNK_INFO or len(data) % 8 or \
                    len(fields.get("chunk_pos", b"")) != 8:
                return None
            (cpos,) = struct.unpack("<Q", fields["chunk_pos"])
            pairs = struct.unpack(f"<{len(data) // 4}I", data)
            out[cpos] = Counter(dict(zip(pairs[::2], pairs[1::2], strict=True)))
            for key in ("start_time", "end_time"):
                if len(fields.get(key, b"")) == 8:
                    sec, nsec = struct.unpack("<II", fields[key])
                    span.append(sec + nsec * 1e-9)
    except (OSError, _Incomplete, _Damaged):
        return None
    return out
