"""The members of a population fit: each data set checked and stacked, the filter's settings and the
compiled programs of the problem.

[`prepare_members()`][greyid.population.members.prepare_members] is what
[`fit_population()`][greyid.population.fit.fit_population] and a result's ``member()`` run on their data sets.
"""

from __future__ import annotations

from dataclasses import dataclass

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import numpy as np

from ..data.files import read_source
from ..data.prepare import as_frames
from ..errors import DataError, ModelError, PopulationWarning, warn  # noqa: F401  (PopulationWarning: re-exported)
from ..estimate.batch import pad_series
from ..estimate.estimation import check_observed
from ..filters.accuracy import needs_substeps
from ..filters.api import accurate_options, check_at_parameters, filter_options, prepare_datasets
from ..model.options import FILTER_KEYS, rename_columns
from . import laplace
from .spec import PopulationSpec


#: The filter's settings a population fit takes besides ``method``, as model.fit does.
FILTER_OPTIONS = tuple(k for k in FILTER_KEYS if k != "method")


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


def prepare_members(model, names, sources, spec: PopulationSpec, raw_covariates, time, hold, time_unit,
                     columns, minimum: int | None = None) -> Members:
    """The data sets checked and stacked; at least ``minimum`` must remain (default: more than the random
    effects, as a population fit needs)."""
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
    if minimum is not None and len(kept) < minimum:
        raise DataError(f"the data set cannot be used: {next(iter(left_out.values()))}")
    for name, why in left_out.items():
        warn(f"data set '{name}' is left out of the population fit: {why}", PopulationWarning)
    if minimum is None and len(kept) <= max(spec.n_random, 1):
        raise DataError(f"{len(kept)} data set(s) can be fitted, too few for a population with {spec.n_random} "
                        "random effect(s): a population fit needs more data sets than random effects")
    length = max(len(np.asarray(s.t)) for s in inputs)
    unique = max(len(np.asarray(s.unique_dt)) for s in inputs)
    data = jax.device_put(pad_series(inputs, length, unique))
    raw = np.array(rows, dtype=float).reshape(len(kept), len(spec.covariates))
    x = (raw - spec.covariate_mean) / spec.covariate_sd if spec.covariates else raw
    return Members(kept, frames, data, x, raw, np.array(n_obs), left_out)


def population_filter(model, spec: PopulationSpec, members: Members, method, time, hold, time_unit, options):
    """The filter's settings: as given, with as many sub-steps as accuracy needs at the start (chosen on the
    first member, as model.fit chooses them, see greyid.filters.accuracy) where none are given."""
    structure = model.structure
    settings = {k: v for k, v in options.items() if v is not None}
    if settings.get("substeps") is None and needs_substeps(structure):
        first = prepare_datasets(structure, spec.theta0, members.frames[0], time, hold, time_unit, check=False)
        settings.pop("substeps", None)
        return accurate_options(structure, spec.theta0, first, method, **settings)[0]
    return filter_options(structure, method, **settings)


def population_programs(structure, spec: PopulationSpec, options) -> laplace.LaplacePrograms:
    """The compiled programs of this population problem, built once per model structure."""
    key = ("population", options, spec.key())
    if key not in structure.cache:
        structure.cache[key] = laplace.build(structure, spec, options)
    return structure.cache[key]
