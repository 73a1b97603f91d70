"""stderr of a command without numba's one-time kernel notices (``factors.jitcache``): on a
cold cache (a clean clone, as in CI) a command that runs an EKF says that its kernels are being
compiled, or that the Python reference code runs while a background build compiles them, in
lines of their own before anything else it says; whether they come depends on how far the
suite's background build has got, not on the command under test."""

from __future__ import annotations

NOTICES = ("ddfuse: numba's compiled kernels are not cached yet", "ddfuse: compiling ",
           "ddfuse: compiled ", "ddfuse: numba's compiled kernels are not cached, and no")


def without_kernel_notices(err: str) -> str:
    """``err`` less the kernel notices' lines, stripped."""
    return "\n".join(ln for ln in err.strip().splitlines()
                     if not ln.startswith(NOTICES)).strip()
