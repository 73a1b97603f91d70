"""ddfuse.factors.linear: the linear factor equals the Python heading factor it replaces (error and
linearisation), including across the +-pi wrap."""

import math

import gtsam
import numpy as np
import pytest
from ddfuse.factors.heading import heading_factor
from ddfuse.factors.linear import heading_row, linear_state_factor
from ddfuse.factors.state import DIM, make_state

K = 7


def vals(state):
    v = gtsam.Values()
    v.insert(K, np.asarray(state, dtype=float))
    return v


def info(factor, values):
    """Augmented information [A b]^T [A b] of the whitened linearisation (order-free)."""
    return factor.linearize(values).augmentedInformation()


def random_state(rng, psi):
    return make_state(x=rng.normal(0, 50), y=rng.normal(0, 50), psi=psi, v=rng.normal(0, 1),
                      w=rng.normal(0, 0.3), bg=rng.normal(0, 0.01), hoff=rng.normal(0, 0.5),
                      k_v=1 + rng.normal(0, 0.02), k_w=1 + rng.normal(0, 0.02))


@pytest.mark.parametrize("use_offset", [True, False])
def test_matches_custom_factors(use_offset):
    rng = np.random.default_rng(3)
    for _ in range(50):
        # heading near the wrap, measurement on either side of +-pi
        lin = random_state(rng, psi=rng.choice([-1, 1]) * (math.pi - abs(rng.normal(0, 0.05))))
        z = math.remainder(lin[2] + (lin[6] if use_offset else 0.0) + rng.normal(0, 0.1),
                           2 * math.pi)
        sh = 0.02
        lf = linear_state_factor(K, [heading_row(z, sh, use_offset)], lin)
        customs = [heading_factor(K, z, sh, use_offset=use_offset)]
        # at the linearisation point and moved from it (psi by up to ~0.3 rad, not past pi)
        for x in (lin, lin + rng.normal(0, 0.1, DIM)):
            v = vals(x)
            want = sum(f.error(v) for f in customs)
            assert lf.error(v) == pytest.approx(want, rel=1e-9, abs=1e-12)
            np.testing.assert_allclose(info(lf, v), sum(info(f, v) for f in customs),
                                       rtol=1e-9, atol=1e-9)


def test_single_row_and_wrap_sign():
    lin = make_state(psi=3.1, hoff=0.0)
    z = -3.1  # 2 pi - 6.2 = 0.083 rad ahead of the state, across the wrap
    f = linear_state_factor(K, [heading_row(z, 1.0, use_offset=False)], lin)
    # whitened error at lin is wrap(3.1 - (-3.1)) = 6.2 - 2 pi, not 6.2
    assert f.error(vals(lin)) == pytest.approx(0.5 * (6.2 - 2 * math.pi) ** 2, rel=1e-12)
    # linear beyond lin: psi = 3.1 + 0.083 reaches the measurement
    at = lin.copy()
    at[2] = 3.1 + (2 * math.pi - 6.2)
    assert f.error(vals(at)) == pytest.approx(0.0, abs=1e-20)


def test_no_rows_is_an_error():
    with pytest.raises(ValueError, match="at least one row"):
        linear_state_factor(K, [], make_state())
