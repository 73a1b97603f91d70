"""Summary of smoother_runs.py JSONs: RMSE mean (all seeds and without seed 14) per estimator,
and the paired difference against ekf_igvc without seed 14.

    python docs/results/igvc_gps_weight/smsum.py SM_HM.json SM_HUSKY.json   # from the repo root
"""

import json
import sys

import numpy as np

for f in sys.argv[1:]:
    with open(f) as fh:
        r = json.load(fh)
    seeds = sorted(r, key=int)
    names = list(r[seeds[0]])
    print(f)
    ref = 'ekf_igvc'
    for n in names:
        v = np.array([r[s][n] for s in seeds])
        m = np.array([s != '14' for s in seeds])
        d = (v - np.array([r[s][ref] for s in seeds]))[m] * 1000
        print(f'  {n:22s} mean {v.mean():.4f}  w/o14 {v[m].mean():.4f}   '
              f'vs ekf_igvc {d.mean():+6.1f} mm, better on {int((d < 0).sum())}/19')
