"""Maximum likelihood and MAP estimation (chapter 3) with exact derivatives.

``model.fit(data, ...)`` maximises the Gaussian log-likelihood (3.18) — or a
robust or k-step version of it, or the posterior with a Gaussian prior (3.46) —
over the free parameters.  Bounds are handled by smooth transforms; the
optimiser (BFGS on exact JAX gradients, then Newton steps on the exact
Hessian) treats a non-finite evaluation as a rejected step.  The uncertainty
comes from the exact Hessian of the negative log-posterior at the optimum,
mapped back to the natural parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ..data.prepare import as_frames
from ..errors import ModelError
from ..filters.api import filter_options, prepare_datasets
from ..progress import FitProgress
from .criteria import GaussianPrior, check_robust
from .objective import Problem, compiled
from .transforms import Transform

CRITERIA = ("ml", "map")


@dataclass
class Optimum:
    z: np.ndarray
    value: float
    gradient: np.ndarray
    hessian: np.ndarray | None
    iterations: int
    evaluations: int
    converged: bool
    message: str


def _starting_points(transform: Transform, theta0: np.ndarray, starts: int, seed: int) -> list[np.ndarray]:
    """The initial values, then ``starts − 1`` random points inside the bounds."""
    rng = np.random.default_rng(seed)
    points = [transform.to_z(theta0)]
    for _ in range(starts - 1):
        theta = theta0.copy()
        for i, kind in enumerate(transform.kind):
            lo, hi = transform.lower[i], transform.upper[i]
            if kind == 3:
                theta[i] = rng.uniform(lo + 0.02 * (hi - lo), hi - 0.02 * (hi - lo))
            elif kind == 1:
                theta[i] = lo + (theta0[i] - lo) * math.exp(rng.uniform(-1.5, 1.5))
            elif kind == 2:
                theta[i] = hi - (hi - theta0[i]) * math.exp(rng.uniform(-1.5, 1.5))
            else:
                theta[i] = theta0[i] + rng.uniform(-1, 1) * max(abs(theta0[i]), 1.0)
        points.append(transform.to_z(theta))
    return points


def _no_report(iteration: int, stage: str, f: float, g: np.ndarray) -> None:
    pass


def _bfgs(fun, z, f, g, inverse, maxiter: int, gtol: float = 1e-4, report=_no_report):
    """BFGS with a backtracking (Armijo) line search that tries the full step first.

    Near a well-scaled start the full quasi-Newton step is usually accepted, so
    most iterations cost one evaluation.  Updates that would lose positive
    definiteness (sᵀy ≤ 0) are skipped.
    """
    eye = np.eye(len(z))
    stalled = 0
    for iteration in range(1, maxiter + 1):
        p = -inverse @ g
        slope = float(g @ p)
        if not slope < 0:  # not a descent direction: restart from scaled steepest descent
            inverse = eye / max(float(np.max(np.abs(g))), 1.0)
            p = -inverse @ g
            slope = float(g @ p)
        alpha = 1.0
        for _ in range(50):
            f_new, g_new = fun(z + alpha * p)
            if f_new <= f + 1e-4 * alpha * slope:
                break
            # Quadratic interpolation of the step, kept within [0.1, 0.5] of the last one.
            curvature = f_new - f - slope * alpha
            trial = -slope * alpha**2 / (2.0 * curvature) if curvature > 0 else 0.1 * alpha
            alpha = float(np.clip(trial, 0.1 * alpha, 0.5 * alpha))
        else:
            return z, f, g, iteration, False, "line search found no decrease"
        s = alpha * p
        y = g_new - g
        sy = float(s @ y)
        decrease = f - f_new
        z, f, g = z + s, f_new, g_new
        report(iteration, "bfgs", f, g)
        if sy > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
            rho = 1.0 / sy
            A = eye - rho * np.outer(s, y)
            inverse = A @ inverse @ A.T + rho * np.outer(s, s)
        if np.max(np.abs(g)) < gtol:
            return z, f, g, iteration, True, "converged: gradient below tolerance"
        # The Newton steps that follow converge quadratically: hand over once BFGS
        # only creeps.
        stalled = stalled + 1 if decrease <= 1e-10 * max(1.0, abs(f)) else 0
        if stalled >= 2:
            return z, f, g, iteration, True, "converged: no further decrease"
    return z, f, g, maxiter, False, "maximum number of iterations reached"


def _minimise(value_and_grad, hessian, z0: np.ndarray, maxiter: int, report=_no_report) -> Optimum:
    """BFGS on exact gradients from the exact Hessian, then Newton steps on the exact Hessian."""
    evaluations = 0
    best = {"f": np.inf}

    def fun(z):
        nonlocal evaluations
        evaluations += 1
        f, g = value_and_grad(jnp.asarray(z))
        f, g = float(f), np.asarray(g)
        if not (np.isfinite(f) and np.all(np.isfinite(g))):
            # A failed evaluation is a rejected step: a large value sends the line search back.
            return (abs(best["f"]) + 1.0) * 1e6 if np.isfinite(best["f"]) else 1e100, np.zeros_like(z)
        best["f"] = min(best["f"], f)
        return f, g

    f0, g0 = fun(z0)
    if not np.isfinite(best["f"]):
        raise ModelError("the criterion is not finite at the starting values; check the initial parameter values")
    # Start BFGS from the exact Hessian where it is positive definite: the scales of
    # physical parameters differ by orders of magnitude, and an identity start wastes
    # many iterations learning them.
    inverse = np.eye(len(z0)) / max(float(np.max(np.abs(g0))), 1.0)
    H0 = np.asarray(hessian(jnp.asarray(z0)))
    if np.all(np.isfinite(H0)):
        w, V = np.linalg.eigh(0.5 * (H0 + H0.T))
        floor = max(np.max(np.abs(w)), 1e-8) * 1e-6
        inverse = (V / np.maximum(np.abs(w), floor)) @ V.T
    z, f, g, iterations, bfgs_ok, message = _bfgs(fun, np.asarray(z0, dtype=float), f0, g0, inverse, maxiter,
                                                  report=report)
    # Newton polish: quadratic convergence near the optimum, and its Hessian is needed anyway.
    H, H_is_current = None, False
    newton_converged = False
    for _ in range(20):
        H, H_is_current = np.asarray(hessian(jnp.asarray(z))), True
        try:
            L = np.linalg.cholesky(0.5 * (H + H.T))
        except np.linalg.LinAlgError:
            break
        step = -np.linalg.solve(L.T, np.linalg.solve(L, g))
        decrement = float(-g @ step)
        if decrement < 1e-12 * max(1.0, abs(f)):
            newton_converged = True
            break
        for _ in range(30):
            f_new, g_new = fun(z + step)
            if f_new <= f + 1e-4 * g @ step:
                break
            step = step / 2
        else:
            break
        z, f, g = z + step, f_new, g_new
        H_is_current = False
        iterations += 1
        report(iterations, "newton", f, g)
    if not H_is_current:  # the uncertainty needs the Hessian at the final point
        H = np.asarray(hessian(jnp.asarray(z)))
    converged = newton_converged or bfgs_ok
    if newton_converged:
        message = "converged: Newton decrement below tolerance"
    return Optimum(z, f, g, H, iterations, evaluations, converged, str(message))


def fit(model, data, time="t", hold="zoh", method=None, criterion="ml", prior=None, robust=None,
        horizon=1, starts=1, seed=0, init=None, time_unit=None, maxiter=1000, progress=False, **filter_settings):
    """Estimate the free parameters of ``model`` from ``data``; see :meth:`Model.fit`."""
    from .results import FitResult, build_result

    structure = model.structure
    if criterion not in CRITERIA:
        raise ModelError(f"unknown criterion '{criterion}'; use 'ml' or 'map'")
    if criterion == "map" and prior is None:
        raise ModelError("criterion='map' needs a prior: prior={'mean': {...}, 'sd': {...}}")
    if criterion == "ml" and prior is not None:
        raise ModelError("a prior was given with criterion='ml'; use criterion='map'")
    robust = check_robust(robust)
    if not isinstance(starts, int) or starts < 1:
        raise ModelError(f"starts must be a positive integer, got {starts!r}")
    options = filter_options(structure, method, **filter_settings)

    names = structure.parameter_names
    declared = model.parameters
    init = dict(init or {})
    unknown = [k for k in init if k not in names]
    if unknown:
        raise ModelError(f"init given for '{unknown[0]}', which is not a parameter of the model")
    theta0 = np.zeros(len(names))
    free, lower, upper = [], [], []
    for i, name in enumerate(names):
        p = declared.get(name)
        if p is not None and p.fixed:
            theta0[i] = p.init
            continue
        value = init.get(name, None if p is None else p.init)
        if value is None:
            raise ModelError(f"parameter '{name}' has no initial value; set it with set_parameter('{name}', init=...)")
        lo, hi = (None, None) if p is None else (p.lower, p.upper)
        if (lo is not None and value <= lo) or (hi is not None and value >= hi):
            raise ModelError(f"the initial value {value} of '{name}' must lie strictly inside its bounds [{lo}, {hi}]")
        theta0[i] = value
        free.append(i)
        lower.append(lo)
        upper.append(hi)
    if not free:
        raise ModelError("every parameter is fixed; there is nothing to estimate")
    transform = Transform.from_bounds(lower, upper)
    gaussian_prior = None if prior is None else GaussianPrior.from_spec(prior, names)
    problem = Problem(options, robust, int(horizon), tuple(free), transform, gaussian_prior,
                      () if gaussian_prior is None else tuple(names.index(n) for n in gaussian_prior.names))

    frames = as_frames(data)
    datasets = [inputs for _, inputs in prepare_datasets(structure, theta0, frames, time, hold, time_unit)]

    value_and_grad, hessian, theta_of_z, _ = compiled(structure, problem)
    args = problem.arguments(theta0)

    def vg(z):
        return value_and_grad(z, *args, datasets)

    def hess(z):
        return hessian(z, *args, datasets)

    free_theta0 = theta0[list(free)]
    label = "log-likelihood" if criterion == "ml" and robust is None and horizon == 1 else "criterion"
    optima = []
    with FitProgress(progress, starts, label) as shown:
        # The optimiser minimises −(criterion); progress shows the criterion itself.
        def report(iteration, stage, f, g):
            shown.iteration(iteration, stage, -f, float(np.max(np.abs(g))))

        for i, z0 in enumerate(_starting_points(transform, free_theta0, starts, seed)):
            shown.begin_start(i)
            optimum = _minimise(vg, hess, z0, maxiter, report)
            shown.end_start(-optimum.value, optimum.iterations, optimum.converged, optimum.message)
            optima.append(optimum)
    best = min(optima, key=lambda o: o.value if np.isfinite(o.value) else np.inf)
    theta = np.asarray(theta_of_z(jnp.asarray(best.z), *args[:3]))
    settings = dict(time=time, hold=hold, method=options.method, form=options.form, substeps=options.substeps,
                    iterations=options.iterations, criterion=criterion, robust=robust, horizon=int(horizon),
                    starts=starts, time_unit=time_unit, prior=prior)
    return build_result(model, frames, theta, problem, best, optima, settings)
