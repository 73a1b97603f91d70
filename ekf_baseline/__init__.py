"""The EKFs that the specification documents in shared/seeds describe, with their errors fixed."""
