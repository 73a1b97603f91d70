"""One table of every variant run on husky-multipath: instantaneous GPS gain proxy
k = HPH'/(HPH' + R) (median over fixes, per axis) and RMSE without seed 14.

Reads the v*_hm.json files that variants.py wrote into DIR (default: the current directory),
in name order; a variant in more than one file takes its row from the later one. From the
repo root:

    python docs/results/igvc_gps_weight/collect.py DIR > docs/results/igvc_gps_weight/gain_table.md
"""

import json
import re
import sys
from pathlib import Path

import numpy as np

folder = Path(sys.argv[1]) if len(sys.argv) > 1 else Path.cwd()
files = sorted(folder.glob('v*_hm.json'))
if not files:
    sys.exit(f'no v*_hm.json in {folder}')
rows = {}
for f in files:
    with open(f) as fh:
        r = json.load(fh)
    seeds = sorted(r, key=int)
    for n in r[seeds[0]]:
        m = re.search(r'_R([0-9.]+)$', n)
        c = float(m.group(1)) if m else 1.0
        h = np.array([r[s][n]['hph_med'] for s in seeds])
        # The original v3_hm.json was written by an earlier variants.py, which subtracted R = 1
        # for every variant (so it holds HPH' + c - 1); the present one subtracts each variant's
        # own c. Such a file is recognised by its median HPH' (a real one is ~0.005 m^2).
        if f.name == 'v3_hm.json' and m and np.median(h) > 0.5 * abs(c - 1.0):
            h = h + 1.0 - c
        rm = np.array([r[s][n]['rmse'] for s in seeds if s != '14'])
        r0 = np.array([r[s]['ekf']['rmse'] for s in seeds if s != '14'])
        d = (rm - r0) * 1000
        rows[n] = (1000 * np.median(h / (h + c)), rm.mean(), d.mean(),
                   d.std(ddof=1) / np.sqrt(len(d)), f'{int((d < 0).sum())}/{len(d)}')
print('| variant | gain k x1e3 | RMSE w/o 14 (m) | vs ekf (mm) | better than ekf |')
print('|---|---|---|---|---|')
for n, (k, rm, d, se, w) in sorted(rows.items(), key=lambda kv: kv[1][0]):
    print(f'| {n} | {k:.2f} | {rm:.4f} | {d:+.1f} +- {se:.1f} | {w} |')
ks = np.array([v[0] for v in rows.values()])
rs = np.array([v[1] for v in rows.values()])
print('corr(gain, rmse) over variants:', np.corrcoef(ks, rs)[0, 1].round(3))
