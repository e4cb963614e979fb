"""Models and experiments of the thesis' validation studies (section 7.2, appendix A.7)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..api import Model
from ..simulate.signals import prbs

#: Section 7.2: H in W/K, C in Wh/K, incremental variances in K² per hour.
TEST_CELL_PARAMETERS = {
    "Hi": 55.29, "Hm": 13.86, "Ci": 325.0, "Cm": 387.8,
    "s1i": 0.00167, "s1m": 0.00978, "s2": 0.00019, "Ti0": 20.0, "Tm0": 12.0,
}

#: UA-value [W/K] and internal heat capacity CI [MJ/K] of table 7.1.
TEST_CELL_DERIVED = {"UA": "Hi*Hm/(Hi+Hm)", "CI": "(Ci + Hi*Cm/(Hm+Hi))*3600/1e6"}


def test_cell_model() -> Model:
    """The two-time-constant test-cell model (7.43)–(7.46), time in hours (library "test_cell")."""
    from ..library import load_model

    return load_model("test_cell")


def test_cell_inputs(n: int = 1512, seed: int = 0) -> pd.DataFrame:
    """Inputs of section 7.2: 20-minute sampling, PRBS heating (order 6, 8 h clock,
    0/300 W) and an outdoor surface temperature with a daily cycle and weather."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 3.0
    weather = np.cumsum(rng.normal(0.0, 0.08, n))
    weather -= np.linspace(weather[0], weather[-1], n)  # no drift over the experiment
    te = 8.0 + 5.0 * np.sin(2 * np.pi * (t - 9.0) / 24.0) + weather
    qh = prbs(6, clock=24, levels=(0.0, 300.0), length=n)
    return pd.DataFrame({"t": t, "Te": te, "Qh": qh})


#: Appendix A.7: a = 10, b = 1, c = 2, d = 10, σ² = 0.3, σ_m² = 0.03, N(0) = (2, 5).
LOTKA_VOLTERRA_PARAMETERS = {
    "a": 10.0, "b": 1.0, "c": 2.0, "d": 10.0, "s1": 0.3, "s2": 0.3, "m1": 0.03, "m2": 0.03,
    "N10": 2.0, "N20": 5.0,
}


def lotka_volterra_model() -> Model:
    """The stochastic Lotka–Volterra predator–prey model (A.66)–(A.69) (library "lotka_volterra")."""
    from ..library import load_model

    return load_model("lotka_volterra")


def lotka_volterra_times(n: int = 500, step: float = 0.005) -> np.ndarray:
    """Sampling times of A.7 (sampling time 0.005)."""
    return np.arange(n) * step
