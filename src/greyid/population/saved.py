"""A population fit on disk: JSON with the model, the population parameters and each member's mode.

``PopulationResult.save(path)`` writes it atomically (a process killed meanwhile
leaves the previous file whole); [`load_population()`][greyid.population.result.load_population] rebuilds the result —
its tables, summary and tests — without refitting.  The members' data are not
in the file: where they were given as CSV paths the paths are kept and read
again by ``member()``; otherwise ``load_population(path, data=...)`` takes them.
"""

from __future__ import annotations

import json

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
