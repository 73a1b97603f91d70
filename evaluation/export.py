"""Write and read trajectories as TUM (evo-compatible) and as CSV with the pose covariance."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from ddfuse.estimation.runner import Trajectory
from ddfuse.evaluation.atomic_files import replacing

CSV_COLUMNS = ["t", "x", "y", "yaw"] + [f"cov_{a}{b}" for a in ("x", "y", "yaw")
                                         for b in ("x", "y", "yaw")]


_CHUNK = 4096  # rows formatted per ``%``: a few MB of Python floats at a time, whatever the length


def _write_rows(path: Path, n: int, rows: Callable[[int, int], np.ndarray], fmt: str,
                header: str | None = None) -> None:
    """What ``np.savetxt(path, rows(0, n), fmt=fmt, header=header, comments="")`` writes, byte
    for byte, formatted in one ``%`` per ``_CHUNK`` rows instead of one per row (4x faster) and
    written as it goes: ``rows(a, b)`` gives rows a..b-1 (a (b - a, k) array), so that neither
    a long track's text nor its whole table of rows is in memory at once; whole or not at all
    (``atomic_files.replacing``)."""
    with replacing(path) as f:
        if header is not None:
            f.write(header + "\n")
        line = fmt + "\n"
        for a in range(0, n, _CHUNK):
            part = rows(a, min(a + _CHUNK, n))
            f.write((line * len(part)) % tuple(part.ravel().tolist()))


def write_tum(path: Path, traj: Trajectory) -> None:
    """TUM format: ``t x y z qx qy qz qw`` per line (z = 0, yaw about z); NaN yaw -> 0."""
    def rows(a: int, b: int) -> np.ndarray:
        yaw = np.nan_to_num(traj.pose[a:b, 2])
        z = np.zeros(b - a)
        return np.column_stack([traj.t[a:b], traj.pose[a:b, 0], traj.pose[a:b, 1], z, z, z,
                                np.sin(yaw / 2), np.cos(yaw / 2)])

    _write_rows(path, len(traj), rows, "%.9f %.6f %.6f %.6f %.9f %.9f %.9f %.9f")


def write_csv(path: Path, traj: Trajectory) -> None:
    """CSV: t (s), x, y (m), yaw (rad) and the 3x3 covariance of (x, y, yaw), row-major.

    The stamp is written in fixed point (ns): bag stamps are epoch seconds (~1.7e9), which a
    significant-digit format would round to whole seconds. NaN stays NaN (no heading, no
    covariance)."""
    def rows(a: int, b: int) -> np.ndarray:
        cov = traj.cov_at(slice(a, b)).reshape(b - a, 9)
        return np.column_stack([traj.t[a:b], traj.pose[a:b], cov])

    _write_rows(path, len(traj), rows, ",".join(["%.9f"] + ["%.10g"] * 12),
                header=",".join(CSV_COLUMNS))


def read_csv(path: Path) -> Trajectory:
    """Read a CSV written by write_csv back into a Trajectory."""
    a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2).reshape(-1, len(CSV_COLUMNS))
    return Trajectory(a[:, 0], a[:, 1:4], a[:, 4:].reshape(-1, 3, 3))


def read_tum(path: Path) -> Trajectory:
    """Read a TUM file written by write_tum (or evo) into a Trajectory (yaw from the quaternion)."""
    a = np.loadtxt(path, ndmin=2)
    qx, qy, qz, qw = a[:, 4], a[:, 5], a[:, 6], a[:, 7]
    # The scale-invariant form: the file's 9-decimal quaternion is not exactly unit length.
    yaw = np.arctan2(2 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)
    n = len(a)
    return Trajectory(a[:, 0], np.column_stack([a[:, 1], a[:, 2], yaw]),
                      np.full((n, 3, 3), np.nan))
