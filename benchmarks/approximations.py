"""How far each likelihood approximation is from the truth on strongly nonlinear models (issue "strongly
nonlinear and non-Gaussian models").

    python benchmarks/approximations.py [--rows 200] [--particles 20000]

Two one-state models simulated finely (Euler–Maruyama, 100 steps per sampling interval):

* ``double well``: dx = (x − x³)dt + σ dω, y = x + e, σ = 0.7, e ~ N(0, 0.1²): the state
  hops between two wells, its predictive density is bimodal;
* ``logistic``: dx = r x (1 − x/K)dt + s x dω, y = x + e (multiplicative noise).

At the simulating parameters, ``compare_methods`` gives each Gaussian filter's and the Laplace
method's log-likelihood beside the particle filter's estimate (8 runs of ``--particles``
particles, its Monte Carlo standard error): the difference is each approximation's bias.
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


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, default=200)
    parser.add_argument("--particles", type=int, default=20000)
    args = parser.parse_args()
    from greyid.estimate.approximations import compare_methods

    pd.set_option("display.width", 120)
    for model, params, data in models(args.rows):
        for name, value in params.items():
            model.set_parameter(name, init=value)
        table = compare_methods(model, params, data, methods=["ekf", "ukf", "gaussian2", "laplace"],
                                particles=args.particles)
        print(f"\n{model.name}, {args.rows} rows, particle reference {args.particles} particles × 8 runs")
        print(table.to_string(float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
