"""The Laplace method's one-step residuals of counts (issue "strongly nonlinear and non-Gaussian models").

    python benchmarks/one_step.py [--rows 150] [--calls 3] [--substeps 1]

Poisson counts of a latent Ornstein–Uhlenbeck log-rate (dl = −a(l − μ)dt + s dω,
n ~ Poisson(exp l), a = 0.5, μ = 2, s = 0.5, one sample per unit of time, the
tests' model), simulated by greyid with a fixed seed.  Prints the time of
``laplace_residuals`` (method "cdf", the default for counts: two tails and the
density of each count by Laplace's method, a mode per observation) on its first
call in this process (compiling) and the fastest of ``--calls`` later ones.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=150)
    parser.add_argument("--calls", type=int, default=3)
    parser.add_argument("--substeps", type=int, default=1)
    args = parser.parse_args()
    import greyid
    from greyid.filters.api import laplace_residuals

    m = greyid.Model("counts")
    m.add_system("dl = -a*(l - mu)*dt + s*dw1")
    m.add_observation("n = exp(l)", distribution="poisson")
    m.set_initial_state(mean={"l": "mu"}, covariance="stationary")
    params = dict(a=0.5, mu=2.0, s=0.5)
    data = m.simulate(params, np.arange(float(args.rows)), seed=8).frame()[["t", "n"]]
    start = time.perf_counter()
    residuals = laplace_residuals(m, params, data, substeps=args.substeps)
    print(f"{args.rows} rows  one-step residuals (cdf) first: {time.perf_counter() - start:.2f} s  "
          f"(sd {np.nanstd(residuals.to_numpy()):.4f})", flush=True)
    times = []
    for _ in range(args.calls):
        start = time.perf_counter()
        laplace_residuals(m, params, data, substeps=args.substeps)
        times.append(time.perf_counter() - start)
    print(f"{args.rows} rows  one-step residuals (cdf) compiled: {min(times):.3f} s (fastest of {args.calls})")


if __name__ == "__main__":
    main()
