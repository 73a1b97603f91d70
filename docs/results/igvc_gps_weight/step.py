"""Step response for variants: 1 m GPS step east (cross-track for the N-S lawnmower legs) or
north (along-track) from T (default 200 s) on; the difference of the estimates with and without
the step is the response of the position, hoff and k_v (perturb.perturbed moves the fixes).

    python docs/results/igvc_gps_weight/step.py husky-multipath ekf,ekf_igvc 1 6 [T]
"""

import sys

import numpy as np
from harness import feed, make_seed
from perturb import perturbed
from variants import VARIANTS

scen = sys.argv[1]
names = sys.argv[2].split(',')
seeds = range(int(sys.argv[3]), int(sys.argv[4]) + 1)
T = float(sys.argv[5]) if len(sys.argv) > 5 else 200.0
lags = [0.4, 2, 5, 10, 20, 30, 60, 100, 150, 195]
lags = [L for L in lags if T + L < 399.5]
agg = {(n, ax): [] for n in names for ax in (0, 1)}
for s in seeds:
    sim, cfg, stream, pose = make_seed(scen, s)
    o0, _ = feed(stream, {n: VARIANTS[n](cfg, stream, pose) for n in names})
    for ax in (0, 1):
        st2 = perturbed(stream, stream.datum, sim.t0 + T, 1.0 if ax == 0 else 0.0,
                        1.0 if ax == 1 else 0.0)
        o1, _ = feed(st2, {n: VARIANTS[n](cfg, st2, pose) for n in names})
        for n in names:
            a, b = o0[n], o1[n]
            k = min(len(a['t']), len(b['t']))
            t = a['t'][:k] - sim.t0
            dp = b['pose'][:k] - a['pose'][:k]
            sn = a['names']
            ds = b['state'][:k] - a['state'][:k]
            ih = [i for i, x in enumerate(sn) if x.startswith('hoff')][0]
            ikv = sn.index('k_v')
            row = [np.interp(T + L, t, dp[:, ax]) for L in lags]
            row += [np.degrees(ds[-1, ih]), ds[-1, ikv], np.interp(T + 20, t, dp[:, 1 - ax])]
            agg[(n, ax)].append(row)
for ax, lab in ((0, 'EAST step (cross-track on the N-S legs)'), (1, 'NORTH step (along-track)')):
    print(f'\n{lab}: position response (m) on the stepped axis, mean over {len(seeds)} seeds; '
          'hoff/k_v change at the end (mean)')
    print('variant'.ljust(16) + ''.join(f'{L:>7}s' for L in lags[:1]) + ' (mm) '
          + ''.join(f'{L:>7}s' for L in lags[1:]) + '  hoff_deg      k_v')
    for n in names:
        A = np.array(agg[(n, ax)])
        print(n.ljust(16) + f'{1000 * A[:, 0].mean():8.2f}     '
              + ''.join(f'{v:8.3f}' for v in A[:, 1:len(lags)].mean(0))
              + f'{A[:, -3].mean():10.3f}{A[:, -2].mean():9.4f}')
