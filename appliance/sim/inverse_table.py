"""The inverse of an increasing function of one variable, tabulated once and polished by Newton.

The materials (`appliance.sim.rubber`, `appliance.sim.metal`) answer "at what stretch is this
stress?" with it, to about 1e-12 relative.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class InverseTable:
    """Inverse of an increasing function, tabulated, with Newton polishing.

    The inverse x(f) is interpolated by cubic Hermite pieces between table nodes, using the
    one-sided slopes 1 / f'(x) at both ends of each interval (so a kink of f at a node costs
    no accuracy), and then refined by Newton steps kept inside the interval. With a peak of f
    at the last node (f' = 0 there, as at a metal's maximum force) the last interval uses the
    square-root law of a quadratic maximum instead. Targets beyond the table are reached by
    plain Newton steps from its nearer end.

    Args:
        x: (m,) strictly increasing abscissae, m >= 2.
        f: the function, vectorised, strictly increasing on [x[0], x[-1]].
        fprime: its derivative, vectorised, > 0 inside the intervals.
        peak_at_end: f' vanishes at x[-1].
        newton_steps: Newton steps after the interpolation (one reaches about 1e-15 relative
            where f is smooth; near a peak convergence is slower).
    """

    def __init__(
        self,
        x: FloatArray,
        f: Callable[[FloatArray], FloatArray],
        fprime: Callable[[FloatArray], FloatArray],
        *,
        peak_at_end: bool = False,
        newton_steps: int = 1,
    ) -> None:
        self.x = np.asarray(x, np.float64)
        self.newton_steps = newton_steps
        self.f_of_x = f
        self.fprime_of_x = fprime
        self.f = f(self.x)
        self.peak_at_end = peak_at_end
        self.slope_left = 1.0 / fprime(np.nextafter(self.x[:-1], np.inf))
        slope_right = fprime(np.nextafter(self.x[1:], -np.inf))
        if peak_at_end:
            slope_right[-1] = 1.0
        self.slope_right = 1.0 / slope_right

    def __call__(self, target: npt.ArrayLike) -> FloatArray:
        """x with f(x) = target, elementwise, of the shape of `target`."""
        target = np.asarray(target, np.float64)
        flat = np.atleast_1d(target).ravel()
        x, f = self.x, self.f
        m = x.size
        index = np.clip(np.searchsorted(f, flat) - 1, 0, m - 2)
        x_lo, x_hi = x[index], x[index + 1]
        f_lo, f_hi = f[index], f[index + 1]
        step = f_hi - f_lo
        t = (flat - f_lo) / step
        t2 = t * t
        t3 = t2 * t
        guess = (
            (2.0 * t3 - 3.0 * t2 + 1.0) * x_lo
            + (t3 - 2.0 * t2 + t) * step * self.slope_left[index]
            + (3.0 * t2 - 2.0 * t3) * x_hi
            + (t3 - t2) * step * self.slope_right[index]
        )
        if self.peak_at_end:
            last = index == m - 2
            root = np.sqrt(np.clip((f[-1] - flat) / (f[-1] - f[-2]), 0.0, 1.0))
            guess = np.where(last, x[-1] - (x[-1] - x[-2]) * root, guess)
        outside = (flat < f[0]) | (flat > f[-1])
        guess = np.where(flat < f[0], x[0], np.where(flat > f[-1], x[-1], guess))
        lower = np.where(outside, -np.inf, x_lo)
        upper = np.where(outside, np.inf, x_hi)
        if self.peak_at_end:
            upper = np.where(flat > f[-1], x[-1], upper)
        for _ in range(self.newton_steps):
            slope = self.fprime_of_x(guess)
            residual = self.f_of_x(guess) - flat
            with np.errstate(divide="ignore", invalid="ignore"):
                moved = guess - residual / slope
            guess = np.where(np.isfinite(moved), np.clip(moved, lower, upper), guess)
        return guess.reshape(target.shape)
