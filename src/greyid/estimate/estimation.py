"""Maximum likelihood and MAP estimation (chapter 3) with exact derivatives.

``model.fit(data, ...)`` maximises the Gaussian log-likelihood (3.18) — or a
robust or k-step version of it, or the posterior with a Gaussian prior (3.46) —
over the free parameters.  Bounds are handled by smooth transforms; the
optimiser (Newton steps on the exact Hessian in a trust region, see
`optimize`) treats a non-finite evaluation as a rejected step.  The uncertainty
comes from the exact Hessian of the negative log-posterior at the optimum,
mapped back to the natural parameters.
"""

from __future__ import annotations

from concurrent.futures import wait
from contextlib import ExitStack
from dataclasses import dataclass, replace

import numpy as np

from ..data.prepare import as_frames
from ..errors import DataError, ModelError
from ..schema import OPTIMIZERS
from ..filters.accuracy import LOGLIK_TOLERANCE, MAX_SUBSTEPS, SubstepChoice, chooses_substeps
from ..filters.api import check_at_parameters, check_equations_finite, filter_options, prepare_datasets
from ..filters.kalman import takes_steady_state
from ..filters.protocol import ENKF, LAPLACE, PARTICLE, STOCHASTIC
from ..model.delays import delay_parameters
from ..model.options import DATA_KEYS, ESTIMATION_KEYS, FILTER_KEYS
from ..progress import FitProgress
from .criteria import GaussianPrior, check_robust
from .covariance import check_cov_type, default_cov_type, score_covariance
from . import objective
from .objective import Derivatives, Problem, combine_scoring, compiled, step_scores
from .batch import BatchedPrograms, drive, prune_trailing
from .lbfgs import QUASI_EVALUATIONS_PER_PARAMETER, lbfgs_search, quasi_newton_start
from .optimize import EXACT, GRADIENT, SCORING, VALUE, NotFiniteError, Optimum, run_alone
from .settings import FitSettings
from .trust_region import HANDOVER_DECREASE, MAX_STEP, Search
from .starts import nested_start, reductions, space_filling
from .transforms import NONE, Transform

CRITERIA = ("ml", "map")
# "scoring": Fisher scoring far from the optimum, exact Newton near it (Gaussian
# criteria; robust and k-step criteria have no scoring matrix and use Newton only);
# "newton": exact Newton steps throughout; "auto": scoring where a Hessian costs
# much more than a gradient, rows × (free parameters)² ≥ SCORING_WORK, the quasi-Newton start
# where a Hessian of one block is large (see QUASI_WORK), Newton steps otherwise; "quasi-newton":
# L-BFGS steps on value and exact gradient from each start run alone, then exact Newton
# steps (lbfgs.quasi_newton_start; a fit's starts run together take
# Newton steps); "lbfgs": L-BFGS to the optimum and the Hessian there by central differences of the exact
# gradient, as TMB's sdreport (lbfgs.lbfgs_search): no Hessian program to compile, each start alone;
# "auto" takes it for the Laplace method (searches_by_lbfgs).
# The names are greyid.schema.OPTIMIZERS (model files are checked against them).

#: Below this (padded rows × free parameters²) the exact Hessian is cheap enough that scoring does
#: not repay the compilation of its program (the test cell, 1.2e5, fits faster by scoring only once
#: compiled); the PRBS1 building models (≥ 1.7e5) fit several times faster by scoring
#: (``benchmarks/fit.py``, docs/performance.md).
SCORING_WORK = 150_000
#: Below this (padded rows × free parameters²) a Hessian's rows are one block in one thread: split,
#: each block repeats the value and gradient, and the threads' hand-over and the machine's other
#: load cost more than the rows save: a default Armadillo fit (240 × 7², 1.2e4) is slower split
#: whatever the number of CPUs, the test cell (9 parameters) gains from the split from about 600 rows
#: (``benchmarks/fit.py``).
SPLIT_WORK = 40_000
#: Where a Hessian is one block (rows × free parameters² below SPLIT_WORK), "auto" starts a search
#: alone with quasi-Newton steps from rows × free parameters² × states² of this on: each exact
#: Hessian's second-order directions then carry products of large state matrices, and L-BFGS steps
#: on gradients repay the second program they compile within a few fits.  The Armadillo house
#: with a Matérn-3/2 force (233 × 9² × 4², 3.0e5) fits compiled in 0.075 s against 0.154 s by Newton
#: steps (first fit +0.56 s with an empty cache); the plain house (233 × 7² × 2², 4.6e4), whose first
#: fit is most of what a user waits for, keeps Newton steps (quasi-Newton: 0.019 against 0.033 s
#: compiled, +0.26 s cold, +0.41 s warm).  ``benchmarks/latent_forces.py``, docs/performance.md.
QUASI_WORK = 150_000


#: Starts asking for the same kind of evaluation that are evaluated by one vectorised
#: program; fewer run side by side in threads with the single fit's programs, whose
#: compilation they share (for a few starts, as in the PRBS1 model selection, the vectorised
#: programs' compilation is not repaid).
VECTORISE_STARTS = 8


#: Newton decrement gᵀH⁻¹g on doubling the sub-steps below which the estimates stay:
#: a shift of the estimates by about a tenth of a standard error.
SHIFT_TOLERANCE = 0.01


def _accurate_substeps(structure, problem, best, args, datasets, optimize):
    """Double the filter's sub-steps until the fit no longer depends on them (see filters.accuracy).

    At the optimum for m sub-steps, the criterion and its gradient with 2m tell
    the change of the log-likelihood and, through the Newton decrement with the
    Hessian already at hand, how far the estimates would move; when either is
    too large the fit is repeated with 2m from the current optimum.
    """
    while True:
        m = problem.options.substeps
        finer = replace(problem, options=replace(problem.options, substeps=2 * m))
        value, gradient = compiled(structure, finer).value_and_grad(best.z, *args, datasets)
        change = abs(float(value) - best.value)
        shift = float(gradient @ np.linalg.pinv(0.5 * (best.hessian + best.hessian.T)) @ gradient)
        if change <= LOGLIK_TOLERANCE and abs(shift) <= SHIFT_TOLERANCE:
            return problem, best, SubstepChoice(m, change, True)
        if 2 * m >= MAX_SUBSTEPS:
            previous = best.iterations
            best = optimize(finer, best.z)
            return finer, replace(best, iterations=best.iterations + previous), SubstepChoice(2 * m, change, False)
        previous = best.iterations
        problem, best = finer, optimize(finer, best.z)
        best = replace(best, iterations=best.iterations + previous)


def _describe(names, theta, free) -> str:
    return ", ".join(f"{names[i]}={theta[i]:.6g}" for i in free)


def check_settings(criterion, prior, robust, horizon, cov_type, optimizer, starts, seed=0):
    """The estimation settings, checked; returns ``(robust, cov_type)`` in their normal form."""
    if criterion not in CRITERIA:
        raise ModelError(f"unknown criterion '{criterion}'; use 'ml' or 'map'")
    if criterion == "map" and prior is None:
        raise ModelError("criterion 'map' needs a prior: declare one on the parameters (prior = { mean = ..., sd = "
                         "... } in a model file's [parameters], set_parameter(..., prior=(mean, sd)) in Python) or "
                         "give prior={'mean': {...}, 'sd': {...}} to fit")
    if criterion == "ml" and prior is not None:
        raise ModelError("a prior was given with criterion='ml'; use criterion='map'")
    robust = check_robust(robust)
    cov_type = default_cov_type(robust, int(horizon)) if cov_type is None else check_cov_type(cov_type)
    if optimizer not in OPTIMIZERS:
        raise ModelError(f"unknown optimizer {optimizer!r}; use one of {list(OPTIMIZERS)}")
    if not isinstance(starts, int) or starts < 1:
        raise ModelError(f"starts must be a positive integer, got {starts!r}")
    if seed is not None and (not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0):
        raise ModelError(f"seed must be a non-negative integer (the random starts' seed), got {seed!r}")
    return robust, cov_type


@dataclass(frozen=True)
class FreeParameters:
    """Where θ starts and which of its elements are estimated, within which bounds."""

    names: tuple[str, ...]
    theta0: np.ndarray  # every parameter: the fixed ones' values, the free ones' starts
    free: tuple[int, ...]
    lower: tuple
    upper: tuple
    transform: Transform

    @property
    def z0(self) -> np.ndarray:
        return self.transform.to_z(self.theta0[list(self.free)])


def free_parameters(model, init=None) -> FreeParameters:
    """The model's free parameters with their starts (``init`` overrides declared values) and bounds."""
    names = model.structure.parameter_names
    declared = model.parameters
    init = dict(init or {})
    unknown = [k for k in init if k not in names]
    if unknown:
        raise ModelError(f"init given for '{unknown[0]}', which is not a parameter of the model")
    theta0 = np.zeros(len(names))
    # A delay that is a parameter itself must stay ≥ 0 wherever the optimiser goes.
    delays = delay_parameters(model.structure)
    free, lower, upper = [], [], []
    for i, name in enumerate(names):
        p = declared.get(name)
        if p is not None and p.fixed:
            theta0[i] = p.init
            continue
        value = init.get(name, None if p is None else p.init)
        if value is None:
            raise ModelError(
                f"'{name}' appears in the model's equations but is neither a state, a declared input nor a "
                f"parameter with a value: a state needs its equation d{name} = ...; declare it as an input "
                f"(add_inputs('{name}'), or `inputs = [...]` in a model file's [model]) or give it a value "
                f"(set_parameter('{name}', init=...), or `{name} = {{ init = ... }}` under [parameters])")
        lo, hi = (None, None) if p is None else (p.lower, p.upper)
        if name in delays and (lo is None or lo < 0):
            raise ModelError(f"'{name}' is the delay of {delays[name]}; give it a lower bound of 0 or more "
                             f"(set_parameter('{name}', lower=0, ...)): a negative delay would look ahead in time")
        if (lo is not None and value <= lo) or (hi is not None and value >= hi):
            raise ModelError(f"the initial value {value} of '{name}' must lie strictly inside its bounds [{lo}, {hi}]")
        theta0[i] = value
        free.append(i)
        lower.append(lo)
        upper.append(hi)
    if not free:
        raise ModelError("every parameter is fixed; there is nothing to estimate")
    return FreeParameters(tuple(names), theta0, tuple(free), tuple(lower), tuple(upper),
                          Transform.from_bounds(lower, upper))


def make_problem(structure, parameters: FreeParameters, method, criterion_settings, filter_settings) -> Problem:
    """The [`Problem`][greyid.estimate.objective.Problem] of these parameters and settings (``(robust, horizon,
    prior)``)."""
    robust, horizon, prior = criterion_settings
    options = filter_options(structure, method, **filter_settings)
    names = list(parameters.names)
    gaussian_prior = None if prior is None else GaussianPrior.from_spec(prior, names)
    return Problem(options, robust, int(horizon), parameters.free, parameters.transform, gaussian_prior,
                   () if gaussian_prior is None else tuple(names.index(n) for n in gaussian_prior.names))


def check_observed(prepared, n_free: int, where: str = "the data") -> None:
    observed = sum(int(np.sum(~np.isnan(series.outputs))) for series, _ in prepared)
    if observed <= n_free:
        raise DataError(f"{where} hold {observed} observed output value(s) for {n_free} free parameters; "
                        "a fit needs more observations than parameters (fix some parameters or add data)")


def uses_scoring(optimizer: str, rows: int, n_free: int) -> bool:
    return optimizer == "scoring" or (optimizer == "auto" and rows * n_free ** 2 >= SCORING_WORK)


def searches_by_lbfgs(optimizer: str, method: str) -> bool:
    """Whether a fit searches by L-BFGS with the Hessian by differences of the gradient: asked for by
    ``optimizer="lbfgs"``, and taken by ``"auto"`` for the Laplace method, as ctsmTMB fits (``nlminb`` and
    ``sdreport``).  A Laplace Hessian's program differentiates the mode's implicit derivative and the
    log-determinant's rule once more and compiles about as long as the value and gradient's; without it a
    first fit of ctsmTMB's Ornstein2D example takes about 0.6 of the time, and on that example the compiled
    fits are faster too, at 10³ and 10⁴ rows (``benchmarks/laplace.py --optimizer``, docs/performance.md).
    The standard errors carry the differences' error (about 1e-6 relative; ``optimizer="newton"`` gives
    the exact Hessian's)."""
    return optimizer == "lbfgs" or (optimizer == "auto" and method == LAPLACE)


def one_block(rows: int, n_free: int) -> bool:
    """Whether an exact Hessian is computed in one block (one thread): rows × free parameters² below
    SPLIT_WORK."""
    return rows * n_free ** 2 < SPLIT_WORK


def uses_quasi_start(optimizer: str, scoring: bool, rows: int = 0, n_free: int = 0, n_states: int = 0) -> bool:
    """Whether a search alone begins with a quasi-Newton start
    ([`quasi_newton_start()`][greyid.estimate.lbfgs.quasi_newton_start]).

    Asked for by ``optimizer="quasi-newton"``, and taken by ``"auto"`` where a Hessian is one
    block whose work with the states, ``rows × n_free² × n_states²``, reaches QUASI_WORK.  It
    pays where an exact Hessian costs several gradients: one block in one thread (padded rows ×
    free parameters² below SPLIT_WORK), about
    n/2 forward gradients (``benchmarks/fit.py --against``).  Above it, split over the CPUs, an exact
    Hessian costs hardly two, and the L-BFGS steps of an ill-conditioned start cost more than
    the Newton steps they save (the test cell).  It compiles a second program, the value and
    gradient, so a first fit with an empty cache takes longer.
    """
    if scoring:
        return False
    return optimizer == "quasi-newton" or (optimizer == "auto" and one_block(rows, n_free)
                                           and rows * n_free ** 2 * n_states ** 2 >= QUASI_WORK)


def new_search(problem: Problem, z0, maxiter: int, report, scoring: bool, handover: float | None = None) -> Search:
    """A [`Search`][greyid.estimate.trust_region.Search] from ``z0`` with this problem's settings (scoring if asked and
    possible)."""
    scoring = scoring and objective.takes_scoring(problem)
    # On long series an exact Hessian costs dozens of scoring steps, and the
    # scoring matrix is close to it near the optimum: Newton only to finish.
    if handover is None:
        handover = 0.0 if problem.long_series else HANDOVER_DECREASE
    limit = np.where(problem.transform.kind == NONE, np.inf, MAX_STEP)
    return Search(z0, maxiter, report, scoring=scoring, value=scoring, handover=handover, step_limit=limit,
                  expand=scoring and problem.long_series)


def single_programs(structure, problem: Problem, arguments: tuple, stack: ExitStack, compile_at=None,
                    gradient: bool = False) -> dict:
    """``{kind: evaluate(z)}`` for one search at a time, the derivatives' directions split over threads.

    With ``compile_at`` (a point z), the exact program compiles in the background
    while the search takes its first (scoring or quasi-Newton) steps; ``gradient`` adds
    the value and gradient (kind GRADIENT) for a quasi-Newton start, traced first and
    compiled in a thread while the exact program, which shares its trace, is traced.
    """
    programs = compiled(structure, problem)
    rows = sum(inputs.t.shape[0] for inputs in arguments[-1])
    # With the steady state a shorter series' Hessian costs about as much as its first rows: split
    # over threads, each block would repeat them.
    # A small problem's Hessian is one block whatever the machine (SPLIT_WORK), so its answer
    # does not depend on how many CPUs there are either.
    steady = problem.options.steady_state and takes_steady_state(structure, problem.options)
    workers = 1 if steady or one_block(rows, len(problem.free)) else None
    out = {}
    if gradient:
        pending = programs.value_and_grad.compile_in_background(np.zeros(len(problem.free)), *arguments)
        stack.callback(wait, [pending])

        def value_and_grad(z):
            return pending.result()(np.asarray(z, dtype=np.float64), *arguments)

        out[GRADIENT] = value_and_grad
    exact = programs.derivatives_sharing if gradient else programs.derivatives
    out[EXACT] = stack.enter_context(Derivatives(exact, len(problem.free), arguments, workers=workers))
    if programs.scoring is not None:
        # One thread on long series: two concurrent scoring programs of 10⁶ rows
        # have deadlocked in XLA's CPU runtime (benchmarks/length.py).
        out[SCORING] = stack.enter_context(Derivatives(
            programs.scoring, len(problem.free), arguments, combine=combine_scoring,
            workers=1 if problem.long_series else None))

        def value(z, program=programs.value):
            return (program(np.asarray(z, dtype=np.float64), *arguments),)

        out[VALUE] = value
    if compile_at is not None:
        out[EXACT].compile_ahead(compile_at)
    return out


class SearchesAlone:
    """Runs one search at a time, with each problem's [`single_programs()`][greyid.estimate.estimation.single_programs]
    opened once
    (a fit's starts and its refits with more sub-steps share them)."""

    def __init__(self, structure, arguments: tuple, stack: ExitStack):
        self.structure, self.arguments, self.stack, self.programs = structure, arguments, stack, {}

    def run(self, problem: Problem, search: Search, quasi: bool = False, lbfgs: bool = False) -> Optimum:
        """``search`` to its end; with ``quasi``, from where a quasi-Newton start gets to (see
        [`quasi_newton_start()`][greyid.estimate.lbfgs.quasi_newton_start]); with ``lbfgs``, by L-BFGS on the value
        and gradient alone ([`lbfgs_search()`][greyid.estimate.lbfgs.lbfgs_search]), no Hessian program compiled."""
        if lbfgs:
            key = (problem.key(), "lbfgs")
            if key not in self.programs:
                program = compiled(self.structure, problem).value_and_grad
                executable = program.executable(np.zeros(len(problem.free)), *self.arguments)
                arguments = self.arguments
                self.programs[key] = lambda z: executable(np.asarray(z, dtype=np.float64), *arguments)
            return lbfgs_search(self.programs[key], search.z0, search.maxiter, search.report)
        key = (problem.key(), quasi)
        if key not in self.programs:
            # Compiled ahead only where compilation, not evaluation, dominates: on long
            # series the background evaluation would cost more than it saves.
            ahead = (search.scoring or quasi) and not problem.long_series
            self.programs[key] = single_programs(self.structure, problem, self.arguments, self.stack,
                                                 search.z0 if ahead else None, gradient=quasi)
        programs = self.programs[key]
        if not quasi:
            return run_alone(search, programs)
        start = quasi_newton_start(programs[GRADIENT], search.z0, QUASI_EVALUATIONS_PER_PARAMETER * len(search.z0),
                                   search.report)
        search.z0, report, done = start.z, search.report, start.iterations
        search.report = lambda iteration, stage, f, g: report(done + iteration, stage, f, g)
        optimum = run_alone(search, programs)
        return replace(optimum, iterations=optimum.iterations + done,
                       evaluations=optimum.evaluations + start.evaluations)


def failed_start(z0, error: ModelError) -> Optimum:
    n = len(z0)
    return Optimum(np.asarray(z0), np.inf, np.full(n, np.nan), np.full((n, n), np.nan), 0, 1, False,
                   f"failed: {error}")


def reduced_starts(model, parameters: FreeParameters, starts: int) -> list[tuple[str, np.ndarray]]:
    """``[(label, z), ...]``: where ``model`` reduces to a smaller one it extends, from its initial values
    (see [`reductions()`][greyid.estimate.starts.reductions]); none for a single start."""
    if starts <= 1:
        return []
    names, free = parameters.names, parameters.free
    out = []
    for text, values in reductions(model, names, free, parameters.lower, parameters.upper):
        theta = parameters.theta0[list(free)].copy()
        for j, i in enumerate(free):
            theta[j] = values.get(names[i], theta[j])
        out.append((text, parameters.transform.to_z(theta)))
    return out


def start_points(parameters: FreeParameters, starts: int, seed: int, scoring_auto: bool, nested=None,
                 reduced=()):
    """``(points, labels, newton_only)``: the starts of a fit, in z.

    The initial values (after a nested fit's estimates, if given), then
    ``starts − 1`` more: with ``scoring_auto`` the initial values again with Newton
    steps only, then the ``reduced`` starts (``[(label, z), ...]``: where the model
    reduces to a smaller one, see [`reductions()`][greyid.estimate.starts.reductions]),
    then points of a space-filling design.
    """
    z0 = parameters.z0
    points, labels = ([z0], ["initial values"]) if nested is None else ([nested, z0], ["nested fit", "initial values"])
    extra, extra_labels, newton_only = [], [], [False] * len(points)
    if scoring_auto and starts > 1:
        # Scoring's matrix has no negative curvature, so from one start it can settle in
        # another basin than exact Newton steps: the first extra start repeats the initial
        # values with Newton steps only.
        extra.append(z0)
        extra_labels.append("initial values, Newton steps")
    for label, z in reduced:
        if len(extra) < starts - 1:
            extra.append(z)
            extra_labels.append(label)
    # The design's points after as many as the starts above take (with no reduced start, the points a fit
    # took before reduced starts existed).
    filling = list(space_filling(parameters.transform, z0, starts - 1, seed))[len(extra):]
    extra += filling
    extra_labels += ["space-filling"] * len(filling)
    newton_only += [label == "initial values, Newton steps" for label in extra_labels]
    return points + extra, labels + extra_labels, newton_only


def neighbouring_delays(structure, parameters: FreeParameters, z_best, prepared):
    """Starts with each estimated delay in the middle of the sampling intervals next to its estimate's.

    A held input switches at the sampling instants, so the likelihood in τ has a
    kink wherever τ is a whole number of sampling intervals and may hold a local
    optimum in each interval between two: the neighbouring intervals are where a
    better one lies (starting just one interval away from the estimate can climb
    back across the kink).  ``[(z, label)]``; the other parameters stay at ``z_best``.
    """
    delays = delay_parameters(structure)
    positions = [j for j, i in enumerate(parameters.free) if parameters.names[i] in delays]
    if not positions:
        return []
    steps = np.concatenate([np.diff(series.times) for series, _ in prepared])
    step = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
    if step <= 0:
        return []
    transform = parameters.transform
    theta = transform.to_theta(np.asarray(z_best), np)
    out = []
    for j in positions:
        lo = parameters.lower[j] if parameters.lower[j] is not None else -np.inf
        hi = parameters.upper[j] if parameters.upper[j] is not None else np.inf
        cell = np.floor(theta[j] / step)
        for side, middle in (("shorter", (cell - 0.5) * step), ("longer", (cell + 1.5) * step)):
            if lo < middle < hi:
                moved = theta.copy()
                moved[j] = middle
                name = parameters.names[parameters.free[j]]
                out.append((transform.to_z(moved), f"{name} in the next sampling interval, {side}"))
    return out


def search_delays(structure, parameters: FreeParameters, prepared, best: Optimum, optima: list, labels: list,
                  run) -> Optimum:
    """The best of ``best`` and refits (``run(z) -> Optimum``) from
    [`neighbouring_delays()`][greyid.estimate.estimation.neighbouring_delays];
    the refits are appended to ``optima`` and ``labels`` (the fit's table of starts)."""
    for z_start, label in neighbouring_delays(structure, parameters, best.z, prepared):
        labels.append(label)
        optima.append(run(z_start))
        if optima[-1].value < best.value - 1e-9:
            best = optima[-1]
    return best


def fit_model(model, data, prior=None, init=None, init_from=None, progress=False, **given):
    """[`Model.fit()`][greyid.api.Model.fit]: the settings resolved as the model's methods resolve them
    (given, else the model's), then [`fit()`][greyid.estimate.estimation.fit]; the fit's numbers."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS + ESTIMATION_KEYS)
    settings.pop("prior_correlation", None)
    if model.units:
        model.check_units(time=settings.get("time"))
    if prior is None and settings.get("criterion") == "map":
        prior = model.prior()
    return fit(model, data, prior=prior, init=init, init_from=init_from, progress=progress, **settings)


def fit(model, data, time="t", hold="zoh", method=None, criterion="ml", prior=None, robust=None,
        horizon=1, starts=1, seed=0, init=None, time_unit=None, maxiter=500, progress=False, cov_type=None,
        init_from=None, optimizer="auto", **filter_settings):
    """Estimate the free parameters of ``model`` from ``data`` with these settings; see
    [`Model.fit()`][greyid.api.Model.fit]."""
    structure = model.structure
    robust, cov_type = check_settings(criterion, prior, robust, horizon, cov_type, optimizer, starts, seed)
    parameters = free_parameters(model, init)
    names, theta0, free = parameters.names, parameters.theta0, parameters.free
    transform = parameters.transform
    if method in STOCHASTIC:  # the seed fixes the particle and ensemble filters' random numbers too
        filter_settings = dict(filter_settings, seed=seed)
    problem = make_problem(structure, parameters, method, (robust, horizon, prior), filter_settings)

    frames = as_frames(data)
    # The checks at θ₀ (positive variances, a valid P₀) cost a compilation of their
    # own; they run only if the criterion is not finite at the start, to say why.
    prepared = prepare_datasets(structure, theta0, frames, time, hold, time_unit, check=False)
    if sum(series.n_rows for series, _ in prepared) > objective.LONG_SERIES:
        problem = replace(problem, long_series=True)  # memory independent of the series' length
    prepared = objective.evaluated_datasets(problem, prepared)  # several lengths: one filter program
    datasets = [inputs for _, inputs in prepared]
    check_observed(prepared, len(free))

    rows = sum(series.n_rows for series, _ in prepared)
    by_lbfgs = searches_by_lbfgs(optimizer, problem.options.method)
    use_scoring = uses_scoring(optimizer, rows, len(free)) and not by_lbfgs
    args = problem.arguments(theta0)
    nested = None
    if init_from is not None:
        warm = nested_start(model, init_from, names, free, parameters.lower, parameters.upper)
        free_theta0 = theta0[list(free)]
        nested = transform.to_z(np.array([warm.get(names[i], free_theta0[j]) for j, i in enumerate(free)]))
    points, labels, newton_only = start_points(parameters, starts, seed, use_scoring and optimizer == "auto", nested,
                                               reduced_starts(model, parameters, starts))
    label = "log-likelihood" if criterion == "ml" and robust is None and horizon == 1 else "criterion"

    def not_finite(problem, z_start, i):
        theta_start = problem.theta(z_start, theta0)
        for series, inputs in prepared:
            check_at_parameters(structure, theta_start, series, inputs)
            check_equations_finite(structure, theta_start, series, inputs)
        return ModelError("the criterion or its derivatives are not finite at the "
                          f"{labels[i] if i < len(labels) else 'refit'} (start {i + 1}) "
                          f"({_describe(names, theta_start, free)}); check the initial parameter values")

    with FitProgress(progress, len(points), label) as shown, ExitStack() as open_programs:
        # The optimiser minimises −(criterion); progress shows the criterion itself.
        def reporter(i):
            def report(iteration, stage, f, g):
                shown.iteration(iteration, stage, -f, float(np.max(np.abs(g))), start=i)
            return report

        def finished(i, optimum):
            shown.end_start(-optimum.value, optimum.iterations, optimum.converged, optimum.message, start=i)

        alone = SearchesAlone(structure, (*args, datasets), open_programs)

        def optimize(problem, z_start, i, exact_only=False, start=False):
            """One search alone (one start, or the refit with more sub-steps)."""
            search = new_search(problem, z_start, maxiter, reporter(i), use_scoring and not exact_only)
            shown.begin_start(i)
            quasi = start and uses_quasi_start(optimizer, search.scoring, rows, len(free), structure.n_states)
            try:
                optimum = alone.run(problem, search, quasi=quasi, lbfgs=by_lbfgs)
            except NotFiniteError:
                raise not_finite(problem, z_start, i) from None
            finished(i, optimum)
            return optimum

        # With the steady state each start runs alone: vectorised over starts, each start's switch
        # would run both forms.
        if len(points) == 1 or problem.long_series or problem.options.steady_state or by_lbfgs:
            optima = [optimize(problem, z_start, i, newton_only[i], start=True) for i, z_start in enumerate(points)]
        else:
            # All starts together, each request kind evaluated for all of them by one
            # vectorised program; starts that trail far behind are pruned.
            searches = [new_search(problem, z_start, maxiter, reporter(i), use_scoring and not newton_only[i])
                        for i, z_start in enumerate(points)]
            with BatchedPrograms(structure.cache, problem.key(), compiled(structure, problem), len(free), args,
                                 datasets, vectorise_from=VECTORISE_STARTS) as batched:
                if any(search.scoring for search in searches):
                    batched.compile_exact_ahead(points[0])
                results = drive(searches, batched, prune=prune_trailing,
                                finished=lambda i, r: None if isinstance(r, ModelError) else finished(i, r))
            if isinstance(results[0], ModelError):
                raise not_finite(problem, points[0], 0)
            optima = [failed_start(points[i], r) if isinstance(r, ModelError) else r for i, r in enumerate(results)]
        best = min(optima, key=lambda o: o.value if np.isfinite(o.value) else np.inf)
        if hold == "zoh":
            best = search_delays(structure, parameters, prepared, best, optima, labels,
                                 lambda z: optimize(problem, z, len(optima)))
        substep_choice = None
        if filter_settings.get("substeps") is None and chooses_substeps(structure, problem.options.method,
                                                                        problem.options.scheme):
            problem, best, substep_choice = _accurate_substeps(structure, problem, best, args, datasets,
                                                               lambda p, z: optimize(p, z, len(optima)))
    call = dict(time=time, hold=hold, criterion=criterion, robust=robust, horizon=int(horizon), starts=starts,
                optimizer=optimizer, time_unit=time_unit, prior=prior, cov_type=cov_type, seed=seed,
                hessian="differences" if by_lbfgs else "exact")
    return finish(model, frames, problem, best, optima, args, datasets, theta0, call, labels, substep_choice)


def finish(model, frames, problem: Problem, best, optima, args, datasets, theta0, call: dict, labels,
           substep_choice=None):
    """The [`FitResult`][greyid.api.FitResult] of an optimum: θ, the score covariance if asked, the
    settings kept with it.

    ``call`` holds the fit's own settings (time, hold, criterion, robust, horizon,
    starts, optimizer, time_unit, prior, cov_type).
    """
    from .optimum import build_result

    theta = problem.theta(best.z, theta0)
    options = problem.options
    scores = None
    if call["cov_type"] != "hessian":
        scores = score_covariance(step_scores(model.structure, problem, best.z, args, datasets), int(call["horizon"]))
    settings = FitSettings(**call, method=options.method, form=options.form, substeps=options.substeps,
                           iterations=options.iterations, steady_state=options.steady_state,
                           substep_note=None if substep_choice is None else substep_choice.describe(),
                           substeps_accurate=None if substep_choice is None else substep_choice.accurate,
                           start_labels=tuple(labels),
                           particles=options.particles if options.method in STOCHASTIC else None,
                           resample=options.resample if options.method == PARTICLE else None,
                           inflation=options.inflation if options.method == ENKF else None,
                           proposal=options.proposal if options.method == PARTICLE else None,
                           scheme=options.scheme if options.method == LAPLACE else None)
    return build_result(model, frames, theta, problem, best, optima, settings, scores)
