"""Newton's method in a scaled trust region, after Fisher scoring, or with a BFGS matrix (chapter 3).

A search is explicit state: [`Search`][greyid.estimate.trust_region.Search] holds its settings,
[`SearchState`][greyid.estimate.trust_region.SearchState] where it stands, including the
evaluation it asks for next (``state.request``: a kind of
[`greyid.estimate.optimize`][greyid.estimate.optimize] and a point z).  ``search.init()``
starts one, ``search.step(state, answer)`` takes the answer ``(outputs, finite)`` (see
[`settle()`][greyid.estimate.optimize.settle]) and moves to the next request, until
``state.optimum`` is set.  So one search runs alone
([`run_alone()`][greyid.estimate.optimize.run_alone]) or beside others whose requests are
evaluated together by one batched program ([`drive()`][greyid.estimate.batch.drive]).

The method: Fisher-scoring steps first (F the expected information, positive
semi-definite and about a gradient's cost), handing over to exact Newton steps near
the optimum or where scoring converges slowly (HANDOVER_DECREASE, SLOW_STEPS); the
optimum's Hessian is always the exact one.  The region is the ellipsoid ‖D p‖ ≤ Δ with
D_i = √|H_ii| (the largest seen so far, as in MINPACK), so steps do not depend on the
units of the parameters; ``step_limit`` caps each coordinate's move per step (MAX_STEP
for log and logistic coordinates).  With value evaluations a Newton trial point (or a
scoring one after a rejection) is judged on its value first, the derivatives taken only
where it is accepted.  A non-finite evaluation is a rejected step.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .optimize import EXACT, GRADIENT, SCORING, VALUE, NotFiniteError, Optimum, _no_report, run_alone

#: Newton decrement gᵀH⁻¹g, relative to max(1, |f|), below which a point with a
#: positive definite Hessian is the optimum to the precision of f.
DECREMENT_TOLERANCE = 1e-12
#: Eigenvalues of the (scaled) Hessian within ±SINGULAR·max|eigenvalue| of zero make
#: it singular: an ill-determined direction, where only the gradient can tell.
SINGULAR = 1e-8
#: Gradient (max-norm, in z) below which a point with a singular Hessian is stationary.
GRADIENT_TOLERANCE = 1e-6
#: Largest move of a log or logistic coordinate z in one step (estimation's step_limit).
MAX_STEP = 10.0

#: Scoring hands over to exact Newton steps once its model predicts less than this
#: decrease of the criterion (½gᵀF⁻¹g) and its steps are no longer held back by the
#: trust region: close enough for quadratic convergence.
HANDOVER_DECREASE = 1.0
#: A search that gains less than STALL_GAIN in the criterion (log-likelihood units)
#: over STALL_STEPS accepted steps, the last about as much as the others (so not
#: converging quadratically), where the Hessian has a flat or curved-down
#: direction, crawls along a ridge towards a limit at infinity (a sensor's time
#: constant → 0): it stops there, not converged, rather than crawl on for a
#: few hundredths of a log-likelihood unit, far below what a test or an interval sees.
STALL_STEPS = 10
STALL_GAIN = 0.05


#: Longer trial steps, by value alone, after a scoring step held back by the trust region
#: did well (long series, where a value costs a few scoring steps' tenth).
MAX_EXPANSIONS = 4
#: Where no step decreases the criterion any more, the gradient below which that is
#: rounding at a minimum rather than a failed search.
COLLAPSE_GRADIENT = 1e-4
#: Smallest scale of a coordinate in the trust region, relative to the largest.
SCALE_FLOOR = 1e-6
#: Accepted steps in a row, each of about the same length and sign in a coordinate,
#: after which a jump of EXTRAPOLATION steps along those coordinates is tried.
CRAWL_STEPS = 2
EXTRAPOLATION = 8.0
#: ... or once it converges slowly: this many full (not region-limited) steps in a
#: row, each decreasing the criterion by more than SLOW_RATIO times the one before.
SLOW_STEPS = 3
SLOW_RATIO = 0.5


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


def crawling(gains: list[float]) -> bool:
    """The last STALL_STEPS steps gained less than STALL_GAIN together, the last about as
    much as the others: crawling, not converging."""
    window = gains[-STALL_STEPS:]
    return len(window) == STALL_STEPS and sum(window) < STALL_GAIN and window[-1] > 0.1 * np.mean(window)


@dataclass
class Trial:
    """The step under evaluation: p in z, q = D p scaled, the model's predicted decrease, and how it is
    judged (by its value first, and whether longer steps may follow)."""

    p: np.ndarray
    q: np.ndarray
    predicted: float
    clipped: bool
    judged: bool
    expanding: bool
    f: float = np.inf
    g: np.ndarray | None = None
    H: np.ndarray | None = None
    actual: float = -np.inf
    rho: float = -np.inf
    step: float = 0.0
    expansions: int = 0


@dataclass
class SearchState:
    """Where a search stands: the current point and its derivatives, the region, the counters, and the
    evaluation asked for (``request``) and what for (``phase``); ``optimum`` once it has ended."""

    z: np.ndarray
    f: float = np.inf
    g: np.ndarray | None = None
    H: np.ndarray | None = None
    stage: str = "newton"  # "scoring", "newton" or "quasi-newton"
    current: str = EXACT  # the kind of a full evaluation in this stage
    quasi: np.ndarray | None = None  # the BFGS matrix of a quasi-Newton search
    scale: np.ndarray | None = None  # D before its floor: the largest √|H_ii| seen
    d: np.ndarray | None = None
    w: np.ndarray | None = None  # eigenvalues (ascending) and vectors of the scaled Hessian
    V: np.ndarray | None = None
    radius: float = 1.0
    ceiling: float = np.inf  # the last step length rejected, which the region grows back to slowly
    crawl_previous: np.ndarray | None = None  # the last accepted step and how many alike in a row
    crawl_streak: int = 0
    slow: int = 0
    last_decrease: float = np.inf
    interior: bool = True
    rejected: bool = False
    gains: list[float] = field(default_factory=list)  # decrease of each accepted step, for the stall test
    iterations: int = 0  # accepted steps
    evaluations: int = 0
    history: list[float] = field(default_factory=list)  # the criterion after each accepted step
    trial: Trial | None = None
    jump: np.ndarray | None = None
    phase: str = "start"
    request: tuple[str, np.ndarray] | None = None
    converged: bool = False
    message: str = "maximum number of iterations reached"
    optimum: Optimum | None = None


@dataclass
class Search:
    """The settings of one minimisation from ``z0`` (see the module doc).

    Parameters
    ----------
    z0 : array
        The starting point in unbounded coordinates.
    maxiter : int
        Accepted steps allowed.
    report : callable
        ``report(iteration, stage, f, g)`` after each accepted step.
    scoring : bool
        Fisher-scoring steps first (requests of kind SCORING).
    value : bool
        Judge trial points by their value first (requests of kind VALUE).
    handover : float
        Scoring hands over once its model predicts less decrease than this; 0 keeps scoring
        up to its own convergence (long series, where an exact Hessian costs dozens of scoring steps).
    step_limit : array or float
        The largest move of each coordinate in one step.
    hessian : array, optional
        A Hessian approximation at or near the start: the search is then quasi-Newton, asking for
        values and gradients only (kind GRADIENT) and updating it by BFGS after each accepted step
        (warm starts near the optimum whose Hessian barely changes, the refits of a profile).
    expand : bool
        After a scoring step held back by the region that gains what the model promised, up to
        MAX_EXPANSIONS doubled steps along the region's path, judged by value alone (long series,
        where a value costs a tenth of a scoring step).
    """

    z0: np.ndarray
    maxiter: int = 500
    report: Callable = _no_report
    scoring: bool = False
    value: bool = False
    handover: float = HANDOVER_DECREASE
    step_limit: np.ndarray | float = np.inf
    hessian: np.ndarray | None = None
    expand: bool = False

    # ---------------------------------------------------------------- the protocol

    def init(self) -> SearchState:
        """The state before the first evaluation, which it requests."""
        z = np.asarray(self.z0, dtype=float)
        state = SearchState(z=z, scale=np.zeros(len(z)), crawl_previous=np.zeros(len(z)))
        state.current = SCORING if self.scoring else EXACT
        state.stage = "newton" if state.current == EXACT else "scoring"
        if self.hessian is not None:
            state.current, state.stage = GRADIENT, "quasi-newton"
            # BFGS keeps a positive definite approximation so, and only so: |eigenvalues|.
            quasi = np.array(self.hessian, dtype=float)
            w0, V0 = np.linalg.eigh(0.5 * (quasi + quasi.T))
            top = max(float(np.max(np.abs(w0))), 1e-300)
            state.quasi = (V0 * np.maximum(np.abs(w0), SINGULAR * top)) @ V0.T
        return self._ask(state, "start", state.current, z)

    def step(self, state: SearchState, answer: tuple) -> SearchState:
        """Take the answer ``(outputs, finite)`` to ``state.request`` and move on to the next request
        (or to the optimum).  The state is updated in place and returned.

        Raises
        ------
        NotFiniteError
            The criterion or its derivatives are not finite at the start, or the Hessian at a hand-over.
        """
        outputs, finite = answer
        if state.request is not None and state.request[0] == GRADIENT:
            outputs = (*outputs, state.quasi)  # (f, g) and the BFGS matrix in place of a Hessian
        state.request = None
        return getattr(self, f"_after_{state.phase}")(state, outputs, finite)

    # ---------------------------------------------------------------- requests and the loop

    @staticmethod
    def _ask(state: SearchState, phase: str, kind: str, z: np.ndarray) -> SearchState:
        state.evaluations += 1
        state.phase, state.request = phase, (kind, z)
        return state

    def _eigen(self, state: SearchState, H) -> None:
        state.scale = np.maximum(state.scale, np.sqrt(np.abs(np.diag(H))))
        scale = state.scale
        # A coordinate with (nearly) no curvature where the search starts — an initial
        # state whose only observation lies in a robust norm's linear part — would get a
        # scale near 0 and trial steps of 1e16 in it, and the region would collapse
        # before any step is taken: its scale is floored relative to the others.
        d = np.maximum(scale, SCALE_FLOOR * scale.max()) if scale.max() > 0 else np.ones_like(scale)
        Hs = 0.5 * (H + H.T) / np.outer(d, d)
        state.d = d
        state.w, state.V = np.linalg.eigh(Hs)

    def _accept(self, state: SearchState, z, f, g, H, iterations: int) -> None:
        if iterations > state.iterations or not state.history:
            state.history.append(f)
        state.z, state.f, state.g, state.H, state.iterations = z, f, g, H, iterations

    def _after_start(self, state, outputs, finite):
        if not finite:
            raise NotFiniteError("the criterion or its derivatives are not finite at the starting values")
        f, g, H = outputs
        self._accept(state, state.z, float(f), g, H, 0)
        self._eigen(state, H)
        # The first region admits the full Newton step (or, where H is indefinite, a step
        # as long as the scaled gradient) up to a length of 10 in scaled units.
        w, a = state.w, state.V.T @ (g / state.d)
        state.radius = float(np.clip(np.linalg.norm(a / w) if w[0] > 0 else np.linalg.norm(a), 1.0, 10.0))
        return self._next(state)

    def _hand_over(self, state, phase: str) -> SearchState:
        """From scoring to exact Newton steps: the exact Hessian at the current point."""
        return self._ask(state, phase, EXACT, state.z)

    def _handed_over(self, state, outputs, finite) -> None:
        if not finite:  # the Hessian alone can overflow where the value does not
            raise NotFiniteError("the criterion's Hessian is not finite during the search")
        f_exact, state.g, state.H = outputs
        state.f, state.current, state.stage = float(f_exact), EXACT, "newton"
        state.crawl_previous, state.crawl_streak = np.zeros(len(state.z)), 0
        self._eigen(state, state.H)

    def _after_handover(self, state, outputs, finite):
        self._handed_over(state, outputs, finite)
        state.gains.clear()
        return self._next(state)

    def _after_collapse_handover(self, state, outputs, finite):
        self._handed_over(state, outputs, finite)
        state.radius = max(state.radius, 1e-3)
        return self._next(state)

    def _next(self, state: SearchState) -> SearchState:
        """The top of the search's loop: converged, stalled, handing over, or the next trial step."""
        if state.iterations >= self.maxiter:
            return self._finish(state)
        z, f, g, H, d, w, V = state.z, state.f, state.g, state.H, state.d, state.w, state.V
        a = V.T @ (g / d)
        top = max(abs(w[-1]), 1e-300)
        stalled = crawling(state.gains) and not w[0] > SINGULAR * top
        if state.stage == "scoring":
            positive = w > SINGULAR * top
            expected = 0.5 * float(np.sum(a[positive] ** 2 / w[positive]))
            # Close only if scoring's own steps fit in the region: steps held back by it
            # follow a flat direction, where its small prediction says nothing.
            close = expected < self.handover and state.interior
            if close or state.slow >= SLOW_STEPS or stalled or _stationary(f, g, w, a):
                return self._hand_over(state, "handover")
        elif _stationary(f, g, w, a):
            state.converged, state.message = True, "converged: Newton decrement below tolerance"
            return self._finish(state)
        elif stalled:
            state.message = (f"stalled: the last {STALL_STEPS} steps gained {sum(state.gains[-STALL_STEPS:]):.2g} in "
                             "total along a flat or curved-down direction (the optimum may lie at a limit)")
            return self._finish(state)
        q = trust_region_step(w, V, g / d, state.radius)  # the step in scaled coordinates q = D p
        p = q / d
        step_limit = self.step_limit
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
        boundary = clipped or np.linalg.norm(q) >= 0.99 * state.radius
        expanding = self.expand and state.stage == "scoring" and boundary
        # Judge by the value alone where a rejection is likely to waste the derivatives:
        # exact Newton steps (costly), scoring steps after a rejection, or steps that may grow.
        judged = self.value and (state.stage == "newton" or state.rejected or expanding) and state.quasi is None
        state.trial = Trial(p, q, predicted, clipped, judged, expanding)
        if judged:
            return self._ask(state, "trial_value", VALUE, z + p)
        return self._ask(state, "trial", state.current, z + p)

    def _after_trial_value(self, state, outputs, finite):
        (state.trial.f,) = outputs
        return self._judge(state, finite)

    def _after_trial(self, state, outputs, finite):
        trial = state.trial
        trial.f, trial.g, trial.H = outputs
        return self._judge(state, finite)

    def _judge(self, state, finite):
        """The trial's decrease against the model's, and the region's new radius."""
        trial = state.trial
        trial.actual = state.f - trial.f if finite else -np.inf
        predicted, actual = trial.predicted, trial.actual
        trial.rho = actual / predicted if predicted > 0 else (1.0 if actual >= 0 else -np.inf)
        trial.step = step = np.linalg.norm(trial.q)
        state.interior = step < 0.99 * state.radius and not trial.clipped  # a full step, not held back
        if trial.rho < 0.25:
            state.radius, state.ceiling = 0.25 * step, step
        elif trial.rho > 0.75 and step >= 0.99 * state.radius:
            # Not straight back to a length that just failed: on a curved ridge the region
            # would cycle 5 → 10 → 20 (rejected) → 5, wasting every third evaluation.
            radius = state.radius
            state.radius = 2.0 * radius if 2.0 * radius < 0.9 * state.ceiling else max(radius, 0.9 * state.ceiling)
            state.ceiling *= 1.5
        if trial.judged and trial.expanding and trial.rho > 0.75:
            return self._expand(state)
        return self._derivatives(state)

    def _expand(self, state):
        """A step held back by the region that did as well as the model promised: longer ones along the
        region's path, judged by their values, before the derivatives."""
        trial = state.trial
        if trial.expansions >= MAX_EXPANSIONS:
            return self._derivatives(state)
        longer = trust_region_step(state.w, state.V, state.g / state.d, 2.0 * trial.step) / state.d
        longer = np.clip(longer, -self.step_limit, self.step_limit)
        if np.linalg.norm(state.d * longer) < 1.01 * trial.step:
            return self._derivatives(state)  # the model's full step, or the coordinates' limits, reached
        trial.expansions += 1
        state.jump = longer
        return self._ask(state, "expansion", VALUE, state.z + longer)

    def _after_expansion(self, state, outputs, finite):
        trial, longer = state.trial, state.jump
        (f_longer,) = outputs
        if not finite or f_longer >= trial.f:
            return self._derivatives(state)
        trial.p, trial.q, trial.f = longer, state.d * longer, float(f_longer)
        trial.actual, trial.step = state.f - trial.f, float(np.linalg.norm(state.d * longer))
        state.radius = max(state.radius, 2.0 * trial.step)
        return self._expand(state)

    def _derivatives(self, state):
        """A point judged by its value alone and accepted: its derivatives."""
        trial = state.trial
        if trial.rho > 1e-4 and trial.judged:
            return self._ask(state, "derivatives", state.current, state.z + trial.p)
        return self._after_step(state)

    def _after_derivatives(self, state, outputs, finite):
        trial = state.trial
        trial.f, trial.g, trial.H = outputs
        if not finite:  # the derivatives alone overflow: a rejected step
            state.radius, trial.rho = 0.25 * trial.step, -np.inf
        return self._after_step(state)

    def _bfgs(self, H, p, g_old, g_new):
        """BFGS: the approximation made to map the step p onto the change of gradient."""
        y, Hp = np.asarray(g_new) - np.asarray(g_old), H @ p
        if y @ p <= 1e-12 * np.linalg.norm(y) * np.linalg.norm(p) or p @ Hp <= 0:
            return H  # no curvature information along p: keep H positive definite
        return H - np.outer(Hp, Hp) / (p @ Hp) + np.outer(y, y) / (y @ p)

    def _crawl(self, state, step):
        """A jump of EXTRAPOLATION steps after CRAWL_STEPS steps alike (the crawl along an exponential
        tail or a ridge, where each Newton step has about the same length and direction while the
        criterion's decrease shrinks geometrically), or None."""
        norm, before = np.linalg.norm(step), np.linalg.norm(state.crawl_previous)
        aligned = norm > 0 and before > 0 and step @ state.crawl_previous > 0.95 * norm * before
        steady = aligned and 0.5 < norm / before < 2.0
        state.crawl_streak = state.crawl_streak + 1 if steady else 0
        state.crawl_previous = step.copy()
        if state.crawl_streak < CRAWL_STEPS:
            return None
        state.crawl_streak = 0
        jump = EXTRAPOLATION * step
        return np.clip(jump, -2 * self.step_limit, 2 * self.step_limit)

    def _after_step(self, state):
        """An accepted trial becomes the current point; a rejected one shrinks the region."""
        trial = state.trial
        rho = trial.rho
        state.rejected = rho <= 1e-4
        if rho > 1e-4:
            # Slow: full steps (not held back by the region) that gain almost as much as the last.
            state.slow = state.slow + 1 if state.interior and trial.actual > SLOW_RATIO * state.last_decrease else 0
            state.last_decrease = trial.actual
            state.gains.append(trial.actual)
            H_new = trial.H
            if state.quasi is not None:
                state.quasi = H_new = self._bfgs(state.H, trial.p, state.g, trial.g)
            self._accept(state, state.z + trial.p, float(trial.f), trial.g, H_new, state.iterations + 1)
            self._eigen(state, state.H)
            self.report(state.iterations, state.stage, state.f, state.g)
            jump = self._crawl(state, trial.p)
            if jump is None:
                return self._next(state)
            state.jump = jump
            if self.value:
                return self._ask(state, "jump_value", VALUE, state.z + jump)
            return self._ask(state, "jump", state.current, state.z + jump)
        if state.radius < 1e-10 * (1.0 + np.linalg.norm(state.d * state.z)):
            if state.stage == "scoring":  # the expected information misleads here: exact steps decide
                return self._hand_over(state, "collapse_handover")
            # Rounding in f can hide the last decrease: a point without negative
            # curvature and with a small gradient is then the minimum to working precision.
            w = state.w
            flat = w[0] >= -SINGULAR * max(abs(w[-1]), 1e-300) and np.max(np.abs(state.g)) < COLLAPSE_GRADIENT
            state.converged = bool(flat)
            state.message = ("converged: no step decreases the criterion at working precision" if flat
                             else "no step decreases the criterion (trust region collapsed)")
            return self._finish(state)
        return self._next(state)

    def _after_jump_value(self, state, outputs, finite):
        (f_try,) = outputs
        if finite and float(f_try) < state.f:
            return self._ask(state, "jump", state.current, state.z + state.jump)
        return self._next(state)

    def _after_jump(self, state, outputs, finite):
        f_try, g_try, H_try = outputs
        if finite and float(f_try) < state.f:
            state.last_decrease = state.f - float(f_try)
            state.gains.append(state.last_decrease)
            if state.quasi is not None:
                state.quasi = H_try = self._bfgs(state.H, state.jump, state.g, g_try)
            self._accept(state, state.z + state.jump, float(f_try), g_try, H_try, state.iterations + 1)
            self._eigen(state, state.H)
            self.report(state.iterations, "extrapolation", state.f, state.g)
        return self._next(state)

    def _finish(self, state):
        if state.stage == "scoring":
            return self._hand_over(state, "final_handover")
        return self._done(state)

    def _after_final_handover(self, state, outputs, finite):
        self._handed_over(state, outputs, finite)
        return self._done(state)

    def _done(self, state):
        if not state.converged and _stationary(state.f, state.g, state.w, state.V.T @ (state.g / state.d)):
            state.converged, state.message = True, "converged: Newton decrement below tolerance"
        self._accept(state, state.z, state.f, state.g, state.H, state.iterations)
        state.phase = "done"
        state.optimum = Optimum(state.z, state.f, state.g, state.H, state.iterations, state.evaluations,
                                state.converged, state.message)
        return state

    def stopped(self, state: SearchState, message: str) -> Optimum:
        """Where the search stands, as an unconverged [`Optimum`][greyid.estimate.optimize.Optimum] (a pruned
        start)."""
        return Optimum(state.z, state.f, state.g, state.H, state.iterations, state.evaluations, False, message)


def newton_trust_region(evaluate: Callable, z0: np.ndarray, maxiter: int = 500,
                        report: Callable = _no_report, scoring: Callable | None = None,
                        value: Callable | None = None, handover: float = HANDOVER_DECREASE,
                        step_limit: np.ndarray | float = np.inf) -> Optimum:
    """Minimise with ``evaluate(z) -> (f, g, H)``, after Fisher scoring with ``scoring(z) -> (f, g, F)``
    if given, judging trial points by ``value(z) -> f`` if given; see
    [`Search`][greyid.estimate.trust_region.Search]."""
    search = Search(z0, maxiter, report, scoring is not None, value is not None, handover, step_limit)
    programs = {EXACT: evaluate, SCORING: scoring, VALUE: None if value is None else lambda z: (value(z),)}
    return run_alone(search, programs)
