"""Test utility: rewrite a ROS1 bag message by message, keeping its write order, to make the
time faults of real recordings: the recording clock stepping back (``step_back``) and messages
recorded twice (``duplicate``). Written uncompressed with rosbags' writer; the connections,
their definitions and md5sums are the source's. ``ekf_metrics`` runs the ekf on such a bag.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterable
from pathlib import Path

from ddfuse.evaluation import cli
from rosbags.rosbag1 import Reader, Writer

Edit = Callable[[str, int, bytes], Iterable[tuple[int, bytes]]]


def rewrite(src: Path, dest: Path, edit: Edit) -> Path:
    """``dest``: ``src`` with each message (topic, record time ns, ROS1 bytes), in record order,
    replaced by the (record time ns, bytes) that ``edit`` gives for it (none, one or more)."""
    dest = Path(dest)
    dest.unlink(missing_ok=True)
    with Reader(src) as r, Writer(dest) as w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                        md5sum=c.digest) for c in r.connections}
        for c, t, raw in r.messages():
            for t2, raw2 in edit(c.topic, t, raw):
                w.write(conns[c.id], t2, raw2)
    return dest


def restamp(raw: bytes, by_ns: int) -> bytes:
    """ROS1 bytes of a message with a header, its header stamp moved by ``by_ns``."""
    seq, sec, nsec = struct.unpack_from("<III", raw)
    ns = sec * 1_000_000_000 + nsec + by_ns
    return struct.pack("<III", seq, ns // 1_000_000_000, ns % 1_000_000_000) + raw[12:]


def step_back(src: Path, dest: Path, at_s: float, by_s: float,
              stamps_kept: tuple[str, ...] = ()) -> Path:
    """The recording clock stepped back by ``by_s`` s when ``at_s`` s of the bag had been
    recorded: the record time of every message after it, and its header stamp except on the
    topics ``stamps_kept`` (stamped by another clock), ``by_s`` s earlier."""
    with Reader(src) as r:
        cut = r.start_time + round(at_s * 1e9)
    by = round(by_s * 1e9)

    def edit(topic: str, t: int, raw: bytes):
        if t < cut:
            return [(t, raw)]
        return [(t - by, raw if topic in stamps_kept else restamp(raw, -by))]

    return rewrite(src, dest, edit)


def duplicate(src: Path, dest: Path, topics: tuple[str, ...], new_seq: bool = False) -> Path:
    """Every message on ``topics`` recorded twice in a row (``new_seq``: the copy with another
    header seq, as a republisher numbers it)."""
    def edit(topic: str, t: int, raw: bytes):
        if topic not in topics:
            return [(t, raw)]
        copy = struct.pack("<I", struct.unpack_from("<I", raw)[0] + 1) + raw[4:] if new_seq else raw
        return [(t, raw), (t, copy)]

    return rewrite(src, dest, edit)


def ekf_metrics(bag: Path, cfg: Path, out: Path) -> tuple[dict, list[str]]:
    """The ekf's metrics and the run's warnings of ``ddfuse run`` on ``bag`` into ``out``."""
    assert cli.main(["run", str(bag), "-c", str(cfg), "-o", str(out), "--estimators", "ekf",
                     "--no-report"]) == 0
    metrics = json.loads((Path(out) / "metrics.json").read_text())
    return metrics["estimators"]["ekf"], metrics["warnings"]
