"""How far each likelihood approximation is from the truth on strongly nonlinear models (issue "strongly
nonlinear and non-Gaussian models").

    python benchmarks/approximations.py [--rows 200] [--particles 20000]

Two one-state models simulated finely (Euler–Maruyama, 100 steps per sampling interval):

* ``double well``: dx = (x − x³)dt + σ dω, y = x + e, σ = 0.7, e ~ N(0, 0.1²): the state
  hops between two wells, its predictive density is bimodal;
* ``logistic``: dx = r x (1 − x/K)dt + s x dω, y = x + e (multiplicative noise);
* ``logistic, log x``: the same model and data, the state worked as log x
  (``transform_state("x", "log")``, a Lamperti transform: its noise is additive).

At the simulating parameters, ``compare_methods`` gives each Gaussian filter's and the Laplace
method's log-likelihood beside the particle filter's estimate (8 runs of ``--particles``
particles with the ``--proposal`` proposal, default ``ekf``, and its Monte Carlo standard
error): the difference is each approximation's bias.

    python benchmarks/approximations.py --coverage 200 [--rows 200]

instead fits ``--coverage`` series of Poisson counts of a latent Ornstein–Uhlenbeck log-rate
((a, μ, s) = (0.5, 2, 0.5), ``--rows`` samples each) by the Laplace method (``fit_many``) and
prints each parameter's mean estimate, the estimates' spread beside the mean standard error,
and how often the 95 % Wald interval covers the simulated value.
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd


def simulate(drift, diffusion, x0, rows, noise, seed):
    rng = np.random.default_rng(seed)
    h, sub = 0.01, 100
    x, ys = x0, []
    for _ in range(rows):
        ys.append(x + noise * rng.normal())
        for _ in range(sub):
            x = x + drift(x) * h + diffusion(x) * np.sqrt(h) * rng.normal()
    return pd.DataFrame({"t": np.arange(float(rows)), "y": ys})


def models(rows):
    import greyid

    well = greyid.Model("double well")
    well.add_system("dx = (x - x^3)*dt + sigma*dw1")
    well.add_observation("y = x", variance="e^2")
    well.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
    params = dict(sigma=0.7, e=0.1)
    data = simulate(lambda x: x - x**3, lambda x: 0.7, 1.0, rows, 0.1, 1)
    yield well, params, data

    logistic = greyid.Model("logistic")
    logistic.add_system("dx = r*x*(1 - x/K)*dt + s*x*dw1")
    logistic.add_observation("y = x", variance="v")
    logistic.set_initial_state(mean={"x": 10.0}, covariance=[[1.0]])
    params = dict(r=0.3, K=100.0, s=0.3, v=4.0)
    data = simulate(lambda x: 0.3 * x * (1 - x / 100), lambda x: 0.3 * x, 10.0, rows, 2.0, 2)
    yield logistic, params, data

    # The same model and data with x worked as log x (a Lamperti transform): its noise is additive there.
    transformed = greyid.Model.from_dict(dict(logistic.to_dict(), name="logistic, log x"))
    transformed.transform_state("x", "log")
    yield transformed, params, data


def coverage(replications: int, rows: int):
    import warnings

    import greyid

    m = greyid.Model("counts")
    m.add_system("dl = -a*(l - mu)*dt + s*dw1")
    m.add_observation("n = exp(l)", distribution="poisson")
    for name, value, lower in (("a", 0.5, 1e-3), ("mu", 2.0, -5), ("s", 0.5, 1e-3)):
        m.set_parameter(name, init=value, lower=lower, upper=10)
    m.set_initial_state(mean={"l": "mu"}, covariance="stationary")
    series = []
    for i in range(replications):
        rng = np.random.default_rng(1000 + i)
        level, counts = 2.0, []
        for _ in range(rows):
            counts.append(rng.poisson(np.exp(level)))
            level = 2.0 + (level - 2.0) * np.exp(-0.5) + 0.5 * np.sqrt(1 - np.exp(-1.0)) * rng.normal()
        series.append(pd.DataFrame({"t": np.arange(float(rows)), "n": counts}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = greyid.fit_many(m, series, method="laplace").table
    print(f"Laplace fits of {replications} series of {rows} Poisson counts; converged: {table['converged'].sum()}")
    for name, truth in dict(a=0.5, mu=2.0, s=0.5).items():
        estimate, error = table[name], table[f"{name}_se"]
        covered = ((estimate - 1.96 * error <= truth) & (truth <= estimate + 1.96 * error)).mean()
        print(f"{name:3s} simulated {truth:5.2f}  mean {estimate.mean():7.4f}  spread {estimate.std(ddof=1):7.4f}  "
              f"mean standard error {error.mean():7.4f}  95 % coverage {covered:6.1%}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=200)
    parser.add_argument("--particles", type=int, default=20000)
    parser.add_argument("--coverage", type=int, default=0)
    parser.add_argument("--proposal", default="ekf")
    parser.add_argument("--model", action="append", default=[], help="a model's name to run (repeat; default: all)")
    args = parser.parse_args()
    if args.coverage:
        return coverage(args.coverage, args.rows)
    from greyid.estimate.approximations import compare_methods

    pd.set_option("display.width", 120)
    for model, params, data in models(args.rows):
        if args.model and model.name not in args.model:
            continue
        for name, value in params.items():
            model.set_parameter(name, init=value)
        table = compare_methods(model, params, data, methods=["ekf", "ukf", "gaussian2", "laplace"],
                                particles=args.particles, proposal=args.proposal)
        print(f"\n{model.name}, {args.rows} rows, particle reference {args.particles} particles × 8 runs, "
              f"{args.proposal} proposal")
        print(table.to_string(float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
