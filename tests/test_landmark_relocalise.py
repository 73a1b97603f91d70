"""A pose from one frame of sightings (``ekf_baseline.landmark_relocalise``): right, with an
honest covariance, and refusing frames that cannot fix it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from ddfuse.ekf_baseline.landmark_model import range_bearing_terms
from ddfuse.ekf_baseline.landmark_relocalise import fit_pose, with_common_bearing

SD_R, SD_B = 0.1, 0.02


def _frame(rng, pose, landmarks, swap=None, common=0.0):
    rows = []
    c = rng.normal(0, common) if common else 0.0  # one draw for the frame
    for i, (lx, ly) in enumerate(landmarks):
        r, b, *_ = range_bearing_terms(*pose, lx, ly)
        if swap is not None and i == swap:  # reported as another landmark's
            lx, ly = landmarks[(i + 1) % len(landmarks)]
        rows.append((lx, ly, r + rng.normal(0, SD_R), b + c + rng.normal(0, SD_B),
                     SD_R**2, SD_B**2))
    return rows


def test_the_fit_is_unbiased_and_its_covariance_honest():
    rng = np.random.default_rng(7)
    nees = []
    for _ in range(400):
        pose = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-math.pi, math.pi)])
        lms = pose[:2] + rng.uniform(-15, 15, size=(int(rng.integers(2, 6)), 2))
        fit = fit_pose(_frame(rng, pose, lms))
        assert fit is not None
        e = fit.pose - pose
        e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
        nees.append(e @ np.linalg.solve(fit.cov, e))
        assert np.allclose(fit.cov, fit.cov.T) and np.all(np.linalg.eigvalsh(fit.cov) > 0)
    # 400 draws of chi2(3): mean 3 with a standard error of 0.12
    assert 2.6 < np.mean(nees) < 3.4, np.mean(nees)


def test_a_bearing_error_common_to_the_frame_goes_into_the_heading_variance():
    """A camera's heading error at the exposure (``noise.bearing_common``, 0.05 rad here,
    2.5x the own 0.02): with it, the heading NEES is chi2(1)'s 1; without it the fit claims
    the own sigma's heading and is over-confident (NEES ~17)."""
    rng = np.random.default_rng(11)
    sc = 0.05
    with_c, without = [], []
    for _ in range(400):
        pose = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-math.pi, math.pi)])
        lms = pose[:2] + rng.uniform(-15, 15, size=(int(rng.integers(2, 6)), 2))
        fit = fit_pose(_frame(rng, pose, lms, common=sc))
        e = (fit.pose[2] - pose[2] + math.pi) % (2 * math.pi) - math.pi
        without.append(e * e / fit.cov[2, 2])
        with_c.append(e * e / with_common_bearing(fit, sc * sc).cov[2, 2])
    assert 0.85 < np.mean(with_c) < 1.15, np.mean(with_c)
    assert np.mean(without) > 3.0, np.mean(without)


def test_any_heading_is_found_without_a_starting_guess():
    rng = np.random.default_rng(1)
    lms = np.array([[5.0, 0.0], [0.0, 7.0], [-4.0, -3.0]])
    for psi in np.linspace(-math.pi, math.pi, 13, endpoint=False):
        pose = np.array([1.0, -2.0, psi])
        fit = fit_pose(_frame(rng, pose, lms))
        err = (fit.pose[2] - psi + math.pi) % (2 * math.pi) - math.pi
        assert abs(err) < 5 * SD_B and np.hypot(*(fit.pose[:2] - pose[:2])) < 0.5


def test_a_misidentified_landmark_makes_the_frame_inconsistent():
    rng = np.random.default_rng(3)
    pose = np.array([0.0, 0.0, 0.3])
    lms = np.array([[6.0, 1.0], [2.0, 8.0], [-5.0, 4.0], [-3.0, -6.0]])
    assert fit_pose(_frame(rng, pose, lms)).consistent
    assert not fit_pose(_frame(rng, pose, lms, swap=1)).consistent


@pytest.mark.parametrize("rows", [
    [(3.0, 4.0, 5.0, 0.1, 0.01, 0.001)],  # one sighting: the heading is free
    [(3.0, 4.0, 5.0, 0.1, 0.01, 0.001), (3.0, 4.0, 5.01, 0.11, 0.01, 0.001)],  # one place twice
    [(3.0, 4.0, 0.0, 0.1, 0.01, 0.001), (1.0, 4.0, 5.0, 0.1, 0.01, 0.001)],  # at the origin
])
def test_a_frame_that_cannot_fix_the_pose_gives_none(rows):
    assert fit_pose(rows) is None
