"""Thesis section 6.5: single-frequency input designs for a scalar model — local, Bayesian, minimax.

    python studies/section_6_5.py

Model (6.73)–(6.74): dx = −a x dt + b u dt + dw with incremental variance r,
y_k = x_k + e_k with variance r₂; b = 1, r = 1, r₂ = 0.1, sampling interval
τ = 1, the input held between samples, θ = (a, b).  A single sinusoid of unit
power (variance 1) at angular frequency ω (rad per time unit); the information
per sample is M̄_F(ω) = M̄_c + M̃_F(ω) (6.47–6.49, `greyid.design`).

* local design at a = 0.8 (J₁ = −log det M̄_F, (6.84));
* Bayesian design with a uniform on [0.5, 1.1] (J₂ = E_a(−log det M̄_F), (6.83));
* minimax design over a ∈ [0.5, 1.1] (J₃ = max_a(−log det M̄_F), (6.85)–(6.86)).

Each is found twice: over single sinusoids by a grid search, as the thesis
does, and over multisines of any number of sinusoids by
``design.optimal_multisine`` (local, ``prior=`` and ``minimax=``).

The thesis' ω* and J are printed beside greyid's.  Its conventions for the
input power and for M̄_c are not stated; with unit power and M̄_c included the
local and minimax frequencies come within 0.01 of the thesis', the values of J
differ (see docs/design.md).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

import greyid
from greyid import design

THESIS = {"local": (0.6606, 0.6107), "Bayesian": (0.4575, 1.1951), "minimax": (0.8128, 1.3741)}


def scalar_model() -> greyid.Model:
    m = greyid.Model("section_6_5")
    m.add_system("dx = (-a*x + b*u)*dt + sqrt(r)*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r2")
    m.set_initial_state(mean={"x": "0"}, covariance=[["1"]])
    for name, value in dict(a=0.8, b=1.0).items():
        m.set_parameter(name, init=value, lower=0.0, upper=10.0)
    for name, value in dict(r=1.0, r2=0.1).items():
        m.set_parameter(name, init=value, fixed=True)
    return m


def criterion_curves(model, omegas, a_values):
    """−log det M̄_F(ω) for each a (rows) and ω (columns)."""
    rows = []
    for a in a_values:
        M_u, M_c, _ = design.frequency_information_grid(model, dict(a=a, b=1.0, r=1.0, r2=0.1), omegas, "u", 1.0,
                                                        free=["a", "b"])
        rows.append([-np.linalg.slogdet(M_c + M)[1] for M in M_u])
    return np.array(rows)


def designs(model=None, points: int = 1500, a_points: int = 61) -> dict:
    model = model or scalar_model()
    omegas = np.linspace(0.005, np.pi, points)
    local = criterion_curves(model, omegas, [0.8])[0]
    spread = criterion_curves(model, omegas, np.linspace(0.5, 1.1, a_points))
    out = {}
    for name, curve in (("local", local), ("Bayesian", spread.mean(axis=0)), ("minimax", spread.max(axis=0))):
        best = int(np.argmin(curve))
        out[name] = (float(omegas[best]), float(curve[best]))
    return out


def multisine_designs(model=None, a_points: int = 31) -> dict:
    """The same three designs as multisines (any number of sinusoids), by ``design.optimal_multisine``."""
    model = model or scalar_model()
    params = dict(a=0.8, b=1.0, r=1.0, r2=0.1)
    uniform = pd.DataFrame({"a": np.linspace(0.5, 1.1, a_points)})
    options = dict(free=["a", "b"])
    return {"local": design.optimal_multisine(model, params, "u", 1.0, **options),
            "Bayesian": design.optimal_multisine(model, params, "u", 1.0, prior=uniform, **options),
            "minimax": design.optimal_multisine(model, params, "u", 1.0, minimax=uniform, **options)}


def main() -> None:
    print("single sinusoid (grid search over omega):")
    print(f"{'design':10s} {'omega* greyid':>14s} {'J greyid':>9s} {'omega* thesis':>14s} {'J thesis':>9s}")
    for name, (omega, value) in designs().items():
        print(f"{name:10s} {omega:14.4f} {value:9.4f} {THESIS[name][0]:14.4f} {THESIS[name][1]:9.4f}")
    print("\noptimal multisine (design.optimal_multisine; a on 31 points of [0.5, 1.1]):")
    for name, best in multisine_designs().items():
        sines = ", ".join(f"{w:.3f} at {f:.4f}" for f, w in zip(best.frequencies, best.weights))
        print(f"{name:10s} J = {best.value:.4f}   power {sines}   "
              f"equivalence {best.max_derivative:.6f} <= {best.support_derivative:.6f}")


if __name__ == "__main__":
    main()
