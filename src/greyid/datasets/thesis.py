"""Models and experiments of the thesis' validation studies (section 7.2, appendix A.7)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..model import Model
from ..simulate.signals import prbs

#: Section 7.2: H in W/K, C in Wh/K, incremental variances in K² per hour.
TEST_CELL_PARAMETERS = {
    "Hi": 55.29, "Hm": 13.86, "Ci": 325.0, "Cm": 387.8,
    "s1i": 0.00167, "s1m": 0.00978, "s2": 0.00019, "Ti0": 20.0, "Tm0": 12.0,
}

#: UA-value [W/K] and internal heat capacity CI [MJ/K] of table 7.1.
TEST_CELL_DERIVED = {"UA": "Hi*Hm/(Hi+Hm)", "CI": "(Ci + Hi*Cm/(Hm+Hi))*3600/1e6"}


def test_cell_model() -> Model:
    """The two-time-constant test-cell model (7.43)–(7.46), time in hours."""
    m = Model("test_cell")
    m.add_system("dTi = (Hi/Ci*(Tm - Ti) + Qh/Ci)*dt + sqrt(s1i)*dw1")
    m.add_system("dTm = (Hi/Cm*(Ti - Tm) + Hm/Cm*(Te - Tm))*dt + sqrt(s1m)*dw2")
    m.add_inputs("Te", "Qh")
    m.add_observation("Ttr = Ti", variance="s2")
    m.set_initial_state(mean={"Ti": "Ti0", "Tm": "Tm0"}, covariance="process")
    inits = {
        "Hi": (40.0, 1.0, 500.0), "Hm": (10.0, 0.1, 200.0), "Ci": (250.0, 10.0, 5000.0),
        "Cm": (300.0, 10.0, 5000.0), "s1i": (0.003, 1e-7, 1.0), "s1m": (0.005, 1e-7, 1.0),
        "s2": (0.0005, 1e-8, 1.0), "Ti0": (20.0, 0.0, 40.0), "Tm0": (15.0, -10.0, 40.0),
    }
    for name, (init, lower, upper) in inits.items():
        m.set_parameter(name, init=init, lower=lower, upper=upper)
    return m


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
    """The stochastic Lotka–Volterra predator–prey model (A.66)–(A.69)."""
    m = Model("lotka_volterra")
    m.add_system("dN1 = (a*N1 - b*N1*N2)*dt + sqrt(s1)*dw1")
    m.add_system("dN2 = (c*N1*N2 - d*N2)*dt + sqrt(s2)*dw2")
    m.add_observation("y1 = N1", variance="m1")
    m.add_observation("y2 = N2", variance="m2")
    m.set_initial_state(mean={"N1": "N10", "N2": "N20"}, covariance=[[0.01, 0.0], [0.0, 0.01]])
    inits = {
        "a": (8.0, 0.1, 100.0), "b": (0.8, 0.01, 10.0), "c": (1.6, 0.01, 20.0), "d": (8.0, 0.1, 100.0),
        "s1": (0.2, 1e-4, 10.0), "s2": (0.2, 1e-4, 10.0), "m1": (0.05, 1e-5, 1.0), "m2": (0.05, 1e-5, 1.0),
        "N10": (2.0, 0.01, 20.0), "N20": (5.0, 0.01, 20.0),
    }
    for name, (init, lower, upper) in inits.items():
        m.set_parameter(name, init=init, lower=lower, upper=upper)
    return m


def lotka_volterra_times(n: int = 500, step: float = 0.005) -> np.ndarray:
    """Sampling times of A.7 (sampling time 0.005)."""
    return np.arange(n) * step
