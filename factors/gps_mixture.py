"""Max-mixture GPS factor: a fix is an inlier or an outlier, whichever explains it better at the
current estimate (Olson & Agarwal, "Inference on networks of mixtures for robust robot
mapping", IJRR 2013).

Two zero-mean Gaussian components of the fix's error r = h(x) - z (``ddfuse.factors.gps``'s
model, local ENU, m): the inlier N(0, S_in) of prior weight 1 - w and the outlier N(0, S_out)
of weight w. Per component i the negative log-likelihood is

    l_i = 0.5 r^T S_i^-1 r + c_i,   c_i = 0.5 ln det S_i - ln w_i

and the factor takes the component of the smaller l_i. Its error is 3-D with a unit noise
model, (W_i r, sqrt(2 (c_i - c_min))) with W_i^T W_i = S_i^-1, so 0.5 |error|^2 = l_i - c_min
>= 0 and the choice is remade at every linearisation: within the smoother's lag a decision
is revisited as later data move the estimate. The Jacobian is (W_i H, 0), H the GPS factor's
(``gps_predict_jacobian``).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from ddfuse.factors.gps import gps_predict_jacobian

__all__ = ["MixtureModel", "gps_maxmix_factor", "mixture_component"]


class MixtureModel:
    """The two components of a fix: covariances ``inlier`` and ``outlier`` (2, 2) m^2 and the
    outlier's prior weight ``w_out`` in (0, 1). Holds their whitening matrices and constants."""

    def __init__(self, inlier: np.ndarray, outlier: np.ndarray, w_out: float) -> None:
        if not 0.0 < w_out < 1.0:
            raise ValueError(f"outlier weight must be in (0, 1), got {w_out!r}")
        self.w, self.c = [], []
        for cov, weight in ((inlier, 1.0 - w_out), (outlier, w_out)):
            cov = np.asarray(cov, dtype=float)
            chol = np.linalg.cholesky(cov)  # S = L L^T, so W = L^-1 whitens
            self.w.append(np.linalg.inv(chol))
            self.c.append(float(np.sum(np.log(np.diag(chol))) - math.log(weight)))
        self.c_min = min(self.c)

    def choose(self, r: np.ndarray) -> int:
        """0 (inlier) or 1 (outlier): the component of the larger likelihood of error ``r``."""
        l0 = 0.5 * float(np.sum((self.w[0] @ r) ** 2)) + self.c[0]
        l1 = 0.5 * float(np.sum((self.w[1] @ r) ** 2)) + self.c[1]
        return 0 if l0 <= l1 else 1


def mixture_component(model: MixtureModel, state: np.ndarray, east: float, north: float,
                      lever_arm: tuple[float, float] = (0.0, 0.0), dt_fix: float = 0.0) -> int:
    """The component (0 inlier, 1 outlier) the factor takes at keyframe ``state``."""
    pred, _ = gps_predict_jacobian(state, lever_arm, dt_fix)
    return model.choose(np.array((pred[0] - east, pred[1] - north)))


def gps_maxmix_factor(key: int, east: float, north: float, model: MixtureModel,
                      lever_arm: tuple[float, float] = (0.0, 0.0), dt_fix: float = 0.0
                      ) -> gtsam.CustomFactor:
    """Max-mixture GPS factor on the 9-state ``key`` (``ddfuse.factors.state``): fix ``east``,
    ``north`` (m, local ENU), antenna ``lever_arm`` (m, body), ``dt_fix`` = fix time - keyframe
    time (s). A ``gtsam.CustomFactor`` of dimension 3 with a unit noise model (module
    docstring)."""
    z = np.array((float(east), float(north)))
    lever = (float(lever_arm[0]), float(lever_arm[1]))
    dt = float(dt_fix)
    consts = [math.sqrt(2.0 * (c - model.c_min)) for c in model.c]
    unit = gtsam.noiseModel.Unit.Create(3)

    def error(this, values, H):
        pred, jac = gps_predict_jacobian(values.atVector(key), lever, dt)
        r = pred - z
        i = model.choose(r)
        w = model.w[i]
        if H is not None:
            j = np.zeros((3, jac.shape[1]))
            j[:2] = w @ jac
            H[0] = j
        return np.array((*(w @ r), consts[i]))

    return gtsam.CustomFactor(unit, [key], error)
