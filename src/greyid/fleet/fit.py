"""One model fitted to many data sets at once (a fleet of houses, an engine's operating points).

``fit_many(model, datasets)`` checks and prepares every data set (a data set
that fails becomes a row with its error; the others go on), groups them by
padded length, and runs the searches of all members of a group together:
each member keeps its own trust region and convergence, and the requests of
all members are evaluated by one program vectorised over them
([`greyid.estimate.batch`][greyid.estimate.batch], the mechanism batched starts use).  Each member's
result is the `FitResult` a separate ``model.fit``
gives.  Series longer than [`LONG_SERIES`][greyid.estimate.objective.LONG_SERIES] rows
are fitted one at a time (their programs keep memory independent of length).
"""

from __future__ import annotations

from typing import Mapping

import pandas as pd

from ..data.files import named_datasets
from ..errors import DataError, ModelError
from ..model.options import resolve
from .distributed import fit_on_cluster
from .members import fit_members
from .result import FleetResult

def member_inits(init, names: list) -> list[dict | None]:
    """Initial values per data set: one mapping for all, a DataFrame indexed by the data sets' names,
    or a mapping data set name → mapping."""
    if init is None:
        return [None] * len(names)
    if isinstance(init, pd.DataFrame):
        missing = [n for n in names if n not in init.index]
        if missing:
            raise DataError(f"init has no row for data set '{missing[0]}'")
        return [{k: float(v) for k, v in init.loc[n].items() if pd.notna(v)} for n in names]
    if isinstance(init, Mapping) and init and all(isinstance(v, Mapping) for v in init.values()):
        return [dict(init[n]) if n in init else None for n in names]
    if isinstance(init, Mapping):
        return [dict(init)] * len(names)
    raise DataError("init must be a mapping parameter → value, a DataFrame with one row per data set, "
                    "or a mapping data set → mapping")


def fit_many(model, datasets, time: str | None = None, hold: str | None = None, scheduler=None,
             progress=False, init=None, chunk_size: int = 256, worker_timeout: float | None = None,
             **options) -> FleetResult:
    """Fit one model to each of many data sets in one call (a fleet of houses, an engine's operating points).

    Every data set is checked and prepared (one that fails becomes a row with its
    error; the others go on), the data sets are grouped by padded length, and the
    searches of a group's members run together: each keeps its own trust region and
    convergence, and every request is evaluated by one program vectorised over the
    members.  Each member's fit is the [`FitResult`][greyid.api.FitResult]
    a separate ``model.fit`` gives.

    Parameters
    ----------
    model : Model
        The model.
    datasets : mapping or sequence
        ``{name: DataFrame or CSV path}``, or a list (named 0, 1, ...).
    time : str, optional
        The name of the time column.
    hold : {"zoh", "foh"}, optional
        How inputs are held between samples.
    scheduler : dask.distributed.Client, optional
        Run the members on a Dask cluster, in chunks of ``chunk_size``.
    progress : bool or callable
        Print (or pass to the callable) how many members have finished.
    init : mapping or pandas.DataFrame, optional
        Starting values: one mapping for every member, a DataFrame indexed by the
        data sets' names, or ``{name: mapping}``.
    chunk_size : int
        Members per task on a cluster.
    worker_timeout : float, optional
        Seconds a cluster may have no worker before its pending members are given
        up as failed rows (default 60).
    **options
        The settings of [`Model.fit()`][greyid.api.Model.fit] (``method``,
        ``criterion``, ``starts``, ``maxiter``, ...), but ``steady_state``.

    Returns
    -------
    FleetResult
        A table with one row per data set, and each data set's fit.

    Raises
    ------
    DataError
        ``datasets`` that are one DataFrame or not a mapping or list, or names that are not unique.
    ModelError
        ``steady_state=True`` (a single fit's setting).

    Examples
    --------
    >>> import greyid
    >>> from greyid.datasets import building_model, load_building_data
    >>> data = load_building_data()
    >>> fleet = greyid.fit_many(building_model(), {"week 1": data.iloc[:500], "week 2": data.iloc[500:]})
    >>> list(fleet.table.index)
    ['week 1', 'week 2']
    """
    if resolve(model._options, options, ("steady_state",)).get("steady_state"):
        raise ModelError("steady_state=True is for single fits (model.fit, model.likelihood): a fleet evaluates "
                         "its data sets together in one program, where each series' switch would run both forms")
    names, sources = named_datasets(datasets)
    if len(set(map(str, names))) != len(names):
        raise DataError("the data sets' names must be unique")
    inits = member_inits(init, names)
    if scheduler is not None:
        return fit_on_cluster(scheduler, model, names, sources, inits, chunk_size, progress,
                              dict(time=time, hold=hold, **options), worker_timeout)
    rows, fits = fit_members(model, names, sources, inits, progress, dict(time=time, hold=hold, **options))
    return FleetResult(model, names, rows, fits)
