"""Step response to a GPS perturbation: run the estimators on the original stream and on a copy
whose fixes from t_step on are moved by (de, dn) metres; the difference of the estimates is the
estimators' response to that GPS error (nearly linear for these filters).

step.py uses `perturbed` for the variants of variants.py (REPORT.md, section 2b). Run alone it
does the same for registry estimators (a 1 m step at 200 s, east then north):

    python docs/results/igvc_gps_weight/perturb.py husky-multipath ekf,ekf_igvc 1 6
"""

import copy
import sys
from dataclasses import replace

import numpy as np
from ddfuse.estimation import geodesy
from ddfuse.estimation.measurements import GpsFix
from harness import build, feed, make_seed


def perturbed(stream, datum, t_from, de, dn, t_to=np.inf):
    s2 = copy.copy(stream)
    ms = []
    for m in stream.measurements:
        if isinstance(m, GpsFix) and t_from <= m.t < t_to and m.enu is not None:
            e, n, u = m.enu
            e, n = e + de, n + dn
            lat, lon, alt = geodesy.enu_to_geodetic(e, n, u, *datum)
            m = replace(m, lat=lat, lon=lon, alt=alt, enu=(e, n, u))
        ms.append(m)
    s2.measurements = ms
    return s2


def response(scen, seed, names, t_rel, de, dn, t_to_rel=np.inf, factory=None):
    sim, cfg, stream, pose = make_seed(scen, seed)
    datum = stream.datum
    mk = factory or (lambda: build(cfg, stream, pose, names))
    o0, _ = feed(stream, mk())
    st2 = perturbed(stream, datum, sim.t0 + t_rel, de, dn, sim.t0 + t_to_rel)
    mk2 = factory or (lambda: build(cfg, st2, pose, names))
    o1, _ = feed(st2, mk2())
    res = {}
    for n in o0:
        a, b = o0[n], o1[n]
        k = min(len(a['t']), len(b['t']))
        assert np.allclose(a['t'][:k], b['t'][:k])
        t = a['t'][:k] - sim.t0
        dp = b['pose'][:k] - a['pose'][:k]
        ds = b['state'][:k] - a['state'][:k] if a['state'] is not None else None
        res[n] = (t, dp, ds, a['names'])
    return res


if __name__ == '__main__':
    scen = sys.argv[1]
    names = sys.argv[2].split(',')
    seeds = range(int(sys.argv[3]), int(sys.argv[4]) + 1)
    lags = [0.5, 1, 2, 5, 10, 20, 30, 60, 100, 150]
    agg = {n: [] for n in names}
    for s in seeds:
        for (de, dn) in ((1.0, 0.0), (0.0, 1.0)):
            r = response(scen, s, names, 200.0, de, dn)
            for n, (t, dp, ds, sn) in r.items():
                ax = 0 if de else 1
                row = [np.interp(200.0 + L, t, dp[:, ax]) for L in lags]
                ih = [i for i, x in enumerate(sn) if x.startswith('hoff')][0]
                ikv = sn.index('k_v')
                row += [np.degrees(np.interp(350.0, t, ds[:, ih])), np.interp(350.0, t, ds[:, ikv])]
                agg[n].append(row)
    print('step response of position (m) to a 1 m GPS step at 200 s, mean over seeds x 2 axes; '
          'then hoff (deg) and k_v change at 350 s (rms)')
    print('estimator'.ljust(18) + ''.join(f'{L:>7}s' for L in lags) + '   hoff_deg   k_v')
    for n in names:
        A = np.array(agg[n])
        print(n.ljust(18) + ''.join(f'{v:8.3f}' for v in A[:, :len(lags)].mean(0))
              + f'{np.sqrt((A[:, -2]**2).mean()):10.3f}{np.sqrt((A[:, -1]**2).mean()):9.4f}')
