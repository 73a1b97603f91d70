"""numba's on-disk kernel cache, guarded against stale kernels.

numba re-validates a cached kernel only by the time stamp and size of the file that defines it,
not of the modules whose functions it compiles in (``register_jitable``, ``njit`` callees). A
change to one of those would silently keep running the old machine code. ``guard_cache`` keeps a
hash of every source beside the cache and drops the module's cached kernels when it changes; call
it before the kernels are first compiled or loaded. ``compiling`` says on the terminal what a
slow compile is doing.
"""

from __future__ import annotations

import hashlib
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["NOTICE_AFTER_S", "compiling", "guard_cache", "on_cold_cache"]

NOTICE_AFTER_S = 3.0  # s: a compile longer than this is announced (a cache load is ~0.1-0.3 s
# of CPU, up to ~2 s of wall time on a loaded machine; a cold compile tens of seconds)


def _stderr(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


_notice: list[Callable[[str], None]] = [_stderr]  # where compiling writes its lines

# What the EKFs do when their kernels are not in numba's cache (``ekf_baseline.compiled.usable``):
# "compile" them then and there (the library's default: tens of seconds, announced), or
# "reference": run the Python reference path this time (the same estimates to 1e-9, slower)
# while a background process compiles the kernels into the cache for the next runs
# (``ddfuse run`` chooses this: docs/design/performance.md).
_policy = {"cold": "compile"}


def on_cold_cache(policy: str | None = None) -> str:
    """The policy for kernels missing from numba's cache ("compile" or "reference"), set to
    ``policy`` when given."""
    if policy is not None:
        if policy not in ("compile", "reference"):
            raise ValueError(f"on_cold_cache: 'compile' or 'reference', got {policy!r}")
        _policy["cold"] = policy
    return _policy["cold"]


@contextmanager
def compiling(what: str) -> Iterator[None]:
    """Around numba compiling (or loading from its cache) the kernels ``what``: when it takes
    longer than NOTICE_AFTER_S s (a cold compile: the first run after installing or changing
    the package, tens of seconds), one line says what is being compiled, and one when it is
    done, with the seconds it took. Loading from the cache (~0.1 s) says nothing."""
    t0 = time.perf_counter()
    said = threading.Event()

    def announce() -> None:
        said.set()
        _notice[0](f"ddfuse: compiling {what} (numba, once: the compiled code is cached for "
                   "the next runs) ...")

    timer = threading.Timer(NOTICE_AFTER_S, announce)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        if said.is_set():
            _notice[0](f"ddfuse: compiled {what} in {time.perf_counter() - t0:.0f} s")


def guard_cache(sources: Iterable[Path], cache: Path, stem: str) -> None:
    """Drop ``cache/<stem>.*.nbi|nbc`` unless the SHA-256 of ``sources`` (read in order) equals
    the one stored in ``cache/<stem>.sources.sha256`` (then written). A read-only tree is left
    alone (numba then uses its user cache, which it invalidates by time stamp only)."""
    h = hashlib.sha256()
    for p in sources:
        h.update(Path(p).read_bytes())
    digest = h.hexdigest()
    stamp = cache / f"{stem}.sources.sha256"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    try:
        cache.mkdir(exist_ok=True)
        for f in cache.glob(f"{stem}.*.nb[ic]"):
            f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass
