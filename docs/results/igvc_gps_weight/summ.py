"""Table of analyze.py's JSON: every numeric diagnostic, mean over seeds per estimator (keys
with 'final' in the name: RMS over seeds, marked r). Seeds to leave out: comma-separated.

    python docs/results/igvc_gps_weight/summ.py OUT.json 14   # from the repo root
"""

import json
import sys

import numpy as np

with open(sys.argv[1]) as f:
    res = json.load(f)
seeds = sorted(res, key=int)
names = list(res[seeds[0]])
keys = [k for k, v in res[seeds[0]][names[0]].items() if isinstance(v, (int, float))]
excl = sys.argv[2].split(',') if len(sys.argv) > 2 else []
ss = [s for s in seeds if s not in excl]
print(f'{len(ss)} seeds')
print('key'.ljust(20) + ''.join(n.rjust(16) for n in names))
for k in keys:
    row = []
    for n in names:
        v = np.array([res[s][n][k] for s in ss], float)
        row.append(f'{np.nanmean(v):.4f}' if 'final' not in k
                   else f'{np.sqrt(np.nanmean(v**2)):.4f}r')
    print(k.ljust(20) + ''.join(r.rjust(16) for r in row))
