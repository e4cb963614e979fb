"""Profile intervals right after a fit: what ``fit.conf_int(method="profile")`` costs.

    python benchmarks/intervals.py [--repeats 3] [--against OTHER_CHECKOUT/src]

For the Armadillo house (pySIP's TwTi_RoRi, 232 rows, 7 free parameters) and the
bundled building model (``greyid demo``'s, 10 free parameters): in fresh processes
with greyid's cache folder switched off, the fit, then ``conf_int(method="profile")``
twice: the first call compiles what the intervals need beyond the fit's programs,
the second runs compiled.  Prints the median and range over ``--repeats`` processes.
With ``--against`` (greyid's ``src`` folder of another checkout) processes of that
code take turns with this one's, and the largest difference between the two codes'
ends is printed in standard errors.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import json, sys, time, warnings
import greyid
warnings.simplefilter("ignore")
if sys.argv[1] == "armadillo":
    from greyid.datasets.reference import armadillo_model
    model = armadillo_model()
    fit = model.fit(greyid.datasets.fetch("armadillo").iloc[:-1], time="Time", hold="foh")
else:
    from greyid.datasets import building_model, load_building_data
    model = building_model()
    fit = model.fit(load_building_data())
start = time.perf_counter()
fit.conf_int(method="profile")
first = time.perf_counter()
ends = fit.conf_int(method="profile")
again = time.perf_counter()
print(json.dumps({"first": first - start, "again": again - first, "lower": ends["lower"].tolist(),
                  "upper": ends["upper"].tolist(), "se": fit.params["std_error"].tolist()}))
"""


def run(case: str, source: Path) -> dict:
    env = dict(os.environ, GREYID_CACHE_DIR="off", PYTHONPATH=str(source))
    done = subprocess.run([sys.executable, "-c", SCRIPT, case], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(done.stderr)
    return json.loads(done.stdout.strip().splitlines()[-1])


def summary(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} s ({min(values):.2f}-{max(values):.2f})"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--against", type=Path, help="greyid's src folder of another checkout")
    args = parser.parse_args()
    codes = {"this": ROOT / "src"} | ({"other": args.against.resolve()} if args.against else {})
    for case in ("armadillo", "building"):
        runs = {name: [] for name in codes}
        for _ in range(args.repeats):
            for name, source in codes.items():  # taking turns
                runs[name].append(run(case, source))
        for name, results in runs.items():
            print(f"{case}, {name} code: first call {summary([r['first'] for r in results])}, "
                  f"compiled {summary([r['again'] for r in results])}")
        if args.against:
            a, b = runs["this"][0], runs["other"][0]
            gap = max(abs(x - y) / s for end in ("lower", "upper") for x, y, s in zip(a[end], b[end], a["se"])
                      if s == s and s > 0 and x == x and y == y)
            print(f"{case}: largest difference of the ends, this code against the other: {gap:.2g} standard errors")


if __name__ == "__main__":
    main()
