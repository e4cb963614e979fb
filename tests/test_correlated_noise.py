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


@pytest.fixture(scope="module")
def simulated():
    """60 rows of the model itself (exact scheme), a fifth of the values missing."""
    m = correlated_model()
    rng = np.random.default_rng(8)
    t = np.cumsum(rng.uniform(0.3, 1.2, 60))
    frame = pd.DataFrame({"t": t, "u": rng.normal(size=60)})
    sim = m.simulate(TRUE, frame, method="exact", seed=4).frame(0)
    Y = sim[["y1", "y2"]].to_numpy().copy()
    Y[rng.random(Y.shape) < 0.2] = np.nan
    df = frame.assign(y1=Y[:, 0], y2=Y[:, 1])
    return m, df, t, frame[["u"]].to_numpy(), Y


def rosenblatt(result):
    """The Kalman filter's innovations whitened by the Cholesky factor of their covariance, row by row: each
    output's one-step transform given the row's outputs before it."""
    eps, R = result.innovations.to_numpy(), result.innovation_cov
    z = np.full_like(eps, np.nan)
    for k in range(len(eps)):
        seen = ~np.isnan(eps[k])
        if seen.any():
            z[k, seen] = np.linalg.solve(np.linalg.cholesky(R[k][np.ix_(seen, seen)]), eps[k, seen])
    return z


@pytest.mark.slow
def test_laplace_method_with_correlated_noise(simulated):
    """The Laplace method on a linear Gaussian model is the exact likelihood; its one-step residuals (each output given
    the rows before and the row's outputs before it) are the Kalman filter's innovations whitened within the row: to
    rounding by the Gaussian predictive (the default), up to the tails' Laplace error by the "cdf" method (largest at
    the first row, whose prior is wide)."""
    from greyid.filters.api import laplace_residuals

    m, df, t, U, Y = simulated
    reference = dense_loglik(TRUE, t, U, Y)
    assert m.loglik(TRUE, df, method="laplace") == pytest.approx(reference, rel=1e-10)
    z = rosenblatt(m.filter(TRUE, df))
    gaussian = laplace_residuals(m, TRUE, df).to_numpy()
    assert np.array_equal(np.isnan(gaussian), np.isnan(z)) and np.nanmax(np.abs(gaussian - z)) < 1e-9
    residuals = laplace_residuals(m, TRUE, df, one_step="cdf").to_numpy()
    assert np.array_equal(np.isnan(residuals), np.isnan(z))
    assert np.nanmax(np.abs(residuals - z)) < 0.1 and np.nanmax(np.abs(residuals - z)[1:]) < 0.06


@pytest.mark.parametrize("proposal", ["bootstrap", "ekf"])
def test_particle_filter_with_correlated_noise(simulated, proposal):
    from greyid.estimate.approximations import particle_loglik

    m, df, t, U, Y = simulated
    reference = dense_loglik(TRUE, t, U, Y)
    estimate = particle_loglik(m, TRUE, df, particles=2000, seed=1, proposal=proposal)
    assert abs(estimate.loglik - reference) < 3 * estimate.std_error + 0.05
    # Without the correlation the estimate moves away.
    independent = particle_loglik(m, dict(TRUE, c12=0.0), df, particles=2000, seed=1, proposal=proposal)
    assert abs(independent.loglik - reference) > 3 * independent.std_error + 1.0
    # Its quantile residuals: each output's own, as the Kalman filter's standardized innovations.
    residuals = m.filter(TRUE, df, method="particle", particles=4000, proposal="ekf").quantile_residuals.to_numpy()
    assert np.nanmax(np.abs(residuals - m.filter(TRUE, df).standardized_innovations.to_numpy())) < 0.15


def test_ensemble_kalman_filter_with_correlated_noise(simulated):
    """The ensemble's estimate approaches the exact value as it grows (seeds averaged), and it perturbs the
    observations with the correlated noise (without it the value is another)."""
    m, df, t, U, Y = simulated
    reference = dense_loglik(TRUE, t, U, Y)
    errors = {P: np.mean([abs(m.loglik(TRUE, df, method="enkf", particles=P, seed=s) - reference) for s in range(4)])
              for P in (50, 5000)}
    assert errors[5000] < 0.3 and errors[5000] < errors[50] / 3
    independent = m.loglik(dict(TRUE, c12=0.0), df, method="enkf", particles=5000)
    assert abs(independent - reference) > 1.0
