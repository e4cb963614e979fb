"""Thesis tables 7.3–7.5: which heating signal tells most about the test cell (section 7.3).

    python studies/table_7_4.py [--hours 504] [--method exact] [--sinusoids periods|rates]

The test-cell model (7.43) with the parameters of section 7.2, sampled every
hour for ``--hours`` hours (504 h by default: the step of period 252 h of table
7.3 switches once on and once off; the thesis says its experiments last about
nine times the largest time constant).  Candidates (table 7.3): PRBS between
0 and 300 W with clock periods 1, 2, 5 and 8 h (orders 9, 8, 7, 6), a step of
period 252 h, and two sinusoids of periods 3 h and 54 h with the binary
signals' power (mean 150 W, variance 150² W²) split 1:1, 1:2 and 1:9. The thesis
writes the sinusoids' "τ₁ = 3 h, τ₂ = 54 h" as periods, and also says that sin3's
frequencies lie exactly at the system's poles, 0.0184 and 0.330 (7.51), which are
1/54 and 1/3: ``--sinusoids rates`` reads τ as time constants, ω = 1/τ rad/h,
instead of periods (ω = 2π/τ, the default). The outdoor surface temperature is a
daily cycle with a slow weather component (seeded), the same for every candidate.

The thesis estimated the information from 100 simulated paths per candidate; here
it is exact (``greyid.design``, linear model) unless ``--method montecarlo``.
The information is that of the seven parameters of (7.43)–(7.46), the initial
states taken as known.  Criteria, each minimised: table 7.4's D = −log det M,
Ds (the noise variances as nuisance), C = tr(V M⁻¹ V)/p and E = λ_max(V M⁻¹ V)
with V = diag(1/θ) (relative precision); table 7.5's variances of UA and CI by
Gauss' formula (7.47–7.48) and D of (UA, CI) = log det of their covariance.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from greyid import design
from greyid.datasets.thesis import TEST_CELL_PARAMETERS, test_cell_model
from greyid.simulate.signals import multisine, prbs

#: UA [W/K] and CI [Wh/K] of (7.48), in the model's units.
PHYSICAL = {"UA": "Hm*Hi/(Hm + Hi)", "CI": "Ci + Hi*Cm/(Hm + Hi)"}


#: The sinusoids' τ [h] of table 7.3.
SINUSOID_TAUS = (3.0, 54.0)


def candidates(hours: int, seed: int = 0, sinusoids: str = "periods") -> dict[str, pd.DataFrame]:
    t = np.arange(hours, dtype=float)
    rng = np.random.default_rng(seed)
    weather = np.cumsum(rng.normal(0.0, 0.25, hours))
    weather -= np.linspace(weather[0], weather[-1], hours)
    te = 8.0 + 5.0 * np.sin(2 * np.pi * (t - 9.0) / 24.0) + weather
    signals = {
        "prbs1": prbs(9, clock=1, levels=(0.0, 300.0), length=hours),
        "prbs2": prbs(8, clock=2, levels=(0.0, 300.0), length=hours),
        "prbs3": prbs(7, clock=5, levels=(0.0, 300.0), length=hours),
        "prbs4": prbs(6, clock=8, levels=(0.0, 300.0), length=hours),
        "step": np.where((t // 252) % 2 == 0, 300.0, 0.0),
    }
    # multisine takes cycles per hour: 1/τ for periods τ, (1/τ)/2π for rates ω = 1/τ rad/h.
    cycles = [1 / tau if sinusoids == "periods" else 1 / (2 * np.pi * tau) for tau in SINUSOID_TAUS]
    for name, split in (("sin1", (1, 1)), ("sin2", (1, 2)), ("sin3", (1, 9))):
        signals[name] = multisine(t, cycles, power=split, total_power=150.0**2, offset=150.0)
    return {name: pd.DataFrame({"t": t, "Te": te, "Qh": q}) for name, q in signals.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=int, default=504)
    parser.add_argument("--method", choices=["exact", "montecarlo"], default="exact")
    parser.add_argument("--n-paths", type=int, default=100)
    parser.add_argument("--sinusoids", choices=["periods", "rates"], default="periods",
                        help="table 7.3's τ = 3 h and 54 h as periods (ω = 2π/τ) or as rates (ω = 1/τ rad/h)")
    args = parser.parse_args(argv)
    model = test_cell_model()
    plans = candidates(args.hours, sinusoids=args.sinusoids)
    # The seven parameters of (7.43)–(7.46); the initial states are taken as known.
    physical, noise = ["Hi", "Hm", "Ci", "Cm"], ["s1i", "s1m", "s2"]
    free = physical + noise
    relative = np.diag([1.0 / TEST_CELL_PARAMETERS[n] for n in free])
    started = time.perf_counter()
    options = dict(method=args.method, n_paths=args.n_paths, free=free)
    standard = design.compare_inputs(model, TEST_CELL_PARAMETERS, plans, criteria={
        "D": "D", "Ds": {"name": "Ds", "interest": physical}, "C": "C", "E": {"name": "E", "V": relative},
    }, **options)
    characteristic = design.compare_inputs(model, TEST_CELL_PARAMETERS, plans, criteria={
        "UA": {"name": "A", "derived": {"UA": PHYSICAL["UA"]}},
        "CI": {"name": "A", "derived": {"CI": PHYSICAL["CI"]}},
        "D_UA,CI": {"name": "D", "derived": PHYSICAL},
    }, **options)
    elapsed = time.perf_counter() - started
    with pd.option_context("display.width", 120, "display.float_format", lambda v: f"{v:.4g}"):
        print(f"Table 7.4: standard criteria ({args.hours} h at 1 h, {args.method} information of {free}; "
              f"Ds: {physical} of interest; E of the relative covariance; sinusoids' τ as {args.sinusoids})")
        print(standard.to_string())
        print("\nTable 7.5: physical criteria (variance of UA [W/K], of CI [Wh/K], D of (UA, CI))")
        print(characteristic.to_string())
    print(f"\n{2 * len(plans)} information matrices and criteria in {elapsed:.1f} s")


if __name__ == "__main__":
    main()
