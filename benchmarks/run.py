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
import time

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

import greyid
from greyid.filters.api import compiled_filter, filter_inputs, filter_options
from greyid.data import prepare_series
from greyid.simulate import prbs


def test_cell():
    m = greyid.Model("testcell")
    m.add_system("dTi = (Hi/Ci*(Tm-Ti) + Qh/Ci)*dt + sqrt(s1i)*dw1")
    m.add_system("dTm = (Hi/Cm*(Ti-Tm) + Hm/Cm*(Te-Tm))*dt + sqrt(s1m)*dw2")
    m.add_inputs("Te", "Qh")
    m.add_observation("Ttr = Ti", variance="s2")
    m.set_initial_state(mean={"Ti": "Ti0", "Tm": "Tm0"}, covariance="process")
    # H in W/K, C in Wh/K, time in hours: dT/dt [K/h] = H/C (T) since W/(Wh/K) = K/h.
    params = dict(Hi=55.29, Hm=13.86, Ci=325.0, Cm=387.8, s1i=0.00167, s1m=0.00978, s2=0.00019,
                  Ti0=20.0, Tm0=15.0)
    t = np.arange(1512) / 3.0
    te = 5 + 4 * np.sin(2 * np.pi * (t - 9) / 24)
    qh = prbs(6, clock=24, levels=(0.0, 300.0), length=1512)
    df = pd.DataFrame({"t": t, "Te": te, "Qh": qh})
    df["Ttr"] = m.simulate(params, df, method="exact", seed=1).outputs[0, :, 0]
    return m, params, df, {}


def lotka_volterra():
    m = greyid.Model("lotka_volterra")
    m.add_system("dN1 = (a*N1 - b*N1*N2)*dt + sqrt(s1)*dw1")
    m.add_system("dN2 = (c*N1*N2 - d*N2)*dt + sqrt(s2)*dw2")
    m.add_observation("y1 = N1", variance="m1")
    m.add_observation("y2 = N2", variance="m2")
    m.set_initial_state(mean={"N1": "N10", "N2": "N20"}, covariance=[[0.01, 0], [0, 0.01]])
    params = dict(a=10.0, b=1.0, c=2.0, d=10.0, s1=0.3, s2=0.3, m1=0.03, m2=0.03, N10=2.0, N20=5.0)
    t = np.arange(500) * 0.005  # sampling time of A.7
    sim = m.simulate(params, t, method="euler", substeps=50, seed=3)
    return m, params, sim.frame(0), {"method": "ekf"}


def bench(name, model, params, df, options, repeat):
    s = model.structure
    opts = filter_options(s, options.get("method"), **{k: v for k, v in options.items() if k != "method"})
    series = prepare_series(df, s.input_names, s.output_names)
    data = filter_inputs(series, "zoh")
    theta = jnp.asarray(model.parameter_vector(params))
    run = compiled_filter(s, opts, keep_outputs=False)
    value = jax.jit(lambda th: run(th, data)[0].loglik.sum())
    grad = jax.jit(jax.value_and_grad(lambda th: run(th, data)[0].loglik.sum()))
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
