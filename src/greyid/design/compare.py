"""Candidate experiments side by side: criteria and ranks (thesis section 7.3, tables 7.4–7.5).

``compare_inputs(model, params, {"prbs 1 h": plan_a, "step": plan_b, ...})``
computes the information of every candidate plan (exact for linear models, by
Monte Carlo otherwise, see [`fisher_information()`][greyid.design.information.fisher_information]) and the
chosen criteria on it, each minimised, with the rank of every candidate per
criterion (1 = best).
"""

from __future__ import annotations

import warnings
from typing import Mapping

import pandas as pd

from ..errors import DataError, ModelError, UndefinedCriterionWarning, UndeterminedWarning, warn
from ..scaled import ScaledInformation
from .criteria import criterion
from .information import fisher_information

#: Table 7.4's standard measures.
STANDARD = {"D": "D", "Ds": "Ds", "C": "C", "E": "E"}


def _spec(label, spec) -> dict:
    if isinstance(spec, str):
        return {"name": spec}
    if isinstance(spec, Mapping) and "name" in spec:
        return dict(spec)
    raise ModelError(f"criterion '{label}' must be a criterion name such as 'D' or a mapping with a 'name' "
                     "(and interest=, derived=, V=, k=)")


def compare_inputs(model, params, candidates: Mapping[str, pd.DataFrame], criteria=None, interest=None,
                   **information_options) -> pd.DataFrame:
    """Candidate experiments side by side: each criterion's value and rank (tables 7.4–7.5).

    Parameters
    ----------
    model : Model
        The model.
    params : mapping of str to float
        The assumed parameter values.
    candidates : mapping of str to pandas.DataFrame
        ``{label: plan}``, each plan the times and inputs of an experiment.
    criteria : mapping, optional
        ``{column label: criterion name}`` or ``{label: {"name": ..., "interest":
        ..., "derived": {...}, "V": ..., "k": ...}}``, e.g.
        ``{"UA": {"name": "A", "derived": {"UA": "Hi*Hm/(Hi+Hm)"}}}`` (default: D,
        C, E, and Ds with ``interest``).
    interest : sequence of str, optional
        The parameters of interest of ``"Ds"``.
    **information_options
        For [`fisher_information()`][greyid.design.information.fisher_information]
        (``time``, ``hold``, ``free``, ``method``, ``n_paths``, ``seed``).

    Returns
    -------
    pandas.DataFrame
        One row per candidate: each criterion and its ``<criterion> rank`` (1 = best;
        empty where the criterion is undefined).  ``attrs["information"]`` holds each
        candidate's matrix, ``attrs["undetermined"]`` the directions a candidate does
        not determine (its criteria of them are +inf; one
        [`UndeterminedWarning`][greyid.errors.UndeterminedWarning] each) and
        ``attrs["undefined"]`` the criteria not defined at ``params`` (C where a
        parameter is 0: NaN; one
        [`UndefinedCriterionWarning`][greyid.errors.UndefinedCriterionWarning] each).

    Raises
    ------
    DataError
        No candidates, or a plan that is not a DataFrame (names the plan).
    ModelError
        A criterion that is not known or lacks its options.
    """
    if not isinstance(candidates, Mapping) or not candidates:
        raise DataError("candidates must be a non-empty mapping name → plan DataFrame")
    if criteria is None:
        criteria = dict(STANDARD) if interest is not None else {k: v for k, v in STANDARD.items() if k != "Ds"}
    specs = {label: _spec(label, spec) for label, spec in criteria.items()}
    values = model.parameter_vector(params)
    point = dict(zip(model.structure.parameter_names, values))
    rows, matrices, undetermined, undefined = {}, {}, {}, {}
    for name, plan in candidates.items():
        if not isinstance(plan, pd.DataFrame):
            raise DataError(f"plan '{name}' is not a DataFrame of times and inputs")
        try:
            info = fisher_information(model, point, plan, **information_options)
        except (DataError, ModelError) as error:
            raise type(error)(f"plan '{name}': {error}") from None
        matrices[name] = info
        row = {}
        scaled = ScaledInformation.of(info.to_numpy(), list(info.index))
        if scaled.singular:
            undetermined[name] = scaled.describe()
            warn(f"plan '{name}' does not determine the direction {undetermined[name]} (scaled "
                          "parameters): its criteria of it are +inf", UndeterminedWarning)
        for label, spec in specs.items():
            options = {k: v for k, v in spec.items() if k != "name"}
            if spec["name"] == "Ds" and "interest" not in options:
                if interest is None:
                    raise ModelError(f"criterion '{label}' (Ds) needs interest=, the parameters of interest")
                options["interest"] = interest
            with warnings.catch_warnings(record=True) as caught:  # said once per candidate, above
                warnings.simplefilter("ignore", UndeterminedWarning)
                warnings.simplefilter("always", UndefinedCriterionWarning)
                row[label] = criterion(info, spec["name"], params=point, **options)
            for said in caught:
                if issubclass(said.category, UndefinedCriterionWarning):
                    undefined.setdefault(label, str(said.message))
                else:
                    warnings.warn_explicit(said.message, said.category, said.filename, said.lineno)
        rows[name] = row
    for label, message in undefined.items():
        warn(f"{label}: {message}; its column is NaN and its rank empty", UndefinedCriterionWarning)
    table = pd.DataFrame.from_dict(rows, orient="index")
    for label in specs:  # an undefined criterion (NaN) has no rank: pandas' nullable integers
        table[f"{label} rank"] = table[label].rank(method="min").astype("Int64")
    table = table[[c for label in specs for c in (label, f"{label} rank")]]
    table.attrs["information"] = matrices
    table.attrs["undetermined"] = undetermined
    table.attrs["undefined"] = undefined
    return table


__all__ = ["compare_inputs", "STANDARD"]
