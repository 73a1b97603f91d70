"""The EKFs that the specification documents in shared/seeds describe, with their errors fixed."""

from ddfuse.estimation.config import GIVEN_POSE_STD  # noqa: F401 - shared with the smoother
