"""Population (mixed-effects) fits: one model, many data sets, shared structure, individual parameters.

``fit_population(model, datasets, random={...})`` maximises the Laplace
approximation of the marginal likelihood Π_i ∫ p(y_i | θ_i) p(η_i) dη_i over
the population parameters φ (:mod:`.spec`): every outer step solves each
member's inner problem (the conditional modes of its random effects, all
members at once by vectorised programs, warm-started from the previous modes)
and evaluates Σ_i ℓ_i(φ) with exact derivatives (:mod:`.laplace`).  The outer
search is greyid's trust-region search (:mod:`greyid.estimate.optimize`):
steps on the members' outer-product information Σ_i ∇ℓ_i∇ℓ_iᵀ far from the
optimum, Newton steps on the exact Hessian near it; the standard errors come
from that exact Hessian.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from .. import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax
import numpy as np
import pandas as pd

from ..data.prepare import as_frames
from ..errors import DataError, ModelError
from ..estimate.batch import pad_series
from ..estimate.estimation import check_observed
from ..estimate.optimize import EXACT, SCORING, VALUE, Search, run_alone, settle
from ..filters.accuracy import needs_substeps
from ..filters.api import accurate_options, check_at_parameters, filter_options, prepare_datasets
from ..fleet.fit import named_datasets, read_source
from ..model.options import rename_columns
from . import laplace
from .spec import PopulationSpec, make_spec


class PopulationWarning(UserWarning):
    """A member left out of a population fit, or a fit that did not converge."""


#: Settings of the data and the filter a population fit takes, as model.fit does.
FILTER_OPTIONS = ("form", "substeps", "iterations", "alpha", "beta", "kappa")


@dataclass
class Members:
    """The data sets that take part: names, frames, the stacked filter inputs and standardised covariates."""

    names: list
    frames: list  # per member: list of DataFrames (one per experiment; population members have one)
    data: object  # FilterInputs stacked over members
    x: np.ndarray  # (members, covariates) standardised
    raw: np.ndarray  # (members, covariates) as given
    n_obs: np.ndarray  # observed output values per member
    left_out: dict  # name -> why


def _prepare_members(model, names, sources, spec: PopulationSpec, raw_covariates, time, hold, time_unit,
                     columns) -> Members:
    structure = model.structure
    kept, frames, inputs, rows, n_obs, left_out = [], [], [], [], [], {}
    for k, (name, source) in enumerate(zip(names, sources)):
        try:
            frame = rename_columns(read_source(source), columns)
            parts = as_frames(frame)
            if len(parts) != 1:
                raise DataError("a population member is one data set (one DataFrame), not several")
            prepared = prepare_datasets(structure, spec.theta0, parts, time, hold, time_unit, check=False,
                                        on_device=False)
            check_at_parameters(structure, spec.theta0, *prepared[0])
            check_observed(prepared, spec.n_random, f"data set '{name}'")
        except (DataError, ModelError) as error:
            left_out[name] = str(error)
            continue
        kept.append(name)
        frames.append(parts)
        inputs.append(prepared[0][1])
        rows.append(raw_covariates[k])
        n_obs.append(int(np.sum(~np.isnan(prepared[0][0].outputs))))
    for name, why in left_out.items():
        warnings.warn(f"data set '{name}' is left out of the population fit: {why}", PopulationWarning,
                      stacklevel=3)
    if len(kept) <= max(spec.n_random, 1):
        raise DataError(f"{len(kept)} data set(s) can be fitted, too few for a population with {spec.n_random} "
                        "random effect(s): a population fit needs more data sets than random effects")
    length = max(len(np.asarray(s.t)) for s in inputs)
    unique = max(len(np.asarray(s.unique_dt)) for s in inputs)
    data = jax.device_put(pad_series(inputs, length, unique))
    raw = np.array(rows, dtype=float).reshape(len(kept), len(spec.covariates))
    x = (raw - spec.covariate_mean) / spec.covariate_sd if spec.covariates else raw
    return Members(kept, frames, data, x, raw, np.array(n_obs), left_out)


class Outer:
    """The outer criterion Σ_i ℓ_i(φ) with its derivatives; keeps the members' modes for warm starts."""

    def __init__(self, programs: laplace.LaplacePrograms, members: Members, spec: PopulationSpec):
        q = spec.n_random
        self.programs, self.members = programs, members
        self.base = tuple(jax.device_put(np.asarray(a, dtype=float)) for a in spec.base())
        self.x = jax.device_put(members.x)
        self.u = np.zeros((len(members.names), q))
        self.evaluations = 0

    def modes(self, phi) -> laplace.Modes:
        modes = laplace.conditional_modes(self.programs, phi, self.u, self.x, self.base, self.members.data)
        if modes.finite.all():
            self.u = modes.u  # warm start for the next evaluation
        self.evaluations += 1
        return modes

    def value(self, phi):
        return (float(np.sum(laplace.laplace_values(self.modes(phi)))),)

    def member_gradients(self, phi, modes=None):
        modes = self.modes(phi) if modes is None else modes
        if not modes.finite.all():
            n = len(phi)
            return np.full(len(modes.u), np.inf), np.full((len(modes.u), n), np.nan), modes
        values, gradients = self.programs.gradient(jax.numpy.asarray(phi), modes.u, self.x, self.base, self.members.data)
        return np.asarray(values), np.asarray(gradients), modes

    def scoring(self, phi):
        values, gradients, _ = self.member_gradients(phi)
        return float(np.sum(values)), gradients.sum(axis=0), gradients.T @ gradients

    def exact(self, phi):
        values, gradients, modes = self.member_gradients(phi)
        if not np.all(np.isfinite(values)):
            n = len(phi)
            return np.inf, np.full(n, np.nan), np.full((n, n), np.nan)
        hessians = np.asarray(self.programs.hessian(jax.numpy.asarray(phi), modes.u, self.x, self.base, self.members.data))
        H = hessians.sum(axis=0)
        return float(np.sum(values)), gradients.sum(axis=0), 0.5 * (H + H.T)


def fit_population(model, datasets, random, covariates: pd.DataFrame | None = None, effects=None,
                   omega: str = "diagonal", time: str | None = None, hold: str | None = None,
                   method: str | None = None, init=None, omega_init=None, maxiter: int = 200,
                   progress=False, **options):
    """Fit a population (nonlinear mixed-effects) SDE model to many data sets; a :class:`PopulationResult`.

    ``datasets``: a mapping name → DataFrame or CSV path (or a list, named 0..n−1),
    one data set per member.  ``random`` maps parameters to their random effect:
    ``"normal"`` (θ_i = θ + η_i) or ``"lognormal"`` (θ_i = θ·exp(η_i)), η_i ~ N(0, Ω),
    Ω diagonal or, with ``omega="full"``, with correlations.  ``covariates``: a
    DataFrame with a row per data set (index: the data sets' names); ``effects``
    maps parameters to covariate columns whose β·covariate is added to the
    parameter's mean (on the log scale for a lognormal parameter).  Parameters
    without a random effect are shared by all members.  The marginal likelihood is
    the Laplace approximation over each member's η (exact where η enters the
    outputs linearly in a linear Gaussian model); see :mod:`greyid.population`.
    """
    from .result import PopulationResult

    names, sources = named_datasets(datasets)
    if len(set(map(str, names))) != len(names):
        raise DataError("the data sets' names must be unique")
    unknown = set(options) - set(FILTER_OPTIONS) - {"time_unit", "columns"}
    if unknown:
        raise ModelError(f"fit_population does not take '{sorted(unknown)[0]}'; it takes time, hold, method, init, "
                         f"omega_init, maxiter, progress and the filter's options {list(FILTER_OPTIONS)}")
    time_unit, columns = options.pop("time_unit", None), options.pop("columns", None)
    settings = model._options if hasattr(model, "_options") else {}
    time = time or settings.get("time") or "t"
    hold = hold or settings.get("hold") or "zoh"
    method = method or settings.get("method")
    spec, raw = make_spec(model, random, covariates, effects, omega, names, init, omega_init)
    members = _prepare_members(model, names, sources, spec, raw, time, hold, time_unit,
                               columns or settings.get("columns"))
    structure = model.structure
    filter_settings = {k: v for k, v in options.items() if v is not None}
    if filter_settings.get("substeps") is None and needs_substeps(structure):
        first = prepare_datasets(structure, spec.theta0, members.frames[0], time, hold, time_unit, check=False)
        filter_settings.pop("substeps", None)
        fo, _ = accurate_options(structure, spec.theta0, first, method, **filter_settings)
    else:
        fo = filter_options(structure, method, **filter_settings)
    key = ("population", fo, spec.key())
    if key not in structure.cache:
        structure.cache[key] = laplace.build(structure, spec, fo)
    programs = structure.cache[key]
    outer = Outer(programs, members, spec)
    phi0 = spec.phi0()
    search = Search(phi0, maxiter, scoring=True, value=True)
    evaluate = {VALUE: outer.value, SCORING: outer.scoring, EXACT: outer.exact}
    optimum = run_alone(search, {k: (lambda f: (lambda z: f(z)))(f) for k, f in evaluate.items()})
    modes = outer.modes(optimum.z)
    call = dict(time=time, hold=hold, method=fo.method, form=fo.form, substeps=fo.substeps,
                iterations=fo.iterations, time_unit=time_unit, omega=omega)
    return PopulationResult.from_optimum(model, spec, members, optimum, modes, programs, call)


__all__ = ["fit_population", "PopulationWarning", "settle"]
