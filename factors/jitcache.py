"""numba's on-disk kernel cache, guarded against stale kernels.

numba re-validates a cached kernel only by the time stamp and size of the file that defines it,
not of the modules whose functions it compiles in (``register_jitable``, ``njit`` callees). A
change to one of those would silently keep running the old machine code. ``guard_cache`` keeps a
hash of every source beside the cache and drops the module's cached kernels when it changes; call
it before the kernels are first compiled or loaded. ``compiling`` says on the terminal what a
slow compile is doing. ``load_cached`` loads a kernel from the cache without ever compiling it;
``build_in_background`` starts the one process that compiles the missing kernels for the next
runs (under the "reference" cold-cache policy of ``ddfuse run``). ``one_compiler`` makes
processes sharing a cache (a process pool's workers, test workers, the background build) compile
each kernel once between them: the others wait for it and load it from the cache.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["BUILD_WAIT_S", "NOTICE_AFTER_S", "as_background_build", "build_in_background",
           "compiling", "deferred_build", "guard_cache", "load_cached", "on_cold_cache",
           "one_compiler", "start_build"]

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


def arg_types(sig: str) -> tuple:
    """The numba argument types of ``sig`` ("(float64[::1], int64)"): the signature under which
    numba caches a kernel typed at its first call, so ``Dispatcher.compile(arg_types(sig))`` and
    that call share one cache entry (numba keys its cache by the signature as given)."""
    from numba.core import sigutils

    args, _ = sigutils.normalize_signature(sig)
    return tuple(args)


def load_cached(dispatcher, sig) -> bool:
    """Load ``dispatcher`` (a ``numba.njit(cache=True)`` function) for the argument types
    ``sig`` (a signature string, or ``arg_types``' tuple: the cache entry's key as compiled)
    from numba's cache where it holds them, never compiling (numba's ``Dispatcher.compile`` up
    to its cache lookup); whether it is now ready for them. False also where numba's internals
    differ from those this mirrors (the caller then compiles)."""
    from numba.core import sigutils
    from numba.core.compiler_lock import global_compiler_lock

    try:
        with global_compiler_lock:
            args, _ = sigutils.normalize_signature(sig)
            if dispatcher.overloads.get(tuple(args)) is not None:
                return True
            # no index file, nothing cached: said without load_overload, which first
            # initialises numba's target context (~0.7 s, all a cold run would spend in numba)
            index = getattr(getattr(dispatcher._cache, "_cache_file", None), "_index_path", None)
            if index is not None and not os.path.exists(index):
                return False
            cres = dispatcher._cache.load_overload(sig, dispatcher.targetctx)
            if cres is None:
                return False
            dispatcher.targetctx.insert_user_function(cres.entry_point, cres.fndesc,
                                                      [cres.library])
            dispatcher.add_overload(cres)
    except AttributeError:  # another numba's internals
        return False
    return True


# python -m: the background build. It compiles (or loads) every kernel a default ``ddfuse run``
# uses, plus the ones named, one at a time; named by module path so that this, the lowest layer,
# imports nothing above it (the builder imports the kernels' modules itself).
BUILDER = "ddfuse.ekf_baseline.kernel_build"
# every kernel a default ``ddfuse run`` (ekf, ekf_igvc, the smoothers) uses, in the order a run
# needs them (the builder's names: ``kernel_build``)
DEFAULT_BUILD = ("uni_event", "world_cov", "joseph", "preintegration", "igvc_event")
_started: set[str] = set()  # the kernels this process has asked a background build for


def lock_path() -> Path:
    """The lock file the one background build at a time holds, in the temp dir: one per user
    and installed copy of ddfuse and numba cache directory (``NUMBA_CACHE_DIR``), so that a
    build for another install or cache never stands in for this one's."""
    uid = os.getuid() if hasattr(os, "getuid") else 0
    where = f"{Path(__file__).resolve().parents[1]}\0{os.environ.get('NUMBA_CACHE_DIR', '')}"
    tag = hashlib.sha256(where.encode()).hexdigest()[:12]
    return Path(tempfile.gettempdir()) / f"ddfuse-kernel-build-{uid}-{tag}.lock"


# s: how long a run waits for a kernel the background build is compiling before compiling it
# too. The build runs at nice 10: on a busy machine its compile can take minutes of wall time,
# while the run's own compile takes seconds to tens of seconds.
BUILD_WAIT_S = 10.0
_role = {"holder": "run"}  # what this process writes into a kernel lock it holds


@contextmanager
def one_compiler(kernel: str) -> Iterator[None]:
    """Around compiling (or loading) ``kernel`` into numba's cache: one process at a time per
    kernel, install and cache (an exclusive ``flock`` beside ``lock_path``). numba does not
    coordinate processes: without this, processes started together on a cold cache each spend
    the kernel's compile (seconds to tens of seconds of CPU) on the same machine code. Inside,
    ``Dispatcher.compile`` finds the kernel in the cache when another process has just compiled
    it, and loads it. A run waits for another run as long as it takes, but for the background
    build (``as_background_build``) at most ``BUILD_WAIT_S``, then compiles unguarded. Never
    held while taking another kernel's lock, so it cannot deadlock; without ``flock`` (Windows)
    it does nothing."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    base = lock_path()
    try:
        lock = open(base.with_name(f"{base.stem}-{kernel}.lock"), "a")  # noqa: SIM115 - held
    except OSError:  # an unwritable temp dir: compile unguarded, as numba alone would
        yield
        return
    with lock:
        if not _wait_for(lock, fcntl):
            yield  # the niced background build has it: compiling here beats waiting behind it
            return
        lock.truncate(0)
        lock.write(_role["holder"])
        lock.flush()
        yield


def _wait_for(lock, fcntl) -> bool:
    """Take ``lock`` (exclusive), waiting as long as a run holds it but at most
    ``BUILD_WAIT_S`` behind the background build; False when that wait ran out."""
    start = time.monotonic()
    while True:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError:
            pass
        if time.monotonic() - start >= BUILD_WAIT_S and _held_by_build(lock.name):
            return False
        time.sleep(0.05)


def _held_by_build(path: str) -> bool:
    try:
        return Path(path).read_text() == "build"
    except OSError:
        return False


def as_background_build() -> None:
    """Mark this process as the background build: a run waiting for a kernel it compiles
    stops waiting after ``BUILD_WAIT_S`` and compiles the kernel itself."""
    _role["holder"] = "build"


def build_running() -> bool:
    """Whether a background build (this user's, any process) holds the lock now."""
    try:
        import fcntl
    except ImportError:  # no flock: assume none, the builder then waits for the lock itself
        return False
    try:
        with open(lock_path(), "a") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                return True
            fcntl.flock(lock, fcntl.LOCK_UN)
    except OSError:
        return False
    return False


def start_build(names: list[str]) -> None:
    """Start the background build (``BUILDER``) of ``names`` and DEFAULT_BUILD, detached (its
    own session, no terminal output); it waits for any build holding the lock. OSError when
    the process cannot be started."""
    subprocess.Popen([sys.executable, "-m", BUILDER, *names],
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True, close_fds=True)


def build_in_background(names: list[str]) -> None:
    """Ask for the kernels ``names`` (the builder's names) to be compiled into numba's cache by
    a background process: one per process, together with DEFAULT_BUILD (every kernel a default
    run uses, so that the kernels found cold later in the same run are in that one build), and
    none while another build holds the lock (it compiles the default set too; a name outside it
    is asked for again by the next run). Inside ``deferred_build`` the process is started when
    that block ends instead. Said once on the terminal, through ``_notice``."""
    todo = [n for n in names if n not in _started]
    if not todo:
        return
    first = not _started
    _started.update(todo)
    _started.update(DEFAULT_BUILD)
    running = build_running()
    deferred = _deferred["on"] and not running
    if deferred:
        _deferred["names"].extend(todo)
    elif not running and not _start(todo):
        return
    if first:
        then = ("and a background process compiles the kernels when this run has finished"
                if deferred else "while a background process "
                f"{'is compiling' if running else 'compiles'} the kernels")
        _notice[0](
            "ddfuse: numba's compiled kernels are not cached yet (first run after installing or "
            "updating ddfuse): this run uses the Python reference code for the EKFs and the "
            f"smoother's preintegration (the same estimates to 1e-9, slower), {then} (about a "
            "minute of CPU, at low priority) for the next runs")


def _start(names: list[str]) -> bool:
    """``start_build(names)``, saying so when it cannot; whether it started."""
    try:
        start_build(names)
    except OSError as e:
        _notice[0](f"ddfuse: numba's compiled kernels are not cached, and no background "
                   f"process could compile them ({e}): this run uses the Python reference "
                   "code (the same estimates to 1e-9, slower)")
        return False
    return True


# ``deferred_build``'s state: whether builds are held back, and the names asked for meanwhile
_deferred: dict = {"on": False, "names": []}


@contextmanager
def deferred_build() -> Iterator[None]:
    """Hold back the background build ``build_in_background`` asks for until the block ends
    (``ddfuse run``: one pass over a bag), when it starts unless another build holds the lock
    by then. On a small machine the build's compiling beside the run slows the run itself
    (measured: docs/results/secondary_speed.md, session 25). A process that builds many
    estimators (``ddfuse tune``, ``mc``, ``run --tune``) starts it at once instead, so that
    its later runs load the kernels as soon as they are cached. Nested blocks: the outermost
    starts it."""
    was = _deferred["on"]
    _deferred["on"] = True
    try:
        yield
    finally:
        _deferred["on"] = was
        if not was:
            names, _deferred["names"] = _deferred["names"], []
            if names and not build_running():
                _start(names)
