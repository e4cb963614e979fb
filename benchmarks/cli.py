"""Command-line commands in fresh processes: what a CLI user waits for.

    python benchmarks/cli.py [--repeats 3]

Times ``greyid demo -q`` and, on the bundled building model and data,
``greyid fit``, ``greyid validate`` and ``greyid report``, each as a new
process: with greyid's caches (XLA's compilations and the kept traced
programs, ``GREYID_CACHE_DIR``) empty, and warm (the same command run once
before).  Prints the median and range over ``--repeats`` processes.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT / "src" / "greyid" / "datasets"


def commands(out: Path) -> dict[str, list[str]]:
    greyid = [sys.executable, "-m", "greyid"]
    fit = out / "fit"
    return {
        "greyid demo -q": greyid + ["demo", "-q", "--out", str(out / "demo")],
        "greyid fit building.toml building.csv": greyid + ["fit", str(DATASETS / "building.toml"),
                                                           str(DATASETS / "building.csv"), "--out", str(fit), "-q"],
        "greyid validate fit.json": greyid + ["validate", str(fit / "fit.json")],
        "greyid report fit.json": greyid + ["report", str(fit / "fit.json"), "--out", str(out / "report.html")],
    }


def run(command: list[str], cache: str) -> float:
    start = time.perf_counter()
    done = subprocess.run(command, env=dict(os.environ, GREYID_CACHE_DIR=cache), capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode not in (0, 1):  # 1: done, with a negative verdict
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    out = Path(tempfile.mkdtemp(prefix="greyid-bench-cli-"))
    times: dict[str, dict[str, list[float]]] = {}
    for _ in range(args.repeats):
        for label, command in commands(out).items():
            cache = tempfile.mkdtemp(prefix="greyid-bench-cache-")  # empty for this command alone
            for state in ("empty cache", "warm cache"):  # the first run fills it
                times.setdefault(label, {}).setdefault(state, []).append(run(command, cache))
    for label, by_state in times.items():
        parts = []
        for state, values in by_state.items():
            values = sorted(values)
            parts.append(f"{state} {values[len(values) // 2]:.2f} s ({values[0]:.2f}–{values[-1]:.2f})")
        print(f"{label}: " + "; ".join(parts))


if __name__ == "__main__":
    main()
