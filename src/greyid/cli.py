"""Command line: ``greyid demo`` runs the main job on the bundled data."""

from __future__ import annotations

import argparse
import sys
import time


def demo() -> int:
    """Filter the bundled building data at the true parameters and print the log-likelihood."""
    from .datasets import TRUE_PARAMETERS, building_model, load_building_data

    model = building_model()
    data = load_building_data()
    print(model)
    print(f"data: {len(data)} rows, t from {data['t'].iloc[0]} to {data['t'].iloc[-1]} h")
    for method in ("kalman", "ekf", "ukf"):
        for hold in ("zoh", "foh"):
            start = time.perf_counter()
            ll = model.loglik(TRUE_PARAMETERS, data, time="t", hold=hold, method=method)
            print(f"log-likelihood at the true parameters ({method:6s}, {hold}): {ll:.6f}"
                  f"   [{time.perf_counter() - start:.2f} s]")
    result = model.filter(TRUE_PARAMETERS, data)
    sd = result.standardized_innovations["yTi"]
    print(f"standardized one-step innovations: mean {sd.mean():.3f}, std {sd.std():.3f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="greyid", description="Grey-box identification with SDEs")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("demo", help="filter the bundled building model data and print its log-likelihood")
    args = parser.parse_args(argv)
    if args.command == "demo":
        return demo()
    return 2


if __name__ == "__main__":
    sys.exit(main())
