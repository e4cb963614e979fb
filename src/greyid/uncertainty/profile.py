"""Profile likelihoods and profile confidence intervals.

The profile of a parameter ψ is ℓ_p(ψ) = max over the other parameters of the
fit's criterion with ψ held; the set {ψ : 2(ℓ̂ − ℓ_p(ψ)) ≤ χ²₁(level)} is the
likelihood-ratio confidence interval (Pawitan, *In all likelihood*, 2001,
ch. 3–4), which follows skewed likelihoods (variances, time constants) where
the Wald interval from the Hessian is symmetric by construction.  A derived
quantity g(θ) is profiled by maximising the criterion under g(θ) = c (SLSQP
with exact gradients).  For a MAP fit the profile is that of the log-posterior.
"""

from __future__ import annotations


from contextlib import ExitStack

import numpy as np
import pandas as pd
from scipy import special

from ..errors import ModelError, warn
from ..estimate.objective import forward_hessian
from ..estimate.optimize import EXACT
from ..estimate.refit import Refit
from ..estimate.results import FitWarning
from ..estimate.transforms import NONE, Transform
from ..estimate.trust_region import DECREMENT_TOLERANCE
from ..filters.protocol import KALMAN

#: Secant steps outwards looking for the end of a profile interval before giving up.
MAX_STEPS = 40
#: Newton steps on an end's equations before the secant search takes over; shortest step's fraction.
NEWTON_STEPS = 30
MIN_STEP = 1.0 / 64
#: An end by Newton's method: |f − f̂ − χ²/2| relative to max(1, |f|) (the deviance then lies within
#: 2e-10·max(1, |f|) of its threshold, the secant search's within 4e-5); the others' Newton decrement
#: meets the fit's own test of an optimum (trust_region.DECREMENT_TOLERANCE).
ROOT_TOLERANCE = 1e-10
#: The two ends: direction along the parameter's coordinate, and name.
SIDES = ((-1.0, "lower"), (1.0, "upper"))


def _chi2_quantile(level: float) -> float:
    """The χ²₁ quantile at ``level``, as ``scipy.stats.chi2.ppf(level, 1)`` computes it (2·P⁻¹(½, level),
    the inverse regularised incomplete gamma function), without importing scipy.stats, a large import."""
    return float(2.0 * special.gammaincinv(0.5, level))


def _criterion_name(fit) -> str:
    s = fit.settings
    gaussian = s.get("criterion", "ml") == "ml" and not s.get("robust") and int(s.get("horizon", 1)) == 1
    return "loglik" if gaussian else "criterion"


def _free(fit) -> list[str]:
    return [n for n in fit.params.index if not fit.params.loc[n, "fixed"]]


def _parameter_transform(fit, name) -> Transform:
    row = fit.params.loc[name]
    lower = None if np.isnan(row["lower_bound"]) else float(row["lower_bound"])
    upper = None if np.isnan(row["upper_bound"]) else float(row["upper_bound"])
    return Transform.from_bounds([lower], [upper])


class _ParameterProfile:
    """Profile points of one parameter, each a refit warm-started from the nearest point solved."""

    def __init__(self, fit, name):
        self.fit, self.name = fit, name
        self.refit = Refit(fit, held=[name])
        self.solved: dict[float, np.ndarray] = {float(fit.params.loc[name, "estimate"]): self.refit.z_hat}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.refit.close()

    def at(self, value: float):
        nearest = min(self.solved, key=lambda v: abs(v - value))
        start = self.refit.predicted(self.solved[nearest], [nearest], [value])
        optimum = self.refit.optimum([value], start)
        self.solved[float(value)] = optimum.z
        return optimum

    def row(self, value: float, optimum) -> dict:
        theta = self.refit.theta(optimum.z, [value])
        row = {self.name: float(value), "criterion": -float(optimum.value)}
        row.update({n: float(theta[self.refit.names.index(n)]) for n in self.refit.free_names})
        row["converged"] = bool(optimum.converged)
        return row


def _grid(fit, name, estimate, se, values, n, span, lower, upper):
    if values is not None:
        grid = np.asarray(values, dtype=np.float64).ravel()
        if grid.size == 0:
            raise ModelError("values= is empty")
        outside = grid[((~np.isnan(lower)) & (grid <= lower)) | ((~np.isnan(upper)) & (grid >= upper))]
        if outside.size:
            raise ModelError(f"profile value {outside[0]:.6g} of '{name}' lies outside its bounds "
                             f"[{lower:.6g}, {upper:.6g}]")
        return np.sort(grid)
    if not (np.isfinite(se) and se > 0):
        raise ModelError(f"'{name}' has no standard error (at a bound, or not determined by the data): "
                         "give the profile's values= explicitly")
    if n < 2:
        raise ModelError(f"n must be at least 2, got {n!r}")
    grid = np.linspace(estimate - span * se, estimate + span * se, n)
    inside = np.ones(n, dtype=bool)
    if not np.isnan(lower):
        inside &= grid > lower
    if not np.isnan(upper):
        inside &= grid < upper
    return grid[inside]


def profile(fit, name: str, values=None, n: int = 21, span: float = 3.0, expression: str | None = None
            ) -> pd.DataFrame:
    """The profile of a fit's criterion in one parameter or derived quantity.

    Each point re-estimates the other parameters, warm-started from its neighbour
    towards the estimate, with the fit's compiled programs.

    Parameters
    ----------
    fit : FitResult
        The fit.
    name : str
        A parameter, or a derived quantity declared on the model (``add_derived``).
    values : array_like, optional
        Where to hold it (default: ``n`` points over the estimate ± ``span``
        standard errors, within the bounds).
    n : int
        The number of points of the default grid.
    span : float
        The default grid's half-width, in standard errors.
    expression : str, optional
        A derived quantity given as an expression in the parameters, named ``name``.

    Returns
    -------
    pandas.DataFrame
        A column named as the quantity, ``loglik`` (the profile log-likelihood;
        ``criterion`` for MAP, robust or k-step fits), the re-estimated parameters,
        ``converged`` and ``deviance`` = 2(ℓ̂ − ℓ_p); ``attrs`` holds the estimate,
        the maximum and the 95 % χ² threshold.

    Raises
    ------
    ModelError
        A name that is neither a parameter nor a derived quantity.
    """
    derived = expression is not None or (name not in fit.params.index and name in fit.model.derived)
    if derived:
        return _derived_profile(fit, name, expression or fit.model.derived[name], values, n, span)
    if name not in fit.params.index:
        raise ModelError(f"'{name}' is neither a parameter nor a derived quantity of model '{fit.model.name}'")
    row = fit.params.loc[name]
    estimate, se = float(row["estimate"]), float(row["std_error"])
    grid = _grid(fit, name, estimate, se, values, n, span, float(row["lower_bound"]), float(row["upper_bound"]))
    rows = {}
    with _ParameterProfile(fit, name) as points:
        # Outwards from the estimate on each side, so every warm start is a neighbour.
        above, below = grid[grid >= estimate], grid[grid < estimate][::-1]
        for side in (above, below):
            for value in side:
                rows[float(value)] = points.row(value, points.at(value))
    return _table(fit, name, [rows[float(v)] for v in grid], estimate)


def _table(fit, name, rows, estimate) -> pd.DataFrame:
    table = pd.DataFrame(rows)
    label = _criterion_name(fit)
    table = table.rename(columns={"criterion": label})
    table["deviance"] = 2.0 * (fit.criterion_value - table[label])
    table.attrs.update(estimate=float(estimate), maximum=float(fit.criterion_value), quantity=name,
                       threshold=_chi2_quantile(0.95), criterion=label)
    return table


# ------------------------------------------------------------------ derived quantities
class _DerivedProfile:
    """max criterion(θ) subject to g(θ) = c, by SLSQP on z with exact gradients."""

    def __init__(self, fit, label, expression):
        import jax

        from ..estimate.objective import compiled
        from ..estimate.results import parameter_expression
        from ..model.equations import parse_expression
        from ..model.structure import lambdify_parameters

        self.fit, self.label = fit, label
        self.refit = Refit(fit)
        names = self.refit.names
        expr = parameter_expression(expression, names, f"derived quantity '{label}'")
        g = lambdify_parameters([expr], [parse_expression(n, "parameter") for n in names], (1,))
        problem, args = self.refit.problem, self.refit.arguments
        programs = compiled(self.refit.structure, problem)

        def constraint(z):
            return g(_theta_jax(problem, z, args))[0]

        self.g_value = jax.jit(constraint)
        self.g_grad = jax.jit(jax.grad(constraint))
        self.value_and_grad = lambda z: programs.value_and_grad(np.asarray(z, dtype=np.float64), *args)
        self.estimate = float(self.g_value(self.refit.z_hat))
        self.solved = {self.estimate: self.refit.z_hat}

    def at(self, c: float):
        nearest = min(self.solved, key=lambda v: abs(v - c))
        z0 = self.solved[nearest]

        def objective(z):
            f, grad = self.value_and_grad(z)
            return float(f), np.asarray(grad, dtype=np.float64)

        from scipy import optimize  # here only: SciPy's optimize imports its statistics, a large import

        result = optimize.minimize(
            objective, z0, jac=True, method="SLSQP",
            constraints=[{"type": "eq", "fun": lambda z: float(self.g_value(z)) - c,
                          "jac": lambda z: np.asarray(self.g_grad(z))}],
            options=dict(maxiter=500, ftol=1e-12))
        self.solved[float(c)] = result.x
        return result

    def row(self, c, result) -> dict:
        theta = self.refit.theta(result.x, [])
        row = {self.label: float(c), "criterion": -float(result.fun)}
        row.update({n: float(theta[self.refit.names.index(n)]) for n in self.refit.free_names})
        row["converged"] = bool(result.success and abs(float(self.g_value(result.x)) - c) <= 1e-8 * max(1, abs(c)))
        return row


def _theta_jax(problem, z, args):
    import jax.numpy as jnp

    base, lower, upper = args[:3]
    return problem.theta(z, base, Transform(problem.transform.kind, lower, upper), jnp)


def _derived_profile(fit, label, expression, values, n, span) -> pd.DataFrame:
    points = _DerivedProfile(fit, label, expression)
    estimate = points.estimate
    if values is None:
        table = fit.derived({label: expression})
        se = float(table.loc[label, "std_error"])
        grid = _grid(fit, label, estimate, se, None, n, span, np.nan, np.nan)
    else:
        grid = _grid(fit, label, estimate, np.nan, values, n, span, np.nan, np.nan)
    rows = {}
    above, below = grid[grid >= estimate], grid[grid < estimate][::-1]
    for side in (above, below):
        for c in side:
            rows[float(c)] = points.row(c, points.at(c))
    points.refit.close()
    return _table(fit, label, [rows[float(c)] for c in grid], estimate)


# ------------------------------------------------------------------ intervals
def profile_interval(fit, name: str, level: float = 0.95, notes: list | None = None,
                     whole: Refit | None = None) -> tuple[float, float]:
    """The ends of the profile-likelihood interval of one parameter.

    On each side, the point where the other parameters maximise the criterion and
    2(ℓ̂ − ℓ) = χ²₁(level): Newton's method on those equations from the Wald end
    (Venzon and Moolgavkar, 1988), one exact Hessian of the fit's program per step,
    where that pays (the exact Kalman filter, see ``_newton_pays``).
    Otherwise, or where it does not converge to a profile maximum on the right side (a skewed or
    flat profile, a bound), the root of √(2(ℓ̂ − ℓ_p)) = √χ²₁(level) along the
    optimiser's coordinate of the parameter (log or logistic where it is bounded):
    that signed root deviance is nearly linear there, so secant steps from the
    Wald guess bracket the end in a few refits and regula falsi closes it.

    Parameters
    ----------
    fit : FitResult
        The fit.
    name : str
        A free parameter.
    level : float
        The confidence level.
    notes : list, optional
        Where to append the messages (an end at a bound, an end not found) instead
        of warning them (the warnings machinery is process-wide: a report computes
        the intervals in a thread of its own).
    whole : Refit, optional
        The fit's problem with no parameter held, to share between parameters
        ([`profile_intervals()`][greyid.uncertainty.profile.profile_intervals] opens one).

    Returns
    -------
    tuple of float
        ``(lower, upper)``: an end that reaches the parameter's bound is the bound,
        with a ``FitWarning`` naming it; NaN where the profile stays below the
        threshold.
    """
    threshold = _chi2_quantile(level)
    transform = _parameter_transform(fit, name)
    with ExitStack() as stack:
        if whole is None:
            whole = stack.enter_context(Refit(fit))
        ends = {side: _newton_end(whole, name, transform, direction, threshold, -fit.criterion_value)
                if _newton_pays(whole.problem) else None for direction, side in SIDES}
        if any(end is None for end in ends.values()):
            points = stack.enter_context(_ParameterProfile(fit, name))
            estimate = float(fit.params.loc[name, "estimate"])
            z_hat = float(transform.to_z([estimate])[0])
            se = float(fit.params.loc[name, "std_error"])
            slope = float(abs(transform.derivative([z_hat])[0]))
            step = se / slope if np.isfinite(se) and se > 0 and slope > 0 else 0.5
            for direction, side in SIDES:
                if ends[side] is None:
                    ends[side] = _interval_end(fit, name, points, transform, z_hat, direction * step, threshold,
                                               side, level, notes)
        return ends["lower"], ends["upper"]


def _newton_pays(problem) -> bool:
    """Whether the ends are sought by Newton's method first: where the fit's Hessian is the exact Kalman
    filter's forward over forward (FORWARD_HESSIAN_MAX free parameters at most, a series short of
    LONG_SERIES rows), four or five Hessians cost less than an end's refits and compile nothing.  Through the
    other filters' derivatives a Hessian costs dozens of gradients, and a long series' refits take scoring
    steps with the fit's programs: there the refits alone (the user guide's Uncertainty page has the figures)."""
    return (problem.options.method == KALMAN and not problem.long_series
            and forward_hessian(KALMAN, len(problem.free)))


def _newton_end(whole: Refit, name: str, transform: Transform, direction: float, threshold: float,
                f_hat: float) -> float | None:
    """One end of a profile interval by Newton's method (Venzon and Moolgavkar, 1988), or None.

    In the fit's coordinates z, with f the criterion to minimise (−ℓ, f̂ = ``f_hat`` at the
    estimate ẑ), i the parameter and o
    the others, the end solves f(z) = f̂ + χ²/2 and ∂f/∂z_o = 0: n equations in n unknowns
    whose Jacobian, (∇f; H_o·), the fit's exact program gives with f. The start is the
    Wald end of the quadratic model at ẑ, z = ẑ ± √χ² H⁻¹e_i / √(H⁻¹)_ii; steps that do not
    reduce the residual are halved. The answer is the end only where the others' Hessian H_oo
    is positive definite there (their maximum, not a saddle), z_i lies on the asked side of
    ẑ_i within the parameter's bounds, and the criterion and the others' Newton decrement
    meet the tolerances: otherwise None, and the secant search takes over.
    """
    i = whole.free_names.index(name)
    others = np.arange(len(whole.z_hat)) != i
    z_hat = whole.z_hat
    H_hat = whole.hessian()
    try:
        column = np.linalg.solve(H_hat, np.eye(len(z_hat))[i])  # H⁻¹e_i
        weight = np.linalg.inv(H_hat[np.ix_(others, others)])  # scales the others' gradient
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(column)) and column[i] > 0):
        return None
    f_end = f_hat + 0.5 * threshold
    evaluate = whole.programs()[EXACT]

    def at(z):
        f, g, H = evaluate(z)
        f, g, H = float(f), np.asarray(g, dtype=np.float64), np.asarray(H, dtype=np.float64)
        g_o = g[others]
        residual = np.concatenate([[f - f_end], g_o])
        merit = (f - f_end) ** 2 + float(g_o @ weight @ g_o)  # ‖D F‖², D = diag(1, H_oo(ẑ)^-½): unit-free
        return residual, g, H, merit

    z = z_hat + direction * np.sqrt(threshold) * column / np.sqrt(column[i])
    residual, g, H, merit = at(z)
    for _ in range(NEWTON_STEPS):
        if not np.isfinite(merit):
            return None
        H_oo = H[np.ix_(others, others)]
        try:
            np.linalg.cholesky(H_oo)  # the others at a maximum of the criterion, not a saddle
            decrement = float(residual[1:] @ np.linalg.solve(H_oo, residual[1:]))
            if abs(residual[0]) < ROOT_TOLERANCE * max(1.0, abs(f_end)) and \
                    decrement < DECREMENT_TOLERANCE * max(1.0, abs(f_end)):
                break
            step = np.linalg.solve(np.vstack([g, H[others]]), -residual)
        except np.linalg.LinAlgError:
            return None
        length = 1.0
        while True:
            trial = at(z + length * step)
            if np.isfinite(trial[3]) and trial[3] < merit:
                break
            length /= 2.0
            if length < MIN_STEP:
                return None
        z = z + length * step
        residual, g, H, merit = trial
    else:
        return None
    z_i = z[i]
    if direction * (z_i - z_hat[i]) <= 0 or _past_bound(transform, z_i):
        return None
    theta = whole.theta(z, [])
    return float(theta[whole.names.index(name)])


def _past_bound(transform: Transform, z: float) -> bool:
    """Whether the optimiser's coordinate z of a bounded parameter has reached its bound: at it to working
    precision, or |z| > 35 (a log or logistic coordinate e^±35 away).  An unbounded parameter's z is the
    parameter itself, which may lie anywhere."""
    if transform.kind[0] == NONE:
        return False
    return bool(transform.at_bound(np.array([z]), np.zeros(1), np.ones(1))[0]) or abs(z) > 35


def _regula_falsi(fun, a, fa, b, fb, tolerance: float = 1e-5, iterations: int = 60) -> float:
    """The root of ``fun`` in [a, b] (fa < 0 ≤ fb), Illinois' regula falsi: for a nearly linear
    function (the signed root deviance) each step gains digits, unlike bisection's one bit.

    1e-5 in the root deviance puts the deviance within 4e-5 of its threshold and the
    end within about 1e-5 standard errors of the exact one (1e-7 took 40 % more refits)."""
    side = 0
    for _ in range(iterations):
        c = b - fb * (b - a) / (fb - fa)
        fc = fun(c)
        if abs(fc) < tolerance or abs(b - a) < tolerance:
            return c
        if fc < 0:
            a, fa = c, fc
            fb = fb / 2 if side == -1 else fb
            side = -1
        else:
            b, fb = c, fc
            fa = fa / 2 if side == 1 else fa
            side = 1
    return c


def _say(message: str, notes: list | None) -> None:
    if notes is None:
        warn(message, FitWarning)
    else:
        notes.append(message)


def _interval_end(fit, name, points, transform, z_hat, step, threshold, side, level, notes=None) -> float:
    """One end of [`profile_interval()`][greyid.uncertainty.profile.profile_interval], along z = ẑ + o·step for o ≥
    0."""
    target = np.sqrt(threshold)

    def theta(o):
        return float(transform.to_theta(np.array([z_hat + o * step]), np)[0])

    def gap(o):
        deviance = 2.0 * (fit.criterion_value + float(points.at(theta(o)).value))
        return np.sqrt(max(deviance, 0.0)) - target

    known = [(0.0, -target)]
    o = target  # the Wald guess
    for _ in range(MAX_STEPS):
        z = z_hat + o * step
        if _past_bound(transform, z):
            end = float(fit.params.loc[name, f"{side}_bound"])
            _say(f"{fit.model.name}: the {side} end of the profile interval of '{name}' runs into "
                 f"its bound {end:.6g} (the likelihood stays within the threshold up to there)", notes)
            return end
        g = gap(o)
        if g >= 0:
            inner, g_inner = max(((p, v) for p, v in known if v < 0), key=lambda pv: pv[0])
            return theta(_regula_falsi(gap, inner, g_inner, o, g))
        known.append((o, g))
        (o0, g0), (o1, g1) = known[-2], known[-1]
        secant = o1 + (0.0 - g1) * (o1 - o0) / (g1 - g0) if g1 > g0 else np.inf
        o = min(max(secant * 1.05, 1.1 * o1), 3.0 * o1)  # a little past the secant root, to bracket it
    _say(f"{fit.model.name}: the profile of '{name}' does not reach the {level:.0%} threshold "
         f"on its {side} side within {MAX_STEPS} steps (the data do not bound it there)", notes)
    return np.nan


def profile_intervals(fit, level: float = 0.95, names=None, notes: list | None = None) -> pd.DataFrame:
    """The profile-likelihood interval of each free parameter.

    Parameters
    ----------
    fit : FitResult
        The fit.
    level : float
        The confidence level.
    names : sequence of str, optional
        The parameters (default: every free one).
    notes : list, optional
        As for [`profile_interval()`][greyid.uncertainty.profile.profile_interval].

    Returns
    -------
    pandas.DataFrame
        ``lower`` and ``upper`` per parameter (NaN for fixed ones).
    """
    if not 0 < level < 1:
        raise ModelError(f"level must lie between 0 and 1, got {level!r}")
    names = list(fit.params.index) if names is None else list(names)
    free = _free(fit)
    out = pd.DataFrame({"lower": np.nan, "upper": np.nan}, index=names)
    if not any(name in free for name in names):
        return out
    with Refit(fit) as whole:  # one problem and one set of programs for every parameter's Newton ends
        for name in names:
            if name in free:
                out.loc[name, ["lower", "upper"]] = profile_interval(fit, name, level, notes, whole)
    return out


def plot_profile(table: pd.DataFrame, ax=None, wald_se: float | None = None):
    """The deviance 2(ℓ̂ − ℓ_p) of a profile, with the 95 % χ² threshold and the Wald parabola.

    Parameters
    ----------
    table : pandas.DataFrame
        A `profile()` table.
    ax : matplotlib.axes.Axes, optional
        Where to draw (default: a new figure).
    wald_se : float, optional
        The parameter's standard error: draws the Wald parabola.

    Returns
    -------
    matplotlib.figure.Figure
        The figure (greyid's plots never show a window).
    """
    if ax is None:
        from matplotlib.figure import Figure

        ax = Figure(figsize=(5, 3.5), layout="constrained").subplots()
    name = table.attrs.get("quantity", table.columns[0])
    x = table[name].to_numpy()
    ax.plot(x, table["deviance"], "o-", label="profile")
    if wald_se is not None and np.isfinite(wald_se):
        ax.plot(x, ((x - table.attrs["estimate"]) / wald_se) ** 2, "--", label="Wald (quadratic)")
    ax.axhline(table.attrs["threshold"], color="grey", lw=0.8, label="95 % χ²₁")
    ax.axvline(table.attrs["estimate"], color="grey", lw=0.5, ls=":")
    ax.set_xlabel(name)
    ax.set_ylabel("2 (ℓ̂ − ℓ_p)")
    ax.legend(fontsize=8)
    return ax.figure
