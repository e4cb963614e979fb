"""Forward selection's time and memory: the user guide's selection of RC models on prbs1.

    python benchmarks/selection.py [--keep]

Runs ``greyid.validation.select_forward`` from ``Ti`` over the library's RC states on the
data set prbs1 (11 fits, as docs/user-guide.md), in this process with the cache folder as it
is, and prints its time, the process's resident memory at the end and at its peak.  ``--keep``
keeps every candidate's compiled programs (the selection releases those of the models it no
longer holds chosen), to measure what that release saves.
"""

from __future__ import annotations

import argparse
import time


def resident_gib(field: str = "VmRSS") -> float:
    """This process's resident memory (``VmRSS``) or its peak (``VmHWM``), in GiB, from /proc."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 2**20
    return float("nan")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--keep", action="store_true", help="keep every candidate's compiled programs")
    args = parser.parse_args()
    import greyid
    from greyid import library, validation
    from greyid.validation import selection

    if args.keep:
        selection.release_compiled = lambda model=None: None
    data = greyid.datasets.fetch("prbs1")

    def extensions(current):
        have = set(current.state_names) - {"Ti"}
        return [library.rc_network(have | {s}) for s in library.RC_STATES if s not in have]

    started = time.perf_counter()
    result = validation.select_forward([library.load_model("Ti"), *[extensions] * 4], data, level=0.05)
    seconds = time.perf_counter() - started
    print(f"forward selection ({len(result.table)} fits, chose {result.chosen.model.name}): {seconds:.1f} s; "
          f"resident memory at the end {resident_gib():.2f} GiB, peak {resident_gib('VmHWM'):.2f} GiB"
          + (" (every candidate's programs kept)" if args.keep else ""))


if __name__ == "__main__":
    main()
