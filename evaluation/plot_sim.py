"""Plot a simulated scenario: truth, GPS fixes, dead reckoning from the wheel odometry.

``plot_sim(result, out_png)`` draws, in the local frame (x east, y north, metres):
the true path, the GPS fixes (converted back to ENU from their lat/lon; outliers marked), the
landmarks and the sightings' count, and the dead reckoning of the wheel odometry (odometry twist,
or wheel speeds through the NOMINAL geometry) started from the true initial pose. A second panel
shows the dead-reckoning position error over time. The command ``ddfuse plot-sim husky --seed 0
-o husky.png`` (``evaluation/cli/plot_sim.py``) simulates a scenario and plots it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ddfuse.estimation.geodesy import geodetic_to_enu
from ddfuse.evaluation.atomic_files import replacing
from ddfuse.evaluation.plots import subplots  # a Figure on its own canvas: the backend left alone
from ddfuse.evaluation.simulate import SimResult, se2_step, wrap


def dead_reckoning(res: SimResult) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Integrate the measured odometry twist (nominal geometry) from the true start pose.

    Each twist sample is applied over its own counting interval (it is that interval's mean), as
    a constant twist. Returns (t s, x m, y m, yaw rad wrapped) at the sample stamps, with the
    start pose prepended at the first interval's opening."""
    enc = res.encoders
    dt = np.diff(enc.t, prepend=enc.t[0] - 1.0 / res.scenario.encoders.rate)
    x0, y0, yaw0 = res.scenario.trajectory.start
    # Vectorised like the truth: heading by cumulative sum, then rotated exact increments.
    yaw_k = yaw0 + np.concatenate([[0.0], np.cumsum(enc.yaw_rate * dt)])
    dx, dy, _ = se2_step(0.0, 0.0, yaw_k[:-1], enc.v, enc.yaw_rate, dt)
    xs = x0 + np.concatenate([[0.0], np.cumsum(dx)])
    ys = y0 + np.concatenate([[0.0], np.cumsum(dy)])
    t = np.concatenate([[enc.t[0] - dt[0]], enc.t])
    return t, xs, ys, wrap(yaw_k)


def plot_sim(res: SimResult, out: str | Path, title: str | None = None) -> Path:
    """Draw the scenario to a PNG at ``out`` and return its path."""
    out = Path(out)
    sc = res.scenario
    gt = res.ground_truth
    t_dr, x_dr, y_dr, _ = dead_reckoning(res)
    fig, (ax, ax2) = subplots(1, 2, figsize=(14, 6.5), gridspec_kw={"width_ratios": [1.6, 1.0]})
    ax.plot(gt.x, gt.y, "-", color="k", lw=1.4, label="truth")
    ax.plot(gt.x[0], gt.y[0], "o", color="k", ms=7, label="start")
    ax.plot(x_dr, y_dr, "-", color="tab:orange", lw=1.0,
            label="dead reckoning (odometry, nominal geometry)")
    if res.gps is not None and len(res.gps.t):
        e, n, _ = geodetic_to_enu(res.gps.lat, res.gps.lon, res.gps.alt, *sc.datum)
        good = ~res.gps.outlier
        ax.plot(e[good], n[good], ".", color="tab:blue", ms=3, alpha=0.6,
                label=f"GPS fixes ({good.sum()})")
        if (~good).any():
            ax.plot(e[~good], n[~good], "x", color="tab:red", ms=7,
                    label=f"GPS outliers ({(~good).sum()})")
        for a, b in sc.gps.outages:
            sel = (gt.t >= a) & (gt.t < b)
            if sel.any():
                ax.plot(gt.x[sel], gt.y[sel], "-", color="tab:purple", lw=3, alpha=0.5,
                        label=f"GPS outage {a:g}-{b:g} s")
    if res.landmarks is not None:
        lm = res.landmarks
        counts = np.bincount(lm.index, minlength=len(lm.ids))
        ax.scatter(lm.positions[:, 0], lm.positions[:, 1], marker="^", s=60, c="tab:green",
                   label=f"landmarks ({len(lm.t)} sightings)", zorder=3)
        for i, p in enumerate(lm.positions):
            ax.annotate(f"{lm.ids[i]} ({counts[i]})", p, fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x east [m]" if sc.datum else "x [m]")
    ax.set_ylabel("y north [m]" if sc.datum else "y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or f"{sc.name} (seed {res.seed}, {sc.duration:g} s)")

    tx, ty, _, _, _ = res.truth.at(t_dr)
    ax2.plot(t_dr, np.hypot(x_dr - tx, y_dr - ty), color="tab:orange",
             label="dead-reckoning position error")
    if res.gps is not None and len(res.gps.t):
        err = np.hypot(*(res.gps.enu[:, :2] - res.gps.true_enu[:, :2]).T)
        ax2.plot(res.gps.t_measured, err, ".", ms=2, color="tab:blue",
                 label="GPS horizontal error")
        ax2.set_yscale("symlog", linthresh=1.0)
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("error [m]")
    ax2.grid(True, alpha=0.3)
    ax2.legend(loc="upper left", fontsize=8)
    ax2.set_title("errors against the truth")
    fig.tight_layout()
    with replacing(out, "wb") as f:  # whole or not at all
        fig.savefig(f, dpi=110, format=Path(out).suffix.lstrip(".") or None)
    return out
