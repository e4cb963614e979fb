"""A population fit on disk: JSON with the model, the population parameters and each member's mode.

``PopulationResult.save(path)`` writes it atomically (a process killed meanwhile
leaves the previous file whole); [`load_population()`][greyid.population.saved.load_population] rebuilds the result —
its tables, summary and tests — without refitting.  The members' data are not
in the file: where they were given as CSV paths the paths are kept and read
again by ``member()``; otherwise ``load_population(path, data=...)`` takes them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError
from ..estimate.transforms import Transform
from .laplace import Modes
from .spec import PopulationSpec

FORMAT = "greyid population fit"
VERSION = 1


def population_to_dict(result) -> dict:
    spec, modes = result.spec, result._modes
    return dict(
        format=FORMAT, version=VERSION, model=result.model.to_dict(),
        spec=dict(names=list(spec.names), theta0=spec.theta0.tolist(), free=list(spec.free),
                  log_scale=list(spec.log_scale), kind=spec.transform.kind.tolist(),
                  lower=spec.transform.lower.tolist(), upper=spec.transform.upper.tolist(),
                  random=list(spec.random), kinds=list(spec.kinds), covariates=list(spec.covariates),
                  effects=[list(e) for e in spec.effects], covariate_mean=spec.covariate_mean.tolist(),
                  covariate_sd=spec.covariate_sd.tolist(), full=spec.full, omega0=spec.omega0.tolist()),
        members=dict(names=[str(n) for n in result.names], x=result._members.x.tolist(),
                     raw=result._members.raw.tolist(), n_obs=result._members.n_obs.tolist(),
                     left_out={str(k): v for k, v in result.left_out.items()},
                     sources=[result.sources.get(n) for n in result.names]),
        modes=dict(u=modes.u.tolist(), value=modes.value.tolist(), hessian=modes.hessian.tolist()),
        phi=result.phi.tolist(), hessian=result.hessian.tolist(), call=result.call,
        converged=result.converged, message=result.message, iterations=result.iterations,
        covariates=None if result.covariates is None else json.loads(result.covariates.to_json(orient="split")))


def load_population(path, data=None):
    """Read a population fit written by [`PopulationResult.save()`][greyid.population.result.PopulationResult.save].

    Parameters
    ----------
    path : str or pathlib.Path
        The JSON file.
    data : mapping of str to pandas.DataFrame, optional
        The members' data sets that were not CSV files (``member()`` needs them).

    Returns
    -------
    PopulationResult
        The fit.

    Raises
    ------
    DataError
        A file that is missing, not JSON, not a saved population fit, or damaged.
    """
    from ..model import Model
    from .fit import Members
    from .result import PopulationResult

    path = Path(path)
    if not path.is_file():
        raise DataError(f"population fit file '{path}' not found")
    try:
        saved = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"'{path}' is not a population fit file ({error})") from None
    if not isinstance(saved, dict) or saved.get("format") != FORMAT:
        raise DataError(f"'{path}' is not a population fit file (written by PopulationResult.save)")
    try:
        model = Model.from_dict(saved["model"])
        s = saved["spec"]
        spec = PopulationSpec(tuple(s["names"]), np.array(s["theta0"], dtype=float), tuple(s["free"]),
                              tuple(bool(v) for v in s["log_scale"]),
                              Transform(np.array(s["kind"], dtype=int), np.array(s["lower"], dtype=float),
                                        np.array(s["upper"], dtype=float)),
                              tuple(s["random"]), tuple(s["kinds"]), tuple(s["covariates"]),
                              tuple(tuple(e) for e in s["effects"]), np.array(s["covariate_mean"], dtype=float),
                              np.array(s["covariate_sd"], dtype=float), bool(s["full"]),
                              np.array(s["omega0"], dtype=float))
        m = saved["members"]
        names = list(m["names"])
        q = len(spec.random)
        members = Members(names, [None] * len(names), None, np.array(m["x"], dtype=float).reshape(len(names), -1),
                          np.array(m["raw"], dtype=float).reshape(len(names), -1),
                          np.array(m["n_obs"], dtype=int), dict(m["left_out"]))
        md = saved["modes"]
        modes = Modes(np.array(md["u"], dtype=float).reshape(len(names), q), np.array(md["value"], dtype=float),
                      np.array(md["hessian"], dtype=float).reshape(len(names), q, q),
                      np.ones(len(names), dtype=bool), np.ones(len(names), dtype=bool))
        result = PopulationResult(model, spec, members, np.array(saved["phi"], dtype=float),
                                  np.array(saved["hessian"], dtype=float), modes, dict(saved["call"]),
                                  saved["converged"], saved["message"], saved["iterations"])
    except (KeyError, TypeError, ValueError) as error:
        raise DataError(f"'{path}' is a damaged population fit file ({type(error).__name__}: {error})") from None
    result.sources = {n: src for n, src in zip(names, m.get("sources", [None] * len(names))) if src}
    if saved.get("covariates") is not None:
        table = saved["covariates"]
        result.covariates = pd.DataFrame(table["data"], index=[str(i) for i in table["index"]],
                                         columns=table["columns"])
    result.frames = {n: None for n in names}
    for name in names:
        if data is not None and name in data:
            result.frames[name] = [data[name]]
    return result
