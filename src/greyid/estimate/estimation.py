"""Maximum likelihood and MAP estimation (chapter 3) with exact derivatives.

``model.fit(data, ...)`` maximises the Gaussian log-likelihood (3.18) — or a
robust or k-step version of it, or the posterior with a Gaussian prior (3.46) —
over the free parameters.  Bounds are handled by smooth transforms; the
optimiser (Newton steps on the exact Hessian in a trust region, see
:mod:`.optimize`) treats a non-finite evaluation as a rejected step.  The uncertainty
comes from the exact Hessian of the negative log-posterior at the optimum,
mapped back to the natural parameters.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import replace

import numpy as np

from ..data.prepare import as_frames
from ..errors import DataError, ModelError
from ..filters.accuracy import LOGLIK_TOLERANCE, MAX_SUBSTEPS, SubstepChoice, needs_substeps
from ..filters.api import check_at_parameters, filter_options, prepare_datasets
from ..progress import FitProgress
from .criteria import GaussianPrior, check_robust
from .covariance import check_cov_type, default_cov_type, score_covariance
from . import objective
from .objective import Derivatives, Problem, combine_scoring, compiled, step_scores
from .optimize import HANDOVER_DECREASE, MAX_STEP, NotFiniteError, newton_trust_region
from .starts import nested_start, space_filling
from .transforms import NONE, Transform

CRITERIA = ("ml", "map")
#: "scoring": Fisher scoring far from the optimum, exact Newton near it (Gaussian
#: criteria; robust and k-step criteria have no scoring matrix and use Newton only);
#: "newton": exact Newton steps throughout; "auto": scoring where a Hessian costs
#: much more than a gradient, rows × (free parameters)² ≥ SCORING_WORK.
OPTIMIZERS = ("auto", "scoring", "newton")
#: Below this the exact Hessian is cheap enough that scoring does not repay the
#: compilation of its program: the test cell (1512 rows, 9 parameters, 1.2e5) fits in
#: 0.19 s by Newton and 0.14 s by scoring, but the first fit costs 0.4 s more; PRBS1
#: building models (1691 rows, 10–22 parameters, ≥ 1.7e5) fit 2–5 times faster by scoring.
SCORING_WORK = 150_000


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


def fit(model, data, time="t", hold="zoh", method=None, criterion="ml", prior=None, robust=None,
        horizon=1, starts=1, seed=0, init=None, time_unit=None, maxiter=500, progress=False, cov_type=None,
        init_from=None, optimizer="auto", **filter_settings):
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
    cov_type = default_cov_type(robust, int(horizon)) if cov_type is None else check_cov_type(cov_type)
    if optimizer not in OPTIMIZERS:
        raise ModelError(f"unknown optimizer {optimizer!r}; use one of {list(OPTIMIZERS)}")
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
            raise ModelError(
                f"'{name}' appears in the model's equations but is neither a state, a declared input nor a "
                f"parameter with a value: a state needs its equation d{name} = ...; declare it as an input "
                f"(add_inputs('{name}'), or `inputs = [...]` in a model file's [model]) or give it a value "
                f"(set_parameter('{name}', init=...), or `{name} = {{ init = ... }}` under [parameters])")
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
    # The checks at θ₀ (positive variances, a valid P₀) cost a compilation of their
    # own; they run only if the criterion is not finite at the start, to say why.
    prepared = prepare_datasets(structure, theta0, frames, time, hold, time_unit, check=False)
    datasets = [inputs for _, inputs in prepared]
    if sum(series.n_rows for series, _ in prepared) > objective.LONG_SERIES:
        problem = replace(problem, long_series=True)  # memory independent of the series' length
    observed = sum(int(np.sum(~np.isnan(series.outputs))) for series, _ in prepared)
    if observed <= len(free):
        raise DataError(f"the data hold {observed} observed output value(s) for {len(free)} free parameters; "
                        "a fit needs more observations than parameters (fix some parameters or add data)")

    rows = sum(series.n_rows for series, _ in prepared)
    use_scoring = optimizer == "scoring" or (optimizer == "auto" and rows * len(free) ** 2 >= SCORING_WORK)
    args = problem.arguments(theta0)
    free_theta0 = theta0[list(free)]
    z0 = transform.to_z(free_theta0)
    points, labels = [z0], ["initial values"]
    if init_from is not None:
        warm = nested_start(model, init_from, names, free, lower, upper)
        warm_theta = np.array([warm.get(names[i], free_theta0[j]) for j, i in enumerate(free)])
        points, labels = [transform.to_z(warm_theta), z0], ["nested fit", "initial values"]
    extra = space_filling(transform, z0, starts - 1, seed)
    labels += ["space-filling"] * (starts - 1)
    newton_only = [False] * len(labels)
    if use_scoring and optimizer == "auto" and starts > 1:
        # Scoring's matrix has no negative curvature, so from one start it can settle in
        # another basin than exact Newton steps (PRBS1's TiThTs: 3902.5 against 3924.5):
        # the first extra start repeats the initial values with Newton steps only.
        extra[0] = z0
        labels[len(points)], newton_only[len(points)] = "initial values, Newton steps", True
    points += extra
    label = "log-likelihood" if criterion == "ml" and robust is None and horizon == 1 else "criterion"
    optima = []
    with FitProgress(progress, len(points), label) as shown, ExitStack() as open_programs:
        # The optimiser minimises −(criterion); progress shows the criterion itself.
        def report(iteration, stage, f, g):
            shown.iteration(iteration, stage, -f, float(np.max(np.abs(g))))

        evaluators = {}  # one threaded evaluator per problem, shared by its starts

        def optimize(problem, z0, i, exact_only=False):
            if problem.key() not in evaluators:
                programs = compiled(structure, problem)
                scoring = value = None
                if programs.scoring is not None and use_scoring:
                    # One thread on long series: two concurrent scoring programs of 10⁶ rows
                    # have deadlocked in XLA's CPU runtime (benchmarks/length.py).
                    scoring = open_programs.enter_context(Derivatives(
                        programs.scoring, len(free), (*args, datasets), combine=combine_scoring,
                        workers=1 if problem.long_series else None))

                    def value(z, program=programs.value):
                        return program(np.asarray(z, dtype=np.float64), *args, datasets)

                evaluators[problem.key()] = (open_programs.enter_context(
                    Derivatives(programs.derivatives, len(free), (*args, datasets))), scoring, value)
            shown.begin_start(i)
            exact, scoring, value = evaluators[problem.key()]
            if exact_only:
                scoring = value = None
            try:
                # On long series an exact Hessian costs dozens of scoring steps, and the
                # scoring matrix is close to it near the optimum: Newton only to finish.
                handover = 0.0 if problem.long_series else HANDOVER_DECREASE
                limit = np.where(problem.transform.kind == NONE, np.inf, MAX_STEP)
                optimum = newton_trust_region(exact, z0, maxiter, report, scoring, value, handover, limit)
            except NotFiniteError:
                theta_start = problem.theta(z0, theta0)
                for series, inputs in prepared:
                    check_at_parameters(structure, theta_start, series, inputs)
                raise ModelError("the criterion or its derivatives are not finite at the "
                                 f"{labels[i] if i < len(labels) else 'refit'} (start {i + 1}) "
                                 f"({_describe(names, theta_start, free)}); check the initial parameter values")
            shown.end_start(-optimum.value, optimum.iterations, optimum.converged, optimum.message)
            return optimum

        for i, z_start in enumerate(points):
            optima.append(optimize(problem, z_start, i, newton_only[i]))
        best = min(optima, key=lambda o: o.value if np.isfinite(o.value) else np.inf)
        substep_choice = None
        if filter_settings.get("substeps") is None and needs_substeps(structure):
            problem, best, substep_choice = _accurate_substeps(structure, problem, best, args, datasets,
                                                               lambda p, z: optimize(p, z, len(optima)))
    theta = problem.theta(best.z, theta0)
    options = problem.options
    scores = None
    if cov_type != "hessian":
        scores = score_covariance(step_scores(structure, problem, best.z, args, datasets), int(horizon))
    settings = dict(time=time, hold=hold, method=options.method, form=options.form, substeps=options.substeps,
                    iterations=options.iterations, criterion=criterion, robust=robust, horizon=int(horizon),
                    starts=starts, optimizer=optimizer, time_unit=time_unit, prior=prior, cov_type=cov_type,
                    substep_note=None if substep_choice is None else substep_choice.describe(),
                    substeps_accurate=None if substep_choice is None else substep_choice.accurate,
                    start_labels=labels)
    return build_result(model, frames, theta, problem, best, optima, settings, scores)
