"""The figure of seed 004's comparison: the g-h filter's fixed gain against the Kalman filter's
computed one (``ddfuse.ekf_baseline.gh_filter``), on the 1-D constant-velocity model.

``gh_comparison(seed)`` runs the Kalman filter, the g-h filter of the Kalata pair and three
hand-picked pairs on one drawn track and returns their position RMS errors (m, over the steps
after ``SETTLE``); ``plot_gh_comparison(out_png)`` draws the start of the track, the Kalman gain
converging to the Kalata pair, and the RMS errors. ``python -m ddfuse.evaluation.gh_figure
[OUT.png]`` writes docs/results/gh_filter.png (the figure docs/design/gh_filter.md shows).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from ddfuse.ekf_baseline.gh_filter import cv_kalman, cv_track, gh_run, kalata_gains
from ddfuse.evaluation.plots import save_png, subplots

DT, ACCEL, MEAS, STEPS, SETTLE = 0.1, 0.5, 0.3, 2000, 200  # s, m/s^2, m, steps, steps
# hand-picked pairs: the seed's "average" g = 0.5 with as large an h; trusting the readings;
# trusting the prediction
PAIRS = ((0.5, 0.5), (0.8, 0.2), (0.05, 0.002))
DEFAULT_OUT = Path("docs/results/gh_filter.png")


def gh_comparison(seed: int = 1) -> dict:
    """The track, each filter's estimates and its position RMS error (m) after SETTLE steps:
    keys 'truth', 'zs', 'kalman', 'gains', 'kalata' ((g, h), estimates), 'pairs' (list of
    ((g, h), estimates)), 'rms' (label -> m)."""
    rng = np.random.default_rng(seed)
    truth, zs = cv_track(rng, STEPS, DT, ACCEL, MEAS)
    est, gains = cv_kalman(zs, DT, ACCEL, MEAS, (0.0, 0.0), (1.0, 1.0))
    gh = kalata_gains(DT, ACCEL, MEAS)
    pairs = [(p, gh_run(zs, DT, 0.0, 0.0, *p)) for p in PAIRS]

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean((e[SETTLE:, 0] - truth[SETTLE:, 0]) ** 2)))

    kal = gh_run(zs, DT, 0.0, 0.0, *gh)
    out = {"truth": truth, "zs": zs, "kalman": est, "gains": gains, "kalata": (gh, kal),
           "pairs": pairs}
    out["rms"] = {"readings": float(np.sqrt(np.mean((zs[SETTLE:] - truth[SETTLE:, 0]) ** 2))),
                  "Kalman": rms(est), f"g-h Kalata ({gh[0]:.3f}, {gh[1]:.4f})": rms(kal)}
    out["rms"].update({f"g-h ({g:g}, {h:g})": rms(e) for (g, h), e in pairs})
    return out


def plot_gh_comparison(out: str | Path = DEFAULT_OUT, seed: int = 1) -> Path:
    """Write the three-panel PNG to ``out``; returns its path."""
    c = gh_comparison(seed)
    fig, (a0, a1, a2) = subplots(3, 1, figsize=(8.0, 10.0))
    n = 120
    t = DT * np.arange(1, STEPS + 1)
    a0.plot(t[:n], c["zs"][:n], ".", color="0.6", ms=3, label="readings")
    a0.plot(t[:n], c["truth"][:n, 0], "k-", lw=1.5, label="truth")
    a0.plot(t[:n], c["kalman"][:n, 0], "-", label="Kalman")
    a0.plot(t[:n], c["kalata"][1][:n, 0], "--", label="g-h, Kalata pair")
    for (g, h), e in c["pairs"]:
        a0.plot(t[:n], e[:n, 0], "-", lw=0.8, label=f"g-h ({g:g}, {h:g})")
    a0.set(xlabel="t (s)", ylabel="position (m)",
           title=f"constant velocity: acceleration {ACCEL} m/s^2, readings {MEAS} m, {1 / DT:g} Hz")
    a0.legend(fontsize=7)
    g, h = c["kalata"][0]
    a1.semilogy(c["gains"][:, 0], label="Kalman g_k")
    a1.semilogy(c["gains"][:, 1], label="Kalman h_k")
    a1.axhline(g, color="C0", ls=":", label=f"Kalata g = {g:.4f}")
    a1.axhline(h, color="C1", ls=":", label=f"Kalata h = {h:.4f}")
    a1.set(xlabel="step", ylabel="gain", xlim=(0, 300),
           title="the computed gain converges to a fixed g-h pair")
    a1.legend(fontsize=7)
    labels = list(c["rms"])
    vals = [c["rms"][k] for k in labels]
    a2.barh(labels, vals, color=["0.6", "C0", "C1", "C2", "C3", "C4"][:len(vals)])
    for i, v in enumerate(vals):
        a2.text(v, i, f" {v:.3f}", va="center", fontsize=8)
    a2.set(xlabel=f"position RMS error after step {SETTLE} (m)",
           title=f"{STEPS} steps, seed {seed}")
    a2.invert_yaxis()
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, out)
    return out


if __name__ == "__main__":
    print(plot_gh_comparison(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_OUT))
