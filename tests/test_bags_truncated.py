"""A ROS1 bag cut short (its recorder killed before it wrote the index, or a partial copy) is read
from the front by estimation.ros1_scan: read_stream raises a BagError saying the bag is truncated
that carries the messages before the cut, and ``ddfuse run`` estimates on them, writes the
results and exits 2.

Oracles that do not depend on the scanner: the full read through rosbags' index (values), and
the intact bag's index (which chunk holds how many messages, at which offsets).
"""

from __future__ import annotations

import dataclasses
import json
import re
import struct
from pathlib import Path

import bagwriter as bw
import numpy as np
import pytest
import yaml
from ddfuse.estimation import ros1_scan
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config, parse_config
from ddfuse.estimation.errors import BagError
from ddfuse.evaluation import cli
from kernel_notices import without_kernel_notices
from rosbags.rosbag1 import Reader

pytest.importorskip("gtsam")
pytest.importorskip("pymap3d")

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "sample_husky.bag"  # LZ4 chunks: odometry, IMU, GPS, ground truth
SAMPLE_CFG = ROOT / "data" / "sample_husky.yaml"
SEED2 = ROOT / "data" / "sample_seed002.bag"  # JointState and landmarks: rosbags' deserialiser
SEED2_CFG = ROOT / "data" / "sample_seed002.yaml"
T0 = 1_600_000_000.0  # s
IMU_CFG = {"sensors": {"imu": [{"topic": "/imu", "use": ["yaw_rate"]}]}}


# --- helpers ---------------------------------------------------------------------------------

def _key(m) -> str:
    """A measurement's field values as text (NaN == NaN, arrays by value)."""
    return repr([v.tolist() if isinstance(v, np.ndarray) else v
                 for v in (getattr(m, f.name) for f in dataclasses.fields(m))])


def _groups(stream) -> dict[tuple[str, str], list[str]]:
    """Measurements and ground truth by (type, sensor), each in the stream's (stamp) order."""
    if isinstance(stream, dict):  # already grouped
        return stream
    out: dict[tuple[str, str], list[str]] = {}
    for m in [*stream.measurements, *stream.ground_truth]:
        out.setdefault((type(m).__name__, m.sensor), []).append(_key(m))
    return out


def assert_prefix(partial, full, whole: bool = False) -> int:
    """Each sensor's measurements in ``partial`` are the first ones of ``full`` (a Stream, or
    its _groups), value for value (all of them if ``whole``). Returns how many there are."""
    p, f = _groups(partial), _groups(full)
    assert set(p) <= set(f)
    for g, ms in p.items():
        assert ms == f[g][:len(ms)], g
        if whole:
            assert len(ms) == len(f[g]), g
    if whole:
        assert set(p) == set(f)
    return sum(len(ms) for ms in p.values())


def cut(src: Path, n: int, dest: Path) -> Path:
    """``dest`` holding the first ``n`` bytes of ``src``."""
    dest.write_bytes(src.read_bytes()[:n])
    return dest


def read_cut(bag: Path, cfg, **kw) -> BagError:
    with pytest.raises(BagError) as e:
        read_stream(bag, cfg, **kw)
    msg = str(e.value)
    assert str(bag) in msg and "truncated" in msg and "\n" not in msg
    return e.value


def messages_read(err: BagError) -> int:
    """N of the error's 'read N messages'."""
    return int(re.search(r"read (\d+) messages", str(err)).group(1))


@dataclasses.dataclass
class ChunkLayout:
    pos: int  # file offset of the chunk record
    datapos: int  # file offset of its (compressed) data
    datasize: int  # bytes
    end: int  # file offset after its index records (where the next chunk starts)
    counts: dict[str, int]  # topic -> messages in the chunk
    offsets: list[int]  # offsets of its message records in the uncompressed chunk, ascending


def layout(bag: Path) -> list[ChunkLayout]:
    """The chunks of an intact bag, from its index as rosbags reads it."""
    with Reader(bag) as r:
        topic = {c.id: c.topic for c in r.connections}
        infos = sorted(r.chunk_infos, key=lambda ci: ci.pos)
        offsets = {ci.pos: sorted(e.offset for idx in r.indexes.values() for e in idx
                                  if e.chunk_pos == ci.pos) for ci in infos}
        out = []
        for i, ci in enumerate(infos):
            ch = r.chunks[ci.pos]
            counts: dict[str, int] = {}
            for cid, n in ci.connection_counts.items():
                counts[topic[cid]] = counts.get(topic[cid], 0) + n
            end = infos[i + 1].pos if i + 1 < len(infos) else None
            out.append(ChunkLayout(ci.pos, ch.datapos, ch.datasize, end, counts, offsets[ci.pos]))
    return out


def configured(cfg) -> set[str]:
    topics = {s.topic for s in cfg.sensors}
    return topics | ({cfg.ground_truth_topic} if cfg.ground_truth_topic else set())


def imu_bag(tmp_path: Path, compression: str = "none", n: int = 3000) -> Path:
    """A ROS1 bag of ``n`` IMU messages at 100 Hz in chunks of about 64 kB."""
    return bw.write_bag(tmp_path / f"imu_{compression}.bag", "ros1",
                        [("/imu", bw.imu(T0 + 0.01 * i, angvel=(0.0, 0.0, 0.001 * i),
                                         wcov=bw.diag(1, 1, 1))) for i in range(n)],
                        compression=compression, chunk_bytes=64 * 1024)


@pytest.fixture(scope="module")
def sample():
    cfg = load_config(SAMPLE_CFG)
    return cfg, read_stream(SAMPLE, cfg), layout(SAMPLE)


# --- where the cut falls ---------------------------------------------------------------------

@pytest.mark.parametrize("n", [0, 5, 13, 100, 4000, 4096 + 20])
def test_cut_inside_the_bag_header(tmp_path, sample, n):
    """Nothing to read before the first chunk: a one-line error, no partial stream."""
    cfg, _, chunks = sample
    assert n < chunks[0].datapos
    bag = cut(SAMPLE, n, tmp_path / "head.bag")
    with pytest.raises(BagError) as e:
        read_stream(bag, cfg)
    msg = str(e.value)
    assert str(bag) in msg and "\n" not in msg and e.value.partial is None
    if n:  # an empty file is reported as such by rosbags
        assert "truncated" in msg


@pytest.mark.parametrize("k", [1, 2, 4])
def test_cut_between_chunks(tmp_path, sample, k):
    """Cut where chunk k starts: exactly the messages of chunks 0..k-1, with their values."""
    cfg, full, chunks = sample
    bag = cut(SAMPLE, chunks[k].pos, tmp_path / "between.bag")
    err = read_cut(bag, cfg)
    want = sum(n for c in chunks[:k] for t, n in c.counts.items() if t in configured(cfg))
    assert messages_read(err) == want
    assert assert_prefix(err.partial, full) > 0
    assert err.partial.duration > 0


def test_cut_inside_an_lz4_chunk_recovers_its_complete_blocks(tmp_path, sample):
    """The LZ4 stream of a cut chunk yields its complete 64 KiB blocks: more messages than the
    complete chunks hold, fewer than with the cut chunk whole."""
    cfg, full, chunks = sample
    c = chunks[2]
    bag = cut(SAMPLE, c.datapos + c.datasize // 2, tmp_path / "mid.bag")
    err = read_cut(bag, cfg)
    before = sum(n for ch in chunks[:2] for t, n in ch.counts.items() if t in configured(cfg))
    with_chunk = before + sum(n for t, n in c.counts.items() if t in configured(cfg))
    assert before < messages_read(err) < with_chunk
    assert "recovered" in str(err)
    assert_prefix(err.partial, full)


def test_cut_inside_an_uncompressed_chunk_recovers_every_complete_record(tmp_path):
    bag = imu_bag(tmp_path)
    cfg = parse_config(IMU_CFG)
    full = read_stream(bag, cfg)
    chunks = layout(bag)
    c = chunks[1]
    for into in (10, c.datasize // 3, c.datasize - 1):
        p = cut(bag, c.datapos + into, tmp_path / f"u{into}.bag")
        err = read_cut(p, cfg)
        # A message record ends where the next begins (or at the chunk's end).
        ends = [*c.offsets[1:], c.datasize]
        want = chunks[0].counts["/imu"] + sum(e <= into for e in ends)
        assert messages_read(err) == want == len(err.partial.measurements)
        assert_prefix(err.partial, full)


def test_cut_inside_a_bz2_chunk_drops_it_and_says_so(tmp_path):
    """bz2 gives nothing before a whole 900 kB block: the cut chunk is lost, the ones before
    are read in full."""
    bag = imu_bag(tmp_path, "bz2")
    cfg = parse_config(IMU_CFG)
    full = read_stream(bag, cfg)
    chunks = layout(bag)
    assert len(chunks) >= 4
    c = chunks[3]
    err = read_cut(cut(bag, c.datapos + c.datasize // 2, tmp_path / "bz.bag"), cfg)
    want = sum(ch.counts["/imu"] for ch in chunks[:3])
    assert messages_read(err) == len(err.partial.measurements) == want
    assert "no complete message could be recovered" in str(err)
    assert_prefix(err.partial, full)


def test_cut_inside_the_index_at_the_end_keeps_every_message(tmp_path, sample):
    cfg, full, chunks = sample
    size = SAMPLE.stat().st_size
    err = read_cut(cut(SAMPLE, size - 10, tmp_path / "index.bag"), cfg)
    assert_prefix(err.partial, full, whole=True)


def test_recorder_killed_before_writing_the_index(tmp_path):
    """The file a killed recorder leaves: index_pos 0 in the bag header and nothing after the
    last chunk written."""
    bag = imu_bag(tmp_path)
    cfg = parse_config(IMU_CFG)
    full = read_stream(bag, cfg)
    chunks = layout(bag)
    data = bytearray(bag.read_bytes()[:chunks[-1].pos])  # the last chunk was never written
    at = data.index(b"index_pos=") + len(b"index_pos=")
    data[at:at + 8] = struct.pack("<Q", 0)
    killed = tmp_path / "killed.bag"
    killed.write_bytes(bytes(data))
    err = read_cut(killed, cfg)
    assert "no index" in str(err)
    assert messages_read(err) == sum(c.counts["/imu"] for c in chunks[:-1])
    assert_prefix(err.partial, full)


@pytest.mark.slow
def test_sweep_of_cut_offsets(tmp_path, sample):
    """30 cuts spread over the file: never anything but a one-line BagError, and whatever was
    read is the start of the full read, value for value, growing with the cut."""
    cfg, full, chunks = sample
    full = _groups(full)
    size = SAMPLE.stat().st_size
    got = []
    for n in np.linspace(0, size, 32).astype(int)[1:-1]:
        bag = cut(SAMPLE, int(n), tmp_path / "sweep.bag")
        with pytest.raises(BagError) as e:
            read_stream(bag, cfg)
        msg = str(e.value)
        assert str(bag) in msg and "truncated" in msg and "\n" not in msg, (n, msg)
        if e.value.partial is None:
            assert n < chunks[1].pos, (n, msg)  # only before the first chunk is complete
            got.append(0)
        else:
            got.append(assert_prefix(e.value.partial, full))
    assert got == sorted(got) and got[-1] > 0.9 * assert_prefix(full, full)


def test_types_without_a_fast_decoder_use_the_bags_definitions(tmp_path):
    """JointState and the landmark message go through rosbags' deserialiser, with the types
    registered from the bag's own connection records."""
    cfg = load_config(SEED2_CFG)
    full = read_stream(SEED2, cfg)
    c = layout(SEED2)[1]
    err = read_cut(cut(SEED2, c.datapos + c.datasize // 2, tmp_path / "s2.bag"), cfg)
    kinds = {type(m).__name__ for m in err.partial.measurements}
    assert {"WheelSpeeds", "LandmarkObservation"} <= kinds
    assert assert_prefix(err.partial, full) > 0
    assert not err.partial.rejected


def test_progress_is_reported_while_scanning(tmp_path, sample):
    cfg, _, _ = sample
    seen: list[float] = []
    read_cut(cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "p.bag"), cfg,
             progress=seen.append)
    assert len(seen) >= 2 and all(0.0 <= f <= 1.0 for f in seen) and seen == sorted(seen)


# --- errors ----------------------------------------------------------------------------------

def test_a_file_that_is_not_a_bag_is_still_not_a_bag(tmp_path, sample):
    cfg, _, _ = sample
    p = tmp_path / "notes.bag"
    p.write_bytes(b"#ROSBAG V1.2\n" + b"x" * 5000)
    assert not ros1_scan.has_magic(p)
    with pytest.raises(BagError) as e:
        read_stream(p, cfg)
    msg = str(e.value)
    assert str(p) in msg and "not a bag" in msg and "\n" not in msg
    assert e.value.partial is None


def test_configured_topic_missing_from_what_could_be_read(tmp_path, sample):
    raw = yaml.safe_load(SAMPLE_CFG.read_text())
    raw["sensors"]["gps"][0]["topic"] = "/gps/missing"
    cfg = parse_config(raw, base=SAMPLE_CFG.parent)
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "m.bag")
    with pytest.raises(BagError) as e:
        read_stream(bag, cfg)
    msg = str(e.value)
    assert str(bag) in msg and "/gps/missing" in msg and "sensors.gps[0].topic" in msg
    assert "/imu/data" in msg and "truncated" in msg and "\n" not in msg


def test_a_wrong_message_type_is_named(tmp_path, sample):
    raw = yaml.safe_load(SAMPLE_CFG.read_text())
    # An Imu topic where NavSatFix is needed (named: sensor names default to the topic).
    raw["sensors"]["gps"][0].update(topic="/imu/data", name="gps")
    cfg = parse_config(raw, base=SAMPLE_CFG.parent)
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "t.bag")
    with pytest.raises(BagError) as e:
        read_stream(bag, cfg)
    assert "sensor_msgs/Imu" in str(e.value) and "sensors.gps[0]" in str(e.value)


def test_scanner_reads_an_intact_bag_like_rosbags():
    """The scanner alone, on the intact sample: the same messages, bytes and record times as
    rosbags' indexed reader, and a clean end."""
    scan = ros1_scan.Ros1Scan(SAMPLE)
    got = sorted((m.conn.topic, m.time_ns, m.data) for m in scan
                 if isinstance(m, ros1_scan.Message))
    with Reader(SAMPLE) as r:
        want = sorted((c.topic, t, d) for c, t, d in r.messages())
        types = {c.topic: c.msgtype for c in r.connections}
    assert got == want
    assert {c.topic: c.msgtype for c in scan.connections.values()} == types
    assert scan.status.complete and scan.status.offset == SAMPLE.stat().st_size


# --- the command line ------------------------------------------------------------------------

def test_cli_run_on_a_truncated_bag_writes_results_and_exits_2(tmp_path, capsys):
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    out = tmp_path / "out"
    rc = cli.main(["run", str(bag), "-c", str(SAMPLE_CFG), "-o", str(out),
                   "--estimators", "ekf"])
    assert rc == 2
    err = without_kernel_notices(capsys.readouterr().err)
    assert "\n" not in err and str(bag) in err and "truncated" in err and str(out) in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert "truncated" in metrics["input_error"]
    assert metrics["duration_s"] > 30 and metrics["estimators"]["ekf"]["samples"] > 100
    assert metrics["estimators"]["ekf"]["ate_rmse_m"] is not None
    rows = (out / "ekf.tum").read_text().splitlines()
    assert len(rows) == metrics["estimators"]["ekf"]["samples"]
    assert (out / "ekf.csv").is_file() and (out / "ground_truth.tum").is_file()


# --- the real bag ----------------------------------------------------------------------------

@pytest.mark.slow
def test_real_husky_bag_cut_at_quarters(tmp_path, husky_bag):
    cfg = load_config(ROOT / "data" / "configs" / "rl_husky_gps.yaml")
    full = read_stream(husky_bag, cfg)
    size = husky_bag.stat().st_size
    counts, durations = [], []
    for frac in (0.25, 0.5, 0.75):
        bag = cut(husky_bag, int(size * frac), tmp_path / f"husky_{int(frac * 100)}.bag")
        err = read_cut(bag, cfg)
        n = assert_prefix(err.partial, full)
        counts.append(messages_read(err))
        durations.append(err.partial.duration)
        # bz2 chunks hold about 40 s: a cut loses at most the chunk it falls in.
        assert frac * full.duration - 60 < err.partial.duration <= frac * full.duration + 5
        assert n > 0
    assert counts == sorted(counts) and durations == sorted(durations)
    out = tmp_path / "out"
    bag = tmp_path / "husky_50.bag"
    assert cli.main(["run", str(bag), "-c", str(ROOT / "data" / "configs" / "rl_husky_gps.yaml"),
                     "-o", str(out), "--estimators", "ekf", "--gps-holdout", "every:5"]) == 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["estimators"]["ekf"]["samples"] > 100
    assert metrics["estimators"]["ekf"]["gps_holdout_rmse_m"] is not None


def test_cli_online_on_a_truncated_bag_replays_what_was_read_and_exits_2(tmp_path, capsys):
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    rc = cli.main(["online", str(bag), "-c", str(SAMPLE_CFG), "--estimators", "ekf",
                   "--every", "10"])
    assert rc == 2
    out, err = capsys.readouterr()
    err = without_kernel_notices(err)
    assert err.startswith("ddfuse: error: ") and "\n" not in err
    assert str(bag) in err and "truncated" in err and "replayed the" in err
    assert "update latency" in out and out.count("t=") > 3


def test_cli_inspect_on_a_truncated_bag_reports_what_was_read_and_exits_2(tmp_path, capsys):
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    assert cli.main(["inspect", str(bag)]) == 2
    out, err = capsys.readouterr()
    err = without_kernel_notices(err)
    assert err.startswith("ddfuse: error: ") and "\n" not in err
    assert str(bag) in err and "truncated" in err
    assert cli.main(["inspect", str(SAMPLE)]) == 0
    full = _topic_counts(capsys.readouterr().out)
    got = _topic_counts(out)
    assert set(got) == set(full) and all(0 < got[t] < full[t] for t in got)


def _topic_counts(out: str) -> dict[str, int]:
    """topic -> count from the table of 'ddfuse inspect' (its rows are YAML comments)."""
    return {m.group(1): int(m.group(2)) for m in
            (re.match(r"# (/\S+)\s+\S+/\S+\s+(\d+)\s", line) for line in out.splitlines()) if m}


def test_cli_bench_on_a_truncated_bag_measures_what_was_read_and_exits_2(tmp_path, capsys):
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    rc = cli.main(["bench", str(bag), "-c", str(SAMPLE_CFG), "--estimators", "ekf",
                   "--json", str(tmp_path / "b.json")])
    assert rc == 2
    out, err = capsys.readouterr()
    err = without_kernel_notices(err)
    assert err.startswith("ddfuse: error: ") and "\n" not in err
    assert str(bag) in err and "truncated" in err
    r = json.loads((tmp_path / "b.json").read_text())[0]
    assert "truncated" in r["input_error"] and 30 < r["duration_s"] < 100
    e = r["estimators"][0]
    assert e["estimator"] == "ekf" and e["error"] is None and e["peak_rss_mb"] > 0
    assert "ekf" in out


@pytest.mark.slow
def test_ddfuse_bench_on_a_truncated_bag_ends_in_one_line_and_nothing_else(tmp_path):
    """As a program (entry() ends with os._exit): the child's pipe leaves no semaphore behind
    for multiprocessing's resource tracker to warn about after the error line."""
    import subprocess
    import sys

    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    p = subprocess.run([sys.executable, "-m", "ddfuse.evaluation.cli", "bench", str(bag), "-c",
                        str(SAMPLE_CFG), "--estimators", "ekf"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2
    assert p.stderr.startswith("ddfuse: error: ") and p.stderr.count("\n") == 1, p.stderr
    assert "ekf" in p.stdout


@pytest.mark.parametrize("name", ["/imu/data", "imu/data", "//a//b/", "/", "a", "/a/b/c/",
                                  "/husky_velocity_controller/odom"])
def test_scanner_normalises_topics_as_rosbags(name):
    from rosbags.rosbag1.reader import normalize

    assert ros1_scan.normalize_topic(name) == normalize(name)


@pytest.mark.parametrize("name", ["sensor_msgs/Imu", "sensor_msgs/msg/Imu", "pkg/action/Do",
                                  "a//b/C", "Plain", "nav_msgs/Odometry",
                                  "ddfuse_msgs/LandmarkObservation"])
def test_scanner_normalises_msgtypes_as_rosbags(name):
    from rosbags.typesys.msg import normalize_msgtype

    assert ros1_scan.normalize_msgtype(name) == normalize_msgtype(name)


def _scan_items(path, monkeypatch=None, fast=True):
    if not fast:
        monkeypatch.setattr(ros1_scan, "_MSG_HLEN", -1)  # every header through _fields
    try:
        return [(type(i).__name__, i.conn.id, i.time_ns, i.data) if type(i) is ros1_scan.Message
                else ("conn", i.id, i.topic, i.msgtype) for i in ros1_scan.Ros1Scan(path)]
    finally:
        if not fast:
            monkeypatch.undo()


def test_message_header_fast_path_reads_both_layouts_as_the_field_parser(monkeypatch):
    """A chunk holding message records in the C++ recorder's header layout (time, conn, op),
    in rosbags' (op, conn, time) and in an unusual order (conn, time, op): the one-unpack fast
    path and the general field parser give the same messages, stamps and connections."""
    def field(name, value):
        return struct.pack("<I", len(name) + 1 + len(value)) + name + b"=" + value

    def record(fields, data):
        head = b"".join(fields)
        return struct.pack("<I", len(head)) + head + struct.pack("<I", len(data)) + data

    conn_hdr = [field(b"op", b"\x07"), field(b"conn", struct.pack("<I", 3)),
                field(b"topic", b"/x")]
    conn_data = b"".join([field(b"topic", b"/x"), field(b"type", b"std_msgs/Empty"),
                          field(b"md5sum", b"0" * 32), field(b"message_definition", b"")])
    recs = [record(conn_hdr, conn_data)]
    for i, order in enumerate((("time", "conn", "op"), ("op", "conn", "time"),
                               ("conn", "time", "op"))):
        vals = {"op": b"\x02", "conn": struct.pack("<I", 3),
                "time": struct.pack("<II", 1_700_000_000 + i, 1000 * i)}
        recs.append(record([field(k.encode(), vals[k]) for k in order], bytes([i]) * (5 + i)))
    buf = b"".join(recs)
    scan = ros1_scan.Ros1Scan(SAMPLE)  # its state, without reading the file

    def items():
        return [(type(x).__name__, x.time_ns, x.data) if type(x) is ros1_scan.Message
                else ("conn", x.id, x.topic) for x in scan._chunk_records(buf)]

    parsed = []
    real_fields = ros1_scan._fields
    monkeypatch.setattr(ros1_scan, "_fields",
                        lambda b, a, e: parsed.append(e - a) or real_fields(b, a, e))
    fast = items()
    # only the connection record (its header and data) and the unusual layout were parsed
    assert len(parsed) == 3
    scan.connections = {}
    monkeypatch.setattr(ros1_scan, "_MSG_HLEN", -1)
    slow = items()
    assert fast == slow
    assert [x[1] for x in fast[1:]] == [1_700_000_000_000_000_000, 1_700_000_001_000_001_000,
                                        1_700_000_002_000_002_000]
    assert [x[2] for x in fast[1:]] == [b"\0" * 5, b"\1" * 6, b"\2" * 7]


def test_message_header_fast_path_equals_field_parser_on_sample_bag(monkeypatch):
    assert _scan_items(SAMPLE) == _scan_items(SAMPLE, monkeypatch, fast=False)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rl_husky_gps.bag", "mrclam1_robot1.bag", "rl_jackal.bag"])
def test_message_header_fast_path_equals_field_parser_on_real_bags(name, monkeypatch):
    from conftest import shared_bag

    path = shared_bag(name)
    assert _scan_items(path) == _scan_items(path, monkeypatch, fast=False)


def test_cli_lag_sweep_on_a_truncated_bag_sweeps_what_was_read_and_exits_2(tmp_path, capsys):
    bag = cut(SAMPLE, SAMPLE.stat().st_size // 2, tmp_path / "half.bag")
    rc = cli.main(["lag-sweep", str(bag), "-c", str(SAMPLE_CFG), "--lags", "2",
                   "--json", str(tmp_path / "s.json")])
    assert rc == 2
    out, err = capsys.readouterr()
    err = without_kernel_notices(err)
    assert err.startswith("ddfuse: error: ") and "\n" not in err
    assert "truncated" in err and err.endswith("swept on what could be read")
    rows = json.loads((tmp_path / "s.json").read_text())
    assert [r["estimator"] for r in rows] == ["ekf", "smoother", "smoother_lagged"]
    assert all(r["rmse_m"] < 0.5 for r in rows)  # against the truth of the part read
    assert "| smoother_lagged | 2 |" in out
