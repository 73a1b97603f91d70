"""GPS NIS (mean of the 2-dof NIS of every fix) and GPS gate rejections / recoveries per
estimator, seeds 1-20.

    python docs/results/igvc_gps_weight/nis.py husky-multipath ekf,ekf_igvc,smoother
"""

import sys

import numpy as np
from harness import feed, make_seed
from variants import VARIANTS

scen = sys.argv[1]
names = sys.argv[2].split(',')
acc = {n: [] for n in names}
for s in range(1, 21):
    sim, cfg, stream, pose = make_seed(scen, s)
    out, ests = feed(stream, {n: VARIANTS[n](cfg, stream, pose) for n in names})
    for n in names:
        inn = [i for i in ests[n].log.innovations if i.kind == 'gps']
        nis = np.array([i.nis for i in inn])
        a = np.array([i.accepted for i in inn])
        rej = sum(v for k, v in ests[n].log.rejected.items() if k[0] == '/fix')
        acc[n].append((np.nanmean(nis), (~a).sum(), rej, len(inn)))
print(f'{scen}: GPS NIS mean (2 dof; expect 2), logged-rejected fixes, rejections counted '
      '(all reasons) -- 20 seeds')
for n in names:
    v = np.array(acc[n], float)
    bad = [s + 1 for s in range(20) if v[s, 2] > 0]
    print(f'{n:12s} NIS mean {v[:, 0].mean():.3f} (seed range {v[:, 0].min():.2f}-'
          f'{v[:, 0].max():.2f}), rejected fixes total {int(v[:, 1].sum())}, rejection counts '
          f'{int(v[:, 2].sum())} on seeds {bad}')
