"""The particle filter's cost per evaluation (issue "strongly nonlinear and non-Gaussian models").

    python benchmarks/particle.py [--particles 1000] [--rows 1000] [--calls 10] [--proposals bootstrap,ekf,ukf]

Three one-state models over ``--rows`` samples, ``--particles`` particles, each proposal
of ``--proposals``: one evaluation of ``model.likelihood(data, method="particle").value(x)``
(the public call, compiled once) and of its value and gradient, and the spread (standard
deviation) of the log-likelihood over 8 runs with independent random numbers
(``particle_loglik``), the figure a proposal is there to reduce:

* ``ou``: an Ornstein–Uhlenbeck state observed with Gaussian noise (its exact
  transition sampled);
* ``poisson``: Poisson counts of a latent Ornstein–Uhlenbeck log-rate;
* ``logistic``: logistic growth with multiplicative noise, Gaussian observations
  (8 Euler–Maruyama sub-steps per interval).

A figure is the fastest of ``--calls`` calls after the first (which compiles).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import durations  # noqa: E402


def models(rows: int):
    import greyid

    rng = np.random.default_rng(0)
    t = np.arange(float(rows))
    # A latent Ornstein–Uhlenbeck state (mean mu, rate 1/2) observed with Gaussian noise, or its exp() as counts.
    for name, mu, s, distribution in (("ou", 1.0, 0.4, None), ("poisson", 2.0, 0.5, "poisson")):
        m = greyid.Model(name)
        m.add_system("dx = -a*(x - mu)*dt + s*dw1")
        if distribution is None:
            m.add_observation("y = x", variance="r")
        else:
            m.add_observation("y = exp(x)", distribution=distribution)
        m.set_initial_state(mean={"x": "mu"}, covariance="stationary")
        x, ys = mu, []
        for _ in t:
            ys.append(x + 0.2 * rng.normal() if distribution is None else rng.poisson(np.exp(x)))
            x = mu + (x - mu) * np.exp(-0.5) + s * np.sqrt(1 - np.exp(-1.0)) * rng.normal()
        params = dict(a=0.5, mu=mu, s=s, **({"r": 0.04} if distribution is None else {}))
        yield name, m, pd.DataFrame({"t": t, "y": ys}), params

    logistic = greyid.Model("logistic")
    logistic.add_system("dx = r*x*(1 - x/K)*dt + s*x*dw1")
    logistic.add_observation("y = x", variance="v")
    logistic.set_initial_state(mean={"x": 10.0}, covariance=[[1.0]])
    x, ys = 10.0, []
    for _ in t:
        ys.append(x + rng.normal())
        for _ in range(20):
            x += 0.05 * (0.3 * x * (1 - x / 100)) + 0.1 * x * np.sqrt(0.05) * rng.normal()
    yield "logistic", logistic, pd.DataFrame({"t": t, "y": ys}), dict(r=0.3, K=100.0, s=0.1, v=1.0)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--rows", type=int, default=1000)
    parser.add_argument("--calls", type=int, default=10)
    parser.add_argument("--proposals", default="bootstrap")
    args = parser.parse_args()
    from greyid.estimate.approximations import particle_loglik

    print(f"{args.particles} particles, {args.rows} rows; fastest of {args.calls} calls after the first")
    for name, model, data, params in models(args.rows):
        for p, value in params.items():
            model.set_parameter(p, init=value)
        for proposal in args.proposals.split(","):
            nll = model.likelihood(data, method="particle", particles=args.particles, proposal=proposal)
            x = np.array([params[n] for n in nll.names])
            start = time.perf_counter()
            nll.value(x)
            first = time.perf_counter() - start
            value, _ = durations(lambda: nll.value(x), args.calls)
            nll.value_and_grad(x)
            both, _ = durations(lambda: nll.value_and_grad(x), args.calls)
            spread = particle_loglik(model, params, data, particles=args.particles, proposal=proposal).spread
            print(f"{name:9s} {proposal:9s} value {1e3 * min(value):8.1f} ms   value and gradient "
                  f"{1e3 * min(both):8.1f} ms   first call {first:5.2f} s   spread over 8 runs {spread:7.3f}")


if __name__ == "__main__":
    main()
