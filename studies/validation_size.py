"""Size and power of the residual tests of greyid.validation (Monte Carlo).

Size: rejection rates at 5 % on Gaussian white noise (inputs independent of it).
Power: AR(1) residuals (φ = 0.4), residuals depending on a lagged input
(0.25·u_{t−1}, u an AR(1)), a quadratic nonlinearity (e_t + 0.6(e²_{t−1} − 1)),
a linear trend (0 → 0.6 over the series), and a linear but non-Gaussian series
(AR(1) driven by centred exponential noise), which the linearity test should
not reject.  Run: python studies/validation_size.py [--replicates 1000] [--n 500]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd
from scipy import signal

from greyid import validation as v

TESTS = {
    "ljung_box": lambda x, u: v.ljung_box(x),
    "turning_points": lambda x, u: v.turning_point_test(x),
    "difference_sign": lambda x, u: v.difference_sign_test(x),
    "rank": lambda x, u: v.rank_test(x),
    "ks_normality": lambda x, u: v.ks_normality(x / x.std()),
    "cumulative_periodogram": lambda x, u: v.cumulative_periodogram_test(x),
    "bispectrum_gaussianity": lambda x, u: v.gaussianity_test(x),
    "bispectrum_linearity": lambda x, u: v.linearity_test(x),
    "input_correlation": lambda x, u: v.input_correlation_test(x, u),
    "coherency": lambda x, u: v.coherency_test(x, u),
}


def scenarios(rng, n):
    u = signal.lfilter([1], [1, -0.5], rng.normal(size=n))
    e = rng.normal(size=n + 1)
    return {
        "white": (e[1:], u),
        "AR(1)": (signal.lfilter([1], [1, -0.4], e[1:]), u),
        "input": (e[1:] + 0.25 * np.concatenate([[0.0], u[:-1]]), u),
        "quadratic": (e[1:] + 0.6 * (e[:-1] ** 2 - 1), u),
        "trend": (e[1:] + np.linspace(0, 0.6, n), u),
        "linear non-Gaussian": (signal.lfilter([1], [1, -0.4], rng.exponential(size=n) - 1), u),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicates", type=int, default=1000)
    parser.add_argument("--n", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    started = time.perf_counter()
    counts = {}
    for _ in range(args.replicates):
        for scenario, (x, u) in scenarios(rng, args.n).items():
            for name, test in TESTS.items():
                key = (name, scenario)
                counts[key] = counts.get(key, 0) + (test(x, u).p_value < 0.05)
    table = pd.Series(counts).unstack() / args.replicates
    table = table.loc[list(TESTS), ["white", "AR(1)", "input", "quadratic", "trend", "linear non-Gaussian"]]
    print(f"rejection rates at 5 %, {args.replicates} replicates of n = {args.n} (seed {args.seed}); "
          f"Monte Carlo s.e. at 5 %: {np.sqrt(0.05 * 0.95 / args.replicates):.3f}")
    print(table.to_string(float_format=lambda v: f"{v:.3f}"))
    print(f"({time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
