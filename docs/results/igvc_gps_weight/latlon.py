"""ekf_igvc carries the position twice: (lat, lon), which the GPS updates, and (x, y), which it
reports and which follows only through their correlation. RMSE of each against the truth, for
three frame_psd values, on husky-multipath seeds 1-20 without 14 (no arguments).

    python docs/results/igvc_gps_weight/latlon.py   # from the repo root
"""

import math

import numpy as np
from harness import feed, make_seed, truth_at
from variants import VARIANTS

acc = {}
for s in [x for x in range(1, 21) if x != 14]:
    sim, cfg, stream, pose = make_seed('husky-multipath', s)
    names = ['ekf_igvc', 'igvc_frame1e-09', 'igvc_frame1e-05']
    out, ests = feed(stream, {n: VARIANTS[n](cfg, stream, pose) for n in names})
    for n in names:
        d = out[n]
        nm = d['names']
        S = d['state']
        lat, lon = np.degrees(S[:, nm.index('lat')]), np.degrees(S[:, nm.index('lon')])
        R = ests[n].radius
        la0, lo0 = math.radians(stream.datum[0]), math.radians(stream.datum[1])
        # east, north on the filter's own sphere
        en = np.column_stack([R * math.cos(la0) * (np.radians(lon) - lo0),
                              R * (np.radians(lat) - la0)])
        tr = truth_at(sim, d['t'])[:, :2]
        r_xy = np.sqrt(np.mean(((d['pose'][:, :2] - tr)**2).sum(1)))
        r_ll = np.sqrt(np.mean(((en - tr)**2).sum(1)))
        gap = np.sqrt(np.mean(((en - d['pose'][:, :2])**2).sum(1)))
        end_gap = np.sqrt(((en[-1] - d['pose'][-1, :2])**2).sum())
        acc.setdefault(n, []).append((r_xy, r_ll, gap, end_gap))
for n, v in acc.items():
    v = np.array(v)
    print(f'{n:18s} RMSE reported x,y {v[:, 0].mean():.4f}  RMSE lat/lon {v[:, 1].mean():.4f}  '
          f'rms |x,y - lat/lon| {v[:, 2].mean():.4f}  at the end {v[:, 3].mean():.4f} m  '
          '(19 seeds)')
