"""The minimiser of the negative log-posterior in unbounded coordinates z.

Fisher scoring far from the optimum, then Newton's method on the exact Hessian,
inside a trust region (Nocedal & Wright, algorithm 4.1, with the subproblem
solved exactly by eigendecomposition).  An exact evaluation returns value,
gradient and Hessian from one compiled program, a scoring one value, gradient
and the innovations' expected information from another, so convergence near the
optimum is quadratic while the steps far from it cost about a gradient.
The trust region, not a line search, keeps it safe far from the optimum: where
the Hessian is indefinite the step follows negative curvature, and a
non-finite evaluation is a rejected step.  A point is called converged only
where it is a minimum to working precision (see [`_stationary()`][greyid.estimate.optimize._stationary]), so a
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
#: Longer trial steps, by value alone, after a scoring step held back by the trust region
#: did well (long series, where a value costs a few scoring steps' tenth).
MAX_EXPANSIONS = 4
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
            # Along a direction of zero curvature and zero slope the model is flat: no
            # reason to move (Fisher's matrix where a parameter has no effect); along
            # negative curvature, to the region's edge.
            if w[0] < 0:
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


#: Largest move of a log or logistic coordinate z in one step (estimation's step_limit).
MAX_STEP = 10.0

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

    def __init__(self, n: int, step_limit: np.ndarray | float = np.inf):
        self.step_limit = step_limit
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
        jump = EXTRAPOLATION * step
        return np.clip(jump, -2 * self.step_limit, 2 * self.step_limit)


#: Scoring hands over to exact Newton steps once its model predicts less than this
#: decrease of the criterion (½gᵀF⁻¹g) and its steps are no longer held back by the
#: trust region: close enough for quadratic convergence.
HANDOVER_DECREASE = 1.0
#: ... or once it converges slowly: this many full (not region-limited) steps in a
#: row, each decreasing the criterion by more than SLOW_RATIO times the one before.
SLOW_STEPS = 3
SLOW_RATIO = 0.5
#: A search that gains less than STALL_GAIN in the criterion (log-likelihood units)
#: over STALL_STEPS accepted steps, the last about as much as the others (so not
#: converging quadratically), where the Hessian has a flat or curved-down
#: direction, crawls along a ridge towards a limit at infinity (a sensor's time
#: constant → 0): it stops there, not converged, rather than crawl on for a
#: few hundredths of a log-likelihood unit, far below what a test or an interval sees.
STALL_STEPS = 10
STALL_GAIN = 0.05


def _crawling(gains: list[float]) -> bool:
    """The last STALL_STEPS steps gained less than STALL_GAIN together, the last about as
    much as the others: crawling, not converging."""
    window = gains[-STALL_STEPS:]
    return len(window) == STALL_STEPS and sum(window) < STALL_GAIN and window[-1] > 0.1 * np.mean(window)


#: Kinds of evaluation a search asks for: (f, g, H) exact, (f, g, F) scoring, (f,) value.
EXACT, SCORING, VALUE, GRADIENT = "exact", "scoring", "value", "gradient"


def settle(outputs) -> tuple[tuple, bool]:
    """An evaluation's outputs as float arrays, and whether all of them are finite."""
    out = tuple(np.asarray(a, dtype=float) for a in outputs)
    return out, all(np.all(np.isfinite(a)) for a in out)


class Search:
    """One minimisation, written as a generator of evaluation requests.

    `requests()` yields ``(kind, z)`` (kind EXACT, SCORING or VALUE) and
    receives ``(outputs, finite)`` (see [`settle()`][greyid.estimate.optimize.settle]); it returns the
    [`Optimum`][greyid.estimate.optimize.Optimum].  So one search runs alone
    ([`newton_trust_region()`][greyid.estimate.optimize.newton_trust_region]) or
    beside others whose requests are evaluated together in one batched program
    ([`batch`][greyid.estimate.batch]: the starts of a fit, the data sets of a fleet), each with its
    own trust region and convergence.  ``z``, ``f`` and ``iterations`` show
    where the search stands.
    """

    def __init__(self, z0: np.ndarray, maxiter: int = 500, report: Callable = _no_report,
                 scoring: bool = False, value: bool = False, handover: float = HANDOVER_DECREASE,
                 step_limit: np.ndarray | float = np.inf, hessian: np.ndarray | None = None,
                 expand: bool = False):
        self.z = np.asarray(z0, dtype=float)
        self.f, self.iterations = np.inf, 0
        self.gradient = self.hessian = None
        self.history: list[float] = []  # the criterion after each accepted step
        self.maxiter, self.report, self.scoring, self.value = maxiter, report, scoring, value
        self.handover, self.step_limit = handover, step_limit
        self.initial_hessian = None if hessian is None else np.array(hessian, dtype=float)
        self.expand = expand
        self.evaluations = 0
        self.stage = SCORING if scoring else "newton"

    def _ask(self, kind, z):
        self.evaluations += 1
        return (yield kind, z)

    def requests(self):
        """Newton steps in a scaled trust region, after Fisher scoring if it is available.

        The search takes Fisher-scoring steps first (F the expected information,
        positive semi-definite and about a gradient's cost) and hands over to exact
        Newton steps near the optimum or where scoring converges slowly (see
        HANDOVER_DECREASE, SLOW_STEPS); the optimum's Hessian is always the exact
        one.  The region is the ellipsoid ‖D p‖ ≤ Δ with D_i = √|H_ii| (the largest
        seen so far, as in MINPACK), so steps do not depend on the units of the
        parameters; ``step_limit`` caps each coordinate's move per step (MAX_STEP
        for log and logistic coordinates).  ``handover=0`` keeps scoring up to its
        own convergence (long series, where one exact Hessian costs dozens of
        scoring steps).  With value evaluations a Newton trial point (or a scoring
        one after a rejection) is judged on its value first, the derivatives taken
        only where it is accepted.

        With ``hessian`` (a Hessian approximation at or near the start) the search is
        quasi-Newton: it asks for values and gradients only (kind GRADIENT) and
        updates the approximation by BFGS after each accepted step, for warm starts
        near the optimum whose Hessian barely changes (the refits of a profile).

        With ``expand`` (long series, where a value costs a tenth of a scoring step) a
        scoring step held back by the region that gains what the model promised is
        followed by up to MAX_EXPANSIONS doubled steps along the region's path, judged
        by value alone, before the derivatives are taken at the best of them.
        """
        step_limit, report = self.step_limit, self.report
        current = SCORING if self.scoring else EXACT
        stage = "newton" if current == EXACT else "scoring"
        quasi = self.initial_hessian
        if quasi is not None:
            current, stage, self.stage = GRADIENT, "quasi-newton", "quasi-newton"
            # BFGS keeps a positive definite approximation so, and only so: |eigenvalues|.
            w0, V0 = np.linalg.eigh(0.5 * (quasi + quasi.T))
            top = max(float(np.max(np.abs(w0))), 1e-300)
            quasi = (V0 * np.maximum(np.abs(w0), SINGULAR * top)) @ V0.T

        def ask(kind, z):
            if kind != GRADIENT:
                return (yield from self._ask(kind, z))
            (f, g), finite = yield from self._ask(kind, z)
            return (f, g, quasi), finite

        def updated(H, p, g_old, g_new):
            """BFGS: the approximation made to map the step p onto the change of gradient."""
            y, Hp = np.asarray(g_new) - np.asarray(g_old), H @ p
            if y @ p <= 1e-12 * np.linalg.norm(y) * np.linalg.norm(p) or p @ Hp <= 0:
                return H  # no curvature information along p: keep H positive definite
            return H - np.outer(Hp, Hp) / (p @ Hp) + np.outer(y, y) / (y @ p)

        z = self.z
        (f, g, H), finite = yield from ask(current, z)
        if not finite:
            raise NotFiniteError("the criterion or its derivatives are not finite at the starting values")
        f = float(f)
        self._accept(z, f, g, H, 0)
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
        ceiling = np.inf  # the last step length rejected, which the region grows back to slowly
        crawl = _Crawl(len(z), step_limit)
        slow, last_decrease, interior, rejected = 0, np.inf, True, False
        gains: list[float] = []  # decrease of each accepted step, for the stall test

        def hand_over():
            """From scoring to exact Newton steps: the exact Hessian at the current point."""
            nonlocal current, stage, f, g, H, d, w, V, crawl
            (f_exact, g, H), finite = yield from ask(EXACT, z)
            if not finite:  # the Hessian alone can overflow where the value does not
                raise NotFiniteError("the criterion's Hessian is not finite during the search")
            f, current, stage, crawl = float(f_exact), EXACT, "newton", _Crawl(len(z), step_limit)
            self.stage = stage
            d, w, V = eigen(H)

        converged, message = False, "maximum number of iterations reached"
        while iterations < self.maxiter:
            a = V.T @ (g / d)
            stalled = _crawling(gains) and not w[0] > SINGULAR * max(abs(w[-1]), 1e-300)
            if stage == "scoring":
                positive = w > SINGULAR * max(abs(w[-1]), 1e-300)
                expected = 0.5 * float(np.sum(a[positive] ** 2 / w[positive]))
                # Close only if scoring's own steps fit in the region: steps held back by it
                # follow a flat direction, where its small prediction says nothing.
                close = expected < self.handover and interior
                if close or slow >= SLOW_STEPS or stalled or _stationary(f, g, w, a):
                    yield from hand_over()
                    gains.clear()
                    continue
            elif _stationary(f, g, w, a):
                converged, message = True, "converged: Newton decrement below tolerance"
                break
            elif stalled:
                message = (f"stalled: the last {STALL_STEPS} steps gained {sum(gains[-STALL_STEPS:]):.2g} in "
                           "total along a flat or curved-down direction (the optimum may lie at a limit)")
                break
            q = trust_region_step(w, V, g / d, radius)  # the step in scaled coordinates q = D p
            p = q / d
            if np.any(np.abs(p) > step_limit):
                # Beyond e^±10 a log or logistic coordinate has no more to give; longer steps
                # along a flat model only carry the search off to a bound.  Clipped coordinate
                # by coordinate, so the others keep their step.
                p = np.clip(p, -step_limit, step_limit)
                q = d * p
                clipped = True
            else:
                clipped = False
            predicted = -(g @ p + 0.5 * p @ (H @ p))
            boundary = clipped or np.linalg.norm(q) >= 0.99 * radius
            expanding = self.expand and stage == "scoring" and boundary
            # Judge by the value alone where a rejection is likely to waste the derivatives:
            # exact Newton steps (costly), scoring steps after a rejection, or steps that may grow.
            judged = self.value and (stage == "newton" or rejected or expanding) and quasi is None
            if judged:
                (f_new,), finite = yield from ask(VALUE, z + p)
            else:
                (f_new, g_new, H_new), finite = yield from ask(current, z + p)
            actual = f - f_new if finite else -np.inf
            rho = actual / predicted if predicted > 0 else (1.0 if actual >= 0 else -np.inf)
            step = np.linalg.norm(q)
            interior = step < 0.99 * radius and not clipped  # a full step of the model, not held back
            if rho < 0.25:
                radius, ceiling = 0.25 * step, step
            elif rho > 0.75 and step >= 0.99 * radius:
                # Not straight back to a length that just failed: on a curved ridge the region
                # would cycle 5 → 10 → 20 (rejected) → 5, wasting every third evaluation.
                radius = 2.0 * radius if 2.0 * radius < 0.9 * ceiling else max(radius, 0.9 * ceiling)
                ceiling *= 1.5
            if judged and expanding and rho > 0.75:
                # A step held back by the region that did as well as the model promised: longer
                # ones along the region's path, judged by their values, before the derivatives.
                for _ in range(MAX_EXPANSIONS):
                    longer = trust_region_step(w, V, g / d, 2.0 * step) / d
                    longer = np.clip(longer, -step_limit, step_limit)
                    if np.linalg.norm(d * longer) < 1.01 * step:
                        break  # the model's full step, or the coordinates' limits, reached
                    (f_longer,), finite = yield from ask(VALUE, z + longer)
                    if not finite or f_longer >= f_new:
                        break
                    p, q, f_new = longer, d * longer, float(f_longer)
                    actual, step = f - f_new, float(np.linalg.norm(d * longer))
                    radius = max(radius, 2.0 * step)
            if rho > 1e-4 and judged:
                (f_new, g_new, H_new), finite = yield from ask(current, z + p)
                if not finite:  # the derivatives alone overflow: a rejected step
                    radius, rho = 0.25 * step, -np.inf
            rejected = rho <= 1e-4
            if rho > 1e-4:
                # Slow: full steps (not held back by the region) that gain almost as much as the last.
                slow = slow + 1 if interior and actual > SLOW_RATIO * last_decrease else 0
                last_decrease = actual
                gains.append(actual)
                if quasi is not None:
                    quasi = H_new = updated(H, p, g, g_new)
                z, f, g, H = z + p, float(f_new), g_new, H_new
                d, w, V = eigen(H)
                iterations += 1
                self._accept(z, f, g, H, iterations)
                report(iterations, stage, f, g)
                jump = crawl.update(p)
                promising = jump is not None
                if promising and self.value:
                    (f_try,), finite = yield from ask(VALUE, z + jump)
                    promising = finite and float(f_try) < f
                if promising:
                    (f_try, g_try, H_try), finite = yield from ask(current, z + jump)
                    if finite and float(f_try) < f:
                        last_decrease = f - float(f_try)
                        gains.append(last_decrease)
                        if quasi is not None:
                            quasi = H_try = updated(H, jump, g, g_try)
                        z, f, g, H = z + jump, float(f_try), g_try, H_try
                        d, w, V = eigen(H)
                        iterations += 1
                        self._accept(z, f, g, H, iterations)
                        report(iterations, "extrapolation", f, g)
            elif radius < 1e-10 * (1.0 + np.linalg.norm(d * z)):
                if stage == "scoring":  # the expected information misleads here: exact steps decide
                    yield from hand_over()
                    radius = max(radius, 1e-3)
                    continue
                # Rounding in f can hide the last decrease: a point without negative
                # curvature and with a small gradient is then the minimum to working precision.
                flat = w[0] >= -SINGULAR * max(abs(w[-1]), 1e-300) and np.max(np.abs(g)) < COLLAPSE_GRADIENT
                converged = bool(flat)
                message = ("converged: no step decreases the criterion at working precision" if flat
                           else "no step decreases the criterion (trust region collapsed)")
                break
        if stage == "scoring":
            yield from hand_over()
        if not converged and _stationary(f, g, w, V.T @ (g / d)):
            converged, message = True, "converged: Newton decrement below tolerance"
        self._accept(z, f, g, H, iterations)
        return Optimum(z, f, g, H, iterations, self.evaluations, converged, message)

    def _accept(self, z, f, g, H, iterations):
        if iterations > self.iterations or not self.history:
            self.history.append(f)
        self.z, self.f, self.gradient, self.hessian, self.iterations = z, f, g, H, iterations

    def stopped(self, message: str) -> Optimum:
        """Where the search stands, as an unconverged [`Optimum`][greyid.estimate.optimize.Optimum] (a pruned start)."""
        return Optimum(self.z, self.f, self.gradient, self.hessian, self.iterations, self.evaluations, False,
                       message)


def run_alone(search: Search, programs: dict[str, Callable]) -> Optimum:
    """Run one [`Search`][greyid.estimate.optimize.Search], evaluating each request with ``programs[kind](z)``."""
    requests = search.requests()
    try:
        kind, z = next(requests)
        while True:
            kind, z = requests.send(settle(programs[kind](z)))
    except StopIteration as done:
        return done.value


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
    from which [`Search`][greyid.estimate.optimize.Search] takes exact Newton steps, so the optimum, its Hessian and the
    convergence test are those of Newton's method.  It stops at ``max_evaluations``, where the
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


def newton_trust_region(evaluate: Callable, z0: np.ndarray, maxiter: int = 500,
                        report: Callable = _no_report, scoring: Callable | None = None,
                        value: Callable | None = None, handover: float = HANDOVER_DECREASE,
                        step_limit: np.ndarray | float = np.inf) -> Optimum:
    """Minimise with ``evaluate(z) -> (f, g, H)``, after Fisher scoring with ``scoring(z) -> (f, g, F)``
    if given, judging trial points by ``value(z) -> f`` if given; see
    [`Search.requests()`][greyid.estimate.optimize.Search.requests]."""
    search = Search(z0, maxiter, report, scoring is not None, value is not None, handover, step_limit)
    programs = {EXACT: evaluate, SCORING: scoring, VALUE: None if value is None else lambda z: (value(z),)}
    return run_alone(search, programs)
