"""Error spectra of each estimator's position error and of the GPS error, in frequency bands
(20-400 s, mean-square per band), averaged over seeds; plus the transfer (cross-spectrum / GPS
spectrum, real part and coherence) per band, and the spectrum of the difference of the first
two estimators.

    python docs/results/igvc_gps_weight/spectra.py husky-multipath 1 20 ekf,ekf_igvc
"""

import sys

import numpy as np
from harness import feed, gps_error_at, make_seed, truth_at
from variants import VARIANTS

scen = sys.argv[1]
seeds = range(int(sys.argv[2]), int(sys.argv[3]) + 1)
names = sys.argv[4].split(',')
bands = [(0, 0.005), (0.005, 0.01), (0.01, 0.02), (0.02, 0.05), (0.05, 0.1), (0.1, 0.3),
         (0.3, 5.1)]
acc = {n: np.zeros(len(bands)) for n in names + ['gps']}
cross = {n: np.zeros(len(bands), complex) for n in names}
diffp = np.zeros(len(bands))
T0, T1 = 20.0, 400.0  # skip the first 20 s (initial transient)
for s in seeds:
    sim, cfg, stream, pose = make_seed(scen, s)
    out, ests = feed(stream, {n: VARIANTS[n](cfg, stream, pose) for n in names})
    tg = sim.t0 + np.arange(T0, T1, 0.1)
    g = gps_error_at(sim, tg)
    G = np.fft.rfft(g - g.mean(0), axis=0)
    f = np.fft.rfftfreq(len(tg), 0.1)
    E = {}
    for n in names:
        d = out[n]
        tr = truth_at(sim, d['t'])
        e = d['pose'][:, :2] - tr[:, :2]
        ei = np.column_stack([np.interp(tg, d['t'], e[:, k]) for k in range(2)])
        E[n] = np.fft.rfft(ei, axis=0)  # not demeaned: bias counts as DC
    for b, (lo, hi) in enumerate(bands):
        m = (f >= lo) & (f < hi)
        acc['gps'][b] += (abs(G[m])**2).sum()
        for n in names:
            acc[n][b] += (abs(E[n][m])**2).sum()
            cross[n][b] += (E[n][m] * np.conj(G[m])).sum()
        if len(names) >= 2:
            diffp[b] += (abs(E[names[0]][m] - E[names[1]][m])**2).sum()
N = len(tg)
norm = 2.0 / N**2 / len(seeds)  # -> mean-square (m^2) contributed by the band (approx.)
print('band Hz'.ljust(16) + ''.join(n.rjust(12) for n in ['gps'] + names) + '  diff(0-1)'
      + ''.join(('H_' + n).rjust(14) for n in names))
for b, (lo, hi) in enumerate(bands):
    row = f'{lo:.3f}-{hi:.3f}'.ljust(16)
    row += ''.join(f'{acc[n][b] * norm:12.4f}' for n in ['gps'] + names)
    row += f'{diffp[b] * norm:11.4f}'
    row += ''.join(f'{(cross[n][b] / acc["gps"][b]).real:7.3f}'
                   f'{abs(cross[n][b])**2 / (acc["gps"][b] * acc[n][b]):7.2f}' for n in names)
    print(row)
print('total'.ljust(16) + ''.join(f'{acc[n].sum() * norm:12.4f}' for n in ['gps'] + names)
      + f'{diffp.sum() * norm:11.4f}')
