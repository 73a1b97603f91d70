"""numba's on-disk kernel cache, guarded against stale kernels.

numba re-validates a cached kernel only by the time stamp and size of the file that defines it,
not of the modules whose functions it compiles in (``register_jitable``, ``njit`` callees). A
change to one of those would silently keep running the old machine code. ``guard_cache`` keeps a
hash of every source beside the cache and drops the module's cached kernels when it changes; call
it before the kernels are first compiled or loaded.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

__all__ = ["guard_cache"]


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
