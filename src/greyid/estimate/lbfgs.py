"""SciPy's L-BFGS on the exact value and gradient: the quasi-Newton start, which moves a search's start
closer to the optimum before Newton's method takes over (``optimizer="quasi-newton"``), and the whole
search with the Hessian by differences of the gradient (``optimizer="lbfgs"``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .optimize import NotFiniteError, Optimum, _no_report, settle
from .trust_region import _stationary

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


def _minimize(value_and_grad: Callable, z0: np.ndarray, stage: str, report: Callable, stop_where_not_finite: bool,
              options: dict):
    """SciPy's L-BFGS-B (no bounds) from z0 on ``value_and_grad``: ``(best, result)``, the best point seen (a
    [`QuasiStart`][greyid.estimate.lbfgs.QuasiStart]) and SciPy's result (None where it stopped at a non-finite
    evaluation).  Each accepted step is reported as ``stage``.  A non-finite value or gradient ends the search
    with ``stop_where_not_finite``; otherwise it is a point the line search steps back from (far above every
    value seen), and at z0 a NotFiniteError."""
    from scipy.optimize import minimize  # imported while the fit compiles (estimation.fit)

    best = QuasiStart(np.asarray(z0, dtype=float), np.inf, 0, 0)

    def evaluate(z):
        f, g = settle(value_and_grad(np.asarray(z, dtype=np.float64)))[0]
        best.evaluations += 1
        f = float(f)
        if not (np.isfinite(f) and np.all(np.isfinite(g))):
            if stop_where_not_finite:
                raise _NotFinite
            if best.evaluations == 1:
                raise NotFiniteError("the criterion or its gradient is not finite at the starting values")
            return abs(best.value) * 1e3 + 1e10, np.zeros_like(np.asarray(g, dtype=np.float64))
        if f < best.value:
            best.z, best.value, best.gradient = np.array(z, dtype=float), f, g
        return f, g

    def step_done(intermediate):
        best.iterations += 1
        report(best.iterations, stage, best.value, best.gradient)

    try:
        result = minimize(evaluate, best.z, jac=True, method="L-BFGS-B", callback=step_done, options=options)
    except _NotFinite:
        result = None
    return best, result


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
    best, _ = _minimize(value_and_grad, z0, "quasi-newton", report, stop_where_not_finite=True,
                        options=dict(maxfun=max_evaluations, maxiter=max_evaluations, gtol=QUASI_GRADIENT, ftol=0.0))
    return best


#: A search by ``optimizer="lbfgs"`` stops where the gradient's largest element (in z) falls below this,
#: the tolerance of a Newton search that has no Hessian to judge its decrement by
#: ([`GRADIENT_TOLERANCE`][greyid.estimate.trust_region.GRADIENT_TOLERANCE]).
LBFGS_GRADIENT = 1e-6
#: Central differences of the gradient take steps of this many of each coordinate's conditional standard
#: deviation 1/√H_ii (in z), so that the Hessian does not depend on the parameters' units.  Their error
#: falls as the step's square down to the gradient's own precision: a Laplace fit's standard errors within
#: 1e-6 of the exact Hessian's with a parameter near its bound (a step of 1e-3 gave 1e-4, of 1e-5 7e-8, of
#: 1e-6 1e-6).
DIFFERENCE_STEP = 1e-4


def difference_hessian(value_and_grad: Callable, z: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The Hessian at z by central differences of the exact gradient, symmetrised, the step along z_i
    ``DIFFERENCE_STEP · scales[i]`` (TMB's ``sdreport`` differences its gradient so, R's ``optimHess``)."""
    n = len(z)
    H = np.empty((n, n))
    for i in range(n):
        h = DIFFERENCE_STEP * scales[i]
        step = np.zeros(n)
        step[i] = h
        ahead = settle(value_and_grad(z + step))[0][1]
        behind = settle(value_and_grad(z - step))[0][1]
        H[:, i] = (np.asarray(ahead) - np.asarray(behind)) / (2 * h)
    return 0.5 * (H + H.T)


def conditional_scales(curvatures: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Each coordinate's conditional standard deviation 1/√H_ii from a Hessian's diagonal, ``fallback[i]``
    where H_ii is not a positive finite number."""
    d = np.asarray(curvatures, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(d) & (d > 0), 1.0 / np.sqrt(np.abs(d)), fallback)


def scaled_difference_hessian(value_and_grad: Callable, z: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """The Hessian at z by [`difference_hessian()`][greyid.estimate.lbfgs.difference_hessian] twice: first with
    steps along ``scales`` (a guess: a quasi-Newton search's curvature can be far off along a poorly determined
    direction), then with the first Hessian's conditional standard deviations (where they are positive, else
    the guess).  ``4 · len(z)`` gradients."""
    first = np.diag(difference_hessian(value_and_grad, z, scales))
    return difference_hessian(value_and_grad, z, conditional_scales(first, scales))


def lbfgs_search(value_and_grad: Callable, z0: np.ndarray, maxiter: int, report: Callable = _no_report):
    """``optimizer="lbfgs"``: SciPy's L-BFGS-B (no bounds, in z) on the exact value and gradient until the
    gradient's largest element falls below LBFGS_GRADIENT, then the Hessian at the optimum by central
    differences of the gradient
    ([`scaled_difference_hessian()`][greyid.estimate.lbfgs.scaled_difference_hessian]).

    Only the value and gradient's program is compiled (about half of a Laplace fit's first compilation,
    none of the Hessian's); the price is L-BFGS's linear convergence (more evaluations than Newton's
    steps) and a Hessian, so standard errors, carrying the differences' error.  A non-finite evaluation
    is a point the line search must step back from.  Returns an
    [`Optimum`][greyid.estimate.optimize.Optimum].
    """
    z0 = np.asarray(z0, dtype=np.float64)
    best, result = _minimize(value_and_grad, z0, "lbfgs", report, stop_where_not_finite=False,
                             options=dict(maxiter=maxiter, maxfun=20 * maxiter, gtol=LBFGS_GRADIENT, ftol=0.0))
    best.gradient = np.asarray(best.gradient, dtype=np.float64)
    # The first steps' scales: L-BFGS's own variances.
    variances = np.diag(result.hess_inv.todense()) if hasattr(result.hess_inv, "todense") else np.ones(len(z0))
    scales = np.where(np.isfinite(variances) & (variances > 0), np.sqrt(np.abs(variances)), 1.0)
    hessian = scaled_difference_hessian(value_and_grad, best.z, scales)
    evaluations = best.evaluations + 4 * len(z0)
    # Judged as a Newton search judges its end: the Newton decrement gᵀH⁻¹g negligible against |f| where the
    # Hessian is positive definite (L-BFGS itself stops where f no longer decreases, which the inner
    # optimisation's precision can reach before its own gradient tolerance).
    largest = float(np.max(np.abs(best.gradient)))
    if not np.all(np.isfinite(hessian)):
        # A gradient a difference step away is not finite (the optimum on the edge of where the model is
        # defined): no Hessian to judge the end by, nor standard errors from it.
        return Optimum(best.z, best.value, best.gradient, hessian, best.iterations, evaluations, False,
                       "L-BFGS stopped where the Hessian by differences of the gradient is not finite (a gradient "
                       f"a step of {DIFFERENCE_STEP:g} standard deviations away is not; the gradient's largest "
                       f"element {largest:.3g}): {result.message}")
    d = np.sqrt(np.abs(np.diag(hessian)))
    d = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(hessian / np.outer(d, d))
    converged = _stationary(best.value, best.gradient / d, w, V.T @ (best.gradient / d))
    message = ("converged: Newton decrement below tolerance (L-BFGS, the Hessian by differences)" if converged else
               f"L-BFGS stopped short of the optimum (the gradient's largest element {largest:.3g}): {result.message}")
    return Optimum(best.z, best.value, best.gradient, hessian, best.iterations, evaluations, converged, message)
