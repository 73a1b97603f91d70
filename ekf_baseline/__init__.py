"""The EKFs that the specification documents in shared/seeds describe, with their errors fixed."""

# Standard deviations (m, rad) of a given initial pose -- the config's initial_pose, or the first
# ground-truth pose with initial_pose: ground_truth -- for every filter alike: position and
# heading are taken as known to 1 cm and 5 mrad. A wrong start is caught by the gate's lock-out
# recovery (ekf_baseline.kalman), not by a wide initial covariance.
GIVEN_POSE_STD = (0.01, 0.005)
