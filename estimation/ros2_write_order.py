"""Reading a ROS 2 bag's messages in the order they were written (sqlite3 and MCAP storage).

rosbags' reader returns a ROS 2 bag's messages sorted by record time, which hides a recording
clock that stepped back (``ddfuse.estimation.clock_steps``). The storage keeps the write order:
sqlite3 numbers its rows in insertion order (``messages.id``) and an MCAP file holds its chunks,
and the messages in each, in the order they were written. ``WriteOrder.of(directory)`` reads a
bag directory's ``metadata.yaml`` (its storage, compression and files, in the order they were
written when a recording is split); ``WriteOrder.messages(connections)`` then yields (rosbags
connection, record time ns, CDR bytes) in write order, the same triples as
``AnyReader.messages``, so that decoding stays rosbags' CDR deserialiser.

Not read this way (``of`` returns None and the reason; the caller keeps the sorted read): a bag
compressed per file or per message (``compression_mode`` set; rosbags decompresses those), a
storage plugin other than sqlite3 and mcap, a metadata.yaml that does not parse. A message is
matched to its connection by topic name and type; one of an unconfigured topic is never read.
MCAP chunks compressed with zstd or lz4 (``ros2 bag record``'s default) are read: the ``mcap``
package decompresses them with its dependencies zstandard and lz4 (without them, the sorted read).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

__all__ = ["WriteOrder"]

STORAGES = ("sqlite3", "mcap")


@dataclass(frozen=True)
class WriteOrder:
    """A ROS 2 bag whose storage files can be read in write order: ``storage`` ('sqlite3' or
    'mcap') and its ``files`` (paths, in metadata.yaml's order)."""

    storage: str
    files: tuple[Path, ...]

    @classmethod
    def of(cls, directory: Path) -> tuple[WriteOrder | None, str]:
        """(the write-order reading of the ROS 2 bag in ``directory``, with its metadata.yaml,
        '') or (None, why its storage cannot be read that way: module docstring)."""
        try:
            meta = yaml.safe_load((Path(directory) / "metadata.yaml").read_text())
            info = meta["rosbag2_bagfile_information"]
            storage = info["storage_identifier"]
            files = tuple(Path(directory) / Path(p).name for p in info["relative_file_paths"])
            compressed = str(info.get("compression_mode") or "").lower() not in ("", "none")
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            return None, "its metadata.yaml cannot be read"
        if storage not in STORAGES:
            return None, f"storage plugin {storage!r}"
        if compressed:
            return None, f"compressed per {str(info['compression_mode']).lower()}"
        if storage == "mcap":
            try:  # the mcap package's own dependencies, which rosbags' reader does not need
                import lz4.frame  # noqa: F401
                import zstandard  # noqa: F401
            except ImportError:
                return None, "the mcap package cannot decompress chunks (zstandard or lz4 absent)"
        return cls(storage, files), ""

    def messages(self, connections: Sequence) -> Iterator[tuple[object, int, bytes]]:
        """(connection, record time ns, CDR bytes) of the messages on ``connections`` (rosbags
        connections of this bag: .topic, .msgtype), file after file, each in write order."""
        by_name = {(c.topic, c.msgtype): c for c in connections}
        read = self._sqlite3 if self.storage == "sqlite3" else self._mcap
        for path in self.files:
            yield from read(path, by_name)

    @staticmethod
    def _sqlite3(path: Path, by_name: dict) -> Iterator[tuple[object, int, bytes]]:
        # immutable: the bag is not changed while it is read, so sqlite takes no locks
        db = sqlite3.connect(f"{path.resolve().as_uri()}?immutable=1", uri=True)
        try:
            conns = {tid: by_name[(name, msgtype)]
                     for tid, name, msgtype in db.execute("SELECT id, name, type FROM topics")
                     if (name, msgtype) in by_name}
            if not conns:
                return
            marks = ",".join("?" * len(conns))
            rows = db.execute(f"SELECT topic_id, timestamp, data FROM messages "
                              f"WHERE topic_id IN ({marks}) ORDER BY id", tuple(conns))
            for tid, ns, data in rows:
                yield conns[tid], ns, data
        finally:
            db.close()

    @staticmethod
    def _mcap(path: Path, by_name: dict) -> Iterator[tuple[object, int, bytes]]:
        from mcap.reader import make_reader

        topics = sorted({topic for topic, _ in by_name})
        with open(path, "rb") as f:
            channels: dict[int, object] = {}  # channel id -> connection, or None: not wanted
            for schema, channel, msg in make_reader(f).iter_messages(topics=topics,
                                                                      log_time_order=False):
                conn = channels.get(channel.id, channels)
                if conn is channels:
                    conn = channels[channel.id] = by_name.get(
                        (channel.topic, schema.name if schema is not None else ""))
                if conn is not None:
                    yield conn, msg.log_time, msg.data
