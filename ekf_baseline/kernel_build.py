"""The background build: numba's kernels compiled into its cache by a process started by
``factors.jitcache.build_in_background``, while the run that found them missing uses the
Python reference code (the EKFs' reference filters with ``joseph_numpy``'s update, the
smoother's Python preintegration; the "reference" cold-cache policy of ``factors.jitcache``).

``python -m ddfuse.ekf_baseline.kernel_build NAME...`` compiles (or loads, if another process
cached them meanwhile) the kernels NAME and then every kernel of ``jitcache.DEFAULT_BUILD``,
one at a time: one such process at a time per install and cache (a lock file,
``jitcache.lock_path``), each detached from the run that started it (its own session, no
terminal output), so that it outlives the run. NAME is a ``kalman_jit`` entry point, ``joseph``
(``joseph.innovation_cov`` and ``apply_update``) or ``preintegration`` (the smoother's kernel,
``factors.preintegration_jit``). A compile that fails leaves the cache as it was: the next run
finds the kernel missing again and says so."""

from __future__ import annotations

import os
import sys

from ddfuse.factors import jitcache


def build(name: str) -> None:
    """Compile (or load from numba's cache) the kernel ``name`` (module docstring)."""
    if name == "joseph":
        from ddfuse.ekf_baseline import joseph

        joseph.ready()
    elif name == "preintegration":
        from ddfuse.factors import preintegration_jit

        preintegration_jit.ready()
    else:
        from ddfuse.ekf_baseline.compiled import kernels

        kernels().ready(name)


def main(names: list[str]) -> int:
    """Compile (or load) ``names`` and ``jitcache.DEFAULT_BUILD`` into numba's cache, one build
    at a time per install and cache."""
    import fcntl

    if hasattr(os, "nice"):
        os.nice(10)  # behind the run that started it (and the user's other work)
    jitcache.as_background_build()
    with open(jitcache.lock_path(), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another build first: then these may load from it
        jitcache._notice[0] = lambda _line: None  # detached: nothing to say, nobody to read it
        for name in dict.fromkeys([*names, *jitcache.DEFAULT_BUILD]):
            build(name)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
