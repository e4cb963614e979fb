"""The Fisher information of a planned experiment (6.29–6.30), before any data exist.

``method="montecarlo"`` is the approach of section 7.3: simulate ``n_paths``
data sets from the model at the assumed parameters on the plan's times and
inputs, and average the outer products of the per-observation scores through
the filter (each an unbiased estimate of the information, since the scores of
the prediction-error decomposition are martingale differences), with the Monte
Carlo standard error of every entry.  It serves linear and nonlinear models.
``method="exact"`` (the default for linear models) computes the expected
information of the finite experiment exactly, in O(N), from the filter
augmented with its parameter sensitivities ([`exact`][greyid.design.exact]).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import DataError, ModelError
from ..estimate.information import loglik_derivatives
from ..filters.api import prepare_datasets
from ..scaled import RANK_TOLERANCE, ScaledInformation
from .exact import exact_information

METHODS = ("exact", "montecarlo")


def _free_names(model, free):
    names = list(model.structure.parameter_names)
    if free is None:
        declared = model.parameters
        return [n for n in names if not (n in declared and declared[n].fixed)]
    unknown = [n for n in free if n not in names]
    if unknown:
        raise ModelError(f"'{unknown[0]}' is not a parameter of model '{model.name}'")
    return list(free)


def fisher_information(model, params, plan: pd.DataFrame, time: str = "t", hold: str = "zoh", free=None,
                       method: str | None = None, n_paths: int = 100, seed: int = 0, filter_method=None,
                       simulation: str | None = None, substeps: int = 20) -> pd.DataFrame:
    """Information matrix of the experiment ``plan`` at ``params`` (natural parameters).

    ``plan`` holds the time column and the inputs (every output is planned to be
    observed at every row); ``free`` names the parameters the matrix is taken for
    (default: the model's non-fixed ones).  ``method`` is ``"exact"`` (linear
    models; the default for them) or ``"montecarlo"`` (any model; the default for
    nonlinear ones), with ``n_paths`` simulated data sets.  Returns a DataFrame
    indexed and columned by those names; ``attrs["method"]`` says how it was
    computed, and for Monte Carlo ``attrs["standard_error"]`` holds the standard
    error of each entry and ``attrs["n_paths"]`` the number of simulated data sets.
    """
    if method is None:
        method = "exact" if model.structure.is_linear else "montecarlo"
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r}; use one of {list(METHODS)}")
    if method == "exact" and not model.structure.is_linear:
        raise ModelError(f"method='exact' needs a linear model, and model '{model.name}' is "
                         f"{model.structure.kind}; use method='montecarlo'")
    if not isinstance(plan, pd.DataFrame):
        raise DataError("the plan must be a DataFrame with the time column and the inputs")
    present = [o for o in model.output_names if o in plan.columns]
    if present:
        raise DataError(f"the plan holds the output column '{present[0]}'; a plan has times and inputs only")
    if method == "montecarlo" and (not isinstance(n_paths, int) or n_paths < 2):
        raise ModelError(f"n_paths must be an integer of at least 2, got {n_paths!r}")
    names = _free_names(model, free)
    values = model.parameter_vector(params)
    all_names = list(model.structure.parameter_names)
    point = dict(zip(all_names, values))
    if method == "exact":
        observed = plan.assign(**{o: 0.0 for o in model.output_names})  # every output observed; values unused
        prepared = prepare_datasets(model.structure, values, observed, time, hold, None)
        index = tuple(all_names.index(n) for n in names)
        F = sum(exact_information(model.structure, values, inputs, index) for _, inputs in prepared)
        info = pd.DataFrame(F, index=names, columns=names)
        info.attrs["method"] = "exact"
        return info
    simulation = simulation or ("exact" if model.structure.is_linear else "milstein")
    sims = model.simulate(point, plan, n_paths=n_paths, seed=seed, method=simulation, substeps=substeps,
                          hold=hold, time=time)
    k = len(names)
    samples = np.empty((n_paths, k, k))
    for i in range(n_paths):
        data = plan.copy()
        for j, name in enumerate(model.output_names):
            data[name] = sims.outputs[i, :, j]
        samples[i] = loglik_derivatives(model, point, data, names, "opg", time=time, hold=hold,
                                        method=filter_method).information
    mean = samples.mean(axis=0)
    error = samples.std(axis=0, ddof=1) / np.sqrt(n_paths)
    info = pd.DataFrame(0.5 * (mean + mean.T), index=names, columns=names)
    info.attrs["standard_error"] = pd.DataFrame(error, index=names, columns=names)
    info.attrs["n_paths"] = n_paths
    info.attrs["method"] = "montecarlo"
    return info


def local_identifiability(info: pd.DataFrame, tolerance: float = RANK_TOLERANCE) -> pd.DataFrame:
    """Which parameters the planned experiment determines, from the information matrix.

    The matrix is scaled to unit diagonal (`greyid.scaled`: the verdict does
    not depend on the parameters' units); eigenvalues below ``tolerance`` times
    the largest are flat directions, whose loadings (above 0.05 of the largest)
    name the parameters involved.  Returns one row per flat direction
    (``eigenvalue``, ``parameters``, ``loadings``); an empty table means locally
    identifiable at these values.  The same directions make
    [`cramer_rao_bound()`][greyid.design.criteria.cramer_rao_bound] infinite.
    """
    scaled = ScaledInformation.of(info.to_numpy(dtype=np.float64), list(info.index), tolerance)
    eigenvalues = scaled.eigenvalues[scaled.null_mask]
    rows = [dict(eigenvalue=float(w), parameters=list(d), loadings=d)
            for w, d in zip(eigenvalues, scaled.directions())]
    return pd.DataFrame(rows, columns=["eigenvalue", "parameters", "loadings"])
