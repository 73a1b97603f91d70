"""A record that grows through a run with its full blocks written to a file instead of memory.

``SpilledColumn`` is a column of one numeric type (the runner's per-call timings, float32;
the columns of a spilling ``runner.TrackBuilder``, float64): values are appended to ``tail``
(an ``array.array``: the cheap append of the timed loop), and ``spill()`` (called between
messages) writes the tail to the column's file whenever it holds ``block`` values or more and
empties it. So a run holds at most about one block per column in memory whatever its length;
the readers walk the column ``blocks()`` at a time from the file, then the tail, or map it
whole read-only (``mapped``, its touched pages dropped by ``release``), and
``np.asarray(column)`` gives it whole in memory for callers that want it so.

The file is raw values in native byte order, nothing else; it belongs to the run that made it,
whose caller removes it (``evaluation.pipeline.run_bag``: the whole spill directory, once the
run's results are written).
"""

from __future__ import annotations

import mmap
from array import array
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from ddfuse.estimation.interrupts import deliver, held_signals

BLOCK = 1 << 16  # values per spilled block (256 kB of float32)


class SpilledColumn:
    """A growing column of ``dtype`` values (an ``array`` type code's: 'f' float32, 'd'
    float64), its full blocks in the file ``path``."""

    def __init__(self, path: str | Path, dtype: str = "f", block: int | None = None) -> None:
        block = BLOCK if block is None else block
        if block < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.block = int(block)
        self.tail = array(dtype)  # appended, not yet in the file
        self.spilled = 0  # values in the file
        self._file = None

    def append(self, value: float) -> None:
        self.tail.append(value)
        if len(self.tail) >= self.block:
            self.spill()

    def spill(self, force: bool = False) -> None:
        """Write the tail to the file if it holds a block or more (``force``: any values at
        all), then it is empty. The
        count of spilled values moves only once the bytes are written: a write that fails
        (a full disk) raises ``OSError`` with the tail still whole, and the next spill writes
        over the part it left; Ctrl-C or SIGTERM meanwhile is held until the file and the
        count agree, then raised (``ddfuse.estimation.interrupts``)."""
        n = len(self.tail)
        if n < self.block and not (force and n):
            return
        with held_signals() as held:
            if self._file is None:  # a new file for the first block, appended to after a close
                self._file = open(self.path, "r+b" if self.spilled else "wb")  # noqa: SIM115
            self._file.seek(self.spilled * self.dtype.itemsize)
            self._file.truncate()
            self._file.write(memoryview(self.tail).cast("B"))
            self._file.flush()
            self.spilled += n
            del self.tail[:]
        deliver(held)

    def close(self) -> None:
        """Close the file (the column stays readable, and a later ``spill`` appends to it)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def remove(self) -> None:
        """Close and delete the file: the column then holds only its tail."""
        self.close()
        self.path.unlink(missing_ok=True)
        self.spilled = 0

    def __len__(self) -> int:
        return self.spilled + len(self.tail)

    @property
    def shape(self) -> tuple[int]:
        return (len(self),)

    def blocks(self, size: int | None = None) -> Iterator[np.ndarray]:
        """The values in order, ``size`` (default ``block``) at a time (the last block of the
        file and the tail may be shorter), each a new array."""
        size = int(size or min(self.block, BLOCK))
        if self.spilled:
            if self._file is not None:
                self._file.flush()
            with open(self.path, "rb") as f:
                left = self.spilled
                while left:
                    a = np.fromfile(f, self.dtype, min(size, left))
                    if not len(a):
                        raise OSError(f"{self.path}: ended {left} values early")
                    left -= len(a)
                    yield a
        tail = np.frombuffer(self.tail, self.dtype) if len(self.tail) else None
        if tail is not None:
            for a in range(0, len(tail), size):
                yield tail[a:a + size].copy()

    def mapped(self) -> tuple[np.ndarray, mmap.mmap | None]:
        """The whole column read-only from its file, memory-mapped (the tail spilled first),
        and the map (None, with an empty array, when the column is empty): its pages count
        in this process's memory only while touched (``release``)."""
        self.spill(force=True)
        self.close()
        if not self.spilled:
            return np.zeros(0, self.dtype), None
        with open(self.path, "rb") as f:
            m = mmap.mmap(f.fileno(), self.spilled * self.dtype.itemsize,
                          access=mmap.ACCESS_READ)
        return np.frombuffer(m, self.dtype), m

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        parts = list(self.blocks())
        out = np.concatenate(parts) if parts else np.zeros(0, self.dtype)
        return out if dtype is None else out.astype(dtype)


def release(maps) -> None:
    """Drop the touched pages of the memory maps ``maps`` (``SpilledColumn.mapped``'s) from
    this process: they stay in the file (and the page cache) and are read again when next
    touched. A map already closed is skipped."""
    for m in maps:
        if m is not None and not m.closed:
            m.madvise(mmap.MADV_DONTNEED)
