"""greyid beside pySIP on the same problems: the Armadillo model on 232, 10⁴ and 10⁵ rows.

    python benchmarks/beside_pysip.py make DIR      # greyid's environment: the data sets, as CSV files
    python benchmarks/beside_pysip.py greyid DIR    # greyid's environment: fit each, timed
    python benchmarks/beside_pysip.py pysip DIR     # pySIP's environment: fit each, timed
    python benchmarks/beside_pysip.py pysip-call DIR  # pySIP's environment: its criterion per call
    (after DIR, the data sets' names to run only those, e.g. armadillo_10000)

pySIP (locie/pySIP, not on PyPI) needs an environment of its own: its
dependencies are pinned below NumPy 2 (numpy 1.26, pandas 1.5, numba 0.59,
pymc 5.10, pydantic 1), then ``pip install --no-deps`` of its repository.
The data: the Armadillo house's own 232 rows (pySIP's file, last row dropped as
pySIP's tests drop it) and the Armadillo model (pySIP's TwTi_RoRi, first-order
hold) simulated at its fitted parameters on the house's inputs repeated to
10⁴ and 10⁵ rows (1800 s apart).  Each tool fits from the same starting values
as pySIP's test (its scales); "first" is the first fit in the process
(compilation included), "second" a second fit of the same data.  ``pysip-call``
times pySIP's negative log-posterior on the 232 rows at its optimum (the
fastest of 300 calls), and its value with the gradient as its fit takes them:
SciPy's 3-point differences, two evaluations per free parameter
(greyid's side: ``benchmarks/likelihood.py``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import durations, fastest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LENGTHS = (10_000, 100_000)


def make(folder: Path) -> None:
    import numpy as np
    import pandas as pd

    import greyid
    from greyid.datasets.reference import armadillo_model

    folder.mkdir(parents=True, exist_ok=True)
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    data.to_csv(folder / "armadillo_232.csv", index=False)
    model = armadillo_model()
    fitted = model.fit(data, time="Time", hold="foh").values
    for n in LENGTHS:
        reps = -(-n // len(data))
        long = pd.concat([data] * reps, ignore_index=True).iloc[:n].copy()
        long["Time"] = np.arange(n) * 1800.0
        sim = model.simulate(fitted, long, seed=1, time="Time", hold="foh")
        long["T_int"] = sim.outputs[0, :, 0]
        long.to_csv(folder / f"armadillo_{n}.csv", index=False)
        print(f"wrote {n} rows")


def files(folder: Path):
    """The data sets, or those named after DIR on the command line (e.g. armadillo_10000)."""
    names = sys.argv[3:] or ["armadillo_232"] + [f"armadillo_{n}" for n in LENGTHS]
    return [folder / f"{name}.csv" for name in names]


def run_greyid(folder: Path) -> None:
    import pandas as pd

    from greyid.datasets.reference import armadillo_model

    for path in files(folder):
        data = pd.read_csv(path)
        model = armadillo_model()
        times, fit = durations(lambda: model.fit(data, time="Time", hold="foh"), 2)
        print(f"greyid {path.name}: first {times[0]:.2f} s, second {times[1]:.2f} s, log L {fit.loglik:.4f}, "
              f"{fit.iterations} iterations", flush=True)


def pysip_parameters() -> list:
    """pySIP's own test of the Armadillo fit (tests/data/test_armadillo.py): its parameters and scales."""
    from pysip.params.prior import LogNormal, Normal

    day = 3600.0 * 24.0
    return [
        dict(name="Ro", scale=1e-2, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="Ri", scale=1e-3, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="Cw", scale=1e7 / day, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="Ci", scale=1e6 / day, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="sigw_w", scale=1e-2 * day ** 0.5, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="sigw_i", value=0, transform="fixed"),
        dict(name="sigv", scale=1e-2, bounds=(0, None), prior=LogNormal(1, 1)),
        dict(name="x0_w", loc=25, scale=5, prior=Normal(0, 1)),
        dict(name="x0_i", value=26.701, transform="fixed"),
        dict(name="sigx0_w", value=1, transform="fixed"),
        dict(name="sigx0_i", value=0.1, transform="fixed"),
    ]


def run_pysip(folder: Path) -> None:
    import pandas as pd
    from pysip.regressors import Regressor
    from pysip.statespace.thermal_network import TwTi_RoRi

    day = 3600.0 * 24.0
    parameters = pysip_parameters()
    for path in files(folder):
        df = pd.read_csv(path).set_index("Time")
        df.index /= day
        times = []
        for _ in range(2):
            regressor = Regressor(ss=TwTi_RoRi(parameters, hold_order=1), outputs="T_int", inputs=["T_ext", "P_hea"])
            start = time.perf_counter()
            regressor.fit(df=df)
            times.append(time.perf_counter() - start)
        loglik = regressor.log_likelihood(df=df)
        print(f"pySIP {path.name}: first {times[0]:.2f} s, second {times[1]:.2f} s, "
              f"its log_likelihood() {loglik:.4f}", flush=True)


def run_pysip_call(folder: Path) -> None:
    import numpy as np
    import pandas as pd
    from scipy.optimize._numdiff import approx_derivative  # what minimize(jac="3-point") calls

    from pysip.regressors import Regressor
    from pysip.statespace.thermal_network import TwTi_RoRi

    day = 3600.0 * 24.0
    df = pd.read_csv(folder / "armadillo_232.csv").set_index("Time")
    df.index /= day
    regressor = Regressor(ss=TwTi_RoRi(pysip_parameters(), hold_order=1), outputs="T_int", inputs=["T_ext", "P_hea"])
    regressor.fit(df=df)
    data = regressor.prepare_data(df)
    eta = np.array(regressor.ss.parameters.eta_free)

    value = fastest(lambda: regressor._target(eta, *data))
    gradient = fastest(lambda: approx_derivative(lambda e: regressor._target(e, *data), eta, method="3-point"))
    print(f"pySIP armadillo_232: criterion {value * 1e3:.3f} ms per call; value and 3-point gradient "
          f"({2 * len(eta)} more calls) {(value + gradient) * 1e3:.3f} ms", flush=True)


if __name__ == "__main__":
    action, folder = sys.argv[1], Path(sys.argv[2])
    {"make": make, "greyid": run_greyid, "pysip": run_pysip, "pysip-call": run_pysip_call}[action](folder)
