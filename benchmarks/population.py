"""Population benchmark (issue "Population models"): Armadillo-size houses with two random effects.

    python benchmarks/population.py [--sizes 100,1000] [--scheduler local] [--cache-dir DIR] [--timings]
                                    [--layouts] [--method laplace] [--hessian exact|differences]

Houses: the Armadillo model (pySIP's TwTi_RoRi, first-order hold, 232 rows; data
the data set armadillo) simulated at its fitted parameters with a lognormal spread
of 20 % in Ro and 30 % in Cw (one house per seed).  For each size it fits the
population with ``Ro`` and ``Cw`` lognormal and prints the time of
``greyid.fit_population`` on the first call (compiling its programs, on an empty
cache folder in a fresh process, or loading them from ``--cache-dir``) and on a second call, with the estimates
beside the true spread and the process's peak resident memory so far (run one size
per process to compare sizes; Python's allocation tracing, tracemalloc, is left off:
it slows the tracing of a first call by half).  ``--scheduler local`` runs the members' inner
optimisations on a Dask LocalCluster with two workers; ``--timings`` also prints
the seconds of each call spent in the members' modes, the outer gradients and the
outer Hessian (in this process, so not with ``--scheduler local``).  ``--layouts``
then fits, in the same process and on the same houses, the nested layouts a model
selection compares: a full Ω, and a covariate effect of a floor area (drawn per
house) on Ro, printing the first call of each.  ``--method`` sets each member's likelihood (e.g. ``laplace``,
the Laplace method over the states; ``enkf``) and ``--hessian`` the outer Hessian (``fit_population``'s
``hessian=``: by default the members' second derivatives by differences of their slopes, or ``exact``).
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SPREAD = {"Ro": 0.2, "Cw": 0.3}


def houses(model, data, fitted, count: int, seed: int = 7) -> dict:
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(count):
        member = dict(fitted)
        for name, sd in SPREAD.items():
            member[name] = fitted[name] * np.exp(sd * rng.normal())
        sim = model.simulate(member, data, seed=seed + k, time="Time", hold="foh")
        out[f"house{k:05d}"] = data.assign(T_int=sim.outputs[0, :, 0])
    return out


def time_the_steps(spent: dict) -> None:
    """Wrap the members' programs so that each call's seconds add up in ``spent`` (name -> [seconds, calls])."""
    import jax

    from greyid.population import laplace

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            out = jax.block_until_ready(fn(*args, **kwargs))
            entry = spent.setdefault(name, [0.0, 0])
            entry[0] += time.perf_counter() - start
            entry[1] += 1
            return out

        return wrapper

    laplace.MemberPrograms.gradient = timed("outer gradients", laplace.MemberPrograms.gradient)
    laplace.MemberPrograms.hessian = timed("outer Hessian", laplace.MemberPrograms.hessian)
    if hasattr(laplace.MemberPrograms, "hessian_by_differences"):  # (not in an older checkout)
        laplace.MemberPrograms.hessian_by_differences = timed("outer Hessian by differences",
                                                              laplace.MemberPrograms.hessian_by_differences)
    laplace.conditional_modes = timed("members' modes", laplace.conditional_modes)  # as evaluate() calls it


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", default="100,1000")
    parser.add_argument("--scheduler", default=None, choices=[None, "local"])
    parser.add_argument("--cache-dir", default=None, help="greyid's cache folder (default: a new, empty one)")
    parser.add_argument("--timings", action="store_true", help="seconds in the modes, gradients and Hessian")
    parser.add_argument("--layouts", action="store_true", help="then a full Omega and a covariate effect")
    parser.add_argument("--method", default=None, help="each member's likelihood (default: the Kalman filter)")
    parser.add_argument("--hessian", default=None, choices=[None, "exact", "differences"],
                        help="the outer Hessian (default: fit_population's own)")
    args = parser.parse_args()
    import os
    import tempfile

    # An empty cache folder: the first call compiles everything, as in a fresh installation (with
    # --cache-dir, a folder a previous run filled: the first call loads the programs kept there).
    os.environ["GREYID_CACHE_DIR"] = args.cache_dir or tempfile.mkdtemp(prefix="greyid-bench-population-")
    import jax

    import greyid
    from greyid.datasets.reference import armadillo_model

    model = armadillo_model()
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    fitted = model.fit(data, time="Time", hold="foh").values
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), {jax.local_device_count()} device(s)")
    client = None
    if args.scheduler == "local":
        from distributed import Client, LocalCluster

        client = Client(LocalCluster(n_workers=2, threads_per_worker=1))
    random = {name: "lognormal" for name in SPREAD}
    on = {} if client is None else dict(scheduler=client)
    if args.hessian is not None:
        on["hessian"] = args.hessian
    if args.method is not None:
        on["method"] = args.method
    spent: dict = {}
    if args.timings:
        time_the_steps(spent)
    for size in [int(v) for v in args.sizes.split(",")]:
        fleet = houses(model, data, fitted, size)
        for attempt in ("first", "second"):
            spent.clear()
            start = time.perf_counter()
            fit = greyid.fit_population(model, fleet, random, time="Time", hold="foh", **on)
            seconds = time.perf_counter() - start
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"{size} houses, {attempt} call: {seconds:.1f} s, {fit.iterations} iterations, "
                  f"converged {fit.converged}, peak resident memory of "
                  f"the process so far {rss:.0f} MiB")
            for name, (seconds, calls) in spent.items():
                print(f"  {name}: {seconds:.1f} s in {calls} calls")
        omega = {name: round(float(fit.params.loc[f"omega_{name}", "estimate"]), 3) for name in SPREAD}
        print(f"  omega {omega} (simulated {SPREAD}); loglik {fit.loglik:.3f}")
        if args.layouts:
            import pandas as pd

            area = pd.DataFrame({"area": np.random.default_rng(1).uniform(80.0, 200.0, size)}, index=list(fleet))
            for label, layout in (("full Omega", dict(omega="full")),
                                  ("covariate effect on Ro", dict(covariates=area, effects={"Ro": ["area"]}))):
                start = time.perf_counter()
                nested = greyid.fit_population(model, fleet, random, time="Time", hold="foh", **layout, **on)
                print(f"{size} houses, {label}, first call: {time.perf_counter() - start:.1f} s, "
                      f"{nested.iterations} iterations, loglik {nested.loglik:.3f}")
    if client is not None:
        client.close()
        client.cluster.close()


if __name__ == "__main__":
    main()
