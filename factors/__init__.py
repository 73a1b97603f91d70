"""GTSAM factors for a differential-drive robot. Imports nothing else of ddfuse.

State: one gtsam Vector key per keyframe, the 9-vector [x, y, psi, v, w, bg, hoff, k_v, k_w] of
``ddfuse.factors.state`` (world = local ENU frame).

Modules (import them directly; this package imports nothing eagerly so that the pure-math
``ddfuse.factors.kinematics`` can be used without loading gtsam):

* ``kinematics``         exact SE(2) constant-twist step and its Jacobian (no gtsam, no numpy)
* ``state``              index constants and layout of the state vector
* ``preintegration``     wheel+gyro preintegration and its 2-key motion factor;
  ``preintegration_jit`` its compiled accumulator (``jitcache`` guards numba's cache)
* ``gps``                GPS position factor (lever arm, latency) and its prediction
* ``landmark``           range(-bearing) factors to known landmarks
* ``linear``             linear rows (heading) folded into one C++ factor; ``heading`` is its
  CustomFactor reference, kept because tests check ``linear`` against it
* ``gyro``               gyro-bias factor (gyro vs odometry yaw rate)
* ``noise``              noise-model helper
"""
