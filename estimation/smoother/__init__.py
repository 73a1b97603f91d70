"""The GTSAM ISAM2 fixed-lag smoother (``FixedLagSmoother``) and its whole-run reference
(``BatchSmoother``), split by job into collaborators:

* ``fixed_lag``: the estimator, routing each message; keyframes;
* ``window``: gtsam's incremental fixed-lag smoother, the keyframes and the lagged output;
* ``held_twist``: the held wheel/gyro samples and their preintegration;
* ``heading``: heading samples accumulated per keyframe interval, their gate;
* ``gps``, ``landmarks``: the absolute measurements' factors; ``gating``: gates, lock-outs;
* ``initialisation``: start (given pose, GPS course), restart after a gap, recovery;
* ``noise``, ``isam2``: process noise, robust kernels, ISAM2 settings; ``outputs``; ``batch``.

Design and history: docs/design/smoother.md.
"""

from ddfuse.estimation.gps_course import COURSE_SIGMA_MAX, INIT_DISTANCE
from ddfuse.estimation.smoother.batch import BatchSmoother, SharedBatch
from ddfuse.estimation.smoother.fixed_lag import FixedLagSmoother
from ddfuse.estimation.smoother.held_twist import ODOMETRY_WAIT
from ddfuse.estimation.smoother.initialisation import (
    GAP_HEADING_SIGMA,
    MAX_RECOVERIES,
    RECOVERY_WINDOW,
    RESTART_HEADING_WAIT,
)
from ddfuse.estimation.smoother.isam2 import RELINEARIZE, RELINEARIZE_SKIP, isam2_params
from ddfuse.estimation.smoother.noise import (
    MIN_KEYFRAME_DT,
    POSE_NOISE_FLOOR,
    WALK_FLOOR,
    SmootherNoise,
    walk_floor,
)

__all__ = [
    "COURSE_SIGMA_MAX", "GAP_HEADING_SIGMA", "INIT_DISTANCE", "MAX_RECOVERIES", "MIN_KEYFRAME_DT",
    "ODOMETRY_WAIT", "POSE_NOISE_FLOOR", "RECOVERY_WINDOW", "RELINEARIZE", "RELINEARIZE_SKIP",
    "RESTART_HEADING_WAIT", "WALK_FLOOR", "BatchSmoother", "FixedLagSmoother", "SharedBatch",
    "SmootherNoise",
    "isam2_params", "walk_floor",
]
