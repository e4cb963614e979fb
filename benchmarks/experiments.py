"""One model fitted to several experiments at once: ``model.fit([frame, frame, ...])``.

    python benchmarks/experiments.py [--experiments 8] [--repeats 3]

Simulates ``--experiments`` Armadillo houses (pySIP's TwTi_RoRi, 232 rows, first-order hold; Ro and Cw
spread as in ``benchmarks/population.py``), then, in a fresh process with an empty cache folder
per repeat, times the first ``model.fit`` of all of them together (the programs of a fit to several
data sets compile then; the process has fitted and simulated the single house before) and the
second (compiled).  Prints the log-likelihood and iterations, which do not change between repeats.
The data come from ../shared/data (or GREYID_DATA_MIRROR).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def one_process(count: int) -> None:
    """Run in a fresh process: print ``first second loglik iterations``."""
    sys.path.insert(0, str(HERE))
    import greyid
    from greyid.datasets.reference import armadillo_model
    from population import houses

    model = armadillo_model()
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    fitted = model.fit(data, time="Time", hold="foh").values
    frames = list(houses(model, data, fitted, count).values())
    start = time.perf_counter()
    fit = model.fit(frames, time="Time", hold="foh")
    first = time.perf_counter() - start
    start = time.perf_counter()
    model.fit(frames, time="Time", hold="foh")
    second = time.perf_counter() - start
    print(f"{first} {second} {fit.loglik!r} {fit.iterations}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        one_process(args.experiments)
        return
    firsts, seconds = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, GREYID_CACHE_DIR=cache)
            out = subprocess.run([sys.executable, __file__, "--child", "--experiments", str(args.experiments)],
                                 env=env, check=True, capture_output=True, text=True).stdout.split()
        first, second, loglik, iterations = float(out[0]), float(out[1]), out[2], out[3]
        firsts.append(first)
        seconds.append(second)
        print(f"{args.experiments} experiments: first fit {first:.2f} s, compiled {second:.3f} s, "
              f"log L {loglik}, {iterations} iterations")
    print(f"median of {args.repeats}: first fit {statistics.median(firsts):.2f} s "
          f"({min(firsts):.2f}–{max(firsts):.2f}), compiled {statistics.median(seconds):.3f} s "
          f"({min(seconds):.3f}–{max(seconds):.3f})")


if __name__ == "__main__":
    main()
