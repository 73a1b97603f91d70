"""The codes the compiled EKF kernels (``ddfuse.ekf_baseline.kalman_jit``) and their Python
side (``ddfuse.ekf_baseline.compiled``) share: the kernels' return bits, the message types of
their ``typ`` argument, and the measurement kinds per sensor of each filter in the kernels' slot
order. Plain constants, so that importing them loads no numba."""

# the kernels' return bits (their meaning: kalman_jit's module docstring)
DEFER = 1
REJECTED = 2
GROW = 4
# message types: the kernels' ``typ`` argument
T_NONE, T_GYRO, T_HEAD, T_ODOM, T_GPS, T_WHEELS, T_ACCEL, T_HEAD_POSE = range(8)
# measurement kinds (slots per sensor) of the unicycle and of the IGVC filter, in the kernels'
# K_* / KI_* order
UNI_KINDS = ("gyro", "heading", "v", "yaw_rate", "wheels", "gps")
IGVC_KINDS = ("gyro", "heading", "accel", "odometry", "wheels", "gps")
LANDMARK_KINDS = ("landmark",)
