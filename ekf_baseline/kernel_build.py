"""The EKF kernels compiled into numba's cache by a background process (started by
``compiled.build_in_background``), while the run that found them missing uses the filters'
Python reference path (``compiled.usable``, under the "reference" cold-cache policy of
``factors.jitcache``).

``python -m ddfuse.ekf_baseline.kernel_build NAME...`` compiles the ``kalman_jit`` entry points
NAME (or loads them, if another process cached them meanwhile): one such process at a time per
user (a lock file), each detached from the run that started it (its own session, no terminal
output), so that it outlives the run. A compile that fails leaves the cache as it was: the next
run finds the kernels missing again and says so."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from ddfuse.factors import jitcache


def lock_path() -> Path:
    """The lock file one background build at a time holds (per user, in the temp dir)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"ddfuse-kernel-build-{uid}.lock"


def main(names: list[str]) -> int:
    """Compile (or load) ``names`` into numba's cache, one build at a time per user."""
    import fcntl

    from ddfuse.ekf_baseline.compiled import kernels

    if hasattr(os, "nice"):
        os.nice(10)  # behind the run that started it (and the user's other work)
    with open(lock_path(), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another build first: then these may load from it
        kj = kernels()
        jitcache._notice[0] = lambda _line: None  # detached: nothing to say, nobody to read it
        kj.ready(*names)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
