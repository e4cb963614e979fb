"""Case 2 of the thesis (chapter 8): the fuel film of a spark-ignition engine at eleven operating points.

    python studies/fuel_film.py [--seed 0] [--figure cpgram.png]
    python studies/fuel_film.py --data DIR        # your own measurements

The engine measurements are not public.  Each operating point of table 8.2 is
simulated from the library's ``fuel_film`` model (8.1)–(8.3) with the table's
parameters and noise levels, as the thesis' experiment was run: a PRBS of order
6 with T_prbs = 0.5 s on the injected fuel flow, 3000 samples every 12.5 ms.
The fuel flow is set so that φ ≈ 1 (ṁ_fi = 1/k_b) with ±8 % PRBS steps (an
engine in open loop tolerates little deviation from stoichiometry).  The
delays Δt are estimated as a continuous parameter (the thesis reports them on
the sampling grid).  All points are fitted in one batched call
(``greyid.fit_many``), the residuals' cumulative periodograms are tested
(figure 8.3), and X, τ_s, τ_ff and Δt are related to the operating conditions
by best-subset regression with Mallows' C_p (section 8.4, ``greyid.fleet.relate``)
on the thesis' explanatory variables: throttle angle α and speed N (table 8.2),
manifold pressure P_man and air flow ṁ_a (table 8.3).

With ``--data DIR``: one CSV per operating point (columns t [s], mfi [g/s],
phi) and ``DIR/conditions.csv`` with a ``file`` column naming them (without
``.csv``) and the covariates (those of throttle, rpm, pman, ma it has).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import greyid  # noqa: E402
from greyid import library  # noqa: E402
from greyid.fleet import relate  # noqa: E402
from greyid.simulate.signals import prbs  # noqa: E402
from greyid.validation.spectral import cumulative_periodogram, cumulative_periodogram_test  # noqa: E402

#: Table 8.2: operating point, its Δt, and each estimate with its standard error.
TABLE_8_2 = pd.DataFrame.from_records([
    ("s20g2", 20.5, 1970, 0.138, 0.102, 0.0048, 1.87, 0.296, 0.330, 0.014, 2.41, 0.071, 0.80e-3, 0.90e-4, 0.25e-5, 0.29e-5, 0.44e-10, 0.12e-9),
    ("s30g1", 30.1, 4520, 0.038, 0.054, 0.0020, 0.56, 0.072, 0.188, 0.011, 0.80, 0.008, 0.22e-2, 0.96e-3, 0.14e-7, 0.60e-8, 0.71e-4, 0.16e-4),
    ("s30g4", 30.8, 1610, 0.038, 0.111, 0.0058, 1.62, 0.436, 0.238, 0.027, 0.89, 0.031, 0.22e-7, 0.66e-7, 0.36e-5, 0.36e-5, 0.73e-4, 0.72e-5),
    ("s40g2", 40.8, 5550, 0.025, 0.029, 0.0069, 0.30, 0.173, 0.156, 0.036, 0.41, 0.016, 0.28e-6, 0.29e-5, 0.40e-7, 0.11e-6, 0.31e-2, 0.19e-3),
    ("s40g3", 41.1, 4150, 0.013, 0.055, 0.0015, 0.98, 0.138, 0.171, 0.014, 0.45, 0.007, 0.39e-1, 0.21e-2, 0.45e-4, 0.40e-4, 0.30e-8, 0.43e-9),
    ("s40g4", 42.7, 2040, 0.075, 0.077, 0.0040, 1.10, 0.266, 0.249, 0.033, 0.59, 0.026, 0.17e-2, 0.94e-3, 0.13e-3, 0.58e-4, 0.60e-4, 0.11e-4),
    ("s50g3", 51.1, 5410, 0.000, 0.040, 0.0021, 1.31, 0.435, 0.114, 0.025, 0.38, 0.010, 0.67e-7, 0.54e-5, 0.90e-4, 0.49e-4, 0.19e-3, 0.12e-4),
    ("s50g4", 51.1, 2310, 0.063, 0.071, 0.0038, 0.99, 0.240, 0.207, 0.023, 0.47, 0.012, 0.58e-2, 0.16e-2, 0.39e-4, 0.40e-4, 0.36e-4, 0.99e-5),
    ("s60g4", 61.0, 2630, 0.038, 0.059, 0.0027, 1.65, 0.374, 0.172, 0.020, 0.40, 0.009, 0.47e-2, 0.27e-2, 0.13e-7, 0.78e-7, 0.84e-4, 0.13e-4),
    ("s70g4", 71.0, 2700, 0.038, 0.059, 0.0028, 1.14, 0.274, 0.231, 0.031, 0.40, 0.016, 0.27e-3, 0.73e-3, 0.24e-3, 0.87e-4, 0.68e-4, 0.57e-5),
    ("s80g4", 80.4, 2350, 0.050, 0.061, 0.0038, 1.94, 0.836, 0.173, 0.067, 0.43, 0.033, 0.86e-2, 0.34e-2, 0.25e-3, 0.12e-3, 0.61e-4, 0.15e-4),
], columns=["file", "throttle", "rpm", "delta_t", "tau_s", "tau_s_se", "tau_ff", "tau_ff_se", "X", "X_se", "kb",
            "kb_se", "s1f", "s1f_se", "s1ff", "s1ff_se", "s2", "s2_se"]).set_index("file")

#: Table 8.3: the manifold pressure P_man [kPa] and the air flow ṁ_a [g/s] measured at each point.
TABLE_8_3 = pd.DataFrame.from_records([
    ("s20g2", 39.49, 6.89), ("s30g1", 45.67, 17.07), ("s30g4", 83.56, 12.56), ("s40g2", 70.26, 33.09),
    ("s40g3", 77.15, 29.00), ("s40g4", 93.25, 18.03), ("s50g3", 85.36, 36.48), ("s50g4", 95.58, 19.69),
    ("s60g4", 97.08, 22.91), ("s70g4", 98.06, 23.48), ("s80g4", 98.45, 21.92),
], columns=["file", "pman", "ma"]).set_index("file")

#: The explanatory variables of section 8.4: throttle angle α, speed N, manifold pressure, air flow.
EXPLANATORY = ["throttle", "rpm", "pman", "ma"]

PARAMETERS = ["delta_t", "tau_s", "tau_ff", "X", "kb", "s1f", "s1ff", "s2"]
SAMPLES, STEP, CLOCK = 3000, 0.0125, 40  # 3000 samples at 12.5 ms; T_prbs = 0.5 s = 40 samples


def truth(point: pd.Series) -> dict:
    """The model's parameters at one operating point, from steady state at φ = 1."""
    fuel = 1.0 / point["kb"]
    return {**{name: float(point[name]) for name in PARAMETERS}, "mf0": fuel, "mff0": float(point["X"]) * fuel}


def experiment(point: pd.Series, seed: int, samples: int = SAMPLES) -> pd.DataFrame:
    """One operating point's PRBS experiment, simulated from table 8.2's parameters."""
    fuel = 1.0 / point["kb"]
    shift = np.random.default_rng(seed).integers(0, 63)  # each point starts elsewhere in the sequence
    mfi = np.roll(prbs(6, clock=CLOCK, levels=(0.92 * fuel, 1.08 * fuel), length=samples + 63 * CLOCK),
                  -shift * CLOCK)[:samples]
    data = pd.DataFrame({"t": np.arange(samples) * STEP, "mfi": mfi})
    sim = library.load_model("fuel_film").simulate(truth(point), data, method="exact", seed=seed)
    return data.assign(phi=sim.outputs[0, :, 0])


def starting_values(data: pd.DataFrame) -> dict:
    """What a user would start from: k_b from the mean φ per mean fuel flow, a steady start."""
    fuel = float(data["mfi"].iloc[:40].mean())
    return {"kb": float(data["phi"].mean() / data["mfi"].mean()), "mf0": fuel, "mff0": 0.3 * fuel}


def fit_points(datasets: dict) -> "greyid.fleet.FleetResult":
    """All operating points in one batched call."""
    inits = {name: starting_values(data) for name, data in datasets.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bound and flat-direction warnings are in the table's columns
        return greyid.fit_many(library.load_model("fuel_film"), datasets, init=inits)


def comparison(fleet, reference: pd.DataFrame | None) -> pd.DataFrame:
    """Estimates (and standard errors) beside table 8.2's, with z = (estimate − table)/se."""
    table = fleet.table
    rows = []
    for name in table.index:
        row = {"file": name, "loglik": table.loc[name, "loglik"], "converged": bool(table.loc[name, "converged"])}
        for p in PARAMETERS:
            row[p], row[f"{p}_se"] = table.loc[name, p], table.loc[name, f"{p}_se"]
            if reference is not None:
                row[f"{p}_z"] = (row[p] - reference.loc[name, p]) / row[f"{p}_se"]
        rows.append(row)
    return pd.DataFrame(rows).set_index("file")


def whiteness(fleet, datasets: dict) -> pd.DataFrame:
    """The cumulative periodogram test of each point's standardised residuals (figure 8.3)."""
    out = {}
    for name in datasets:
        fit = fleet.fits[name]
        if fit is None:
            continue
        residuals = fit.residuals["phi"]
        test = cumulative_periodogram_test(residuals)
        out[name] = {"KS statistic": test.statistic, "p_value": test.p_value}
    return pd.DataFrame(out).T


def regressions(fleet, covariates: pd.DataFrame) -> dict:
    """Section 8.4: the best subsets for X, τ_s, τ_ff (Mallows' C_p) and Δt against 1/ṁ_a."""
    out = {}
    candidates = [c for c in EXPLANATORY if c in covariates.columns]
    for parameter in ("X", "tau_s", "tau_ff"):
        out[parameter] = relate(fleet, covariates, parameter, candidates=candidates)
    inverse = covariates.assign(inverse_ma=1.0 / covariates["ma"])
    out["delta_t"] = relate(fleet, inverse, "delta_t", candidates=["inverse_ma"], weighted=False)
    return out


def plot_periodogram(fleet, name: str, path: str) -> None:
    """Figure 8.3: the cumulative periodogram of one point's residuals with its 95 % band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cp = cumulative_periodogram(fleet.fits[name].residuals["phi"], dt=STEP)
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(cp.index, cp["cumulative"], label="residuals")
    ax.plot(cp.index, cp["white"], "k-", lw=0.8, label="white noise")
    for sign in (-1, 1):
        ax.plot(cp.index, cp["white"] + sign * cp["band_95%"], "k--", lw=0.8, label="95 % band" if sign > 0 else None)
    ax.set(xlabel="frequency [Hz]", ylabel="cumulative periodogram", title=f"{name}: residuals of φ")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def own_data(directory: Path) -> tuple[dict, pd.DataFrame]:
    conditions = pd.read_csv(directory / "conditions.csv").set_index("file")
    datasets = {name: pd.read_csv(directory / f"{name}.csv") for name in conditions.index}
    return datasets, conditions


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=None, help="a directory of your own measurements")
    parser.add_argument("--figure", default=None, help="write figure 8.3 (s60g4) to this file")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    if args.data is None:
        datasets = {name: experiment(point, args.seed + k) for k, (name, point) in enumerate(TABLE_8_2.iterrows())}
        conditions = TABLE_8_2[["throttle", "rpm"]].join(TABLE_8_3)
        reference = TABLE_8_2
    else:
        datasets, conditions = own_data(args.data)
        reference = None
    simulated = time.perf_counter()
    fleet = fit_points(datasets)
    fitted = time.perf_counter()
    pd.set_option("display.width", 200)
    table = comparison(fleet, reference)
    shown = ["converged"] + [c for p in PARAMETERS[:5] for c in (p, f"{p}_se")]
    print(table[shown].to_string(float_format=lambda v: f"{v:.4g}"))
    if reference is not None:
        z = table[[f"{p}_z" for p in PARAMETERS]].abs()
        print(f"\n|z| = |estimate − table 8.2| / se: {int((z < 2).sum().sum())} of {z.count().sum()} within 2 se, "
              f"{int((z < 3).sum().sum())} within 3; largest {z.max().max():.2f}")
        print(z.to_string(float_format=lambda v: f"{v:.2f}"))
    print("\ncumulative periodogram tests of the residuals (figure 8.3):")
    print(whiteness(fleet, datasets).to_string(float_format=lambda v: f"{v:.3f}"))
    if args.figure:
        plot_periodogram(fleet, "s60g4" if "s60g4" in datasets else next(iter(datasets)), args.figure)
    print("\nsection 8.4, best subsets by Mallows' C_p:")
    for parameter, relation in regressions(fleet, conditions).items():
        best = relation.best
        terms = ", ".join(f"{name} {value:+.4g} (p {best.pvalues[name]:.2g})" for name, value in best.params.items())
        print(f"\n{parameter}: best subset {terms}, R² {best.rsquared:.2f}")
        print(relation.subsets.head(4).to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"\n(simulation {simulated - started:.0f} s, fits {fitted - simulated:.0f} s, "
          f"total {time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
