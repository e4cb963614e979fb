"""The minimiser of the negative log-posterior in unbounded coordinates z.

Newton's method on the exact Hessian inside a trust region (Nocedal & Wright,
algorithm 4.1, with the subproblem solved exactly by eigendecomposition).
Each evaluation returns value, gradient and Hessian from one compiled program,
so a fit compiles one program, and convergence near the optimum is quadratic.
The trust region, not a line search, keeps it safe far from the optimum: where
the Hessian is indefinite the step follows negative curvature, and a
non-finite evaluation is a rejected step.  A point is called converged only
where it is a minimum to working precision (see :func:`_stationary`), so a
stalled search is reported as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ModelError

#: Newton decrement gᵀH⁻¹g, relative to max(1, |f|), below which a point with a
#: positive definite Hessian is the optimum to the precision of f.
DECREMENT_TOLERANCE = 1e-12
#: Eigenvalues of the (scaled) Hessian within ±SINGULAR·max|eigenvalue| of zero make
#: it singular: an ill-determined direction, where only the gradient can tell.
SINGULAR = 1e-8
#: Gradient (max-norm, in z) below which a point with a singular Hessian is stationary.
GRADIENT_TOLERANCE = 1e-6
#: Where no step decreases the criterion any more, the gradient below which that is
#: rounding at a minimum rather than a failed search.
COLLAPSE_GRADIENT = 1e-4
#: Smallest scale of a coordinate in the trust region, relative to the largest.
SCALE_FLOOR = 1e-6


class NotFiniteError(ModelError):
    """The criterion or its derivatives are not finite where the search starts."""


@dataclass
class Optimum:
    z: np.ndarray
    value: float
    gradient: np.ndarray
    hessian: np.ndarray
    iterations: int
    evaluations: int
    converged: bool
    message: str


def _no_report(iteration: int, stage: str, f: float, g: np.ndarray) -> None:
    pass


class _Counted:
    """Wraps an evaluation: counts calls and says whether everything came back finite."""

    def __init__(self, fun: Callable):
        self.fun = fun
        self.evaluations = 0

    def __call__(self, z):
        self.evaluations += 1
        out = tuple(np.asarray(a, dtype=float) for a in self.fun(z))
        finite = all(np.all(np.isfinite(a)) for a in out)
        return out, finite


def _stationary(f: float, g: np.ndarray, w: np.ndarray, a: np.ndarray) -> bool:
    """A minimum to working precision (a = Vᵀg in the eigenbasis of the Hessian, w ascending).

    With a clearly positive definite Hessian, the Newton decrement gᵀH⁻¹g must be
    negligible against |f|; with a (nearly) singular one — an ill-determined
    direction — the gradient must vanish instead; a direction of clearly negative
    curvature is a saddle point or a ridge, never a minimum.
    """
    largest = max(abs(w[-1]), 1e-300)
    if w[0] < -SINGULAR * largest:
        return False
    if w[0] > SINGULAR * largest:
        return float(np.sum(a * a / w)) < DECREMENT_TOLERANCE * max(1.0, abs(f))
    return bool(np.max(np.abs(g)) < GRADIENT_TOLERANCE)


def trust_region_step(w: np.ndarray, V: np.ndarray, g: np.ndarray, radius: float) -> np.ndarray:
    """Minimiser of gᵀp + ½pᵀHp over ‖p‖ ≤ radius, with H = V diag(w) Vᵀ (w ascending).

    The Newton step when it is inside the region and H is positive definite;
    otherwise p(λ) = −(H + λI)⁻¹g on the boundary, λ > max(0, −w₀) found by
    safeguarded Newton iterations on 1/‖p(λ)‖ (Moré & Sorensen), and in the
    "hard case" (g orthogonal to the lowest eigenvector) the step is completed
    along that eigenvector.
    """
    a = V.T @ g
    if w[0] > 0:
        p = -a / w
        if np.linalg.norm(p) <= radius:
            return V @ p
    low = max(0.0, -w[0])
    lowest = w <= w[0] + 1e-12 * max(1.0, abs(w[-1]))
    if np.all(np.abs(a[lowest]) <= 1e-12 * max(np.linalg.norm(a), 1e-300)):  # hard case
        shift = w[~lowest] + low
        p = np.zeros_like(a)
        p[~lowest] = -a[~lowest] / np.where(shift > 0, shift, 1.0)
        rest = radius**2 - float(p @ p)
        if rest >= 0:
            p[np.flatnonzero(lowest)[0]] += np.sqrt(rest)
            return V @ p
    lam_lo, lam_hi = low, low + np.linalg.norm(a) / radius + 1e-300
    lam = lam_hi
    for _ in range(100):
        d = w + lam
        norm = np.linalg.norm(a / d)
        if abs(norm - radius) <= 1e-6 * radius:
            break
        if norm > radius:
            lam_lo = lam
        else:
            lam_hi = lam
        # Newton on φ(λ) = 1/‖p(λ)‖ − 1/radius, which is nearly linear in λ.
        slope = float(np.sum(a * a / d**3)) / norm**3
        trial = lam - (1.0 / norm - 1.0 / radius) / slope if slope > 0 else np.nan
        lam = trial if lam_lo < trial < lam_hi else 0.5 * (lam_lo + lam_hi)
    return V @ (-a / (w + lam))


#: Accepted steps in a row, each of about the same length and sign in a coordinate,
#: after which a jump of EXTRAPOLATION steps along those coordinates is tried.
CRAWL_STEPS = 2
EXTRAPOLATION = 8.0


class _Crawl:
    """Steps that crawl: along an exponential tail (a noise intensity exp(p) → 0, an
    estimate running to its bound in z, a ridge such as R·C = const) each Newton step
    has about the same length and direction while the criterion's decrease shrinks
    geometrically — linear convergence, half the iterations of an 18-parameter
    building fit.  After CRAWL_STEPS such steps a jump of EXTRAPOLATION steps along
    the last one is proposed; the search takes it only if it lowers the criterion.
    """

    def __init__(self, n: int):
        self.previous = np.zeros(n)
        self.streak = 0

    def update(self, step: np.ndarray) -> np.ndarray | None:
        norm, before = np.linalg.norm(step), np.linalg.norm(self.previous)
        aligned = norm > 0 and before > 0 and step @ self.previous > 0.95 * norm * before
        steady = aligned and 0.5 < norm / before < 2.0
        self.streak = self.streak + 1 if steady else 0
        self.previous = step.copy()
        if self.streak < CRAWL_STEPS:
            return None
        self.streak = 0
        return EXTRAPOLATION * step


def newton_trust_region(evaluate: Callable, z0: np.ndarray, maxiter: int = 500,
                        report: Callable = _no_report) -> Optimum:
    """Minimise with exact Newton steps in a scaled trust region; ``evaluate(z) -> (f, g, H)``.

    The region is the ellipsoid ‖D p‖ ≤ Δ with D_i = √|H_ii| (the largest seen so
    far, as in MINPACK), so steps do not depend on the units of the parameters.
    """
    run = _Counted(evaluate)
    z = np.asarray(z0, dtype=float)
    (f, g, H), finite = run(z)
    if not finite:
        raise NotFiniteError("the criterion or its derivatives are not finite at the starting values")
    f = float(f)
    scale = np.zeros(len(z))

    def eigen(H):
        nonlocal scale
        scale = np.maximum(scale, np.sqrt(np.abs(np.diag(H))))
        # A coordinate with (nearly) no curvature where the search starts — an initial
        # state whose only observation lies in a robust norm's linear part — would get a
        # scale near 0 and trial steps of 1e16 in it, and the region would collapse
        # before any step is taken: its scale is floored relative to the others.
        d = np.maximum(scale, SCALE_FLOOR * scale.max()) if scale.max() > 0 else np.ones_like(scale)
        Hs = 0.5 * (H + H.T) / np.outer(d, d)
        return d, *np.linalg.eigh(Hs)

    d, w, V = eigen(H)
    # The first region admits the full Newton step (or, where H is indefinite, a step
    # as long as the scaled gradient) up to a length of 10 in scaled units.
    a = V.T @ (g / d)
    radius = float(np.clip(np.linalg.norm(a / w) if w[0] > 0 else np.linalg.norm(a), 1.0, 10.0))
    iterations = 0  # accepted steps
    crawl = _Crawl(len(z))
    converged, message = False, "maximum number of iterations reached"
    while iterations < maxiter:
        if _stationary(f, g, w, V.T @ (g / d)):
            converged, message = True, "converged: Newton decrement below tolerance"
            break
        q = trust_region_step(w, V, g / d, radius)  # the step in scaled coordinates q = D p
        p = q / d
        predicted = -(g @ p + 0.5 * p @ (H @ p))
        (f_new, g_new, H_new), finite = run(z + p)
        actual = f - f_new if finite else -np.inf
        rho = actual / predicted if predicted > 0 else (1.0 if actual >= 0 else -np.inf)
        step = np.linalg.norm(q)
        if rho < 0.25:
            radius = 0.25 * step
        elif rho > 0.75 and step >= 0.99 * radius:
            radius = 2.0 * radius
        if rho > 1e-4:
            z, f, g, H = z + p, float(f_new), g_new, H_new
            d, w, V = eigen(H)
            iterations += 1
            report(iterations, "newton", f, g)
            jump = crawl.update(p)
            if jump is not None:
                (f_try, g_try, H_try), finite = run(z + jump)
                if finite and float(f_try) < f:
                    z, f, g, H = z + jump, float(f_try), g_try, H_try
                    d, w, V = eigen(H)
                    iterations += 1
                    report(iterations, "extrapolation", f, g)
        elif radius < 1e-10 * (1.0 + np.linalg.norm(d * z)):
            # Rounding in f can hide the last decrease: a point without negative
            # curvature and with a small gradient is then the minimum to working precision.
            flat = w[0] >= -SINGULAR * max(abs(w[-1]), 1e-300) and np.max(np.abs(g)) < COLLAPSE_GRADIENT
            converged = bool(flat)
            message = ("converged: no step decreases the criterion at working precision" if flat
                       else "no step decreases the criterion (trust region collapsed)")
            break
    if not converged and _stationary(f, g, w, V.T @ (g / d)):
        converged, message = True, "converged: Newton decrement below tolerance"
    return Optimum(z, f, g, H, iterations, run.evaluations, converged, message)
