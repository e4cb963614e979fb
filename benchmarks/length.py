"""Fits of long series: time, iterations and peak memory against the number of samples.

    python benchmarks/length.py [--lengths 1000,10000,100000] [--model logistic|testcell]
        [--optimizer auto|scoring|newton]

Each fit runs in a fresh process (so its peak resident memory is its own):
simulate the series, then fit it.  ``logistic`` is the library's logistic
growth model through the EKF (one sub-step, so every length is the same
problem); ``testcell`` is the thesis' test-cell model (7.43) through the exact
Kalman filter.  Prints seconds for the first fit (compilation included) and
for a second one, the second fit's time in units of one compiled
log-likelihood evaluation, iterations, log-likelihood and the process's peak
resident memory.  ``--optimizer`` as in ``fit``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

SCRIPT = """
import resource, sys, time, warnings
warnings.simplefilter("ignore")
import numpy as np, pandas as pd
model_name, n = sys.argv[1], int(sys.argv[2])
if model_name == "logistic":
    from greyid import library
    m = library.load_model("logistic_growth")
    truth = dict(rho=0.5, K=100.0, sigma=0.05, s2=1.0, x0=10.0)
    df = m.simulate(truth, pd.DataFrame({"t": np.arange(n) * 0.02}), method="euler", substeps=2, seed=1).frame(0)
    options = dict(substeps=1)
else:
    from greyid.datasets import thesis
    m = thesis.test_cell_model()
    inputs = thesis.test_cell_inputs(seed=0)
    reps = -(-n // len(inputs))
    df = pd.concat([inputs] * reps, ignore_index=True).iloc[:n]
    df["t"] = np.arange(n) * (inputs["t"].iloc[1] - inputs["t"].iloc[0])
    df["Ttr"] = m.simulate(thesis.TEST_CELL_PARAMETERS, df, method="exact", seed=1).outputs[0, :, 0]
    options = {}
optimizer = sys.argv[3]
start = time.perf_counter()
fit = m.fit(df, optimizer=optimizer, **options)
seconds = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
start = time.perf_counter()
m.fit(df, optimizer=optimizer, **options)
again = time.perf_counter() - start
m.loglik(fit.values, df, **options)  # compiled
start = time.perf_counter()
for _ in range(3):
    m.loglik(fit.values, df, **options)
one = (time.perf_counter() - start) / 3
print(f"{n:>9d} {seconds:10.1f} {again:10.1f} {again / one:9.0f} {fit.iterations:6d} {fit.loglik:16.4f} {peak:9.2f}")
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", default="1000,10000,100000")
    parser.add_argument("--model", choices=["logistic", "testcell"], default="logistic")
    parser.add_argument("--optimizer", choices=["auto", "scoring", "newton"], default="auto")
    args = parser.parse_args()
    print(f"{args.model}, optimizer {args.optimizer}: samples, first fit [s] (compile included), "
          "second fit [s], second fit in log-likelihood evaluations, iterations, log-likelihood, peak memory [GB]")
    for n in (int(v) for v in args.lengths.split(",")):
        done = subprocess.run([sys.executable, "-c", SCRIPT, args.model, str(n), args.optimizer],
                              capture_output=True, text=True)
        print(done.stdout.strip() if done.returncode == 0 else f"{n:>9d} failed: {done.stderr.strip()[-300:]}")


if __name__ == "__main__":
    main()
