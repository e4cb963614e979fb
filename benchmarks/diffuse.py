"""What the exact diffuse start costs: a continuous local linear trend (level and slope, both unknown at t₀)
started exactly diffuse against the same model started from a large covariance (P₀ = 10⁷ I, the approximate
diffuse start), on simulated series of several lengths.

    python benchmarks/diffuse.py [--lengths 200,2000,20000] [--calls 50]

Prints, per length and start, the first value-and-gradient call in this process (compilation included) and
the compiled call's median and fastest over ``--calls`` calls taken in turns with the other start's (so that
the machine's load falls on both alike), and the ratio of the exact start's median to the approximate one's.
Both go through ``Model.likelihood`` (the steady-state switch on, as for single evaluations).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import pandas as pd


def trend(diffuse: bool):
    import greyid

    m = (greyid.Model().add_system("dx1 = x2*dt + s1*dw1").add_system("dx2 = 0*dt + sb*dw2")
         .add_observation("y = x1", variance="s2")
         .set_parameter("s1", init=0.4, lower=1e-3, upper=10).set_parameter("sb", init=0.1, lower=1e-3, upper=10)
         .set_parameter("s2", init=0.3, lower=1e-3, upper=10))
    if diffuse:
        return m.set_initial_state(mean={}, diffuse=["x1", "x2"])
    return m.set_initial_state(mean={"x1": 0.0, "x2": 0.0}, covariance=[[1e7, 0.0], [0.0, 1e7]])


def series(n: int) -> pd.DataFrame:
    rng = np.random.default_rng(1)
    slope = np.cumsum(rng.normal(0, 0.1 * np.sqrt(0.5), n))
    level = np.cumsum(slope * 0.5 + rng.normal(0, 0.4 * np.sqrt(0.5), n))
    return pd.DataFrame({"t": 0.5 * np.arange(n), "y": level + rng.normal(0, np.sqrt(0.3), n)})


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--lengths", default="200,2000,20000")
    parser.add_argument("--calls", type=int, default=50)
    args = parser.parse_args()
    starts = {"exact diffuse": trend(True), "P0 = 1e7 I": trend(False)}
    print(f"local linear trend, value and gradient, {args.calls} compiled calls each, in turns")
    print(f"{'rows':>6s} {'start':15s} {'first [s]':>9s} {'median [ms]':>11s} {'fastest [ms]':>12s} {'ratio':>6s}")
    for n in (int(v) for v in args.lengths.split(",")):
        data = series(n)
        functions, first, times = {}, {}, {name: [] for name in starts}
        x = np.array([0.4, 0.1, 0.3])
        for name, model in starts.items():
            begin = time.perf_counter()
            functions[name] = model.likelihood(data, time="t")
            value, gradient = functions[name].value_and_grad(x)
            first[name] = time.perf_counter() - begin
        for _ in range(args.calls):
            for name, function in functions.items():
                begin = time.perf_counter()
                value, gradient = function.value_and_grad(x)
                np.asarray(gradient)
                times[name].append(time.perf_counter() - begin)
        base = statistics.median(times["P0 = 1e7 I"])
        for name in starts:
            median = statistics.median(times[name])
            print(f"{n:6d} {name:15s} {first[name]:9.2f} {1e3 * median:11.3f} {1e3 * min(times[name]):12.3f} "
                  f"{median / base:6.2f}")


if __name__ == "__main__":
    main()
