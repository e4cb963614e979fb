"""Filters at their edges: a known initial state (P0 = 0), a noise-free state, and observations that
drive a second-order update's variance negative."""

import warnings

import numpy as np
import pandas as pd
import pytest

import greyid

METHODS = ["kalman", "ekf", "iekf", "ukf", "ekf2", "truncated2", "gaussian2"]


def two_tank(covariance):
    """A linear two-state model whose second state has no noise of its own."""
    m = greyid.Model("tanks")
    m.add_inputs("u")
    m.add_system("dx1 = (-a*x1 + u)*dt + s*dw1", "dx2 = (a*x1 - b*x2)*dt")
    m.add_observation("y = x2", variance="r")
    m.set_initial_state(mean={"x1": 1.0, "x2": 0.5}, covariance=covariance)
    return m


@pytest.mark.parametrize("covariance", [[[0.0, 0.0], [0.0, 0.0]], [[0.3, 0.0], [0.0, 0.0]]])
def test_every_filter_is_exact_with_a_known_initial_state_and_a_noise_free_state(covariance):
    rng = np.random.default_rng(11)
    n = 40
    data = pd.DataFrame({"t": np.arange(n) * 0.5, "u": rng.normal(size=n), "y": rng.normal(size=n)})
    params = dict(a=0.7, b=0.4, s=0.3, r=0.05)
    m = two_tank(covariance)
    exact = m.filter(params, data, method="kalman")
    for method in METHODS:
        for form in ("plain", "sqrt"):
            with warnings.catch_warnings():
                warnings.simplefilter("error", greyid.errors.FilterWarning)
                result = m.filter(params, data, method=method, form=form, substeps=1)
            assert np.all(np.isfinite(result.filtered_cov)) and np.all(np.isfinite(result.loglik_terms))
            variances = np.diagonal(result.filtered_cov, axis1=1, axis2=2)
            assert np.all(variances >= -1e-14), (method, form)
            # Linear model: every filter is the Kalman filter (the UKF's slope along the unspread state
            # is the Jacobian, its limit).
            assert result.loglik == pytest.approx(exact.loglik, rel=1e-9, abs=1e-9), (method, form)
            np.testing.assert_allclose(result.filtered_cov, exact.filtered_cov, atol=1e-10)


def test_the_truncated_second_order_update_cannot_go_negative():
    """h = x², prior N(1, 0.2), y = 1.5, S = 0.01: R = 0.77 > 0, but P − K R Kᵀ = −0.0078.  The guard
    takes the Joseph form (1 − K H)² P + K² S instead, and says so."""
    m = greyid.Model("square")
    m.add_system("dx = 0*x*dt + s*dw1")
    m.add_observation("y = x^2", variance="r")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.2]])
    data = pd.DataFrame({"t": [0.0], "y": [1.5]})
    P, H, S = 0.2, 2.0, 0.01
    R = H * P * H + S - 0.25 * (2.0 * P) ** 2
    K = P * H / R
    assert R == pytest.approx(0.77) and P - K * R * K == pytest.approx(-0.0078, abs=1e-4)
    joseph = (1 - K * H) ** 2 * P + K**2 * S
    for form in ("plain", "sqrt"):
        with pytest.warns(greyid.errors.FilterWarning, match="first row 0"):
            result = m.filter(dict(s=0.0, r=S), data, method="truncated2", form=form)
        assert result.innovation_cov[0, 0, 0] == pytest.approx(R)
        assert result.filtered_cov[0, 0, 0] == pytest.approx(joseph, rel=1e-10)
        assert result.guarded.tolist() == [True]
    # The Gaussian second-order filter keeps the fourth moments: no guard needed, none taken.
    with warnings.catch_warnings():
        warnings.simplefilter("error", greyid.errors.FilterWarning)
        result = m.filter(dict(s=0.0, r=S), data, method="gaussian2")
    assert result.filtered_cov[0, 0, 0] > 0 and result.guarded.tolist() == [False]
