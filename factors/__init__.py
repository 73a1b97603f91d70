"""GTSAM factors for a differential-drive robot. Imports nothing else of ddfuse."""
