"""ekf_baseline.kalman_jit's entry points are compiled by ``ready`` for their one signature,
never at import and never for other argument types (a run compiles only its filters')."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import numpy as np
from ddfuse.ekf_baseline import kalman_jit as k
assert all(not getattr(k, n).signatures for n in k._SIGNATURES), "compiled at import"
try:
    k.world_cov(np.eye(3), 3, 0.0)
except TypeError:
    pass
else:
    raise SystemExit("an entry point ran before ready()")
k.ready("world_cov")
assert len(k.world_cov.signatures) == 1
P = np.diag([1.0, 4.0, 9.0])
out = k.world_cov(P, 3, np.pi / 2)  # rotates the (x, y) block by 90 degrees
assert np.allclose(out, np.diag([4.0, 1.0, 9.0])), out
k.world_cov(P, np.int32(3), 0)  # other integer/float types: converted to the one signature
assert len(k.world_cov.signatures) == 1
untouched = [n for n in k._SIGNATURES if n != "world_cov"]
assert all(not getattr(k, n).signatures for n in untouched), "ready compiled more than asked"
print("ok")
"""


def test_entry_points_compile_only_when_readied():
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:] + r.stdout
    assert r.stdout.strip() == "ok"
