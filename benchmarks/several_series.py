"""A fit to several series of different lengths (independent experiments, (3.18)).

    python benchmarks/several_series.py [--series 6] [--repeats 2]

The data: a two-state linear model with two inputs, ``--series`` irregularly sampled series of 25 to 40
rows (a different length each, as experiments or the members of a population are).  Prints, in fresh
processes with an empty cache folder of their own, the first fit (tracing and compiling included), the
same fit in a later process (programs kept in the folder), and in one process the fit once compiled
(median of five), with the log-likelihood each reached.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time


def series(count: int):
    import numpy as np
    import pandas as pd

    import greyid

    model = greyid.Model("two_rooms")
    model.add_system("dx1 = (-(a + c)*x1 + c*x2 + b*u1)*dt + s1*dw1",
                     "dx2 = (c*x1 - (c + d)*x2 + e*u2)*dt + s2*dw2")
    model.add_inputs("u1", "u2")
    model.add_observation("y = x1", variance="r")
    model.set_initial_state(mean={"x1": "m1", "x2": 0.0}, covariance=[[0.5, 0.0], [0.0, 0.5]])
    truth = dict(a=0.6, b=1.0, c=0.4, d=0.3, e=0.8, s1=0.3, s2=0.2, r=0.05, m1=0.5)
    for name, value in truth.items():
        model.set_parameter(name, init=1.3 * value, lower=0.0 if name[0] in "sr" else None)
    rng = np.random.default_rng(3)
    frames = []
    for k in range(count):
        rows = 25 + (15 * k) // max(count - 1, 1)
        frame = pd.DataFrame({"t": np.cumsum(rng.uniform(0.3, 1.2, rows)), "u1": rng.normal(size=rows),
                              "u2": rng.normal(size=rows)})
        frame["y"] = model.simulate(truth, frame, seed=k).outputs[0, :, 0]
        frames.append(frame)
    return model, frames


def one_fit(count: int) -> None:
    model, frames = series(count)
    start = time.perf_counter()
    fit = model.fit(frames)
    print(time.perf_counter() - start, fit.loglik)


def compiled(count: int) -> None:
    model, frames = series(count)
    model.fit(frames)
    times = []
    for _ in range(5):
        start = time.perf_counter()
        fit = model.fit(frames)
        times.append(time.perf_counter() - start)
    print(statistics.median(times), fit.loglik)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--series", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--part", choices=["one", "compiled"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.part:
        (one_fit if args.part == "one" else compiled)(args.series)
        return
    command = [sys.executable, __file__, "--series", str(args.series), "--part"]
    rows = {"first fit [s]": [], "later process [s]": [], "compiled fit [s]": []}
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as folder:
            env = dict(os.environ, GREYID_CACHE_DIR=folder)
            parts = (("first fit [s]", "one"), ("later process [s]", "one"), ("compiled fit [s]", "compiled"))
            for label, part in parts:
                out = subprocess.run(command + [part], env=env, check=True, capture_output=True, text=True)
                seconds, loglik = out.stdout.split()
                rows[label].append(float(seconds))
    print(f"{args.series} series of 25-40 rows, log-likelihood {float(loglik):.6f}")
    for label, values in rows.items():
        print(f"  {label:20s} {min(values):7.3f} - {max(values):7.3f}")


if __name__ == "__main__":
    main()
