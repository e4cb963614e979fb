"""Estimation benchmarks (issue "Estimation", section Speed).

    python benchmarks/fit.py [--lengths 1000,10000,100000,1000000] [--steady-state] [--quasi-newton] [--lbfgs]
    python benchmarks/fit.py --against OTHER_CHECKOUT/src

Prints, on this machine:
* the Armadillo fit (pySIP's TwTi_RoRi, first-order hold, 232 rows; data from
  ../shared/data) and the test-cell fit (model 7.43, 1512 samples): the first fit
  in a fresh process (import + compile + fit, measured as a subprocess, with an
  empty and with a warm persistent compilation cache; median and range over
  ``--repeats`` processes) and the fit with compiled functions (seven more fits
  in the same process: median and fastest).  greyid's modules are byte-compiled
  first, as ``pip install`` does: with an editable install and
  ``PYTHONDONTWRITEBYTECODE`` set (as on the development machine) every
  process would otherwise compile them again, 0.4 s (``--no-bytecode`` measures that);
* with ``--quasi-newton``, the same first fits with ``optimizer="quasi-newton"``, interleaved;
* with ``--lbfgs``, the same first fits with ``optimizer="lbfgs"`` (no Hessian program), interleaved;
* with ``--steady-state``, the same fits with ``steady_state=True`` (the fit's programs switch
  a shorter series to the filter's steady state), interleaved with the default ones, and both
  compiled in one process, alternating in blocks of ten fits;
* with ``--against OTHER_CHECKOUT/src`` (greyid as it was, e.g. when an issue was filed) only
  the Armadillo model's compiled fits of that checkout beside this one's, default,
  ``steady_state=True``, ``optimizer="quasi-newton"`` and both: processes taking turns, thirty
  compiled fits each;
* log-likelihood + gradient time of the test-cell model against series length.
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
ARMADILLO = ROOT.parent / "shared" / "data" / "armadillo_box" / "armadillo_data_H2.csv"

#: The model, data and fit settings of a case (``sys.argv[1:3]``: case, data file), in a timed process.
CASE_SETUP = """
import pandas as pd
import greyid
from greyid.datasets.reference import armadillo_model
from greyid.datasets import thesis
case, path = sys.argv[1], sys.argv[2]
if case == "armadillo":
    model, data = armadillo_model(), pd.read_csv(path).iloc[:-1]
    kwargs = dict(time="Time", hold="foh")
else:
    model, data = thesis.test_cell_model(), pd.read_csv(path)
    kwargs = {}
"""

FIT_SCRIPT = """
import time, sys
start = time.perf_counter()
""" + CASE_SETUP + """
if sys.argv[3] == "steady":
    kwargs["steady_state"] = True
if sys.argv[3] == "quasi":
    kwargs["optimizer"] = "quasi-newton"
if sys.argv[3] == "lbfgs":
    kwargs["optimizer"] = "lbfgs"
ready = time.perf_counter()
fit = model.fit(data, **kwargs)
first = time.perf_counter()
again = []
for _ in range(7):
    t = time.perf_counter()
    model.fit(data, **kwargs)
    again.append(time.perf_counter() - t)
again.sort()
print(f"{ready - start:.3f} {first - ready:.3f} {again[3]:.3f} {again[0]:.3f} {fit.loglik:.4f} {fit.iterations}")
"""


BLOCKS_SCRIPT = """
import sys, time
import numpy as np
""" + CASE_SETUP + """
rounds = int(sys.argv[3])
variants = {"default": kwargs, "steady_state=True": dict(kwargs, steady_state=True)}
times = {name: [] for name in variants}
for kwargs in variants.values():
    model.fit(data, **kwargs)
for _ in range(rounds):
    for name, kwargs in variants.items():
        for _ in range(10):
            start = time.perf_counter()
            model.fit(data, **kwargs)
            times[name].append(time.perf_counter() - start)
for name, values in times.items():
    v = np.array(values) * 1e3
    q1, q3 = np.percentile(v, [25, 75])
    print(f"{name}: {np.median(v):.1f} ms (quartiles {q1:.1f}–{q3:.1f}, fastest {v.min():.1f})")
"""

#: Compiled fits in one process (``sys.argv[3]``: "default" or settings joined by "+": "steady",
#: "quasi"; ``sys.argv[4]``: how many).
WARM_SCRIPT = """
import sys, time
import numpy as np
""" + CASE_SETUP + """
if "steady" in sys.argv[3]:
    kwargs["steady_state"] = True
if "quasi" in sys.argv[3]:
    kwargs["optimizer"] = "quasi-newton"
fit = model.fit(data, **kwargs)
model.fit(data, **kwargs)
times = []
for _ in range(int(sys.argv[4])):
    start = time.perf_counter()
    model.fit(data, **kwargs)
    times.append(time.perf_counter() - start)
print(f"{np.median(times) * 1e3:.2f} {min(times) * 1e3:.2f} {fit.loglik:.10f}")
"""


def warm_against(case: str, data: Path, other: Path, rounds: int, fits: int = 30) -> None:
    """Compiled fits of another checkout (``other``: its ``src``, default settings) beside this one's,
    default, ``steady_state=True``, ``optimizer="quasi-newton"`` and both: one process each in turn,
    ``rounds`` times."""
    variants = {f"{other} (default)": (dict(os.environ, PYTHONPATH=str(other)), "default"),
                "this checkout (default)": (dict(os.environ), "default"),
                "this checkout, steady_state=True": (dict(os.environ), "steady"),
                'this checkout, optimizer="quasi-newton"': (dict(os.environ), "quasi"),
                'this checkout, both': (dict(os.environ), "steady+quasi")}
    results: dict = {name: [] for name in variants}
    for _ in range(rounds):
        for name, (env, variant) in variants.items():
            out = subprocess.run([sys.executable, "-c", WARM_SCRIPT, case, str(data), variant, str(fits)], env=env,
                                 check=True, capture_output=True, text=True).stdout.split()
            results[name].append((float(out[0]), float(out[1]), out[2]))
    print(f"  compiled fits, {rounds} processes each taking turns, {fits} fits per process "
          "(median of the processes' medians; fastest single fit):")
    medians = {name: sorted(r[0] for r in runs)[len(runs) // 2] for name, runs in results.items()}
    reference = medians[f"{other} (default)"]
    for name, runs in results.items():
        print(f"    {name}: {medians[name]:.1f} ms (processes {min(r[0] for r in runs):.1f}–"
              f"{max(r[0] for r in runs):.1f}; fastest {min(r[1] for r in runs):.1f}), "
              f"{medians[name] / reference:.2f} of the other checkout's; loglik {runs[0][2]}")


def compiled_blocks(case: str, data: Path, rounds: int) -> None:
    """Compiled fits in one process, default and ``steady_state=True`` alternating in blocks of ten
    (the same fit repeated, as a bootstrap or a study repeats it): the fairest comparison of the two
    on a machine whose speed drifts."""
    out = subprocess.run([sys.executable, "-c", BLOCKS_SCRIPT, case, str(data), str(rounds)], check=True,
                         capture_output=True, text=True).stdout
    print("  compiled fits in one process, blocks of 10 alternating, median over " + f"{10 * rounds} fits each:")
    for line in out.strip().splitlines():
        print("    " + line)


def test_cell_data() -> Path:
    """The test-cell series, simulated here once so that the timed process only reads it."""
    import greyid  # noqa: F401
    from greyid.datasets import thesis

    model, data = thesis.test_cell_model(), thesis.test_cell_inputs()
    data["Ttr"] = model.simulate(thesis.TEST_CELL_PARAMETERS, data, method="exact", seed=1).outputs[0, :, 0]
    path = Path(tempfile.mkdtemp(prefix="greyid-bench-data-")) / "test_cell.csv"
    data.to_csv(path, index=False)
    return path


def fit_case(case: str, data: Path, repeats: int, steady_state: bool = False, quasi_newton: bool = False,
             lbfgs: bool = False) -> None:
    """First fits with an empty and a warm compilation cache, ``repeats`` times each (median, range); with
    ``steady_state`` (``quasi_newton``) the same with ``fit(..., steady_state=True)``
    (``optimizer="quasi-newton"``), interleaved with the default."""
    variants = (["default"] + (["steady"] if steady_state else []) + (["quasi"] if quasi_newton else [])
                + (["lbfgs"] if lbfgs else []))
    runs = {(variant, cache): [] for variant in variants for cache in ("cold cache", "warm cache")}
    for _ in range(repeats):
        for variant in variants:
            env = dict(os.environ, GREYID_CACHE_DIR=tempfile.mkdtemp(prefix="greyid-bench-cache-"))
            for cache in ("cold cache", "warm cache"):
                run_fits(runs[variant, cache], case, data, variant, env)
    for (variant, cache), results in runs.items():
        label = {"default": cache, "steady": f"steady_state=True, {cache}",
                 "quasi": f'optimizer="quasi-newton", {cache}', "lbfgs": f'optimizer="lbfgs", {cache}'}[variant]

        def stat(key, fmt):
            values = sorted(r[key] for r in results)
            return f"{values[len(values) // 2]:{fmt}} ({values[0]:{fmt}}–{values[-1]:{fmt}})"
        print(f"  {label}: first fit in a fresh process {stat('first', '.2f')} s, of which import + data + model "
              f"{stat('setup', '.2f')} s; "
              f"interpreter start and exit add {stat('start', '.2f')} s; compiled fit "
              f"{stat('median', '.3f')} s (medians of 7 fits per process; fastest single fit "
              f"{min(r['fastest'] for r in results):.3f} s); loglik {results[0]['loglik']}, "
              f"{results[0]['iterations']} iterations")


def run_fits(results: list, case: str, data: Path, variant: str, env: dict) -> None:
    """One fresh process: its first fit and seven compiled ones, appended to ``results``."""
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", FIT_SCRIPT, case, str(data), variant], env=env, check=True,
                         capture_output=True, text=True).stdout.split()
    total = time.perf_counter() - start
    setup, first, median, fastest = (float(v) for v in out[:4])
    results.append(dict(setup=setup, first=setup + first, start=total - setup - first - 7 * median,
                        median=median, fastest=fastest, loglik=out[4], iterations=out[5]))


def scaling(lengths: list[int]) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from greyid.runtime.jit import jit
    from greyid.estimate.objective import forward_value_and_grad
    from greyid.data import prepare_series
    from greyid.datasets import thesis
    from greyid.filters.api import compiled_filter, filter_inputs, filter_options

    model = thesis.test_cell_model()
    s = model.structure
    theta = jnp.asarray(model.parameter_vector(thesis.TEST_CELL_PARAMETERS))
    run = compiled_filter(s, filter_options(s, None), keep_outputs=False)
    loglik = lambda th, d: run(th, d)[0].loglik.sum()  # noqa: E731
    # Forward mode, as greyid's score computations use (estimate/information.py).
    value_grad = jit(forward_value_and_grad(loglik))
    print(f"  {'samples':>9s} {'compile+run [s]':>16s} {'run [s]':>9s} {'per sample [us]':>16s}")
    for n in lengths:
        data = thesis.test_cell_inputs(n)
        data["Ttr"] = 20.0 + np.random.default_rng(0).normal(size=n)
        inputs = filter_inputs(prepare_series(data, s.input_names, s.output_names), "zoh")
        start = time.perf_counter()
        jax.block_until_ready(value_grad(theta, inputs))
        first = time.perf_counter() - start
        start = time.perf_counter()
        jax.block_until_ready(value_grad(theta, inputs))
        run_time = time.perf_counter() - start
        print(f"  {n:9d} {first:16.2f} {run_time:9.3f} {run_time / n * 1e6:16.2f}")


def byte_compile() -> None:
    """greyid's modules compiled to bytecode, as ``pip install`` leaves them."""
    import compileall

    import greyid

    compileall.compile_dir(Path(greyid.__file__).parent, quiet=1)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--lengths", default="1000,10000,100000,1000000", help="series lengths (\"\": none)")
    parser.add_argument("--repeats", type=int, default=3, help="fresh processes per case and cache state")
    parser.add_argument("--steady-state", action="store_true",
                        help="also fit with steady_state=True (interleaved with the default)")
    parser.add_argument("--quasi-newton", action="store_true",
                        help='also fit with optimizer="quasi-newton" (interleaved with the default)')
    parser.add_argument("--lbfgs", action="store_true",
                        help='also fit with optimizer="lbfgs" (interleaved with the default)')
    parser.add_argument("--against", type=Path, default=None,
                        help="another checkout's src: its compiled Armadillo fits beside this one's")
    parser.add_argument("--no-bytecode", action="store_true",
                        help="do not byte-compile greyid's modules first (see the module's docstring)")
    args = parser.parse_args()
    if not args.no_bytecode:
        byte_compile()
    if args.against is not None:
        warm_against("armadillo", ARMADILLO, args.against.resolve(), 5)
        return
    if ARMADILLO.exists():
        print("Armadillo fit (TwTi_RoRi, foh, 232 rows):")
        fit_case("armadillo", ARMADILLO, args.repeats, args.steady_state, args.quasi_newton, args.lbfgs)
        if args.steady_state:
            compiled_blocks("armadillo", ARMADILLO, 6)
    else:
        print(f"Armadillo data not found at {ARMADILLO}; skipped")
    print("Test-cell fit (7.43, 1512 samples):")
    cell = test_cell_data()
    fit_case("testcell", cell, args.repeats, args.steady_state, args.quasi_newton, args.lbfgs)
    if args.steady_state:
        compiled_blocks("testcell", cell, 3)
    lengths = [int(v) for v in args.lengths.split(",") if v.strip()]
    if lengths:  # --lengths "" leaves the sweep out
        print("Test-cell log-likelihood + gradient against series length:")
        scaling(lengths)


if __name__ == "__main__":
    main()
