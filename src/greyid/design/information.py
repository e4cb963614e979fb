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
from ..estimate.calls import simulate_at
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
    """The information matrix of a planned experiment at assumed parameter values (6.26–6.29).

    Parameters
    ----------
    model : Model
        The model.
    params : mapping of str to float
        A value for every parameter.
    plan : pandas.DataFrame
        The time column and the inputs; no outputs (every output is planned to be
        observed at every row).
    time : str
        The name of the time column.
    hold : {"zoh", "foh"}
        How inputs are held between samples.
    free : sequence of str, optional
        The parameters the matrix is taken for (default: the non-fixed ones).
    method : {"exact", "montecarlo"}, optional
        ``"exact"`` (linear models, their default): the expected information of the
        exact Kalman filter's innovations; ``"montecarlo"`` (any model, the default
        for nonlinear ones): the average of the observed information over
        ``n_paths`` simulated data sets.
    n_paths : int
        Simulated data sets of the Monte Carlo information.
    seed : int
        Their random seed.
    filter_method : str, optional
        The filter of the Monte Carlo information's likelihood (default: the model's).
    simulation : str, optional
        The scheme the data sets are simulated with (default: ``"exact"`` for linear
        models, ``"milstein"`` otherwise).
    substeps : int
        Integration steps per sampling interval of the simulation.

    Returns
    -------
    pandas.DataFrame
        Indexed and columned by the parameters, in the model's natural parameters;
        ``attrs["method"]`` says how it was computed, and for Monte Carlo
        ``attrs["standard_error"]`` holds the standard error of each entry and
        ``attrs["n_paths"]`` the number of data sets.

    Raises
    ------
    ModelError
        The exact information of a nonlinear model, or an unknown method.
    DataError
        A plan that is not a DataFrame of times and inputs, or that holds an output.

    Examples
    --------
    >>> import numpy as np, pandas as pd
    >>> from greyid import design, library
    >>> model = library.load_model("test_cell")
    >>> t = np.arange(200.0)
    >>> plan = pd.DataFrame({"t": t, "Te": 5.0, "Qh": 150.0 * (np.sin(t / 8) > 0)})
    >>> info = design.fisher_information(model, model.initial_values(), plan)
    >>> info.attrs["method"]
    'exact'
    """
    if method is None:
        method = "exact" if model.structure.is_linear else "montecarlo"
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r}; use one of {list(METHODS)}")
    if method == "exact" and not model.structure.is_linear:
        raise ModelError(f"the exact information needs a linear model, and model '{model.name}' is "
                         f"{model.structure.kind}; use the Monte Carlo information (--method montecarlo on the "
                         "command line, method='montecarlo' in Python)")
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
    sims = simulate_at(model, point, plan, n_paths=n_paths, seed=seed, method=simulation, substeps=substeps,
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
    """Which parameters a planned experiment determines, from its information matrix.

    The matrix is scaled to unit diagonal, so the verdict does not depend on the
    parameters' units; eigenvalues below ``tolerance`` times the largest are flat
    directions.  The same directions make
    [`cramer_rao_bound()`][greyid.design.criteria.cramer_rao_bound] infinite.

    Parameters
    ----------
    info : pandas.DataFrame
        An information matrix ([`fisher_information()`][greyid.design.information.fisher_information]).
    tolerance : float
        The relative size of an eigenvalue below which its direction is flat.

    Returns
    -------
    pandas.DataFrame
        One row per flat direction: ``eigenvalue``, ``parameters`` and ``loadings``
        (those above 0.05 of the largest); empty where the experiment determines
        every parameter locally.
    """
    scaled = ScaledInformation.of(info.to_numpy(dtype=np.float64), list(info.index), tolerance)
    eigenvalues = scaled.eigenvalues[scaled.null_mask]
    rows = [dict(eigenvalue=float(w), parameters=list(d), loadings=d)
            for w, d in zip(eigenvalues, scaled.directions())]
    return pd.DataFrame(rows, columns=["eigenvalue", "parameters", "loadings"])
