"""The quasi-Newton start: SciPy's L-BFGS on the exact value and gradient, to move a search's start
closer to the optimum before Newton's method takes over (``optimizer="quasi-newton"``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .optimize import _no_report, settle

#: Value-and-gradient evaluations allowed to the quasi-Newton start, per free parameter.
QUASI_EVALUATIONS_PER_PARAMETER = 3
#: The quasi-Newton start stops where the gradient's largest element (in z) falls below this:
#: close enough for Newton's quadratic convergence to finish in a step or two.
QUASI_GRADIENT = 1e-2


class _NotFinite(Exception):
    """Raised inside SciPy's L-BFGS to end the quasi-Newton start at a non-finite evaluation."""


@dataclass
class QuasiStart:
    """Where the quasi-Newton start ended: the best point seen, and what it took."""

    z: np.ndarray
    value: float
    iterations: int
    evaluations: int
    gradient: np.ndarray | None = None


def quasi_newton_start(value_and_grad: Callable, z0: np.ndarray, max_evaluations: int,
                       report: Callable = _no_report) -> QuasiStart:
    """L-BFGS (SciPy's L-BFGS-B, no bounds) from z0 on ``value_and_grad(z) -> (f, g)``, the exact gradient.

    Far from the optimum a step needs a descent direction, not the exact curvature: an
    evaluation here costs a forward gradient, a few times less than an exact Hessian, and
    about as many of them are needed as Newton takes Hessians.  The start only moves the point
    from which [`Search`][greyid.estimate.trust_region.Search] takes exact Newton steps, so the
    optimum, its Hessian and the convergence test are those of Newton's method.  It stops at
    ``max_evaluations``, where the
    gradient falls below QUASI_GRADIENT, and at the first non-finite value or gradient; it
    returns the best point seen (z0 where nothing was better).
    """
    from scipy.optimize import minimize  # imported while the fit compiles (estimation.fit)

    best = QuasiStart(np.asarray(z0, dtype=float), np.inf, 0, 0)

    def evaluate(z):
        f, g = settle(value_and_grad(np.asarray(z, dtype=np.float64)))[0]
        best.evaluations += 1
        f = float(f)
        if not (np.isfinite(f) and np.all(np.isfinite(g))):
            raise _NotFinite
        if f < best.value:
            best.z, best.value, best.gradient = np.array(z, dtype=float), f, g
        return f, g

    def step_done(intermediate):
        best.iterations += 1
        report(best.iterations, "quasi-newton", best.value, best.gradient)

    try:
        minimize(evaluate, best.z, jac=True, method="L-BFGS-B", callback=step_done,
                 options=dict(maxfun=max_evaluations, maxiter=max_evaluations, gtol=QUASI_GRADIENT, ftol=0.0))
    except _NotFinite:
        pass
    return best


