"""What a latent force costs: the Armadillo fit (pySIP's TwTi_RoRi, 233 rows, first-order hold) without a force,
with the library's Matérn-3/2 force and with its quasi-periodic one.

    python benchmarks/latent_forces.py [--repeats 10] [--skip-quasiperiodic]

Prints, per model, the number of states and free parameters, the first fit in this process (compilation
included), and the compiled fit's median and fastest over ``--repeats`` fits taken in turns with the other
models' (so that the machine's load falls on all alike), and its ratio to the model without a force.
The data come from ../shared/data (or GREYID_DATA_MIRROR).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--skip-quasiperiodic", action="store_true")
    args = parser.parse_args()

    import greyid
    from greyid import library

    data = greyid.datasets.fetch("armadillo")
    models = {"no force": greyid.Model.from_toml(ROOT / "examples" / "armadillo.toml"),
              "Matern-3/2 force": library.load_model("armadillo_matern32")}
    if not args.skip_quasiperiodic:
        models["quasi-periodic force"] = library.load_model("armadillo_quasiperiodic")
    first, compiled, fits = {}, {name: [] for name in models}, {}
    for name, model in models.items():
        start = time.perf_counter()
        fits[name] = model.fit(data)
        first[name] = time.perf_counter() - start
    for _ in range(args.repeats):
        for name, model in models.items():
            start = time.perf_counter()
            model.fit(data)
            compiled[name].append(time.perf_counter() - start)
    base = statistics.median(compiled["no force"])
    print(f"Armadillo fits, {args.repeats} compiled fits each, in turns")
    print(f"{'model':22s} {'states':>6s} {'free':>4s} {'iter':>4s} {'first [s]':>9s} {'median [s]':>10s} "
          f"{'fastest [s]':>11s} {'ratio':>6s}")
    for name, model in models.items():
        times = compiled[name]
        fit = fits[name]
        print(f"{name:22s} {len(model.state_names):6d} {fit.n_params:4d} {fit.iterations:4d} {first[name]:9.2f} "
              f"{statistics.median(times):10.3f} {min(times):11.3f} {statistics.median(times) / base:6.2f}")


if __name__ == "__main__":
    main()
