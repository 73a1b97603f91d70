"""The filters' own standard deviations at the GPS fixes after 50 s (median over fixes, mean of
the variance over seeds): position along / across the heading (for ekf_igvc the lat/lon block
in metres, which is what the GPS sees), hoff, k_v, k_w, gyro bias, speed, heading.

    python docs/results/igvc_gps_weight/sig.py husky-multipath ekf,ekf_igvc,igvc_noaccel 1 5
"""

import sys

import numpy as np
from ddfuse.ekf_baseline.igvc import LAT, LON
from ddfuse.estimation.measurements import GpsFix
from harness import make_seed
from variants import VARIANTS

scen = sys.argv[1]
names = sys.argv[2].split(',')
seeds = range(int(sys.argv[3]), int(sys.argv[4]) + 1)
acc = {n: [] for n in names}
for s in seeds:
    sim, cfg, stream, pose = make_seed(scen, s)
    ests = {n: VARIANTS[n](cfg, stream, pose) for n in names}
    rows = {n: [] for n in names}
    for m in stream.measurements:
        for e in ests.values():
            e.process(m)
        if isinstance(m, GpsFix) and m.t - sim.t0 > 50:
            for n, e in ests.items():
                est = e.estimate()
                nm = est.state_names
                P = est.state_cov
                x = est.state
                psi = est.pose[2]
                c, sn = np.cos(psi), np.sin(psi)
                Rm = np.array([[c, sn], [-sn, c]])
                if 'lat' in nm:
                    # the lat/lon block in metres (what the GPS sees)
                    r = e.radius
                    cl = np.cos(x[LAT])
                    J = np.zeros((2, len(x)))
                    J[0, LON] = r * cl
                    J[1, LAT] = r
                    Pp = J @ P @ J.T
                else:
                    Pp = P[:2, :2]
                Pb = Rm @ Pp @ Rm.T
                ih = [i for i, k in enumerate(nm) if k.startswith('hoff')][0]
                ikv = nm.index('k_v')
                ikw = nm.index('k_w')
                ib = [i for i, k in enumerate(nm) if k.startswith('bg')][0]
                iv = 3 if 'v_odo' in nm else nm.index('v')
                ipsi = nm.index('psi')
                rows[n].append([Pb[0, 0], Pb[1, 1], P[ih, ih], P[ikv, ikv], P[ikw, ikw],
                                P[ib, ib], P[iv, iv], P[ipsi, ipsi]])
    for n in names:
        acc[n].append(np.median(np.array(rows[n]), 0))
print('median over fixes after 50 s, mean over seeds: sigma along, cross (m), hoff (deg), '
      'k_v, k_w, bg(deg/s), v (m/s), psi(deg)')
for n in names:
    A = np.sqrt(np.array(acc[n]).mean(0))
    A[2] = np.degrees(A[2])
    A[5] = np.degrees(A[5])
    A[7] = np.degrees(A[7])
    print(n.ljust(14), ' '.join(f'{v:.5f}' for v in A))
