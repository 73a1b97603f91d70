"""Paired RMSE difference a - b over the seeds of a variants.py JSON, seed 14 left out.

    python docs/results/igvc_gps_weight/pair.py OUT.json ekf_R1.5 ekf_igvc   # from the repo root
"""

import json
import sys

import numpy as np

with open(sys.argv[1]) as f:
    res = json.load(f)
a, b = sys.argv[2], sys.argv[3]
seeds = [s for s in sorted(res, key=int) if s != '14']
d = np.array([res[s][a]['rmse'] - res[s][b]['rmse'] for s in seeds]) * 1000
print(f'{a} - {b} ({len(d)} seeds w/o 14): mean {d.mean():+.1f} mm, sd {d.std(ddof=1):.1f}, '
      f'|d| median {np.median(abs(d)):.1f}, max |d| {abs(d).max():.1f}, '
      f'{a} better {int((d < 0).sum())}/{len(d)}')
