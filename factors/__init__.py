"""GTSAM factors for a differential-drive robot. Imports nothing else of ddfuse.

State: one gtsam Vector key per keyframe, the 9-vector [x, y, psi, v, w, bg, hoff, k_v, k_w] of
``ddfuse.factors.state`` (world = local ENU frame).

Modules (import them directly; this package imports nothing eagerly so that the pure-math
``ddfuse.factors.kinematics`` can be used without loading gtsam):

* ``kinematics``     exact SE(2) constant-twist step and its Jacobian (no gtsam, no numpy)
* ``state``          index constants and layout of the state vector
* ``motion``         2-key motion factor and its process-noise parameters
* ``preintegration`` wheel+gyro preintegration and its 2-key factor (the fast path)
* ``wheel``, ``gyro``, ``heading``, ``gps``, ``landmark``   measurement factors
* ``noise``          noise-model helper; ``checks``  numerical Jacobian checks
"""
