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


def timed(command: list[str], env: dict) -> float:
    start = time.perf_counter()
    out = subprocess.run(command, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr[-3000:])
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="fresh cache folders per variant")
    args = parser.parse_args()
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
