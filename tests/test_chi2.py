"""estimation.chi2.ppf equals scipy.stats.chi2.ppf value for value (gate thresholds and NIS/NEES
bands must not move when the start-up-heavy scipy.stats import is avoided)."""

import math
import subprocess
import sys

import numpy as np
import pytest
from ddfuse.estimation import chi2
from scipy.stats import chi2 as scipy_chi2


@pytest.mark.parametrize("dof", [1, 2, 3, 4.5, 9, 40, 400, 6000.0])
def test_ppf_equals_scipy_bit_for_bit(dof):
    ps = np.concatenate([[0.0, 1e-12, 0.001, 0.025, 0.5, 0.95, 0.975, 0.99, 0.9999, 1.0],
                         np.linspace(0.0, 1.0, 101)])
    for p in ps:
        want = float(scipy_chi2.ppf(p, dof))
        got = chi2.ppf(float(p), dof)
        assert got == want, (p, dof, got, want)


@pytest.mark.parametrize("p,dof", [(-0.1, 2), (1.5, 2), (math.nan, 2), (0.5, 0), (0.5, -1),
                                   (0.5, math.nan)])
def test_ppf_outside_the_domain_is_nan_as_scipy(p, dof):
    assert math.isnan(float(scipy_chi2.ppf(p, dof)))
    assert math.isnan(chi2.ppf(p, dof))


def test_the_filters_and_consistency_do_not_import_scipy_stats():
    """The point of the module: a run's EKF and scoring modules leave scipy.stats unloaded."""
    code = ("import sys, ddfuse.ekf_baseline.kalman, ddfuse.evaluation.consistency, "
            "ddfuse.estimation.estimator;"
            "ddfuse.ekf_baseline.kalman.chi2_threshold(0.99, 2);"
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"


def test_the_known_quantiles_are_the_formulas_to_the_bit():
    from scipy.special import gammaincinv

    for (p, dof), v in chi2.KNOWN.items():
        assert v == 2.0 * float(gammaincinv(dof / 2.0, p)) == float(scipy_chi2.ppf(p, dof))


@pytest.mark.slow
def test_a_run_with_the_usual_gates_and_bands_does_not_import_scipy_special():
    """The sample run's filters and scoring ask only for KNOWN quantiles: scipy.special (0.2 s
    of start-up) stays unloaded; an unusual probability still gets its quantile."""
    code = ("import sys\n"
            "from ddfuse.evaluation import cli\n"
            "cli.main(['run', '-o', sys.argv[1], '--no-report', '--estimators', 'ekf,smoother'])\n"
            "print('scipy.special' in sys.modules)\n"
            "from ddfuse.estimation import chi2\n"
            "print(chi2.ppf(0.9995, 2), 'scipy.special' in sys.modules)\n")
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        out = subprocess.run([sys.executable, "-c", code, d], capture_output=True, text=True,
                             check=True).stdout.split("\n")
    assert out[-3] == "False"
    v, loaded = out[-2].split()
    assert float(v) == float(scipy_chi2.ppf(0.9995, 2)) and loaded == "True"
