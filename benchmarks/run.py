"""Filter benchmarks: compile time, one log-likelihood, one log-likelihood + gradient.

    python benchmarks/run.py [--repeat 20]

Models: the thesis' two-state test-cell model (7.43) with the parameters of
section 7.2 on 1512 samples at 20 min (PRBS heating, order 6, 8 h clock), and
the stochastic Lotka–Volterra model (A.66–A.69) on 500 samples with the EKF.
Times are wall-clock on this machine; "compile" is the first call (trace +
XLA compile + run) minus one later run.
"""

from __future__ import annotations

import argparse
import os
import time

# Measure real compile times: no persistent compilation cache in this process.
os.environ["GREYID_CACHE_DIR"] = "off"

import jax
import jax.numpy as jnp
import numpy as np
from greyid.runtime.jit import jit
from greyid.filters.api import compiled_filter, filter_inputs, filter_options
from greyid.data import prepare_series
from greyid.datasets import thesis


def test_cell():
    m = thesis.test_cell_model()
    df = thesis.test_cell_inputs()
    df["Ttr"] = m.simulate(thesis.TEST_CELL_PARAMETERS, df, method="exact", seed=1).outputs[0, :, 0]
    return m, thesis.TEST_CELL_PARAMETERS, df, {}


def lotka_volterra():
    m = thesis.lotka_volterra_model()
    params = thesis.LOTKA_VOLTERRA_PARAMETERS
    sim = m.simulate(params, thesis.lotka_volterra_times(), method="milstein", substeps=20, seed=3)
    return m, params, sim.frame(0), {"method": "ekf"}


def bench(name, model, params, df, options, repeat):
    s = model.structure
    opts = filter_options(s, options.get("method"), **{k: v for k, v in options.items() if k != "method"})
    series = prepare_series(df, s.input_names, s.output_names)
    data = filter_inputs(series, "zoh")
    theta = jnp.asarray(model.parameter_vector(params))
    run = compiled_filter(s, opts, keep_outputs=False)
    value = jit(lambda th: run(th, data)[0].loglik.sum())
    grad = jit(jax.value_and_grad(lambda th: run(th, data)[0].loglik.sum()))
    rows = []
    for label, fn in (("loglik", value), ("loglik+grad", grad)):
        start = time.perf_counter()
        jax.block_until_ready(fn(theta))
        first = time.perf_counter() - start
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            jax.block_until_ready(fn(theta))
            times.append(time.perf_counter() - start)
        best = min(times)
        rows.append((label, first - best, float(np.median(times)), best))
    print(f"\n{name}: {len(df)} samples, {opts.method} filter, form={opts.form}")
    print(f"  {'call':12s} {'compile [s]':>12s} {'median [ms]':>12s} {'best [ms]':>10s}")
    for label, comp, med, best in rows:
        print(f"  {label:12s} {comp:12.2f} {med * 1e3:12.2f} {best * 1e3:10.2f}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}")
    bench("test cell (7.43)", *test_cell(), args.repeat)
    bench("Lotka-Volterra (A.66)", *lotka_volterra(), args.repeat)


if __name__ == "__main__":
    main()
