"""Population (mixed-effects) fits: one model, many data sets, shared structure, individual parameters.

``fit_population(model, datasets, random={...})`` maximises the Laplace
approximation of the marginal likelihood Π_i ∫ p(y_i | θ_i) p(η_i) dη_i over
the population parameters φ ([`spec`][greyid.population.spec]): every outer step solves each
member's inner problem (the conditional modes of its random effects, all
members at once by vectorised programs, warm-started from the previous modes)
and evaluates Σ_i ℓ_i(φ) with exact derivatives ([`laplace`][greyid.population.laplace]).  The outer
search is greyid's trust-region search (`greyid.estimate.trust_region`):
BFGS steps on the exact gradient from the members' outer-product information
Σ_i ∇ℓ_i∇ℓ_iᵀ, then Newton steps on the Hessian at the end (see
[`_search()`][greyid.population.fit._search]); the standard errors come from that Hessian.  The Hessian takes
the members' second derivatives by central differences of their exact first derivatives, which the gradient's
programs give (``hessian="differences"``), or exactly (``hessian="exact"``: the filter differentiated to fourth
order in a program of its own, several times the gradient's to compile, minutes for the Laplace method over the
states and the ensemble filter, whose derivative rules it differentiates again).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import replace
from pathlib import Path

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import numpy as np
import pandas as pd

from ..errors import DataError, ModelError
from ..estimate.objective import worker_count
from ..estimate.optimize import EXACT, GRADIENT, VALUE, NotFiniteError, run_alone
from ..estimate.trust_region import Search
from ..filters.protocol import PARTICLE
from ..data.files import named_datasets, read_covariates, read_source
from ..model.options import rename_columns
from . import laplace
from .distributed import ClusterEvaluator, evaluate
from .members import FILTER_OPTIONS, Members, PopulationWarning, population_filter, population_programs, prepare_members
from .result import PopulationResult
from .spec import PopulationSpec, make_spec


#: The outer Hessian's two ways: the exact one (the filter's derivatives to fourth order in one program), or
#: the same formula with each member's second derivatives in its parameters' scales by central differences of its
#: exact first derivatives (the gradient's program: nothing more to compile).
HESSIANS = ("exact", "differences")


class Outer:
    """The outer criterion Σ_i ℓ_i(φ) with its derivatives; keeps the members' modes for warm starts.

    Evaluations run here (the members split over the cores) or, with ``evaluator`` (a
    [`ClusterEvaluator`][greyid.population.distributed.ClusterEvaluator]), by chunks of members on a Dask cluster.
    ``hessian``: ``"exact"`` (the members' exact outer Hessians) or ``"differences"`` (the members' second
    derivatives by central differences of their exact first derivatives, by the gradient's programs).  The
    filter's programs of the outer gradient (and of the exact Hessian) compile in the background from the start.
    """

    def __init__(self, programs: laplace.LaplacePrograms | None, members: Members, spec: PopulationSpec,
                 workers: int | None = None, evaluator=None, hessian: str = "exact"):
        self.members = members
        self.hessian = hessian
        # hessian="differences": each member's steps along its free parameters' scales (NaN: not found yet).
        self.steps = np.full((len(members.names), len(spec.free)), np.nan)
        self.u = np.zeros((len(members.names), spec.n_random))
        self.evaluations = 0
        # (φ, modes, values, gradients, path) of the last finite gradient evaluation (path: the Hessian's T, λ)
        self.last_gradient = None
        self.programs = None
        if evaluator is None:
            self.programs = laplace.MemberPrograms(programs, members.x, spec.base(), members.data,
                                                   worker_count() if workers is None else workers)
            self.programs.compile_ahead(spec.phi0(), self.u, hessian=hessian == "exact")
            evaluator = functools.partial(evaluate, self.programs)
        self.evaluator = evaluator

    def _evaluate(self, phi, kind: str):
        modes, values, gradients, hessians, path = self.evaluator(np.asarray(phi, dtype=float), self.u, kind)
        if modes.finite.all():
            self.u = modes.u  # warm start for the next evaluation
        self.evaluations += 1
        return modes, values, gradients, hessians, path

    def _at_last_gradient(self, phi) -> bool:
        last = self.last_gradient
        return last is not None and np.array_equal(last[0], np.asarray(phi, dtype=float))

    def modes(self, phi) -> laplace.Modes:
        if self._at_last_gradient(phi):
            return self.last_gradient[1]
        return self._evaluate(phi, "value")[0]

    def value(self, phi):
        return (float(np.sum(self._evaluate(phi, "value")[1])),)

    def member_gradients(self, phi):
        modes, values, gradients, _, path = self._evaluate(phi, "gradient")
        if gradients is None:
            n = len(phi)
            return np.full(len(modes.u), np.inf), np.full((len(modes.u), n), np.nan), modes
        values, gradients = np.asarray(values), np.asarray(gradients)
        if np.all(np.isfinite(values)) and np.all(np.isfinite(gradients)):
            self.last_gradient = (np.array(phi, dtype=float), modes, values, gradients, path)
        return values, gradients, modes

    def value_and_gradient(self, phi):
        values, gradients, _ = self.member_gradients(phi)
        return float(np.sum(values)), gradients.sum(axis=0)

    def exact(self, phi):
        """Value, gradient and Hessian at φ; where the search's last gradient was taken at this φ (where
        the quasi-Newton stage ends), its modes, values, gradients and the modes' path are used and only the
        Hessian is computed (with ``hessian="differences"``: `_differenced`)."""
        if self.hessian == "differences":
            return self._differenced(np.asarray(phi, dtype=float))
        if self._at_last_gradient(phi):
            _, modes, values, gradients, path = self.last_gradient
            hessians = self.evaluator(np.asarray(phi, dtype=float), modes.u, "hessian", path)[3]
            self.evaluations += 1
        else:
            _, values, gradients, hessians, _ = self._evaluate(phi, "exact")
        if hessians is None or not np.all(np.isfinite(values)):
            n = len(phi)
            return np.inf, np.full(n, np.nan), np.full((n, n), np.nan)
        H = np.asarray(hessians).sum(axis=0)
        return float(np.sum(values)), np.asarray(gradients).sum(axis=0), 0.5 * (H + H.T)

    def _differenced(self, phi):
        """Value, gradient and the Hessian with the members' filters' second derivatives by central differences of
        their exact first derivatives
        ([`hessian_by_differences()`][greyid.population.laplace.MemberPrograms.hessian_by_differences]: the
        gradient's programs at the modes of φ, nothing more to compile); each member's steps are kept for later
        calls."""
        n = len(phi)
        if self._at_last_gradient(phi):  # where the quasi-Newton stage ended
            _, modes, values, gradients, path = self.last_gradient
        else:
            values, gradients, modes = self.member_gradients(phi)
            path = self.last_gradient[4] if self._at_last_gradient(phi) else None
        if path is None or not (np.all(np.isfinite(values)) and np.all(np.isfinite(gradients))):
            return np.inf, np.full(n, np.nan), np.full((n, n), np.nan)
        hessians, (self.steps,) = self.evaluator(np.asarray(phi, dtype=float), modes.u, "differences",
                                                 (*path, self.steps))[3:5]
        self.evaluations += 1
        H = np.asarray(hessians).sum(axis=0)
        return float(np.sum(values)), np.asarray(gradients).sum(axis=0), 0.5 * (H + H.T)

    def close(self):
        if self.programs is not None:
            self.programs.close()


#: Data sets fitted together (their parameters shared) for the population search's start.
POOLED_MEMBERS = 8


def _pooled_start(model, names, sources, init, settings) -> dict | None:
    """The free parameters' estimates from a fit to the first few data sets together, or ``init``
    where that fit fails (the population search then starts from the initial values)."""
    frames = []
    for source in sources:
        try:
            frames.append(rename_columns(read_source(source), settings.get("columns")))
        except (DataError, ModelError):
            continue
        if len(frames) == POOLED_MEMBERS:
            break
    settings = {k: v for k, v in settings.items() if v is not None and k != "columns"}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = model.fit(frames, init=init, **settings)
    except (DataError, ModelError):
        return init
    free = [n for n in model.parameter_names if not fit.params.loc[n, "fixed"]]
    values = dict(init or {})
    for name in free:  # where the pooled fit ends at a bound or fails, the initial value stays
        value, row = float(fit.params.loc[name, "estimate"]), fit.params.loc[name]
        inside = np.isfinite(value) and not row["at_bound"]
        inside &= (pd.isna(row["lower_bound"]) or value > row["lower_bound"])
        inside &= (pd.isna(row["upper_bound"]) or value < row["upper_bound"])
        if inside:
            values[name] = value
    return values


def _progress_report(progress):
    """The outer search's reports when ``progress``: one line per accepted step on standard error, or for a
    callable one dict per step (``iteration``, ``stage``, ``value``: the log-likelihood, ``max_gradient``)."""
    if not progress:
        return lambda iteration, stage, f, g: None
    if callable(progress):
        return lambda iteration, stage, f, g: progress(dict(iteration=iteration, stage=stage, value=-float(f),
                                                            max_gradient=float(np.max(np.abs(g)))))
    import sys

    def report(iteration, stage, f, g):
        print(f"population step {iteration}: log-likelihood {-f:.6f}, largest gradient {np.max(np.abs(g)):.3g}",
              file=sys.stderr, flush=True)

    return report


def _say(progress, phase: str, text: str) -> None:
    """A phase of the fit announced when ``progress``: a line on standard error, or for a callable a dict
    with ``phase`` and ``message``."""
    if callable(progress):
        progress(dict(phase=phase, message=text))
    elif progress:
        import sys

        print(f"population: {text}", file=sys.stderr, flush=True)


def _search(outer: Outer, phi0: np.ndarray, maxiter: int, progress=False):
    """The maximum of Σ_i ℓ_i: quasi-Newton (BFGS) steps on exact gradients, from the members'
    outer-product information at the start, in greyid's trust region; then the Hessian (``outer.exact``), and
    Newton steps on it until the Newton decrement vanishes (usually none: the BFGS optimum is the
    optimum to the criterion's precision).  The Hessian costs dozens of gradients, so the
    search takes it only at the end."""
    try:
        _, gradients, _ = outer.member_gradients(phi0)
        if not np.all(np.isfinite(gradients)):
            raise NotFiniteError("not finite")
        first = Search(phi0, maxiter, _progress_report(progress), hessian=gradients.T @ gradients)
        optimum = run_alone(first, {GRADIENT: outer.value_and_gradient})
    except NotFiniteError:
        raise ModelError("the Laplace marginal likelihood is not finite at the initial values (a member's "
                         "filter fails there): give other initial values (init=...) or omega_init") from None
    final = Search(optimum.z, max(maxiter - optimum.iterations, 1), _progress_report(progress), scoring=False,
                   value=True)
    polished = run_alone(final, {EXACT: outer.exact, VALUE: outer.value})
    return replace(polished, iterations=optimum.iterations + polished.iterations,
                   evaluations=optimum.evaluations + polished.evaluations)


def fit_population(model, datasets, random=None, covariates: pd.DataFrame | None = None, effects=None,
                   omega: str | None = None, time: str | None = None, hold: str | None = None,
                   method: str | None = None, init=None, omega_init=None, start: str = "pooled",
                   maxiter: int = 200, scheduler=None, chunk_size: int | None = None,
                   worker_timeout: float | None = None, progress=False, hessian: str = "differences", **options):
    """Fit a population (nonlinear mixed-effects) SDE model to many data sets.

    Every data set (a house, a patient, an engine) has its own parameters, drawn
    from a population whose typical values, covariate effects and spread are
    estimated together from all data sets.  For data set i, with ψ = θ (a
    ``"normal"`` random effect) or ψ = log θ (``"lognormal"``),
    ψ_i = ψ_typical + Σ_c β_c (x_ic − x̄_c) + η_i, η_i ~ N(0, Ω).  The marginal
    likelihood is the Laplace approximation over each member's η (exact where η
    enters the outputs linearly in a linear Gaussian model).

    Parameters
    ----------
    model : Model
        The model each data set follows.
    datasets : mapping or sequence
        ``{name: DataFrame or CSV path}``, one data set per member, or a list
        (named 0, 1, ...).  A data set that cannot be prepared is left out with a
        ``PopulationWarning`` and listed in the result's ``left_out``.
    random : mapping of str to {"normal", "lognormal"}, optional
        The parameters with a random effect (default: the model's
        [`set_population()`][greyid.api.Model.set_population] or model file's
        ``[population] random``).  Parameters without one are shared by all members.
    covariates : pandas.DataFrame or str, optional
        A row per data set (index: the data sets' names, read as text) or a CSV
        file of them (first column: the names).
    effects : mapping, optional
        ``{parameter: [covariate, ...]}``: covariate effects on the parameters'
        typical values (on the log scale for a lognormal parameter).
    omega : {"diagonal", "full"}, optional
        Independent random effects, or correlated ones.
    time : str, optional
        The name of the time column.
    hold : {"zoh", "foh"}, optional
        How inputs are held between samples.
    method : str, optional
        The filter.
    init : mapping of str to float, optional
        Starting values of the typical values (default: the model's initial values).
    omega_init : mapping or pandas.DataFrame, optional
        Starting standard deviations ``{parameter: sd}``, or Ω itself as a square
        DataFrame labelled by the random parameters (default 0.3 on the log scale,
        30 % of the typical value on the natural scale).
    start : {"pooled", "init"}
        ``"pooled"``: start from a fit of the model to the first eight data sets
        together (from ``init`` where that fit fails); ``"init"``: from the initial values.
    maxiter : int
        The outer search's largest number of steps.
    scheduler : dask.distributed.Client, optional
        Run the members' inner optimisations on a Dask cluster, by chunks; the outer
        search runs here.
    chunk_size : int, optional
        Members per chunk on a cluster (default: one chunk per worker).
    worker_timeout : float, optional
        Seconds the cluster may have no worker before the fit stops with an error (default 60).
    progress : bool or callable
        Print to standard error each phase (the pooled start, the members' programs, which a first run
        compiles) and each step of the outer search; a callable receives one dict per event instead
        (``phase`` and ``message``, or ``iteration``, ``stage``, ``value``, ``max_gradient``).
    hessian : {"differences", "exact"}, default "differences"
        The outer Hessian, for the last Newton steps and the standard errors: the exact formula with each
        member's second derivatives in its free parameters' scales by central differences of its exact first
        derivatives (``2n + 1`` runs of the gradient's filter program for n free parameters, steps of 1e-4
        conditional standard deviations found the first time by second differences of each member's
        likelihood; nothing more to compile; standard errors within about 1e-8 relative of the exact
        Hessian's), or the exact one, whose program (the filter's fourth derivatives) compiles for about as
        long as the rest of a first fit, minutes with ``method="laplace"`` or ``"enkf"``.
    **options
        The filter's settings (``form``, ``substeps``, ``iterations``, ...),
        ``time_unit`` and ``columns``; not ``steady_state``.

    Returns
    -------
    PopulationResult
        The population parameters with their uncertainty, each member's random
        effects and the fit's statistics.

    Raises
    ------
    DataError
        Names that are not unique, a covariates table without a row for a data set
        or with two, a covariate that is missing or not a number.
    ModelError
        No random effects, a random effect on a fixed or unknown parameter, an
        unknown setting, or a criterion not finite at the start.

    See Also
    --------
    greyid.population.result.likelihood_ratio : tests between nested population models.
    greyid.fleet.fit.fit_many : each data set on its own, no population.

    Examples
    --------
    The population tutorial (docs/population.md) runs this on six simulated houses:

    >>> pop = greyid.fit_population(model, houses, random={"Ci": "lognormal"},
    ...                             covariates=covariates, effects={"Ci": ["floor_area"]})  # doctest: +SKIP
    >>> print(pop.summary())  # doctest: +SKIP
    """
    names, sources = named_datasets(datasets)
    if len(set(map(str, names))) != len(names):
        raise DataError("the data sets' names must be unique")
    defaults = getattr(model, "population", {}) or {}
    random = defaults.get("random") if random is None else random
    if random is None:
        raise ModelError("no random effects: name the parameters that vary between data sets, with --random "
                         "PARAMETER:lognormal (or :normal) on the command line, random = { PARAMETER = \"lognormal\" } "
                         "in the model file's [population] table, or random={'PARAMETER': 'lognormal'} in Python")
    effects = defaults.get("effects") if effects is None else effects
    omega = defaults.get("omega", "diagonal") if omega is None else omega
    omega_init = defaults.get("omega_init") if omega_init is None else omega_init
    if covariates is None and defaults.get("covariates"):
        covariates = defaults["covariates"]
        if getattr(model, "source", None) is not None and not Path(covariates).is_absolute():
            covariates = Path(model.source).parent / covariates
    if isinstance(covariates, (str, Path)):
        covariates = read_covariates(covariates)
    unknown = set(options) - set(FILTER_OPTIONS) - {"time_unit", "columns"}
    if unknown:
        raise ModelError(f"fit_population does not take '{sorted(unknown)[0]}'; it takes time, hold, method, init, "
                         f"omega_init, maxiter, progress, hessian and the filter's options {list(FILTER_OPTIONS)}")
    if hessian not in HESSIANS:
        raise ModelError(f"hessian is '{hessian}'; use 'exact' (the exact outer Hessian) or 'differences' (the "
                         "members' second derivatives by central differences of their exact first derivatives)")
    if options.get("steady_state"):
        raise ModelError("steady_state=True is for single fits (model.fit, model.likelihood): a population "
                         "evaluates its members together in one program, where each member's switch would run "
                         "both forms")
    time_unit, columns = options.pop("time_unit", None), options.pop("columns", None)
    settings = model._options if hasattr(model, "_options") else {}
    time = time or settings.get("time") or "t"
    hold = hold or settings.get("hold") or "zoh"
    method = method or settings.get("method")
    if method == PARTICLE:
        raise ModelError("fit_population integrates the random effects by Laplace's method, which needs smooth "
                         "second and third derivatives of each member's likelihood; the particle filter's estimate "
                         "has none (its resampling is discontinuous): use method='laplace', 'enkf' or a Gaussian "
                         "filter")
    columns = columns or settings.get("columns")
    make_spec(model, random, covariates, effects, omega, names, init, omega_init)  # bad input named first
    if start == "pooled":
        _say(progress, "start", f"the start: one fit to the first {min(POOLED_MEMBERS, len(names))} of the "
                                f"{len(names)} members' data together")
        init = _pooled_start(model, names, sources, init, dict(time=time, hold=hold, method=method,
                                                               time_unit=time_unit, columns=columns, **options))
    elif start != "init":
        raise ModelError(f"start is '{start}'; use 'pooled' (a fit to a few members' data together) or 'init' "
                         "(the model's initial values)")
    spec, raw = make_spec(model, random, covariates, effects, omega, names, init, omega_init)
    members = prepare_members(model, names, sources, spec, raw, time, hold, time_unit, columns)
    structure = model.structure
    fo = population_filter(model, spec, members, method, time, hold, time_unit, options)
    _say(progress, "programs", f"the members' programs for {len(members.names)} members (a first run compiles "
                               "them, which can take a minute; greyid's cache folder keeps them for later runs)")
    if scheduler is not None:
        evaluator = ClusterEvaluator(scheduler, model, spec, fo, members, chunk_size,
                                     60.0 if worker_timeout is None else worker_timeout)
        outer = Outer(None, members, spec, evaluator=evaluator, hessian=hessian)
    else:
        outer = Outer(population_programs(structure, spec, fo), members, spec, hessian=hessian)
    phi0 = spec.phi0()
    try:
        last = "the exact Hessian" if hessian == "exact" else "the Hessian by differences of the members' slopes"
        _say(progress, "search", f"the outer search (the members' modes, the gradient, then {last})")
        optimum = _search(outer, phi0, maxiter, progress)
        modes = outer.modes(optimum.z)
    finally:
        outer.close()
    call = dict(time=time, hold=hold, method=fo.method, form=fo.form, substeps=fo.substeps,
                iterations=fo.iterations, time_unit=time_unit, omega=omega, hessian=hessian)
    result = PopulationResult._at_optimum(model, spec, members, optimum, modes, call)
    if covariates is not None:
        kept = {str(n) for n in result.names}
        result.covariates = covariates.loc[[n for n in covariates.index if str(n) in kept]].copy()
        result.covariates.index = result.covariates.index.map(str)
    result.sources = {n: str(src) for n, src in zip(names, sources) if isinstance(src, (str, Path))
                      and n in result.frames}
    return result


__all__ = ["fit_population", "PopulationWarning"]
