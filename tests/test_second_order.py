"""The modified truncated and Gaussian second-order filters (section 4.2.2) against exact moments."""

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

import greyid
from conftest import dense_reference, random_linear_parameters
from test_kalman_dense import random_data


def squared_observation():
    m = greyid.Model("squared")
    m.add_system("dx = a*(2 - x)*dt + s*dw1")
    m.add_observation("y = x^2", variance="e")
    m.set_initial_state(mean={"x": "m0"}, covariance=[["P0"]])
    return m


@pytest.mark.parametrize("y", [0.3, 1.5, 2.4])
def test_update_of_a_squared_observation_uses_exact_gaussian_moments(y):
    """x ~ N(m, P), y = x² + e: E[y] = m² + P and Var(y) = 4m²P + 2P² + S exactly (Gaussian fourth
    moments), which the Gaussian filter uses; the truncated one drops the fourth moments (−P²)."""
    m = squared_observation()
    p = dict(a=1.0, s=0.5, e=0.1, m0=1.0, P0=0.2)
    df = pd.DataFrame({"t": [0.0], "y": [y]})
    mean, P, S = p["m0"], p["P0"], p["e"]
    gaussian = norm.logpdf(y, mean**2 + P, np.sqrt(4 * mean**2 * P + 2 * P**2 + S))
    truncated = norm.logpdf(y, mean**2 + P, np.sqrt(4 * mean**2 * P - P**2 + S))
    assert m.loglik(p, df, method="gaussian2") == pytest.approx(gaussian, rel=1e-12)
    assert m.loglik(p, df, method="truncated2") == pytest.approx(truncated, rel=1e-12)
    assert abs(m.loglik(p, df, method="ekf") - gaussian) > 1e-3  # the EKF ignores the curvature


def test_prediction_of_geometric_brownian_motion_follows_the_exact_moments():
    """dX = μX dt + σX dω: d/dt E[X] = μE[X], d/dt Var = 2μVar + σ²(E[X]² + Var) hold exactly, and the
    second-order filters' ĜGᵀ = σ²(x̂² + P) is exact; the EKF's σ²x̂² is not (17 % low here)."""
    m = greyid.Model("gbm")
    m.add_system("dX = mu*X*dt + sigma*X*dw1")
    m.add_observation("y = log(X)", variance="e")
    m.set_initial_state(mean={"X": 1.0}, covariance=[[0.04]])
    p = dict(mu=0.3, sigma=0.4, e=1e-4)
    df = pd.DataFrame({"t": np.linspace(0, 2, 5), "y": [np.nan] * 4 + [0.1]})
    t, m0, P0 = 2.0, 1.0, 0.04
    mean = m0 * np.exp(p["mu"] * t)
    variance = (m0**2 + P0) * np.exp((2 * p["mu"] + p["sigma"] ** 2) * t) - m0**2 * np.exp(2 * p["mu"] * t)
    for method in ("gaussian2", "truncated2"):
        res = m.filter(p, df, method=method, substeps=256)
        assert res.predicted["X"].iloc[-1] == pytest.approx(mean, rel=1e-10)
        assert res.predicted_cov[-1, 0, 0] == pytest.approx(variance, rel=2e-3), method
    ekf = m.filter(p, df, method="ekf", substeps=256)
    assert ekf.predicted_cov[-1, 0, 0] < 0.9 * variance


@pytest.mark.parametrize("method", ["truncated2", "gaussian2"])
def test_second_order_filters_are_exact_on_linear_models(linear_model, method):
    rng = np.random.default_rng(11)
    params, mats = random_linear_parameters(rng)
    df, t, U, Y = random_data(rng)
    reference, _, _ = dense_reference(mats, t, U, Y, foh=0.0)
    assert linear_model.loglik(params, df, method=method) == pytest.approx(reference, rel=1e-8)


def test_gaussian_second_order_fit():
    """A fit through the Gaussian second-order filter recovers the parameters of a model with a
    squared observation (within 4 standard errors of the truth)."""
    m = squared_observation()
    truth = dict(a=0.5, s=0.3, e=0.05, m0=2.0, P0=0.05)
    for name, value in truth.items():
        m.set_parameter(name, init=value * 1.3, lower=0.0 if name in ("a", "s", "e", "P0") else None)
    m.fix_parameter("P0", 0.05)
    times = pd.DataFrame({"t": np.arange(400) * 0.25})
    df = m.simulate(truth, times, method="milstein", substeps=20, seed=3).frame(0)
    fit = m.fit(df, method="gaussian2")
    assert fit.converged and fit.settings["method"] == "gaussian2"
    for name in ("a", "s", "e"):
        assert abs(fit.values[name] - truth[name]) < 4 * fit.bse[name], name
