"""Variants of ekf / ekf_igvc, one change at a time, on many seeds: RMSE, the filter's own
predicted position variance at the GPS fixes (H P H^T = S - R, a proxy for the GPS gain),
and the paired differences against a reference variant.

VARIANTS maps a name to a factory (cfg, stream, pose) -> estimator; the other scripts of this
directory import it. From the repo root (seeds FIRST..LAST; OUT.json and the reference, the
first name by default, are optional):

    python docs/results/igvc_gps_weight/variants.py husky-multipath 1 20 ekf,ekf_igvc,ekf_R1.5 \\
        OUT.json [REF]
"""

import json
import math
import sys
from dataclasses import replace

import numpy as np
from ddfuse.ekf_baseline.igvc import IgvcEkf, IgvcNoise
from ddfuse.ekf_baseline.unicycle import ProcessNoise, UnicycleEkf
from ddfuse.estimation.measurements import ForwardAccel, GpsFix
from ddfuse.estimation.smoother import FixedLagSmoother
from harness import feed, make_seed, truth_at

IG_DEFAULT = IgvcNoise(position_psd=0.0, heading_psd=0.0)  # what slip 0/0/0 gives


class Drop:
    """Wrap an estimator, withholding messages of the given types."""

    def __init__(self, est, *types):
        self.e, self.types = est, types
        self.log = est.log

    def process(self, m):
        if not isinstance(m, self.types):
            self.e.process(m)

    def estimate(self):
        return self.e.estimate()

    def finish(self):
        self.e.finish()

    def __getattr__(self, k):
        return getattr(self.e, k)


class ScaleGps(Drop):
    """Wrap an estimator, scaling every GPS fix's covariance by c (the stream is untouched)."""

    def __init__(self, est, c):
        super().__init__(est)
        self.c = c

    def process(self, m):
        if isinstance(m, GpsFix):
            m = replace(m, cov=np.asarray(m.cov) * self.c)
        self.e.process(m)


def igvc(cfg, st, pose, **kw):
    return IgvcEkf(cfg, initial_pose=pose, datum=st.datum, **kw)


def igvc_noise(**kw):
    """ekf_igvc with IG_DEFAULT changed by kw."""
    return lambda cfg, st, pose: igvc(cfg, st, pose, noise=replace(IG_DEFAULT, **kw))


def igvc_noaccel(**kw):
    """ekf_igvc without the accelerometer, with IG_DEFAULT changed by kw."""
    return lambda cfg, st, pose: Drop(igvc(cfg, st, pose, noise=replace(IG_DEFAULT, **kw)),
                                      ForwardAccel)


def smoother(cfg, st, pose):
    return FixedLagSmoother(cfg, initial_pose=pose, landmarks=st.landmarks,
                            lag=cfg.smoother.lag, lagged=False)


# what the default ekf derives on husky (twist_densities of max_accel, periods)
EKF_DENS = dict(acc=0.1655710962742286, yaw_acc=0.09037579450177617, pos_long=0.0, pos_lat=0.0,
                heading=0.0)


def ekf_with(**kw):
    d = dict(EKF_DENS)
    d.update(kw)
    return lambda cfg, st, pose: UnicycleEkf(cfg, initial_pose=pose, noise=ProcessNoise(**d))


VARIANTS = {
    'ekf': lambda cfg, st, pose: UnicycleEkf(cfg, initial_pose=pose),
    'ekf_igvc': igvc,
    # igvc without the accelerometer
    'igvc_noaccel': lambda cfg, st, pose: Drop(igvc(cfg, st, pose), ForwardAccel),
    # igvc with the ekf's yaw-acceleration density (0.0904^2)
    'igvc_yawq_ekf': igvc_noise(yaw_accel_psd=0.0904**2),
    'igvc_same': lambda cfg, st, pose: igvc(cfg, st, pose, noise=IG_DEFAULT),
    'igvc_icc': lambda cfg, st, pose: igvc(cfg, st, pose, motion='icc'),
    'ekf_world': lambda cfg, st, pose: UnicycleEkf(cfg, initial_pose=pose, pose_error='world'),
    'ekf_euler': lambda cfg, st, pose: UnicycleEkf(cfg, initial_pose=pose, motion='euler'),
}


def add_variant(name, fn):
    VARIANTS[name] = fn


# ---- process-noise / GPS-weight variants (added after the first findings)
for f in (0.25, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.5, 2.0):
    add_variant(f'ekf_acc{f}', ekf_with(acc=EKF_DENS['acc'] * f))
for c in (0.5, 0.8, 1.25, 1.5, 2.0, 3.0, 5.0, 10.0):
    add_variant(f'ekf_R{c}',
                lambda cfg, st, pose, c=c: ScaleGps(UnicycleEkf(cfg, initial_pose=pose), c))
    add_variant(f'igvc_R{c}', lambda cfg, st, pose, c=c: ScaleGps(igvc(cfg, st, pose), c))
for f in (0.3, 0.5, 2.0, 4.0, 10.0):
    add_variant(f'igvc_jerk{f}', igvc_noise(jerk_psd=0.5 * f))
for f in (10.0, 100.0):
    add_variant(f'igvc_noaccel_jerk{f}', igvc_noaccel(jerk_psd=0.5 * f))
for f in (1e-9, 1e-8, 1e-7, 1e-5):
    add_variant(f'igvc_frame{f:g}', igvc_noise(frame_psd=f))
    add_variant(f'igvc_na_j100_frame{f:g}', igvc_noaccel(frame_psd=f, jerk_psd=50.0))
add_variant('igvc_na_j100_f9_slip0', igvc_noaccel(frame_psd=1e-9, jerk_psd=50.0, slip_var=1e-10))
add_variant('igvc_na_j100_f9_slip0_init',
            igvc_noaccel(frame_psd=1e-9, jerk_psd=50.0, slip_var=1e-10, init_speed_std=1.0,
                         init_yaw_rate_std=0.5))
add_variant('igvc_slip0', igvc_noise(slip_var=1e-10))
add_variant('igvc_slip1e-3', igvc_noise(slip_var=1e-3))
add_variant('smoother', smoother)
add_variant('smoother_R1.5', lambda cfg, st, pose: ScaleGps(smoother(cfg, st, pose), 1.5))
for f in (300.0, 1000.0, 3000.0):
    add_variant(f'igvc_na_f9_jerk{f:g}', igvc_noaccel(frame_psd=1e-9, jerk_psd=0.5 * f))
add_variant('igvc_R0.667', lambda cfg, st, pose: ScaleGps(igvc(cfg, st, pose), 2.0 / 3.0))


def run(scen, seeds, names, outpath=None, ref=None):
    res = {}
    for s in seeds:
        sim, cfg, stream, pose = make_seed(scen, s)
        ests = {n: VARIANTS[n](cfg, stream, pose) for n in names}
        out, ests = feed(stream, ests)
        res[s] = {}
        for n in names:
            d = out[n]
            tr = truth_at(sim, d['t'])
            e = d['pose'][:, :2] - tr[:, :2]
            inn = [i for i in ests[n].log.innovations if i.kind == 'gps' and i.cov is not None]
            c = getattr(ests[n], 'c', 1.0)
            hph = np.array([np.trace(np.asarray(i.cov)) / 2 - c for i in inn])
            res[s][n] = {'rmse': float(np.sqrt(np.mean((e**2).sum(1)))),
                         'hph_med': float(np.median(hph)),
                         'rej': int(sum(v for k, v in ests[n].log.rejected.items()
                                        if k[0] == '/fix'))}
        print(s, ' '.join(f"{n}={res[s][n]['rmse']:.4f}/{res[s][n]['hph_med']:.5f}"
                          for n in names), flush=True)
    if outpath:
        with open(outpath, 'w') as f:
            json.dump(res, f, indent=1)
    summary(res, names, ref or names[0])
    return res


def summary(res, names, ref):
    seeds = sorted(res)
    print(f'\n{len(seeds)} seeds; reference {ref}')
    print('variant'.ljust(18) + 'rmse_mean  rmse_no14  hph_med(m^2)  sigma_gps(m)  d_vs_ref(mm)'
          '  wins_vs_ref  mean_ratio')
    for n in names:
        r = np.array([res[s][n]['rmse'] for s in seeds])
        h = np.array([res[s][n]['hph_med'] for s in seeds])
        r0 = np.array([res[s][ref]['rmse'] for s in seeds])
        m14 = np.array([s != 14 for s in seeds])
        d = (r - r0)[m14] * 1000
        se = d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else 0
        print(n.ljust(18) + f'{r.mean():9.4f}  {r[m14].mean():9.4f}  {np.median(h):12.5f}  '
              f'{np.sqrt(np.median(h)):12.4f}  {d.mean():+7.1f}+-{se:4.1f}  '
              f'{int((d < 0).sum()):3d}/{len(d)}   {np.mean(r[m14] / r0[m14]):.3f}')


if __name__ == '__main__':
    scen = sys.argv[1]
    a, b = int(sys.argv[2]), int(sys.argv[3])
    names = sys.argv[4].split(',')
    run(scen, range(a, b + 1), names, sys.argv[5] if len(sys.argv) > 5 else None,
        sys.argv[6] if len(sys.argv) > 6 else None)
