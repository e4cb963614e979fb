"""Time-varying linear models: the filter and the exact simulation against quadrature.

For dx = (−k(1 + 0.9 sin t)x + u)dt + s dω the transition over [a, b] is
Φ = exp(−∫_a^b k(1 + 0.9 sin v)dv) in closed form, and the input and noise
terms are one-dimensional integrals that SciPy's quad evaluates to 1e-13, so
the exact log-likelihood is a scalar Kalman filter in NumPy.
"""

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import quad

import greyid

TRUE = dict(k=0.7, s=0.4, r=0.01, x0=1.0)


def ltv_model():
    m = greyid.Model("ltv_sine")
    m.add_system("dx = (-k*(1 + 0.9*sin(t))*x + u)*dt + s*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": "x0"}, covariance=[[0.2]])
    for name, value in TRUE.items():
        m.set_parameter(name, init=value, lower=0.0 if name in ("s", "r") else None)
    return m


def decay(p, a, b):
    """∫_a^b k(1 + 0.9 sin v) dv."""
    return p["k"] * ((b - a) + 0.9 * (np.cos(a) - np.cos(b)))


def reference_loglik(p, df, foh):
    x, P, total = p["x0"], 0.2, 0.0
    t, u, y = (df[c].to_numpy() for c in ("t", "u", "y"))
    for i in range(len(t)):
        if i > 0:
            a, b = t[i - 1], t[i]
            def held(v):
                return u[i - 1] + foh * (u[i] - u[i - 1]) * (v - a) / (b - a)
            c = quad(lambda v: np.exp(-decay(p, v, b)) * held(v), a, b, epsabs=1e-13, epsrel=1e-13)[0]
            lam = quad(lambda v: np.exp(-2 * decay(p, v, b)) * p["s"] ** 2, a, b, epsabs=1e-13, epsrel=1e-13)[0]
            x, P = np.exp(-decay(p, a, b)) * x + c, np.exp(-2 * decay(p, a, b)) * P + lam
        R = P + p["r"]
        e = y[i] - x
        total += -0.5 * (np.log(2 * np.pi * R) + e**2 / R)
        x, P = x + P / R * e, P - P**2 / R
    return total


@pytest.fixture(scope="module")
def case():
    m = ltv_model()
    rng = np.random.default_rng(1)
    df = pd.DataFrame({"t": np.arange(100) * 1.0, "u": rng.normal(size=100)})
    df["y"] = m.simulate(TRUE, df, method="exact", substeps=50, seed=3).outputs[0, :, 0]
    return m, df


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_kalman_filter_of_time_varying_model_matches_quadrature(case, hold):
    m, df = case
    exact = reference_loglik(TRUE, df, foh=float(hold == "foh"))
    # Freezing A(t) at the start of each interval was off by 12 here.
    assert m.loglik(TRUE, df, hold=hold) == pytest.approx(exact, abs=0.03)  # automatic sub-steps
    assert m.loglik(TRUE, df, hold=hold, substeps=64) == pytest.approx(exact, abs=3e-4)
    # Second order: doubling the sub-steps divides the error by about four.
    errors = [abs(m.loglik(TRUE, df, hold=hold, substeps=n) - exact) for n in (4, 8)]
    assert 3.0 < errors[0] / errors[1] < 5.0


def test_ekf_of_time_varying_model_matches_quadrature(case):
    m, df = case
    exact = reference_loglik(TRUE, df, foh=0.0)
    assert m.loglik(TRUE, df, method="ekf") == pytest.approx(exact, abs=0.05)
    assert m.loglik(TRUE, df, method="ukf") == pytest.approx(exact, abs=0.05)


def test_fit_chooses_and_reports_substeps(case):
    m, df = case
    fit = m.fit(df)
    assert fit.settings["substeps"] > 1
    assert "sub-steps per interval (automatic" in fit.summary()
    fine = m.fit(df, substeps=64)
    for name in ("k", "s", "x0"):
        assert abs(fit.values[name] - fine.values[name]) < 0.1 * fine.bse[name], name
    assert fit.loglik == pytest.approx(reference_loglik(fit.values, df, 0.0), abs=0.03)
    assert "(as set)" in fine.summary()


def test_exact_simulation_of_time_varying_model(case):
    m, df = case
    sim = m.simulate(TRUE, df, method="exact", noise=False, substeps=8)
    x, t, u = TRUE["x0"], df["t"].to_numpy(), df["u"].to_numpy()
    expected = [x]
    for i in range(1, len(t)):
        a, b = t[i - 1], t[i]
        x = np.exp(-decay(TRUE, a, b)) * x + quad(lambda v: np.exp(-decay(TRUE, v, b)) * u[i - 1], a, b,
                                                  epsabs=1e-13, epsrel=1e-13)[0]
        expected.append(x)
    np.testing.assert_allclose(sim.states[0, :, 0], expected, atol=2e-3)
