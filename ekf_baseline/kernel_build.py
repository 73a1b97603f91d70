"""The EKF kernels compiled into numba's cache by a background process, while the run that
found them missing uses the filters' Python reference path (``compiled.usable``, under the
"reference" cold-cache policy of ``factors.jitcache``).

``python -m ddfuse.ekf_baseline.kernel_build NAME...`` compiles the ``kalman_jit`` entry points
NAME (or loads them, if another process cached them meanwhile): one such process at a time per
user (a lock file), each detached from the run that started it (its own session, no terminal
output), so that it outlives the run. A compile that fails leaves the cache as it was: the next
run finds the kernels missing again and says so."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from ddfuse.factors import jitcache

_started: set[str] = set()  # the kernels this process has asked a background build for


def lock_path() -> Path:
    """The lock file one background build at a time holds (per user, in the temp dir)."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"ddfuse-kernel-build-{uid}.lock"


def build_in_background(names: list[str]) -> None:
    """Start the background build of the entry points ``names`` (once per process each), and
    say so on the terminal (through ``jitcache``'s notice, above any progress bars)."""
    todo = [n for n in names if n not in _started]
    if not todo:
        return
    _started.update(todo)
    try:
        subprocess.Popen([sys.executable, "-m", "ddfuse.ekf_baseline.kernel_build", *todo],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True, close_fds=True)
    except OSError as e:
        jitcache._notice[0](f"ddfuse: the EKF kernels {', '.join(todo)} are not compiled, and "
                            f"no background process could compile them ({e}): this run uses "
                            "the Python reference filters (the same estimates, slower)")
        return
    jitcache._notice[0](
        f"ddfuse: the EKF kernels {', '.join(todo)} are not compiled yet (first run after "
        "installing or updating ddfuse): this run uses the Python reference filters (the same "
        "estimates to 1e-9, slower), while a background process compiles the kernels (numba, "
        "about half a minute of CPU) for the next runs")


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
