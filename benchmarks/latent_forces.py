"""What a latent force costs: the Armadillo fit (pySIP's TwTi_RoRi, 233 rows, first-order hold) without a force,
with the library's Matérn-3/2 force and with its quasi-periodic one.

    python benchmarks/latent_forces.py [--repeats 10] [--skip-quasiperiodic] [--optimizers auto,quasi-newton]

Prints, per model, the number of states and free parameters, the first fit in this process (compilation
included), and the compiled fit's median and fastest over ``--repeats`` fits taken in turns with the other
models' (so that the machine's load falls on all alike), and its ratio to the model without a force fitted
with the default optimizer ("auto"); each optimizer of ``--optimizers`` in turn.
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
    parser.add_argument("--optimizers", default="auto")
    args = parser.parse_args()
    optimizers = args.optimizers.split(",")

    import greyid
    from greyid import library

    data = greyid.datasets.fetch("armadillo")
    models = {"no force": greyid.Model.from_toml(ROOT / "examples" / "armadillo.toml"),
              "Matern-3/2 force": library.load_model("armadillo_matern32")}
    if not args.skip_quasiperiodic:
        models["quasi-periodic force"] = library.load_model("armadillo_quasiperiodic")
    runs = [(name, optimizer) for optimizer in optimizers for name in models]
    first, compiled, fits = {}, {run: [] for run in runs}, {}
    for name, optimizer in runs:
        start = time.perf_counter()
        fits[name, optimizer] = models[name].fit(data, optimizer=optimizer)
        first[name, optimizer] = time.perf_counter() - start
    for _ in range(args.repeats):
        for name, optimizer in runs:
            start = time.perf_counter()
            models[name].fit(data, optimizer=optimizer)
            compiled[name, optimizer].append(time.perf_counter() - start)
    base = statistics.median(compiled["no force", "auto"]) if ("no force", "auto") in compiled else None
    print(f"Armadillo fits, {args.repeats} compiled fits each, in turns")
    print(f"{'model':22s} {'optimizer':12s} {'states':>6s} {'free':>4s} {'iter':>4s} {'first [s]':>9s} "
          f"{'median [s]':>10s} {'fastest [s]':>11s} {'ratio':>6s}")
    for name, optimizer in runs:
        times, fit = compiled[name, optimizer], fits[name, optimizer]
        ratio = f"{statistics.median(times) / base:6.2f}" if base else "     —"
        print(f"{name:22s} {optimizer:12s} {len(models[name].state_names):6d} {fit.n_params:4d} {fit.iterations:4d} "
              f"{first[name, optimizer]:9.2f} {statistics.median(times):10.3f} {min(times):11.3f} {ratio}")

if __name__ == "__main__":
    main()
