"""The per-sample noise of the odometry-driven EKF's inputs, from their own sample scatter.

In ``ekf_landmark`` the odometry (wheel speeds, or odometry v and yaw rate) is the control input,
so its per-sample noise and the robot's slip both enter as process noise, over the same steps,
in the same body-frame directions: the innovations' likelihood cannot tell them apart (the
estimates' correlation near -1: docs/design/tuning.md), and the search hands the input's part
to the slip or back. What the likelihood cannot see, the series
shows: a sensor's white noise is what its samples scatter about a motion that is smooth at the
sample rate. The order-k differences of samples x_j = s(t_j) + e_j, e white with sigma^2,
have variance C(2k, k) sigma^2 plus the k-th difference of the motion s, which shrinks by a
factor dt per order; so sigma from the order-3 differences' RMS about 0 over sqrt(C(6, 3)) =
sqrt(20) (those beyond ``TRIM`` robust sigmas left out), checked against the order-2
differences' (within ``AGREE``: a larger order-2 value says the motion, not the noise, fills
the differences).

Not measured (the likelihood decides, as for any other value) where more than half of the
order-3 differences are exactly 0 (held or coarsely quantised values: commanded velocities, a
twist republished at a higher rate), where fewer than ``MIN_WINDOWS`` windows remain, or where
the two orders disagree. Windows whose samples are all exactly 0 (the robot at rest: an encoder
is quiet then, its noise when moving is what the filter needs) or that span a gap longer than
``GAP`` times the median period are left out. Units are the series' own (rad/s for wheel
speeds, m/s and rad/s for odometry). Pure math; no printing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ddfuse.estimation.measurements import Stream, WheelOdometry, WheelSpeeds

ORDER = 3  # differences of this order give sigma
AGREE = 1.25  # the order-2 differences' sigma at most this times the order-3's
MIN_WINDOWS = 100  # moving windows needed for a value
GAP = 1.5  # a window spanning a period longer than this times the median is left out
CHUNKS = 10  # the standard error from the spread of sigma over this many stretches
MAD_SIGMA = 1.4826  # a Gaussian's sigma over its median absolute deviation
TRIM = 4.0  # differences beyond this many robust sigmas are a gap's or a jump's, not noise


@dataclass(frozen=True)
class Scatter:
    """What one input's series shows: ``sigma`` (its unit, per sample) and the standard error
    of its log (``se_log``) from ``windows`` order-3 difference windows, or ``sigma`` None and
    ``reason`` saying why not."""

    sigma: float | None
    se_log: float | None
    windows: int
    reason: str


def _windows(t: np.ndarray, x: np.ndarray, order: int) -> np.ndarray:
    """The order-``order`` differences of ``x`` (samples at times ``t``, s) over the windows
    that are neither all 0 nor span a gap."""
    if len(x) <= order:
        return np.zeros(0)
    d = np.diff(x, order)
    dt = np.diff(t)
    period = float(np.median(dt)) if len(dt) else 0.0
    span = np.lib.stride_tricks.sliding_window_view(dt, order).max(axis=1)
    rest = np.lib.stride_tricks.sliding_window_view(x == 0.0, order + 1).all(axis=1)
    return d[(span <= GAP * period) & ~rest]


def _sigma(d: np.ndarray, order: int) -> float:
    """Sigma of the samples' noise from their order-``order`` differences ``d``: the RMS of
    those within ``TRIM`` robust sigmas of 0 (a gap's or a jump's difference left out), 0
    where more than half are 0. The RMS, not the MAD alone: of quantised samples (encoder
    counts) the MAD is a whole number of counts, so it moves in steps."""
    mad = MAD_SIGMA * float(np.median(np.abs(d)))
    if mad <= 0.0:
        return 0.0
    kept = d[np.abs(d) <= TRIM * mad]
    return math.sqrt(float(np.mean(kept * kept)) / math.comb(2 * order, order))


def sample_scatter(series: list[tuple[np.ndarray, np.ndarray]]) -> Scatter:
    """The white noise of one quantity measured by the series ``(t, x)`` (several: the
    wheels of one sensor, pooled), module docstring."""
    d3 = [_windows(t, x, ORDER) for t, x in series]
    d2 = np.concatenate([_windows(t, x, ORDER - 1) for t, x in series])
    n = sum(len(d) for d in d3)
    if n < MIN_WINDOWS:
        return Scatter(None, None, n, f"{n} windows of moving samples, under {MIN_WINDOWS}")
    whole = np.concatenate(d3)
    sigma = _sigma(whole, ORDER)
    if sigma <= 0.0:
        return Scatter(None, None, n, (
            f"more than half of its {n} order-{ORDER} differences are 0: held or quantised "
            "values, whose noise their differences do not show"))
    lower = _sigma(d2, ORDER - 1)
    if lower > AGREE * sigma:
        return Scatter(None, None, n, (
            f"its order-2 differences give {lower:.3g}, {lower / sigma:.2f}x the order-3 "
            f"ones' {sigma:.3g}: the motion, not the noise, fills them"))
    parts = [_sigma(c, ORDER) for d in d3 for c in np.array_split(d, CHUNKS) if len(d)]
    parts = [p for p in parts if p > 0.0]
    se = float(np.std(np.log(parts), ddof=1) / math.sqrt(len(parts))) if len(parts) > 1 \
        else None
    return Scatter(sigma, se, n, (
        f"from its own samples' scatter ({n} windows of order-{ORDER} differences; "
        f"order 2 gives {lower:.3g})"))


def input_series(stream: Stream, sensor: str, key: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """The stream's samples of odometry input ``key`` of ``sensor``: ``speed`` (the left and
    right wheel speeds of a wheels sensor, rad/s), ``v`` (m/s) or ``yaw_rate`` (rad/s) of an
    odometry one, as (times s, values) per series."""
    if key == "speed":
        ms = [m for m in stream.measurements if type(m) is WheelSpeeds and m.sensor == sensor]
        t = np.array([m.t for m in ms])
        return [(t, np.array([m.left for m in ms])), (t, np.array([m.right for m in ms]))]
    ms = [m for m in stream.measurements if type(m) is WheelOdometry and m.sensor == sensor
          and getattr(m, key) is not None]
    return [(np.array([m.t for m in ms]), np.array([getattr(m, key) for m in ms], float))]
