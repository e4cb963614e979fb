"""Command line: ``greyid demo`` runs the main job (a fit) on the bundled data."""

from __future__ import annotations

import argparse
import sys
import time


def demo() -> int:
    """Fit the bundled building model to its bundled data and print the summary."""
    from .datasets import TRUE_PARAMETERS, building_model, load_building_data

    model = building_model()
    data = load_building_data()
    print(model)
    print(f"data: {len(data)} rows, t from {data['t'].iloc[0]} to {data['t'].iloc[-1]} h")
    start = time.perf_counter()
    fit = model.fit(data, time="t", hold="zoh")
    print(f"fitted in {time.perf_counter() - start:.2f} s\n")
    print(fit.summary())
    print()
    print("physical characteristics (delta-method standard errors):")
    print(fit.derived({"UA [kW/K]": "1/(Riw + Rwe)", "C_total [kWh/K]": "Ci + Cw"}).to_string())
    truth = model.loglik(TRUE_PARAMETERS, data)
    print(f"\nlog-likelihood at the simulation's true parameters: {truth:.4f}")
    return 0 if fit.converged else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="greyid", description="Grey-box identification with SDEs")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("demo", help="fit the bundled building model to its bundled data and print the summary")
    args = parser.parse_args(argv)
    if args.command == "demo":
        return demo()
    return 2


if __name__ == "__main__":
    sys.exit(main())
