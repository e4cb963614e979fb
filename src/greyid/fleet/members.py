"""The members of a fleet: each data set checked, prepared and searched, in chunks of one padded length.

[`fit_members()`][greyid.fleet.members.fit_members] is what [`fit_many()`][greyid.fleet.fit.fit_many] runs in
its own process and what each Dask worker runs on its chunk ([`greyid.fleet.distributed`][greyid.fleet.distributed]).
"""

from __future__ import annotations

import warnings
from contextlib import ExitStack

import numpy as np

from ..data.files import read_source
from ..data.prepare import as_frames
from ..errors import DataError, ModelError
from ..filters.accuracy import chooses_substeps
from ..filters.api import prepare_datasets
from ..api import FitResult
from ..estimate import estimation, objective
from ..estimate.batch import BatchedPrograms, drive, pad_series, prune_trailing
from ..estimate.objective import compiled
from ..estimate.results import FitWarning
from ..model.options import DATA_KEYS, ESTIMATION_KEYS, FILTER_KEYS, rename_columns, resolve
from ..progress import CountProgress

#: In a fleet, scoring steps are vectorised over the members and cost a fraction of an
#: exact Hessian, which is not: Fisher scoring runs to its own convergence and one exact
#: Hessian ends each member's search, faster than handing over to Newton steps as a single
#: fit does or taking Newton steps only (``benchmarks/fleet.py``).
HANDOVER = 0.0

#: Members whose searches run in one drive: bounds the host memory of the stacked series.
CHUNK = 2048


#: fit()'s settings and their defaults (as in [`greyid.estimate.estimation.fit()`][greyid.estimate.estimation.fit]).
FIT_DEFAULTS = dict(time="t", hold="zoh", method=None, criterion="ml", robust=None, horizon=1, starts=1, seed=0,
                    time_unit=None, maxiter=500, cov_type=None, optimizer="auto")


def fit_members(model, names: list, sources: list, inits: list, progress, given: dict):
    """``(rows, fits)``: the table rows and [`FitResult`][greyid.api.FitResult] (or None) of each data
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
    if s["optimizer"] == "lbfgs":
        raise ModelError("optimizer='lbfgs' is for single fits (model.fit): a fleet's searches run together by "
                         "Newton or scoring steps; use optimizer='auto', 'newton', 'scoring' or 'quasi-newton'")
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
            fits.append(FitResult.of(result))
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
    """A member's [`FitResult`][greyid.api.FitResult], as ``model.fit`` would build it (its warnings kept
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
        if filter_settings.get("substeps") is None and chooses_substeps(structure, problem.options.method,
                                                                        problem.options.scheme):
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


