"""What each mechanism of the compile runtime buys (greyid.runtime, docs/guide/compilation.md).

    python benchmarks/runtime.py [--repeats 3]

Times, in fresh processes with a cache folder of their own (one cold run, then
warm ones), each user-visible wait that a mechanism is kept for, with it and
with it switched off (the variants take turns):

* the Armadillo model's first fit in a script (``benchmarks/fit.py``'s case),
  default and ``optimizer="quasi-newton"``: with everything; without the store
  of traced programs (``GREYID_PROGRAMS=off``); without compiling the exact
  Hessian program in a thread (compiled where it is first needed instead);
* ``greyid demo -q``: with everything; without freezing the imports' objects;
  without either that or keeping every program however quick (a process run
  as a user's script runs the command line).

    python benchmarks/runtime.py --new-object [--repeats 3]

times instead a fit of a model built anew in the process that fitted an equal
one (a notebook cell run again): the Armadillo house, and the Laplace method on
ctsmTMB's Ornstein2D example at 10³ rows (``benchmarks/laplace.py``), each with
the compiled programs of the live model shared and without (``Program._keep``
offering none to the process), in fresh processes with a warm cache folder, taking turns.

Prints the median and range of the wall times (seconds) per variant.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fit as bench  # noqa: E402

#: Compiles where first needed: the thread's compilation switched off.
NO_THREAD = """
from concurrent.futures import Future
from greyid.runtime.jit import Program
def _at_once(self, *args):
    done = Future()
    done.set_result(self.executable(*args))
    return done
Program.compile_in_background = _at_once
"""

DEMO = """
import sys, gc
from greyid import cli
cli.OWN_PROCESS["on"] = sys.argv[1] != "user"
if sys.argv[1] == "no-freeze":
    gc.freeze = lambda: None
sys.exit(cli.main(["demo", "-q", "--out", sys.argv[2]]))
"""


#: A fit of a model built anew after an equal one's fit, in one process (``sys.argv[1:3]``: case, variant).
NEW_OBJECT = """
import sys, time
sys.path.insert(0, sys.argv[3])
if sys.argv[2] == "unshared":
    from greyid.runtime.jit import Program
    Program._keep = lambda self, signature, executable: executable
import pandas as pd
if sys.argv[1] == "armadillo":
    from greyid.datasets.reference import armadillo_model as build
    data, kwargs = pd.read_csv(sys.argv[4]).iloc[:-1], dict(time="Time", hold="foh")
else:
    from laplace import model as build, simulate
    data, kwargs = simulate(1000, 20261127 + 1000), dict(method="laplace", scheme="ctsmtmb")
first = build().fit(data, **kwargs)
start = time.perf_counter()
again = build().fit(data, **kwargs)
print(time.perf_counter() - start, again.loglik == first.loglik)
"""


def new_object(repeats: int) -> None:
    """The fit of a model built anew, with the live model's programs shared and without (see the module doc)."""
    folder = tempfile.mkdtemp(prefix="greyid-runtime-")
    env = dict(os.environ, GREYID_CACHE_DIR=folder)
    times: dict = {}
    for case in ("armadillo", "laplace"):
        command = [sys.executable, "-c", NEW_OBJECT, case, "shared", str(Path(__file__).resolve().parent),
                   str(bench.ARMADILLO)]
        subprocess.run(command, env=env, check=True, capture_output=True)  # fills the cache folder
        for _ in range(repeats):
            for variant in ("shared", "unshared"):
                command[4] = variant
                out = subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout.split()
                assert out[1] == "True", "the new model's fit differs"
                times.setdefault((case, variant), []).append(float(out[0]))
    shutil.rmtree(folder, ignore_errors=True)
    for (case, variant), values in times.items():
        print(f"{case} fit of a model built anew, {variant}: {statistics.median(values):.3f} s "
              f"({min(values):.3f}–{max(values):.3f}, {len(values)} runs)")


def timed(command: list[str], env: dict) -> float:
    start = time.perf_counter()
    out = subprocess.run(command, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr[-3000:])
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="fresh cache folders per variant")
    parser.add_argument("--new-object", action="store_true", help="only the fit of a model built anew")
    args = parser.parse_args()
    if args.new_object:
        new_object(args.repeats)
        return
    fits = {"everything": ("", {}), "no store": ("", {"GREYID_PROGRAMS": "off"}),
            "no compilation in a thread": (NO_THREAD, {})}
    demos = ("own process", "no-freeze", "user")
    times: dict = {}
    for _ in range(args.repeats):
        for setting in ("default", "quasi"):
            for name, (prefix, extra) in fits.items():
                folder = tempfile.mkdtemp(prefix="greyid-runtime-")
                env = dict(os.environ, GREYID_CACHE_DIR=folder, **extra)
                script = "import sys\n" + prefix + bench.FIT_SCRIPT
                for state in ("cold", "warm", "warm"):
                    command = [sys.executable, "-c", script, "armadillo", str(bench.ARMADILLO), setting]
                    times.setdefault((f"Armadillo first fit, {setting}", state, name), []).append(timed(command, env))
                shutil.rmtree(folder, ignore_errors=True)
        for name in demos:
            folder, out = tempfile.mkdtemp(prefix="greyid-runtime-"), tempfile.mkdtemp(prefix="greyid-demo-")
            env = dict(os.environ, GREYID_CACHE_DIR=folder)
            for state in ("cold", "warm", "warm"):
                command = [sys.executable, "-c", DEMO, name, str(Path(out) / "demo")]
                times.setdefault(("greyid demo -q", state, name), []).append(timed(command, env))
            shutil.rmtree(folder, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
    for (what, state, name), values in times.items():
        print(f"{what}, {state} cache, {name}: {statistics.median(values):.2f} s "
              f"({min(values):.2f}–{max(values):.2f}, {len(values)} runs)")


if __name__ == "__main__":
    main()
