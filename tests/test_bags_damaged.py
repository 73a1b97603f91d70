"""A ROS1 bag with one flipped byte is read past its damage: every message that can be read is,
and what cannot is one warning naming the file, the byte, the record and the count lost, the
lost messages counted per topic in ``rejected`` (``bag_drops.DAMAGED``).

The oracle: the intact bag's per-topic message counts (its index, read by rosbags), which the
messages read plus the ones counted lost must equal, topic by topic; and rosbags reading the
damaged copy: where it reads every message, nothing may be counted lost.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import bagwriter as bw
import byteflip
import lz4.frame
import pytest
from ddfuse.estimation import ros1_scan
from ddfuse.estimation.bag_drops import DAMAGED
from ddfuse.estimation.bags import BagStream
from ddfuse.estimation.config import load_config, parse_config
from ddfuse.estimation.errors import BagError
from rosbags.rosbag1 import Reader

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"
SAMPLE_CFG = ROOT / "data" / "sample_husky.yaml"
T0 = 1_600_000_000.0  # s
N = 600  # messages of the crafted bag
CFG = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}],
                   "odometry": [{"topic": "/odom"}]}}


@pytest.fixture(scope="module")
def crafted(tmp_path_factory) -> Path:
    """An uncompressed ROS1 bag of IMU and odometry messages in several chunks."""
    recs = []
    for i in range(N):
        t = T0 + 0.01 * i
        recs.append(("/imu", bw.imu(t, angvel=(0, 0, 0.1), wcov=bw.diag(1, 1, 1))))
        if i % 2 == 0:
            recs.append(("/odom", bw.odometry(t, v=1.0, twist_cov=bw.diag(1, 1, 1, 1, 1, 1))))
    path = tmp_path_factory.mktemp("crafted") / "clean.bag"
    return bw.write_bag(path, "ros1", recs, chunk_bytes=20_000)


def topic_counts(bag: Path) -> Counter:
    with Reader(bag) as r:
        return Counter({c.topic: c.msgcount for c in r.connections})


def rosbags_reads(bag: Path) -> int | None:
    """How many messages rosbags reads from ``bag``; None if it fails."""
    try:
        with Reader(bag) as r:
            return sum(1 for _ in r.messages())
    except Exception:
        return None


def read(bag: Path, cfg) -> tuple[BagStream, Counter, Counter, list[str]]:
    """(stream, messages read per topic, messages counted lost per topic, damage warnings)."""
    bs = BagStream(bag, cfg)
    for _ in bs:
        pass
    lost = Counter({t: n for (t, r), n in bs.rejected.items() if r == DAMAGED})
    return bs, bs.drops.seen, lost, [w for w in bs.warnings if "damaged record at byte" in w]


def assert_accounted(bad: Path, clean_counts: Counter, cfg) -> tuple[Counter, list[str]]:
    """Every configured topic's messages are read or counted lost; a loss has its warning;
    when rosbags reads every message of the damaged copy, nothing is lost."""
    bs, seen, lost, warnings = read(bad, cfg)
    for topic in {s.topic for s in bs._msgs.sources}:
        assert seen[topic] + lost[topic] == clean_counts[topic], (bad, topic)
    if sum(lost.values()):
        assert warnings and all(str(bad) in w for w in warnings)
    if rosbags_reads(bad) == sum(clean_counts.values()):
        assert not sum(lost.values()), bad
    return lost, warnings


def test_flipped_byte_in_a_connection_definition_loses_nothing(crafted, tmp_path):
    """The record's message_definition no longer UTF-8: before, the scanner stopped at the
    first chunk and the run ended with 'no configured sensor topic has a message'."""
    buf = crafted.read_bytes()
    at = buf.index(b"message_definition=") + 40  # the copy in the first chunk
    bad = byteflip.flip(crafted, tmp_path / "bad.bag", at)
    lost, warnings = assert_accounted(bad, topic_counts(crafted), parse_config(CFG))
    assert not lost
    [w] = warnings
    assert "message_definition is not text" in w and "0 messages lost" in w


def test_flipped_byte_in_the_index_connection_loses_nothing(crafted, tmp_path):
    buf = crafted.read_bytes()
    at = buf.rindex(b"message_definition=") + 40  # the copy in the index at the end
    bad = byteflip.flip(crafted, tmp_path / "bad.bag", at)
    assert rosbags_reads(bad) is None  # rosbags cannot open it
    lost, [w] = assert_accounted(bad, topic_counts(crafted), parse_config(CFG))
    assert not lost and "0 messages lost" in w


def test_flipped_byte_in_a_message_payload_reads_every_message(crafted, tmp_path):
    recs = byteflip.records(crafted.read_bytes())
    chunk = [r for r in recs if r.op == ros1_scan.OP_CHUNK][1]
    bad = byteflip.flip(crafted, tmp_path / "bad.bag", (chunk.data + chunk.end) // 2, 0)
    lost, warnings = assert_accounted(bad, topic_counts(crafted), parse_config(CFG))
    assert not lost and not warnings


def test_flipped_byte_in_a_chunk_header_loses_that_chunk_and_says_so(crafted, tmp_path):
    buf = crafted.read_bytes()
    chunk = [r for r in byteflip.records(buf) if r.op == ros1_scan.OP_CHUNK][1]
    op = buf.index(b"op=\x05", chunk.start) + 3
    bad = byteflip.flip(crafted, tmp_path / "bad.bag", op)
    with Reader(crafted) as r:
        [info] = [c for c in r.chunk_infos if c.pos == chunk.start]
        in_chunk = sum(info.connection_counts.values())
    lost, [w] = assert_accounted(bad, topic_counts(crafted), parse_config(CFG))
    assert sum(lost.values()) == in_chunk > 0
    assert f"byte {chunk.start}" in w and f"{in_chunk} messages lost" in w


def test_flipped_byte_in_a_chunk_index_record_loses_nothing(crafted, tmp_path):
    buf = crafted.read_bytes()
    idx = [r for r in byteflip.records(buf) if r.op == ros1_scan.OP_IDXDATA][2]
    bad = byteflip.flip(crafted, tmp_path / "bad.bag", idx.start + 2)  # its header length
    lost, [w] = assert_accounted(bad, topic_counts(crafted), parse_config(CFG))
    assert not lost and "0 messages lost" in w


def test_a_bag_damaged_everywhere_after_its_start_is_still_an_error(crafted, tmp_path):
    """Nothing readable after the first record: the error says the bag is damaged."""
    buf = bytearray(crafted.read_bytes())
    first = byteflip.records(bytes(buf))[1]
    buf[first.start:] = b"\xff" * (len(buf) - first.start)
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(buf))
    with pytest.raises(BagError) as e:
        read(bad, parse_config(CFG))
    assert str(bad) in str(e.value) and "damaged" in str(e.value)


@pytest.mark.parametrize("flip", [(10, 0, "md5sum"), (7, 0, "does not parse")],
                         ids=["field name", "syntax"])
def test_a_damaged_definition_is_replaced_by_the_standard_one(tmp_path, flip):
    """seed002's JointState (read by rosbags' deserialiser, from the definition in the bag's
    index): 'velocity' -> 'welocity' (parses, md5sum not the record's) or 'float64[]' ->
    'float64Z]': before, every wheel message failed to decode."""
    src = ROOT / "data" / "sample_seed002.bag"
    cfg = load_config(ROOT / "data" / "sample_seed002.yaml")
    at = src.read_bytes().rindex(b"float64[] velocity")
    bad = byteflip.flip(src, tmp_path / "bad.bag", at + flip[0], flip[1])
    clean = [repr(m) for m in BagStream(src, cfg)]
    bs = BagStream(bad, cfg)
    assert [repr(m) for m in bs] == clean and not bs.rejected
    [w] = [w for w in bs.warnings if "definition" in w]
    assert str(bad) in w and "/joint_states" in w and flip[2] in w and "standard" in w


@pytest.mark.slow
def test_thirty_random_flips_of_the_sample_each_read_or_counted(tmp_path):
    cfg = load_config(SAMPLE_CFG)
    counts = topic_counts(SAMPLE)
    damaged = 0
    for bad, _ in byteflip.random_flips(SAMPLE, tmp_path, 30, seed=0):
        lost, warnings = assert_accounted(bad, counts, cfg)
        damaged += bool(lost)
    assert damaged >= 5  # the seed hits several chunks whose LZ4 data breaks


@pytest.mark.slow
def test_flips_of_the_real_husky_bag_each_read_or_counted(husky_bag, tmp_path):
    """bz2 chunks: a flipped byte in one fails its CRC and costs the chunk; one in the index's
    connection records costs nothing."""
    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    counts = topic_counts(husky_bag)
    buf = husky_bag.read_bytes()
    chunk = [r for r in byteflip.records(buf) if r.op == ros1_scan.OP_CHUNK][3]
    bad = byteflip.flip(husky_bag, tmp_path / "chunk.bag", (chunk.data + chunk.end) // 2)
    lost, [w] = assert_accounted(bad, counts, cfg)
    assert sum(lost.values()) > 0 and f"byte {chunk.start}" in w
    bad = byteflip.flip(husky_bag, tmp_path / "index.bag",
                        buf.rindex(b"message_definition=") + 40)
    lost, [w] = assert_accounted(bad, counts, cfg)
    assert not lost


def _messages(bag: Path) -> tuple[list[ros1_scan.Message], ros1_scan.ScanStatus]:
    scan = ros1_scan.Ros1Scan(bag, ros1_scan.read_index(bag))
    return [m for m in scan if type(m) is ros1_scan.Message], scan.status


def test_a_broken_lz4_chunk_gives_its_messages_before_the_damage_unaltered(tmp_path):
    """LZ4 as rosbags writes it has no block checksums: a flip garbles the output before the
    decompressor fails. The messages read from such a chunk are those before the damage that
    its index data vouch for, each byte for byte as in the intact bag; the rest are counted
    lost, and the warning says how many were read."""
    cfg = load_config(SAMPLE_CFG)
    counts = topic_counts(SAMPLE)
    buf = SAMPLE.read_bytes()
    chunk = next(r for r in byteflip.records(buf) if r.op == ros1_scan.OP_CHUNK)
    data = buf[chunk.data:chunk.end]
    assert data[:4] == b"\x04\x22\x4d\x18"  # an LZ4 frame
    clean = {(m.conn.topic, m.time_ns): m.data for m in _messages(SAMPLE)[0]}
    breaking = []
    for off in range(len(data) // 8, len(data), len(data) // 40):
        flipped = bytearray(data)
        flipped[off] ^= 0x80
        with _Breaks() as b:
            lz4.frame.decompress(bytes(flipped))
        if b.broke:
            breaking.append(chunk.data + off)
    assert len(breaking) >= 5
    read_from_chunk = 0
    for i, offset in enumerate(breaking):
        bad = byteflip.flip(SAMPLE, tmp_path / f"lz4_{i}.bag", offset)
        lost, [w] = assert_accounted(bad, counts, cfg)
        msgs, status = _messages(bad)
        for m in msgs:
            assert clean[(m.conn.topic, m.time_ns)] == m.data, (offset, m.conn.topic, m.time_ns)
        [dmg] = status.damage
        assert "lz4 data cannot be decompressed" in dmg.what
        read_from_chunk += dmg.salvaged
        assert f"{dmg.salvaged} read from it" in w or not dmg.salvaged
    in_chunk = sum(ros1_scan.read_index(SAMPLE).chunk_counts[chunk.start].values())
    # the damage is spread over the chunk, so about half of its messages come before it
    assert read_from_chunk >= 0.3 * in_chunk * len(breaking)


class _Breaks:
    """Context: whether the block raised lz4's RuntimeError (the decompression failed)."""

    broke = False

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        self.broke = kind is RuntimeError
        return self.broke


def test_trusted_prefix_stops_before_the_last_record_that_checks():
    """Records are trusted while each stands at its index offset with its connection and time;
    the last that checks may hold the damage, so it is left out; no index data, nothing."""

    def record(conn: int, sec: int, payload: bytes) -> bytes:
        fields = b"".join(ros1_scan._U32.pack(len(f)) + f for f in (
            b"op=\x02", b"conn=" + ros1_scan._U32.pack(conn),
            b"time=" + ros1_scan._TIME.pack(sec, 0)))
        return (ros1_scan._U32.pack(len(fields)) + fields + ros1_scan._U32.pack(len(payload))
                + payload)

    recs = [record(1, s, bytes([s]) * 7) for s in range(4)]
    starts = [sum(len(r) for r in recs[:k]) for k in range(4)]
    buf = b"".join(recs)
    entries = [(starts[k], 1, k, 0) for k in range(4)]
    assert ros1_scan._trusted_prefix(buf, entries) == starts[3]  # all check: the last left out
    wrong_time = entries[:2] + [(starts[2], 1, 99, 0), entries[3]]
    assert ros1_scan._trusted_prefix(buf, wrong_time) == starts[1]
    wrong_conn = entries[:1] + [(starts[1], 2, 1, 0)] + entries[2:]
    assert ros1_scan._trusted_prefix(buf, wrong_conn) == 0  # only the first checks: left out
    assert ros1_scan._trusted_prefix(buf, []) == 0
    assert ros1_scan._trusted_prefix(buf[:starts[2] + 5], entries) == starts[1]  # cut head
