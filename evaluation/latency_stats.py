"""Statistics of a long series read a block at a time: exact percentiles by selection, and
the mean, without holding the series (the per-call timings of a run, ``estimation.spill``).

``percentiles(blocks, qs)`` gives numpy's default ('linear') percentiles: the two order
statistics around each virtual index ``(n - 1) q / 100`` are found exactly in two passes over
the blocks (a histogram of the values' top 16 bits in sortable order, then the values of the
few bins that hold the wanted ranks, sorted), and interpolated by numpy's own formula, in
float64. So they equal ``np.percentile`` of the whole float64 series; of a float32 series
they are ``np.percentile``'s to float32 rounding (numpy rounds its result to float32).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np

_TOP = 16  # bits of the sortable key that make the first pass's histogram


def _keys(a: np.ndarray) -> np.ndarray:
    """Unsigned integers that sort as the floats ``a`` do (negative ones bit-inverted, the
    sign bit set on the others)."""
    u = np.dtype(f"u{a.dtype.itemsize}")
    bits = a.view(u)
    sign = u.type(1) << u.type(8 * a.dtype.itemsize - 1)
    return np.where(bits & sign, ~bits, bits | sign)


def _virtual_index(n: int, q: float) -> float:
    """numpy's 'linear' virtual index ``(n - 1) * (q / 100)``, formed as numpy forms it."""
    return float((n - 1) * np.true_divide(q, 100))


def _lerp(a: float, b: float, t: float) -> float:
    """numpy's ``_lerp``: from the nearer end, for the same rounding."""
    d = b - a
    return b - d * (1 - t) if t >= 0.5 else a + d * t


def percentiles(blocks: Callable[[], Iterable[np.ndarray]], qs: Iterable[float]
                ) -> list[float]:
    """The ``qs`` percentiles (0-100) of the series that ``blocks()`` yields (each call a
    new pass from its start; float32 or float64 blocks, no NaN). NaN for an empty series."""
    qs = list(qs)
    hist = None
    n = 0
    dtype = None
    for b in blocks():
        dtype = b.dtype
        k = _keys(np.ascontiguousarray(b)) >> (8 * b.dtype.itemsize - _TOP)
        h = np.bincount(k.astype(np.int64), minlength=1 << _TOP)
        hist = h if hist is None else hist + h
        n += len(b)
    if n == 0:
        return [math.nan] * len(qs)
    cum = np.cumsum(hist)
    want: dict[int, tuple[int, int]] = {}  # rank -> (bin, rank within the bin)
    spots = []
    for q in qs:
        v = _virtual_index(n, q)
        lo = min(max(math.floor(v), 0), n - 1)
        hi = min(lo + 1, n - 1)
        spots.append((lo, hi, v - math.floor(v)))
        for r in (lo, hi):
            b = int(np.searchsorted(cum, r, side="right"))
            want[r] = (b, r - (int(cum[b - 1]) if b else 0))
    bins = sorted({b for b, _ in want.values()})
    found: dict[int, list[np.ndarray]] = {b: [] for b in bins}
    sel = np.array(bins)
    for blk in blocks():
        k = _keys(np.ascontiguousarray(blk)) >> (8 * dtype.itemsize - _TOP)
        hit = np.isin(k, sel)
        if hit.any():
            for b in bins:
                found[b].append(blk[hit & (k == b)])
    ordered = {b: np.sort(np.concatenate(found[b])) for b in bins}
    value = {r: float(ordered[b][i]) for r, (b, i) in want.items()}
    return [_lerp(value[lo], value[hi], g) for lo, hi, g in spots]


def mean(blocks: Iterable[np.ndarray]) -> tuple[float, int]:
    """(mean, count) of the series, summed in float64 block by block (NaN, 0 when empty)."""
    total, n = 0.0, 0
    for b in blocks:
        total += float(np.sum(b, dtype=float))
        n += len(b)
    return (total / n if n else math.nan), n


def blocks_of(series, size: int = 1 << 16) -> Iterable[np.ndarray]:
    """``series`` (an array, or anything with ``blocks(size)``: ``estimation.spill``'s
    SpilledColumn) ``size`` values at a time."""
    if hasattr(series, "blocks"):
        return series.blocks(size)
    a = np.asarray(series).reshape(-1)
    return (a[i:i + size] for i in range(0, len(a), size))
