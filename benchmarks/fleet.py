"""Fleet benchmark (issue "Fleets"): many Armadillo-size houses in one batched call.

    python benchmarks/fleet.py [--sizes 10,100,1000] [--alone 100]

Houses: the Armadillo model (pySIP's TwTi_RoRi, first-order hold, 232 rows; data
the data set armadillo) simulated at its fitted parameters with a different noise
seed per house.  For each fleet size it prints the time of ``greyid.fit_many``
once its programs are compiled (the fleet is fitted twice, the second timed), and
the time per house of compiled one-at-a-time ``model.fit`` calls on the first
``--alone`` houses of the same run, so the speed-up is measured on one machine in
one state.  The fleet's estimates are checked against the separate fits.
On a GPU (``pip install "greyid[cuda]"``) the same script measures the batched
program there: JAX picks the device.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def houses(model, data, fitted, count: int) -> dict:
    sim = model.simulate(fitted, data, n_paths=count, seed=7, time="Time", hold="foh")
    return {f"house{k:05d}": data.assign(T_int=sim.outputs[k, :, 0]) for k in range(count)}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", default="10,100,1000")
    parser.add_argument("--alone", type=int, default=100, help="houses fitted one at a time for the comparison")
    args = parser.parse_args()
    import jax

    import greyid
    from greyid.datasets.reference import armadillo_model

    model = armadillo_model()
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    settings = dict(time="Time", hold="foh")
    fitted = model.fit(data, **settings).values
    sizes = [int(v) for v in args.sizes.split(",")]
    fleet_of = houses(model, data, fitted, max(sizes + [args.alone]))
    names = list(fleet_of)
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()})")

    alone = {}
    for name in names[: args.alone]:
        model.fit(fleet_of[name], **settings)  # compiled after the first
    start = time.perf_counter()
    for name in names[: args.alone]:
        alone[name] = model.fit(fleet_of[name], **settings)
    per_house_alone = (time.perf_counter() - start) / args.alone
    print(f"one at a time, compiled: {per_house_alone * 1e3:.1f} ms per house ({args.alone} houses)")

    print(f"  {'houses':>7s} {'first call [s]':>15s} {'compiled [s]':>13s} {'per house [ms]':>15s} "
          f"{'speed-up':>9s} {'houses/s':>9s} {'converged':>10s} {'max |Δ log L|':>14s}")
    for size in sizes:
        subset = {name: fleet_of[name] for name in names[:size]}
        start = time.perf_counter()
        greyid.fit_many(model, subset, **settings)
        first = time.perf_counter() - start
        start = time.perf_counter()
        fleet = greyid.fit_many(model, subset, **settings)
        compiled = time.perf_counter() - start
        checked = [n for n in names[:size] if n in alone]
        gap = max(abs(fleet.fits[n].loglik - alone[n].loglik) for n in checked) if checked else float("nan")
        print(f"  {size:7d} {first:15.2f} {compiled:13.2f} {compiled / size * 1e3:15.1f} "
              f"{per_house_alone * size / compiled:9.1f} {size / compiled:9.0f} "
              f"{int(fleet.table['converged'].sum()):10d} {gap:14.2e}")


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
