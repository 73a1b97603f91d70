"""Per-seed diagnostics of estimators on a scenario: RMSE, regression of the position error on
the true GPS error, heading / hoff / k_v errors, GPS NIS and rejections, position sigma.

Writes one JSON (seed -> estimator -> diagnostics); summ.py tabulates it. From the repo root:

    python docs/results/igvc_gps_weight/analyze.py husky-multipath 1 20 ekf,ekf_igvc OUT.json

(estimator names are the registry's, as in `mc`; see REPORT.md, section 1).
"""

import json
import math
import sys

import numpy as np
from ddfuse.evaluation.montecarlo import calibration_truth
from harness import build, feed, gps_error_at, make_seed, truth_at, wrap


def diag(sim, d, est=None):
    t = d['t']
    tr = truth_at(sim, t)
    e = d['pose'][:, :2] - tr[:, :2]
    g = gps_error_at(sim, t)
    out = {'rmse': float(np.sqrt(np.mean((e**2).sum(1))))}
    # regression of estimate error on GPS error (both axes pooled)
    ef, gf = e.ravel(), g.ravel()
    beta = float(ef @ gf / (gf @ gf))
    out['beta'] = beta
    out['rmse_resid'] = float(np.sqrt(np.mean((ef - beta * gf)**2) * 2))
    out['corr'] = float(np.corrcoef(ef, gf)[0, 1])
    # error relative to GPS error (how far the estimate sits from the GPS-implied position)
    out['rms_e_minus_g'] = float(np.sqrt(np.mean(((e - g)**2).sum(1))))
    out['heading_rms_deg'] = float(
        np.degrees(np.sqrt(np.mean(wrap(d['pose'][:, 2] - tr[:, 2])**2))))
    names = d['names']
    S = d['state']
    truth = calibration_truth(sim)

    def idx(prefix):
        for i, n in enumerate(names):
            if n.startswith(prefix):
                return i

    ih, ikv, ikw = idx('hoff'), idx('k_v'), idx('k_w')
    tail = slice(len(S) // 10, None)
    out['hoff_err_final_deg'] = float(np.degrees(wrap(S[-1, ih] - truth['hoff'])))
    out['hoff_err_rms_deg'] = float(
        np.degrees(np.sqrt(np.mean(wrap(S[tail, ih] - truth['hoff'])**2))))
    out['kv_err_final'] = float(S[-1, ikv] - truth['k_v'])
    out['kw_err_final'] = float(S[-1, ikw] - truth['k_w'])
    out['kv_err_rms'] = float(np.sqrt(np.mean((S[tail, ikv] - truth['k_v'])**2)))
    out['pos_sigma_med'] = float(
        np.median(np.sqrt(0.5 * (d['cov'][:, 0, 0] + d['cov'][:, 1, 1]))))
    if est is not None:
        inn = [i for i in est.log.innovations if i.kind == 'gps']
        nis = np.array([i.nis for i in inn])
        acc = np.array([i.accepted for i in inn])
        out['gps_nis_mean'] = float(np.nanmean(nis)) if len(nis) else math.nan
        out['gps_n'] = len(nis)
        out['gps_rejected'] = int((~acc).sum()) if len(acc) else 0
        out['rejected'] = {f'{k[0]}|{k[1]}': v for k, v in est.log.rejected.items()}
        out['notes'] = [m for m in est.log.messages
                        if 'recover' in m.lower() or 'lock' in m.lower()][:5]
    return out, e, g


if __name__ == '__main__':
    scen = sys.argv[1]
    seeds = range(int(sys.argv[2]), int(sys.argv[3]) + 1)
    names = sys.argv[4].split(',')
    res = {}
    for s in seeds:
        sim, cfg, stream, pose = make_seed(scen, s)
        ests = build(cfg, stream, pose, names)
        out, ests = feed(stream, ests)
        res[s] = {}
        for n in out:
            r, e, g = diag(sim, out[n], ests[n])
            res[s][n] = r
        print(s, {n: round(res[s][n]['rmse'], 4) for n in out}, flush=True)
    with open(sys.argv[5], 'w') as f:
        json.dump(res, f, indent=1, default=float)
