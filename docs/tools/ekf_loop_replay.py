"""Issue 27's EKF target: ddfuse's unicycle EKF per message against the same compiled kernel
calls replayed in one numba loop (a whole-loop compiled EKF doing the same arithmetic).

    python docs/tools/ekf_loop_replay.py BAG CONFIG [ROUNDS]

It runs ``ekf`` over the bag as ``ddfuse run`` does (the runner, its 10 Hz outputs, the
innovation log) and records every call of the event kernel (``kalman_jit.uni_event``) with its
scalar arguments; where the filter's Python changed the kernel's arrays between two calls (a
deferred update, an initialisation, a gap) it records the arrays as they were before the call
(a resync). The replay runs the calls in one ``njit`` loop per stretch between resyncs, on its
own copy of the arrays and a log buffer large enough for the whole run, and must end on the
filter's state and covariance exactly (it says so). Printed: CPU per message of ddfuse's run,
of the kernel calls from Python (numba's argument unboxing included), and of the replay loop;
min over ROUNDS (default 5). Needs the EKF kernels in numba's cache (run ``ddfuse run`` once)."""

from __future__ import annotations

import sys
import time

import numpy as np
from ddfuse.ekf_baseline import compiled as jit
from ddfuse.estimation.bags import read_stream
from ddfuse.estimation.config import load_config
from ddfuse.estimation.runner import run
from ddfuse.evaluation.estimators import build
from numba import njit

ARRAYS = ("fp", "ip", "W", "sf", "si")


def record(cfg, stream):
    """(the filter after the run, the calls' scalar arguments (k, 12), resyncs {call index:
    the arrays before it})."""
    est = build(cfg, stream, ["ekf"])
    ekf = est["ekf"] if isinstance(est, dict) else est[0]
    calls: list[tuple] = []
    resync: dict[int, dict[str, np.ndarray]] = {}
    after: dict[str, np.ndarray] = {}
    make_core = ekf._compiled_core
    kj = jit.kernels()
    log_fields = (kj.IP_LOGN, kj.IP_LOGCAP)

    def changed(kf) -> bool:
        if not after:
            return True
        for name in ARRAYS:
            a, b = getattr(kf, name), after[name]
            if name == "ip":
                a, b = np.delete(a, log_fields), np.delete(b, log_fields)
            if a.shape != b.shape or not np.array_equal(a, b, equal_nan=True):
                return True
        return False

    def core(x0, P0):
        kf = make_core(x0, P0)
        kernel = ekf._uni_event

        def recorded(fp, ip, W, sf, si, lg, *args):
            if changed(kf):
                resync[len(calls)] = {n: getattr(kf, n).copy() for n in ARRAYS}
            calls.append(tuple(float(a) for a in args))
            code = kernel(fp, ip, W, sf, si, lg, *args)
            after.update({n: getattr(kf, n).copy() for n in ARRAYS})
            return code

        ekf._uni_event = recorded
        return kf

    ekf._compiled_core = core
    run(stream, est)
    return ekf, np.array(calls), resync


def replay_loop(kernel):
    @njit
    def loop(fp, ip, W, sf, si, lg, A, i0, i1):
        for i in range(i0, i1):
            a = A[i]
            kernel(fp, ip, W, sf, si, lg, a[0], a[1], int(a[2]), int(a[3]), a[4], a[5], a[6],
                   a[7], a[8], a[9], int(a[10]), a[11])
    return loop


def python_loop(kernel, fp, ip, W, sf, si, lg, A, i0, i1):
    for a in A[i0:i1].tolist():
        kernel(fp, ip, W, sf, si, lg, a[0], a[1], int(a[2]), int(a[3]), a[4], a[5], a[6],
               a[7], a[8], a[9], int(a[10]), a[11])


def replay(loop, A, resync, kj) -> tuple[float, dict[str, np.ndarray]]:
    """CPU s of the replay and its final arrays."""
    starts = sorted(resync) + [len(A)]
    lg = np.zeros((3 * len(A) + 16, kj.LG_COLS))
    arr = {}
    cpu = 0.0
    for i0, i1 in zip(starts[:-1], starts[1:], strict=True):
        arr = {n: v.copy() for n, v in resync[i0].items()}
        arr["ip"][kj.IP_LOGN], arr["ip"][kj.IP_LOGCAP] = 0, lg.shape[0]
        t0 = time.process_time()
        loop(*(arr[n] for n in ARRAYS), lg, A, i0, i1)
        cpu += time.process_time() - t0
    return cpu, arr


def main(bag: str, config: str, rounds: int = 5) -> None:
    cfg = load_config(config)
    stream = read_stream(bag, cfg)
    n_msg = len(stream.measurements)
    run_cpu = []
    for _ in range(rounds):
        est = build(cfg, stream, ["ekf"])
        t0 = time.process_time()
        run(stream, est)
        run_cpu.append(time.process_time() - t0)
    ekf, A, resync = record(cfg, stream)
    kj = jit.kernels()
    kernel = kj.uni_event
    loop = replay_loop(kernel)
    replay(loop, A[:1], {0: resync[0]}, kj)  # compile the loop
    cpu_loop, cpu_py = [], []
    for _ in range(rounds):
        cpu, arr = replay(loop, A, resync, kj)
        cpu_loop.append(cpu)
        cpu_py.append(replay(lambda *a: python_loop(kernel, *a), A, resync, kj)[0])
    same = all(np.array_equal(arr[n], getattr(ekf.kf, n), equal_nan=True)
               for n in ("W", "sf", "si"))
    k = len(A)
    us = 1e6
    print(f"{bag}: {n_msg} messages, {k} kernel calls, {len(resync)} resyncs; replay ends on "
          f"the filter's arrays exactly: {same}")
    print(f"ddfuse run (runner, outputs, log): {min(run_cpu):.3f} s CPU, "
          f"{min(run_cpu) / n_msg * us:.2f} us per message")
    print(f"kernel calls from Python: {min(cpu_py):.3f} s, {min(cpu_py) / k * us:.2f} us per call")
    print(f"kernel calls in one numba loop: {min(cpu_loop):.3f} s, "
          f"{min(cpu_loop) / k * us:.2f} us per call")
    print(f"ratio, the whole run's CPU over the loop's: {min(run_cpu) / min(cpu_loop):.2f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], *(int(a) for a in sys.argv[3:4]))
