"""Agreement between filters, discretization against the moment equations, stiff models."""

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp

import greyid
from greyid.filters import discretize
from conftest import random_linear_parameters
from test_kalman_dense import random_data


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("method", ["ekf", "iekf", "ukf", "ekf2"])
def test_nonlinear_filters_reduce_to_kalman_on_linear_model(linear_model, method, hold):
    rng = np.random.default_rng(11)
    params, _ = random_linear_parameters(rng)
    df, *_ = random_data(rng, N=40)
    ref = linear_model.loglik(params, df, hold=hold, method="kalman")
    for form in ("sqrt", "plain"):
        ll = linear_model.loglik(params, df, hold=hold, method=method, form=form, substeps=3)
        assert ll == pytest.approx(ref, rel=1e-9), (method, form)


def test_filter_result_forms_agree(linear_model):
    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    df, *_ = random_data(rng, N=40)
    a = linear_model.filter(params, df, form="sqrt")
    b = linear_model.filter(params, df, form="plain")
    np.testing.assert_allclose(a.filtered.to_numpy(), b.filtered.to_numpy(), rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(a.predicted_cov, b.predicted_cov, rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(a.filtered_cov, b.filtered_cov, rtol=1e-8, atol=1e-11)


@pytest.mark.parametrize("foh", [0.0, 1.0])
def test_van_loan_matches_fine_integration_of_moment_equations(foh):
    """Φm + Γb₀ + Υ(b₁−b₀) and ΦPΦᵀ + Λ solve (4.30)–(4.31) over one interval."""
    rng = np.random.default_rng(0)
    n = 3
    A = rng.normal(size=(n, n)) - 1.5 * np.eye(n)
    G = rng.normal(size=(n, 2))
    Q = G @ G.T
    m0, b0, b1 = rng.normal(size=n), rng.normal(size=n), rng.normal(size=n)
    M = rng.normal(size=(n, n))
    P0 = M @ M.T
    tau = 1.3

    def rhs(s, z):
        m, P = z[:n], z[n:].reshape(n, n)
        b = b0 + foh * (s / tau) * (b1 - b0)
        return np.concatenate([A @ m + b, (A @ P + P @ A.T + Q).reshape(-1)])

    sol = solve_ivp(rhs, (0, tau), np.concatenate([m0, P0.reshape(-1)]), rtol=1e-12, atol=1e-13, method="DOP853")
    d = discretize(A, Q, tau)
    m = np.asarray(d.transition @ m0 + d.input_gain @ b0 + foh * d.ramp_gain @ (b1 - b0))
    P = np.asarray(d.transition @ P0 @ d.transition.T + d.noise_covariance)
    np.testing.assert_allclose(m, sol.y[:n, -1], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(P, sol.y[n:, -1].reshape(n, n), rtol=1e-9, atol=1e-10)


def test_discretizations_of_several_steps_match_one_at_a_time():
    """discretize_each, which skips zero steps and runs only the doublings each step needs,
    equals discretize per step, in value and in derivative with respect to A."""
    import jax
    from greyid.filters.discretize import discretize_each

    rng = np.random.default_rng(3)
    n = 2
    A = rng.normal(size=(n, n)) - 2.0 * np.eye(n)
    G = rng.normal(size=(n, n))
    Q = G @ G.T
    taus = np.array([0.0, 0.01, 0.0, 1e3])  # zero padding, no doubling, a dozen doublings
    each = discretize_each(A, Q, taus)
    for k, tau in enumerate(taus):
        one = discretize(A, Q, tau)
        for a, b in zip(each, one):
            np.testing.assert_allclose(a[k], b, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(each.transition[0], np.eye(n))
    np.testing.assert_array_equal(each.noise_covariance[2], np.zeros((n, n)))

    def summary(fun):
        return lambda A: sum(x.sum() for x in jax.tree_util.tree_leaves(fun(A)))
    grad_each = jax.grad(summary(lambda A: discretize_each(A, Q, taus)))(A)
    grad_one = jax.grad(summary(lambda A: [discretize(A, Q, t) for t in taus]))(A)
    np.testing.assert_allclose(grad_each, grad_one, rtol=1e-10, atol=1e-12)


@pytest.fixture(scope="module")
def stiff_model():
    """Indoor air (time constant ~2 min) against a heavy medium (~7 years): eigenvalue ratio > 1e6."""
    m = greyid.Model("stiff")
    m.add_system("dTi = (1/(Ci*Ri)*(Tm-Ti) + 1/(Ci*Ra)*(Ta-Ti) + Ph/Ci)*dt + exp(p1)*dw1")
    m.add_system("dTm = (1/(Cm*Ri)*(Ti-Tm))*dt + exp(p2)*dw2")
    m.add_inputs("Ta", "Ph")
    m.add_observation("y = Ti", variance="exp(e1)")
    m.set_initial_state(mean={"Ti": 20.0, "Tm": 20.0}, covariance=[[1.0, 0.0], [0.0, 1.0]])
    return m


def test_square_root_filter_stays_positive_definite_on_stiff_model(stiff_model):
    params = dict(Ci=0.02, Cm=5000.0, Ri=2.0, Ra=10.0, p1=-3.0, p2=-12.0, e1=-9.0)
    A = np.array([[-(1 / (0.02 * 2) + 1 / (0.02 * 10)), 1 / (0.02 * 2)], [1 / (5000 * 2), -1 / (5000 * 2)]])
    eig = np.abs(np.linalg.eigvals(A))
    assert eig.max() / eig.min() > 1e6
    rng = np.random.default_rng(1)
    N = 20000
    t = np.arange(N) * 1.0  # hours
    df = pd.DataFrame({"t": t, "Ta": 5 + 3 * np.sin(2 * np.pi * t / 24), "Ph": 0.1 * (rng.random(N) > 0.5)})
    sim = stiff_model.simulate(params, df, method="exact", seed=3)
    df["y"] = sim.outputs[0, :, 0]
    res = stiff_model.filter(params, df, form="sqrt")
    assert np.isfinite(res.loglik)
    for covs in (res.filtered_cov, res.predicted_cov):
        assert np.all(np.isfinite(covs))
        assert np.all(np.linalg.eigvalsh(covs) > 0)
    plain = stiff_model.loglik(params, df, form="plain")
    assert plain == pytest.approx(res.loglik, rel=1e-7)
    # The innovations are standard normal when the model is right.
    z = res.standardized_innovations["y"].to_numpy()
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1) < 0.05


def test_ekf_converges_with_substeps_on_nonlinear_model():
    m = greyid.Model("logistic")
    m.add_system("dx = r*x*(1 - x/K)*dt + s*x*dw1")
    m.add_observation("y = log(x)", variance="e")
    m.set_initial_state(mean={"x": "x0"}, covariance=[[0.01]])
    assert m.kind == "nonlinear"
    params = dict(r=0.8, K=10.0, s=0.1, e=0.01, x0=1.0)
    sim = m.simulate(params, np.linspace(0, 15, 60), method="milstein", seed=2, substeps=50)
    df = sim.frame(0)
    lls = [m.loglik(params, df, method="ekf", substeps=k) for k in (4, 8, 16, 32)]
    diffs = np.abs(np.diff(lls))
    assert diffs[-1] < diffs[0] / 4  # first-order convergence of the sub-sampling
    # UKF and IEKF against an exact likelihood: test_nonlinear_filters_on_geometric_brownian_motion.


def gbm_models():
    """Geometric Brownian motion observed in log, and the same process written in log (linear)."""
    gbm = greyid.Model("gbm")
    gbm.add_system("dX = mu*X*dt + sigma*X*dw1")
    gbm.add_observation("y = log(X)", variance="e")
    gbm.set_initial_state(mean={"X": 1.0}, covariance=[[1e-12]])
    log = greyid.Model("log_gbm")
    log.add_system("dz = (mu - sigma^2/2)*dt + sigma*dw1")
    log.add_observation("y = z", variance="e")
    log.set_initial_state(mean={"z": 0.0}, covariance=[[1e-12]])
    for m in (gbm, log):
        m.set_parameter("mu", init=0.05)
        m.set_parameter("sigma", init=0.1, lower=0.0)
        m.set_parameter("e", init=1e-3, lower=0.0)
    return gbm, log


def test_nonlinear_filters_on_geometric_brownian_motion():
    """log X is Brownian motion with drift, so the exact likelihood is the Kalman filter's in log X;
    the EKF, IEKF and UKF approach it as the noise (the nonlinearity) shrinks, and their fits agree."""
    gbm, log = gbm_models()
    times = pd.DataFrame({"t": np.linspace(0, 10, 101)})
    errors = {}
    for sigma in (0.05, 0.0125):
        p = dict(mu=0.1, sigma=sigma, e=1e-4)
        df = log.simulate(p, times, method="exact", seed=4).frame(0)
        exact = log.loglik(p, df)
        errors[sigma] = {method: abs(gbm.loglik(p, df, method=method) - exact) for method in ("ekf", "iekf", "ukf")}
    for method in ("ekf", "iekf", "ukf"):
        assert errors[0.05][method] < 0.15 and errors[0.0125][method] < 0.015, (method, errors)
    p = dict(mu=0.1, sigma=0.05, e=1e-4)
    df = log.simulate(p, times, method="exact", seed=4).frame(0)
    exact_fit = log.fit(df)
    for method in ("ekf", "iekf", "ukf"):
        fit = gbm.fit(df, method=method)
        assert fit.converged, method
        for name in ("mu", "sigma", "e"):
            assert abs(fit.values[name] - exact_fit.values[name]) < 0.1 * exact_fit.bse[name], (method, name)
            assert fit.bse[name] == pytest.approx(exact_fit.bse[name], rel=0.03), (method, name)


def test_filter_starts_with_update_at_first_row(linear_model):
    rng = np.random.default_rng(9)
    params, mats = random_linear_parameters(rng)
    df, *_ = random_data(rng, N=20, missing=0.0)
    res = linear_model.filter(params, df)
    np.testing.assert_allclose(res.predicted.iloc[0].to_numpy(), mats["m0"], rtol=1e-12)
    np.testing.assert_allclose(res.predicted_cov[0], mats["P0"], rtol=1e-10)


def test_stationary_and_process_initial_covariance():
    m = greyid.Model("ou")
    m.add_system("dx = -a*x*dt + s*dw1")
    m.add_observation("y = x", variance="0.1")
    m.set_initial_state(mean={"x": 0.0}, covariance="stationary")
    df = pd.DataFrame({"t": [0.0, 0.5, 1.0], "y": [0.1, -0.2, 0.3]})
    res = m.filter(dict(a=2.0, s=1.0), df)
    assert res.predicted_cov[0, 0, 0] == pytest.approx(1.0 / 4.0, rel=1e-12)  # s²/(2a)
    m.set_initial_state(mean={"x": 0.0}, covariance="process", scale=3.0)
    res = m.filter(dict(a=2.0, s=1.0), df)
    assert res.predicted_cov[0, 0, 0] == pytest.approx(3.0 * (1 - np.exp(-2 * 2.0 * 0.5)) / (2 * 2.0), rel=1e-12)


def test_loglik_gradient_matches_finite_differences(building):
    import jax
    import jax.numpy as jnp
    from greyid.data import prepare_series
    from greyid.filters.api import compiled_filter, filter_inputs, filter_options

    model, params, data = building
    s = model.structure
    data = data.iloc[:200]
    inputs = filter_inputs(prepare_series(data, s.input_names, s.output_names), "foh")
    theta = jnp.asarray(model.parameter_vector(params))
    for method in ("kalman", "ekf"):
        run = compiled_filter(s, filter_options(s, method), keep_outputs=False)
        def f(th):
            return run(th, inputs)[0].loglik.sum()
        g = np.asarray(jax.grad(f)(theta))
        eps = 1e-6 * np.maximum(np.abs(np.asarray(theta)), 1.0)
        fd = np.array([(f(theta.at[i].add(eps[i])) - f(theta.at[i].add(-eps[i]))) / (2 * eps[i])
                       for i in range(len(theta))])
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-4)


def test_bias_corrected_and_unscented_predictions_of_a_quadratic_observation():
    """For x ~ N(m, P) and y = x², E y = m² + P: (4.60) and the unscented transform are exact."""
    m = greyid.Model("square")
    m.add_system("dx = -a*x*dt + s*dw1")
    m.add_observation("y = x^2", variance="r")
    m.set_initial_state(mean={"x": "m0"}, covariance=[["p0"]])
    p = dict(a=1.0, s=0.5, r=0.1, m0=1.5, p0=0.3)
    df = pd.DataFrame({"t": [0.0, 1.0], "y": [2.0, 1.0]})
    for method, expected in (("ekf2", 1.5**2 + 0.3), ("ukf", 1.5**2 + 0.3), ("ekf", 1.5**2)):
        res = m.filter(p, df, method=method)
        assert res.output_predictions["y"].iloc[0] == pytest.approx(expected, rel=1e-12), method


@pytest.mark.parametrize("method", ["ekf", "iekf", "ukf"])
def test_smoothers_of_nonlinear_filters_beat_their_filters(method):
    """On geometric Brownian motion with noisy log observations, the smoothed states lie closer
    to the simulated truth than the filtered ones (RMSE), for every filter."""
    gbm, _ = gbm_models()
    p = dict(mu=0.1, sigma=0.2, e=0.1**2)
    sim = gbm.simulate(p, np.linspace(0, 10, 201), method="milstein", substeps=50, seed=7)
    df = sim.frame(0)
    truth = sim.states[0, :, 0]
    smoothed = gbm.smooth(p, df, method=method)
    filtered = gbm.filter(p, df, method=method)
    def rmse(x):
        return np.sqrt(np.mean((np.log(x) - np.log(truth)) ** 2))
    assert rmse(smoothed.smoothed["X"].to_numpy()) < 0.9 * rmse(filtered.filtered["X"].to_numpy())
