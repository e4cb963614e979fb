"""Correlated measurement noise: the filters against the dense Gaussian likelihood."""

import numpy as np
import pandas as pd
import pytest
from scipy.stats import multivariate_normal

import greyid
from conftest import dense_moments

TRUE = dict(a11=-0.6, a12=0.3, a21=0.2, a22=-0.9, b1=1.0, g1=0.4, g2=0.3, s1=0.05, s2=0.08, c12=0.04)


def correlated_model():
    m = greyid.Model("two_sensors")
    m.add_system("dx1 = (a11*x1 + a12*x2 + b1*u)*dt + g1*dw1")
    m.add_system("dx2 = (a21*x1 + a22*x2)*dt + g2*dw2")
    m.add_inputs("u")
    m.add_observation("y1 = x1", variance="s1")
    m.add_observation("y2 = x1 + x2", variance="s2")
    m.set_observation_covariance([["s1", "c12"], ["c12", "s2"]])
    m.set_initial_state(mean={"x1": 0.5, "x2": -0.2}, covariance=[[0.3, 0.05], [0.05, 0.2]])
    for name, value in TRUE.items():
        m.set_parameter(name, init=value)
    return m


def dense_loglik(p, t, U, Y):
    A = np.array([[p["a11"], p["a12"]], [p["a21"], p["a22"]]])
    mats = dict(A=A, B=np.array([[p["b1"]], [0.0]]), c=np.zeros(2), G=np.diag([p["g1"], p["g2"]]),
                H=np.array([[1.0, 0.0], [1.0, 1.0]]), D=np.zeros((2, 1)), S=np.zeros(2),
                P0=np.array([[0.3, 0.05], [0.05, 0.2]]), m0=np.array([0.5, -0.2]))
    _, _, _, mean, cov = dense_moments(mats, t, U, foh=0.0)
    S = np.array([[p["s1"], p["c12"]], [p["c12"], p["s2"]]])
    cov = cov + np.kron(np.eye(len(t)), S)
    observed = ~np.isnan(Y.reshape(-1))
    return multivariate_normal(mean[observed], cov[np.ix_(observed, observed)]).logpdf(Y.reshape(-1)[observed])


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(3)
    N = 30
    t = np.cumsum(rng.uniform(0.3, 1.2, N))
    U = rng.normal(size=(N, 1))
    Y = rng.normal(size=(N, 2))
    Y[rng.random((N, 2)) < 0.2] = np.nan  # per-element missing values
    df = pd.DataFrame({"t": t, "u": U[:, 0], "y1": Y[:, 0], "y2": Y[:, 1]})
    return correlated_model(), df, t, U, Y


@pytest.mark.parametrize("method", ["kalman", "ekf", "iekf", "ukf"])
@pytest.mark.parametrize("form", ["sqrt", "plain"])
def test_loglik_equals_dense_gaussian(case, method, form):
    m, df, t, U, Y = case
    reference = dense_loglik(TRUE, t, U, Y)
    assert m.loglik(TRUE, df, method=method, form=form) == pytest.approx(reference, rel=1e-8)
    # Without the correlation the likelihood is a different one.
    assert abs(m.loglik(dict(TRUE, c12=0.0), df, method=method, form=form) - reference) > 1e-3


def test_innovations_and_their_covariance_are_in_output_coordinates(case):
    m, df, *_ = case
    res = m.filter(TRUE, df)
    both = df[["y1", "y2"]].notna().all(axis=1).to_numpy()
    k = int(np.flatnonzero(both)[3])
    R = res.innovation_cov[k]
    P = res.predicted_cov[k]
    H = np.array([[1.0, 0.0], [1.0, 1.0]])
    S = np.array([[TRUE["s1"], TRUE["c12"]], [TRUE["c12"], TRUE["s2"]]])
    np.testing.assert_allclose(R, H @ P @ H.T + S, rtol=1e-10)
    np.testing.assert_allclose(res.innovations.iloc[k].to_numpy(),
                               df[["y1", "y2"]].iloc[k].to_numpy() - H @ res.predicted.iloc[k].to_numpy(), rtol=1e-10)


def test_fit_simulated_correlated_noise_and_model_file(tmp_path):
    m = correlated_model()
    times = pd.DataFrame({"t": np.arange(400) * 0.5,
                          "u": np.repeat(np.random.default_rng(1).choice([0.0, 1.0], 40), 10)})
    sim = m.simulate(TRUE, times, method="exact", seed=2)
    e = sim.outputs[0] - np.stack([sim.states[0, :, 0], sim.states[0, :, 0] + sim.states[0, :, 1]], axis=1)
    assert np.corrcoef(e.T)[0, 1] == pytest.approx(0.04 / np.sqrt(0.05 * 0.08), abs=0.12)
    data = times.assign(y1=sim.outputs[0, :, 0], y2=sim.outputs[0, :, 1])
    fit = m.fit(data)
    assert abs(fit.values["c12"] - TRUE["c12"]) < 3 * fit.bse["c12"]
    path = tmp_path / "two.toml"
    m.to_toml(path)
    again = greyid.Model.from_toml(path)
    assert again.loglik(TRUE, data) == pytest.approx(m.loglik(TRUE, data), rel=1e-12)


def test_observation_covariance_is_checked():
    m = correlated_model()
    m.set_observation_covariance([["s1", "c12"], ["c12", "2*s2"]])
    with pytest.raises(greyid.ModelError, match="diagonal entry for 'y2'"):
        m.structure
    m.set_observation_covariance([["s1", "c12"], ["0", "s2"]])
    with pytest.raises(greyid.ModelError, match="not symmetric"):
        m.structure
    m.set_observation_covariance([["s1", "c12"], ["c12", "s2"]])
    df = pd.DataFrame({"t": [0.0, 1.0], "u": [0.0, 0.0], "y1": [0.1, 0.2], "y2": [0.0, 0.3]})
    with pytest.raises(greyid.ModelError, match="not positive definite at row 0"):
        m.loglik(dict(TRUE, c12=1.0), df)
