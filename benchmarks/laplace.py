"""The Laplace method's cost beside ctsmTMB's (issue "strongly nonlinear and non-Gaussian models").

    python benchmarks/laplace.py [--rows 50 1000 10000] [--calls 20] [--fits 1000 10000] [--optimizer newton]
        [--residuals 50] [--one-step cdf] [--per-observation]

ctsmTMB's Ornstein2D example (``create.Ornstein2D.model()``: dx1 = θ(μ + u − x1)dt + σ1 dω1,
dx2 = α(x1 − x2)dt + σ2 dω2, y_i = x_i + e_i, x0 = (3, 3), P0 = 0.1 I), simulated
as ``../shared/peers/ctsmtmb/orn2d_sim.R`` does (sampling interval 0.1, an AR(1)
input held within intervals).  For each length: ``model.likelihood(data,
method="laplace", scheme=...)`` value and gradient per call (fastest of
``--calls`` after the first, which compiles), for ``scheme="ctsmtmb"`` (ctsmTMB's
own computation: one Euler–Maruyama step per interval, 10⁻⁸ jitter) and greyid's
default (exact transitions of these linear dynamics).  ``--fits``: a fit in this
process (first, compiling) and again, by ``--optimizer`` (``auto``, the default, which for the
Laplace method is ``lbfgs``: as ctsmTMB fits, quasi-Newton steps on the value and gradient and
the Hessian by differences of the gradient; ``newton``: exact Newton steps and Hessian).
``--residuals``: a fit's one-step-ahead residuals (``fit.residuals``, the
first in the process, compiling, and again for a second fit, then the fastest of ``--calls``
of ``laplace_residuals``); ``--one-step cdf`` by TMB's
method "cdf" instead of the Gaussian predictive (ctsmTMB's "oneStepGaussian");
``--per-observation`` takes the Gaussian predictive by a Laplace mode of its own for each
observation, as a model whose joint density is not Gaussian does, instead of the one pass
forward that this linear Gaussian example takes (``greyid.filters.laplace.gaussian_joint``).
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

TRUE = dict(theta=5.0, mu=3.0, alpha=2.0, sx=1.0, sy=0.5, e1=0.1, e2=0.1)


def model():
    import greyid

    m = greyid.Model("ornstein2d")
    m.add_system("dx1 = theta*(mu + u - x1)*dt + sx*dw1", "dx2 = alpha*(x1 - x2)*dt + sy*dw2")
    m.add_inputs("u")
    m.add_observation("y1 = x1", variance="e1^2")
    m.add_observation("y2 = x2", variance="e2^2")
    m.set_initial_state(mean={"x1": 3.0, "x2": 3.0}, covariance=[[0.1, 0.0], [0.0, 0.1]])
    for name, value in TRUE.items():
        m.set_parameter(name, init=value * 1.2, lower=1e-3, upper=50)
    return m


def simulate(n: int, seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    h, sub = 1e-3, 100
    u = np.zeros(n)
    for k in range(1, n):
        u[k] = 0.95 * u[k - 1] + 0.3 * rng.normal()
    x = np.zeros((n, 2))
    a = b = 3.0
    x[0] = a, b
    for k in range(n - 1):
        e = rng.normal(size=(sub, 2)) * np.sqrt(h)
        for j in range(sub):
            a, b = a + TRUE["theta"] * (TRUE["mu"] + u[k] - a) * h + TRUE["sx"] * e[j, 0], \
                b + TRUE["alpha"] * (a - b) * h + TRUE["sy"] * e[j, 1]
        x[k + 1] = a, b
    return pd.DataFrame({"t": 0.1 * np.arange(n), "u": u, "y1": x[:, 0] + 0.1 * rng.normal(size=n),
                         "y2": x[:, 1] + 0.1 * rng.normal(size=n)})


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rows", type=int, nargs="*", default=[50, 1000, 10000])
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument("--fits", type=int, nargs="*", default=[1000, 10000])
    parser.add_argument("--residuals", type=int, nargs="*", default=[],
                        help="rows: a fit's one-step-ahead residuals (ctsmTMB's oneStepPredict, 'oneStepGaussian'), "
                             "the first in this process (compiling) and those of a second fit")
    parser.add_argument("--one-step", choices=("gaussian", "cdf"), default=None,
                        help="the residuals' method (default: the fit's, 'gaussian' for these Gaussian outputs)")
    parser.add_argument("--optimizer", default="auto",
                        help="the fits' optimizer: auto (for the Laplace method lbfgs: L-BFGS, the Hessian by "
                             "differences of the gradient, as TMB's sdreport) or newton (exact Newton steps "
                             "and Hessian)")
    parser.add_argument("--per-observation", action="store_true",
                        help="the Gaussian residuals by a Laplace mode per observation (a nonlinear model's way; "
                             "give it a cache folder of its own: the kept program has the same name)")
    args = parser.parse_args()
    from greyid.filters import laplace
    from greyid.filters.api import laplace_residuals

    if args.per_observation:
        laplace.gaussian_joint = lambda structure: False

    for rows in args.rows:
        data = simulate(rows, 20261127 + rows)
        for scheme in ("ctsmtmb", "auto"):
            m = model()
            nll = m.likelihood(data, method="laplace", scheme=scheme)
            x = np.array([TRUE[n] for n in nll.names])
            start = time.perf_counter()
            nll.value_and_grad(x)
            first = time.perf_counter() - start
            both, _ = durations(lambda: nll.value_and_grad(x), args.calls)
            print(f"{rows:6d} rows  scheme {scheme:8s} value and gradient {1e3 * min(both):9.3f} ms "
                  f"(first call {first:.2f} s)", flush=True)
    for rows in args.fits:
        data = simulate(rows, 20261127 + rows)
        for label in ("first", "again"):
            start = time.perf_counter()
            fit = model().fit(data, method="laplace", scheme="ctsmtmb", optimizer=args.optimizer)
            print(f"{rows:6d} rows  fit scheme ctsmtmb optimizer {args.optimizer} {label}: "
                  f"{time.perf_counter() - start:.2f} s  "
                  f"log-likelihood {fit.loglik:.6f}  converged {fit.converged}", flush=True)

    for rows in args.residuals:
        data = simulate(rows, 20261127 + rows)
        for label in ("first", "again"):
            fit = model().fit(data, method="laplace", scheme="ctsmtmb", optimizer=args.optimizer)
            start = time.perf_counter()
            residuals = (fit.residuals if args.one_step is None else
                         laplace_residuals(fit.model, fit.values, data, scheme="ctsmtmb", one_step=args.one_step))
            print(f"{rows:6d} rows  one-step residuals {label}: {time.perf_counter() - start:.2f} s  "
                  f"(sd {np.nanstd(residuals.to_numpy()):.4f})", flush=True)
        times = []
        for _ in range(args.calls):
            start = time.perf_counter()
            laplace_residuals(fit.model, fit.values, data, scheme="ctsmtmb", one_step=args.one_step)
            times.append(time.perf_counter() - start)
        print(f"{rows:6d} rows  one-step residuals compiled: {min(times) * 1e3:.1f} ms (fastest of {args.calls})",
              flush=True)


if __name__ == "__main__":
    main()
