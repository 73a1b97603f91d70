"""Smoother (filtered + lagged) with the GPS covariance scaled by each c, plus optional variants
of variants.py, through the project's runner; RMSE against the exact truth as in
montecarlo.run_seed. Seeds are comma-separated; OUT.json is optional; smsum.py summarises it.

    python docs/results/igvc_gps_weight/smoother_runs.py husky-multipath $(seq -s, 1 20) \\
        1.0,1.5,2.0 ekf,ekf_igvc,ekf_R1.5,ekf_R2.0 OUT.json
"""

import json
import sys
import time

import numpy as np
from ddfuse.estimation.runner import run
from ddfuse.estimation.smoother import FixedLagSmoother
from ddfuse.evaluation.montecarlo import _truth_errors
from harness import make_seed
from variants import VARIANTS, ScaleGps

scen = sys.argv[1]
seeds = [int(x) for x in sys.argv[2].split(',')]
cs = [float(x) for x in sys.argv[3].split(',')]
extra = sys.argv[4].split(',') if len(sys.argv) > 4 and sys.argv[4] else []
outp = sys.argv[5] if len(sys.argv) > 5 else None
res = {}
for s in seeds:
    t0 = time.time()
    sim, cfg, stream, pose = make_seed(scen, s)
    ests = {}
    for c in cs:
        sm = FixedLagSmoother(cfg, initial_pose=pose, landmarks=stream.landmarks,
                              lag=cfg.smoother.lag, lagged=True)
        ests[f'smoother_R{c:g}'] = sm if c == 1.0 else ScaleGps(sm, c)
    for n in extra:
        ests[n] = VARIANTS[n](cfg, stream, pose)
    r = run(stream, ests, output_rate=10.0)
    res[s] = {}
    for name, er in r.runs.items():
        pos, _, _ = _truth_errors(sim, er.trajectory)
        res[s][name] = float(np.sqrt(np.mean(pos * pos)))
    print(s, {k: round(v, 4) for k, v in res[s].items()}, f'{time.time() - t0:.0f}s', flush=True)
if outp:
    with open(outp, 'w') as f:
        json.dump(res, f, indent=1)
