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

import warnings
from contextlib import ExitStack
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

from ..data.prepare import as_frames
from ..errors import DataError, ModelError
from ..filters.accuracy import needs_substeps
from ..filters.api import prepare_datasets
from ..estimate import estimation, objective
from ..estimate.batch import BatchedPrograms, drive, pad_series, prune_trailing
from ..estimate.objective import compiled
from ..estimate.results import FitWarning
from ..model.options import DATA_KEYS, ESTIMATION_KEYS, FILTER_KEYS, rename_columns, resolve
from ..progress import CountProgress
from .result import FleetResult

#: In a fleet, scoring steps are vectorised over the members and cost a fraction of an
#: exact Hessian, which is not (Armadillo model: 1.0 against 7–9 ms per member and
#: step): Fisher scoring runs to its own convergence and one exact Hessian ends each
#: member's search (100 houses: 1.5 s, against 2.6 s handing over to Newton steps
#: as a single fit does and 4.6 s with Newton steps only).
HANDOVER = 0.0

#: Members whose searches run in one drive: bounds the host memory of the stacked series.
CHUNK = 2048


def named_datasets(datasets) -> tuple[list, list]:
    """``(names, sources)`` from a mapping name → data or a sequence (names 0..n−1)."""
    if isinstance(datasets, pd.DataFrame):
        raise DataError("fit_many takes several data sets (a mapping name → DataFrame, or a list); "
                        "for one DataFrame use model.fit")
    if isinstance(datasets, Mapping):
        return list(datasets.keys()), list(datasets.values())
    if isinstance(datasets, (list, tuple)):
        return list(range(len(datasets))), list(datasets)
    raise DataError(f"datasets must be a mapping name → DataFrame or a list, not {type(datasets).__name__}")


def read_source(source) -> pd.DataFrame:
    """A data set given as a DataFrame or as a CSV file's path (read where it is fitted)."""
    if isinstance(source, pd.DataFrame):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.is_dir():
            raise DataError(f"data file '{path}' is a folder")
        if not path.is_file():
            raise DataError(f"data file '{path}' not found")
        from ..model.files import read_csv_file

        return read_csv_file(path)
    raise DataError(f"a data set must be a DataFrame or a CSV file's path, not {type(source).__name__}")


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
    members.  Each member's fit is the [`FitResult`][greyid.estimate.results.FitResult]
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
        The settings of [`Model.fit()`][greyid.model.model.Model.fit] (``method``,
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
        from .distributed import fit_on_cluster

        return fit_on_cluster(scheduler, model, names, sources, inits, chunk_size, progress,
                              dict(time=time, hold=hold, **options), worker_timeout)
    rows, fits = fit_members(model, names, sources, inits, progress, dict(time=time, hold=hold, **options))
    return FleetResult(model, names, rows, fits)


#: fit()'s settings and their defaults (as in [`greyid.estimate.estimation.fit()`][greyid.estimate.estimation.fit]).
FIT_DEFAULTS = dict(time="t", hold="zoh", method=None, criterion="ml", robust=None, horizon=1, starts=1, seed=0,
                    time_unit=None, maxiter=500, cov_type=None, optimizer="auto")


def fit_members(model, names: list, sources: list, inits: list, progress, given: dict):
    """``(rows, fits)``: the table rows and [`FitResult`][greyid.estimate.results.FitResult] (or None) of each data
    set."""
    structure = model.structure
    given = dict(given)
    prior = given.pop("prior", None)
    # As model.fit resolves them: given in the call, else the model's, else the defaults.
    settings = resolve(model._options, given, DATA_KEYS + FILTER_KEYS + ESTIMATION_KEYS)
    settings.pop("prior_correlation", None)
    columns = settings.pop("columns", None)
    if prior is None and settings.get("criterion") == "map":
        prior = model.prior()
    s = dict(FIT_DEFAULTS)
    s.update({k: v for k, v in settings.items() if k in FIT_DEFAULTS})
    filter_settings = {k: v for k, v in settings.items() if k not in FIT_DEFAULTS}
    robust, cov_type = estimation.check_settings(s["criterion"], prior, s["robust"], s["horizon"], s["cov_type"],
                                                 s["optimizer"], s["starts"])
    shared = estimation.free_parameters(model)
    problem = estimation.make_problem(structure, shared, s["method"], (robust, s["horizon"], prior), filter_settings)
    args = problem.arguments(shared.theta0)
    n_free = len(shared.free)

    members = []  # per data set: dict with frames, prepared, parameters, or error
    for name, source, init in zip(names, sources, inits):
        try:
            frame = read_source(source)
            frame = rename_columns(frame, columns)
            parameters = shared if init is None else estimation.free_parameters(model, init)
            frames = as_frames(frame)
            prepared = prepare_datasets(structure, parameters.theta0, frames, s["time"], s["hold"], s["time_unit"],
                                        check=False, on_device=False)
            estimation.check_observed(prepared, n_free)
            members.append(dict(frames=frames, prepared=prepared, parameters=parameters))
        except (ModelError, DataError) as error:
            members.append(dict(error=f"data set '{name}': {error}"))

    results: list = [None] * len(names)
    with CountProgress(len(names), "fleet fit", progress) as shown:
        long = [i for i, m in enumerate(members) if "error" not in m
                and sum(series.n_rows for series, _ in m["prepared"]) > objective.LONG_SERIES]
        for i in long:
            results[i] = _fit_alone(model, members[i], s, robust, cov_type, prior, filter_settings)
            shown.advance()
        batched = [i for i, m in enumerate(members) if "error" not in m and i not in long]
        for group in _length_groups(members, batched):
            for start in range(0, len(group), CHUNK):
                chunk = group[start:start + CHUNK]
                optima = _optimise_chunk(model, problem, args, members, chunk, s, shown)
                for i, (best, all_optima, labels) in zip(chunk, optima):
                    results[i] = _result(model, structure, problem, args, members[i], best, all_optima, labels,
                                         s, robust, cov_type, prior, filter_settings)
        for m in members:
            if "error" in m:
                shown.advance()
    rows, fits = [], []
    for name, member, result in zip(names, members, results):
        if "error" in member:
            rows.append(dict(error=member["error"]))
            fits.append(None)
        elif isinstance(result, str):
            rows.append(dict(error=f"data set '{name}': {result}"))
            fits.append(None)
        else:
            rows.append(dict(error=None))
            fits.append(result)
    return rows, fits


def _length_groups(members, indices):
    """Members grouped by the power of two at or above their padded length (at most 2× padding)."""
    groups: dict[int, list] = {}
    for i in indices:
        length = len(np.asarray(members[i]["prepared"][0][1].t))
        groups.setdefault(1 << (length - 1).bit_length(), []).append(i)
    return [groups[k] for k in sorted(groups)]


def _optimise_chunk(model, problem, args, members, chunk, s, shown):
    """All searches of a chunk of members (with their starts) driven together."""
    structure = model.structure
    inputs = [members[i]["prepared"][0][1] for i in chunk]
    length = max(len(np.asarray(x.t)) for x in inputs)
    unique = max(len(np.asarray(x.unique_dt)) for x in inputs)
    stacked = pad_series(inputs, length, unique)
    searches, owner, labels_of = [], [], []
    for position, i in enumerate(chunk):
        m = members[i]
        scoring = s["optimizer"] not in ("newton", "quasi-newton")  # searches driven together: Newton steps
        # The starts a separate model.fit takes, so that each member's fit is the one it gives.
        points, labels, newton_only = estimation.start_points(
            m["parameters"], s["starts"], s["seed"], scoring and s["optimizer"] == "auto",
            reduced=estimation.reduced_starts(model, m["parameters"], s["starts"]))
        labels_of.append(labels)
        for z0, exact_only in zip(points, newton_only):
            searches.append(estimation.new_search(problem, z0, s["maxiter"], _quiet, scoring and not exact_only,
                                                  HANDOVER))
            owner.append(position)
    owner = np.array(owner)
    remaining = np.bincount(owner, minlength=len(chunk))

    def finished(j, result):
        remaining[owner[j]] -= 1
        if remaining[owner[j]] == 0:
            shown.advance()

    def prune(searches_, running):
        out = {}
        for position in set(owner[list(running)]):
            own = np.flatnonzero(owner == position)
            stops = prune_trailing([searches_[j] for j in own], {k for k, j in enumerate(own) if j in running})
            out.update({int(own[k]): reason for k, reason in stops.items()})
        return out

    with BatchedPrograms(structure.cache, problem.key(), compiled(structure, problem), len(problem.free), args,
                         [stacked], per_member=True, data_index=owner) as batched:
        results = drive(searches, batched, prune=prune if s["starts"] > 1 else None, finished=finished)
    out = []
    for position in range(len(chunk)):
        own = np.flatnonzero(owner == position)
        optima = [results[j] for j in own]
        if isinstance(optima[0], ModelError):
            out.append((f"the criterion is not finite at the initial values ({optima[0]})", None, None))
            continue
        optima = [estimation.failed_start(searches[j].z, r) if isinstance(r, ModelError) else r
                  for j, r in zip(own, optima)]
        best = min(optima, key=lambda o: o.value if np.isfinite(o.value) else np.inf)
        out.append((best, optima, labels_of[position]))
    return out


def _quiet(iteration, stage, f, g):
    pass


def _result(model, structure, problem, args, member, best, optima, labels, s, robust, cov_type, prior,
            filter_settings):
    """A member's [`FitResult`][greyid.estimate.results.FitResult], as ``model.fit`` would build it (its warnings kept
    on it, not shown)."""
    if isinstance(best, str):
        return best
    datasets = [inputs for _, inputs in member["prepared"]]
    substep_choice = None
    with ExitStack() as stack:
        alone = estimation.SearchesAlone(structure, (*args, datasets), stack)  # opens programs only when run

        def optimize(p, z):
            return alone.run(p, estimation.new_search(p, z, s["maxiter"], _quiet, False))

        if s["hold"] == "zoh" and structure.delays:  # as model.fit: the delay's neighbouring sampling intervals
            optima, labels = list(optima), list(labels)
            best = estimation.search_delays(structure, member["parameters"], member["prepared"], best, optima,
                                            labels, lambda z: optimize(problem, z))
        if filter_settings.get("substeps") is None and needs_substeps(structure):
            problem, best, substep_choice = estimation._accurate_substeps(structure, problem, best, args, datasets,
                                                                          optimize)
    call = dict(time=s["time"], hold=s["hold"], criterion=s["criterion"], robust=robust, horizon=int(s["horizon"]),
                starts=s["starts"], optimizer=s["optimizer"], time_unit=s["time_unit"], prior=prior,
                cov_type=cov_type)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)
        return estimation.finish(model, member["frames"], problem, best, optima, args, datasets,
                                 member["parameters"].theta0, call, labels, substep_choice)


def _fit_alone(model, member, s, robust, cov_type, prior, filter_settings):
    """A long series' fit, by ``model.fit``'s own path (memory independent of the length)."""
    kwargs = {k: v for k, v in s.items() if k not in ("robust", "cov_type")}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            return estimation.fit(model, member["frames"], robust=robust, cov_type=cov_type, prior=prior,
                                  init=None if member["parameters"] is None else _init_of(member),
                                  **kwargs, **filter_settings)
    except (ModelError, DataError) as error:
        return str(error)


def _init_of(member) -> dict:
    p = member["parameters"]
    return {p.names[i]: float(p.theta0[i]) for i in p.free}


