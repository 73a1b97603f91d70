"""Test utility: byte-flipped copies of a ROS1 bag (one flipped bit each), at random places
(deterministic seed) or in a chosen record, and a map of the bag's top-level records.

``records(buf)`` lists the top-level records of a bag's bytes as ``Rec(op, start, data, end)``
(byte offsets: the record, its data, its end). ``flip(src, dest, offset, bit)`` writes a copy
with one bit flipped; ``random_flips(src, directory, n, seed)`` writes ``n`` such copies at
random offsets and returns (path, offset) of each.
"""

from __future__ import annotations

import random
import struct
from pathlib import Path
from typing import NamedTuple

from ddfuse.estimation import ros1_scan


class Rec(NamedTuple):
    op: int
    start: int  # byte of the record (its header length)
    data: int  # byte of its data
    end: int  # byte after it


def records(buf: bytes) -> list[Rec]:
    """The top-level records of an intact ROS1 v2.0 bag's bytes."""
    out, pos = [], len(ros1_scan.MAGIC)
    while pos < len(buf):
        (hlen,) = struct.unpack_from("<I", buf, pos)
        fields = ros1_scan._fields(buf, pos + 4, pos + 4 + hlen)
        (dlen,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
        data = pos + 8 + hlen
        out.append(Rec(fields["op"][0], pos, data, data + dlen))
        pos = data + dlen
    return out


def flip(src: Path, dest: Path, offset: int, bit: int = 7) -> Path:
    """``dest``: a copy of ``src`` with bit ``bit`` of byte ``offset`` flipped."""
    buf = bytearray(Path(src).read_bytes())
    buf[offset] ^= 1 << bit
    dest.write_bytes(bytes(buf))
    return dest


def random_flips(src: Path, directory: Path, n: int, seed: int = 0) -> list[tuple[Path, int]]:
    """``n`` copies of ``src`` in ``directory``, each with one random bit flipped (random.Random
    ``seed``): (path, flipped byte) of each."""
    rng = random.Random(seed)
    size = Path(src).stat().st_size
    out = []
    for i in range(n):
        offset, bit = rng.randrange(size), rng.randrange(8)
        out.append((flip(src, Path(directory) / f"flip{i:02d}.bag", offset, bit), offset))
    return out
