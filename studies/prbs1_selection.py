"""Forward model selection on the PRBS1 test house (Bacher & Madsen, 2011).

Start from the one-state model Ti and, at each step, try every extension by one
more state — envelope Te, heater Th, sensor Ts, interior medium Tm — keep the
one with the highest likelihood, and stop when the likelihood-ratio test no
longer rejects at 5 %.  Data: the data set ``prbs1`` (``greyid.datasets.fetch``:
downloaded once, or read from ``GREYID_DATA_MIRROR``).  Run: python studies/prbs1_selection.py
"""

from __future__ import annotations

import argparse
import time

import pandas as pd

import greyid
from greyid import library, validation

def extensions(current: greyid.Model) -> list[greyid.Model]:
    """Every model with one more RC state than ``current``."""
    have = set(current.state_names) - {"Ti"}
    return [library.rc_network(have | {s}) for s in library.RC_STATES if s not in have]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", type=float, default=0.05)
    parser.add_argument("--starts", type=int, default=1)
    args = parser.parse_args(argv)
    data = greyid.datasets.fetch("prbs1")
    started = time.perf_counter()
    result = validation.select_forward([library.load_model("Ti"), extensions, extensions, extensions, extensions],
                                       data, level=args.level, starts=args.starts)
    with pd.option_context("display.width", 140):
        print(result.table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    chosen = result.chosen
    print(f"\nchosen: {chosen.model.name}  ({time.perf_counter() - started:.0f} s)\n")
    print(chosen.summary())
    print(chosen.validate().summary())


if __name__ == "__main__":
    main()
