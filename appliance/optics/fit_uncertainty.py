"""Uncertainty of a quantity derived from a least-squares fit: the fit's covariance, and its
propagation to a function of the fitted parameters (first order, GUM).

    C = s^2 (J^T J)^+        s^2 = r . r / (m - n)     (m residuals, n parameters)
    u(f) = sqrt(g C g^T)     g: the gradient of f, by central differences

The calibrations use it for the scale at the specimen plane.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

RELATIVE_STEP = 1e-6
"""Central-difference step of each parameter, relative to max(1, |parameter|)."""


def fit_covariance(jacobian: FloatArray, residual: FloatArray) -> FloatArray:
    """Covariance of the fitted parameters from the Jacobian (m, n) at the solution and the
    residuals (m,), the residual variance estimated with m - n degrees of freedom (at least 1)."""
    dof = max(1, len(residual) - jacobian.shape[1])
    variance = float(residual @ residual) / dof
    return variance * np.linalg.pinv(jacobian.T @ jacobian)


def propagated_uncertainty(
    function: Callable[[FloatArray], float],
    parameters: FloatArray,
    covariance: FloatArray,
) -> float:
    """Standard uncertainty of `function(parameters)` given the parameters' covariance
    (n, n), by a first-order propagation with a central-difference gradient."""
    gradient = np.zeros(len(parameters))
    for i in range(len(parameters)):
        step = RELATIVE_STEP * max(1.0, abs(parameters[i]))
        up, down = parameters.copy(), parameters.copy()
        up[i] += step
        down[i] -= step
        gradient[i] = (function(up) - function(down)) / (2.0 * step)
    return float(math.sqrt(max(0.0, gradient @ covariance @ gradient)))
