"""Landmark sightings against the ground truth, and where a run's position error lies (the
figures of docs/design/tuning.md, session 21: why the tuned MRCLAM config loses ATE).

    python examples/landmark_residuals.py residuals BAG [-c CONFIG]
    python examples/landmark_residuals.py since-sighting BAG [-c CONFIG] RUN_DIR... [--estimator E]

``residuals``: each sighting's range and bearing minus what the ground-truth pose (interpolated
at its stamp) and the map give; their robust sigma (1.4826 MAD), per range band, against the true
yaw rate, and how sightings of *different* landmarks with one stamp err together (the
correlation of their bearing errors; the robust sigma of half their difference, the part that
is not common to the frame, and of their mean). ``since-sighting``: a run's position error (no
alignment: the runs start from the ground-truth pose in the map's frame) binned by the time
since the last sighting at each of its stamps, RMS and share of the squared error per bin.
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

BINS = (0.0, 0.5, 2.0, 5.0, 10.0, 20.0, 40.0)  # s since the last sighting


def _robust(x: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def _read(bag: str, config: str | None):
    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config

    cfg = load_config(Path(config) if config else Path(bag).with_suffix(".yaml"))
    return read_stream(Path(bag), cfg)


def residuals(stream) -> str:
    from ddfuse.estimation.measurements import LandmarkObservation

    gt = np.array([(p.t, p.x, p.y, p.yaw) for p in stream.ground_truth])
    if not len(gt):
        raise SystemExit("landmark_residuals: the bag has no ground truth")
    yaw = np.unwrap(gt[:, 3])
    rate = np.gradient(yaw, gt[:, 0])
    rows = []  # (t, landmark, range error m, bearing error rad, true range m, true yaw rate)
    for m in stream.measurements:
        if type(m) is not LandmarkObservation or m.landmark_id not in stream.landmarks:
            continue
        x, y, psi = (np.interp(m.t, gt[:, 0], c) for c in (gt[:, 1], gt[:, 2], yaw))
        lx, ly = stream.landmarks[m.landmark_id]
        r = math.hypot(lx - x, ly - y)
        b = math.atan2(ly - y, lx - x) - psi
        eb = (m.bearing - b + math.pi) % (2.0 * math.pi) - math.pi if m.has_bearing else np.nan
        rows.append((m.t, m.landmark_id, m.range - r, eb, r, np.interp(m.t, gt[:, 0], rate)))
    t, er, eb, r, w = (np.array([row[i] for row in rows], float) for i in (0, 2, 3, 4, 5))
    out = [f"{len(rows)} sightings: range error robust sigma {_robust(er):.4f} m, bearing "
           f"{_robust(eb):.4f} rad", "", "| true range | sightings | range error median, robust "
           "sigma (m) | bearing error median, robust sigma (rad) |", "|---|---|---|---|"]
    for lo, hi in ((0, 1.5), (1.5, 3), (3, 5), (5, 10)):
        k = (r >= lo) & (r < hi)
        if not k.any():
            continue
        out.append(f"| {lo}-{hi} m | {k.sum()} | {np.median(er[k]):+.3f}, {_robust(er[k]):.3f} | "
                   f"{np.median(eb[k]):+.4f}, {_robust(eb[k]):.4f} |")
    slope = np.polyfit(w, eb, 1)[0]
    out += ["", f"bearing error against the true yaw rate: correlation "
            f"{np.corrcoef(w, eb)[0, 1]:+.3f}, slope {slope:+.4f} s"]
    frames: dict[float, list] = defaultdict(list)
    for row in rows:
        frames[row[0]].append(row)
    pairs = np.array([(a[3], b[3], a[2], b[2]) for v in frames.values()
                      for i, a in enumerate(v) for b in v[i + 1:] if a[1] != b[1]])
    if len(pairs):
        half = (pairs[:, 0] - pairs[:, 1]) / math.sqrt(2.0)
        shared = sum(len({row[1] for row in v}) for v in frames.values()
                     if len({row[1] for row in v}) > 1)
        out += [f"sightings of different landmarks with one stamp: {len(pairs)} pairs "
                f"({shared} of the sightings); bearing errors correlated "
                f"{np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1]:+.2f}, range errors "
                f"{np.corrcoef(pairs[:, 2], pairs[:, 3])[0, 1]:+.2f}; robust sigma of half the "
                f"bearing difference {_robust(half):.4f} rad, of the pair's mean "
                f"{_robust(pairs[:, :2].mean(axis=1)):.4f} rad"]
    return "\n".join(out)


def since_sighting(stream, runs: list[str], estimator: str) -> str:
    from ddfuse.estimation.measurements import LandmarkObservation

    seen = np.array(sorted({m.t for m in stream.measurements
                            if type(m) is LandmarkObservation}))
    heads = [f"{a:g}-{b:g} s" for a, b in zip(BINS[:-1], BINS[1:], strict=True)]
    out = ["| run | all | " + " | ".join(heads + [f"> {BINS[-1]:g} s or none yet"]) + " |",
           "|---" * (len(heads) + 3) + "|"]
    for d in runs:
        gt = np.loadtxt(Path(d) / "ground_truth.tum")
        e = np.loadtxt(Path(d) / f"{estimator}.tum")
        t = e[:, 0]
        err2 = (e[:, 1] - np.interp(t, gt[:, 0], gt[:, 1])) ** 2 + (
            e[:, 2] - np.interp(t, gt[:, 0], gt[:, 2])) ** 2
        i = np.searchsorted(seen, t, side="right") - 1
        since = np.where(i >= 0, t - seen[np.maximum(i, 0)], np.inf)
        cells = []
        for a, b in zip(BINS, BINS[1:] + (np.inf,), strict=True):
            k = (since >= a) & ((since < b) if b < np.inf else True)
            cells.append(f"{math.sqrt(err2[k].mean()):.3f} ({k.sum()}, "
                         f"{100 * err2[k].sum() / err2.sum():.0f} %)" if k.any() else "")
        out.append(f"| {Path(d).name} | {math.sqrt(err2.mean()):.3f} | " + " | ".join(cells)
                   + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("residuals")
    r.add_argument("bag")
    r.add_argument("-c", "--config")
    s = sub.add_parser("since-sighting")
    s.add_argument("bag")
    s.add_argument("-c", "--config")
    s.add_argument("runs", nargs="+")
    s.add_argument("--estimator", default="smoother_lagged")
    a = ap.parse_args(argv)
    stream = _read(a.bag, a.config)
    print(residuals(stream) if a.cmd == "residuals" else
          since_sighting(stream, a.runs, a.estimator))


if __name__ == "__main__":
    main()
