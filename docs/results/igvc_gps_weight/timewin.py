"""RMS position error per 50 s window, over seeds FIRST..LAST (seed 14 left out), per variant.

    python docs/results/igvc_gps_weight/timewin.py husky-multipath ekf,ekf_igvc 1 20
"""

import sys

import numpy as np
from harness import feed, make_seed, truth_at
from variants import VARIANTS

scen = sys.argv[1]
names = sys.argv[2].split(',')
seeds = [s for s in range(int(sys.argv[3]), int(sys.argv[4]) + 1) if s != 14]
edges = np.arange(0, 401, 50)
ms = {n: np.zeros(len(edges) - 1) for n in names}
for s in seeds:
    sim, cfg, stream, pose = make_seed(scen, s)
    out, _ = feed(stream, {n: VARIANTS[n](cfg, stream, pose) for n in names})
    for n in names:
        d = out[n]
        tr = truth_at(sim, d['t'])
        e2 = ((d['pose'][:, :2] - tr[:, :2])**2).sum(1)
        tt = d['t'] - sim.t0
        for k in range(len(edges) - 1):
            m = (tt >= edges[k]) & (tt < edges[k + 1])
            ms[n][k] += e2[m].mean() / len(seeds)
print(f'RMS position error (m) per window, {len(seeds)} seeds (rms over seeds)')
print('variant'.ljust(16) + ''.join(f'{edges[k]:>4}-{edges[k + 1]:<4}'
                                    for k in range(len(edges) - 1)) + '   all')
for n in names:
    print(n.ljust(16) + ''.join(f'{np.sqrt(v):9.3f}' for v in ms[n])
          + f'{np.sqrt(ms[n].mean()):9.3f}')
