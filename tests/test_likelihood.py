"""model.likelihood(data): the negative log-likelihood as a public object, against model.loglik, the fit,
central differences, a batched call, JAX's own grad, and SciPy's optimiser."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest
from scipy.optimize import minimize

import greyid
from greyid.datasets import building_model, load_building_data
from greyid.schema import check_options


@pytest.fixture(scope="module")
def problem():
    model, data = building_model(), load_building_data()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = model.fit(data)
    return model, data, fit, model.likelihood(data)


def test_value_is_the_negative_log_likelihood(problem):
    model, data, fit, nll = problem
    free = [n for n in model.parameter_names if not fit.params.loc[n, "fixed"]]
    assert nll.names == free
    x_hat = np.array([fit.values[n] for n in nll.names])
    assert nll.value(x_hat) == pytest.approx(-fit.loglik, rel=1e-10)
    x0 = nll.start()
    at_start = {**fit.values, **dict(zip(nll.names, x0))}
    assert nll.value(x0) == pytest.approx(-model.loglik(at_start, data), rel=1e-10)


def test_gradient_and_hessian_against_central_differences(problem):
    _, _, fit, nll = problem
    x = np.array([fit.values[n] for n in nll.names]) * 1.02
    value, gradient = nll.value_and_grad(x)
    assert value == pytest.approx(nll.value(x), rel=1e-12)
    h = 1e-6 * np.maximum(np.abs(x), 1e-3)
    central = np.array([(nll.value(x + h[i] * e) - nll.value(x - h[i] * e)) / (2 * h[i])
                        for i, e in enumerate(np.eye(len(x)))])
    np.testing.assert_allclose(gradient, central, rtol=1e-5, atol=1e-6 * np.abs(central).max())
    hessian = nll.hessian(x)
    rows = np.array([(nll.value_and_grad(x + h[i] * e)[1] - nll.value_and_grad(x - h[i] * e)[1]) / (2 * h[i])
                     for i, e in enumerate(np.eye(len(x)))])
    np.testing.assert_allclose(hessian, rows, rtol=1e-4, atol=1e-6 * np.abs(rows).max())
    np.testing.assert_allclose(hessian, hessian.T, rtol=1e-10, atol=1e-10 * np.abs(hessian).max())


def test_a_2d_x_evaluates_each_row_and_jax_composes(problem):
    _, _, fit, nll = problem
    x = np.array([fit.values[n] for n in nll.names])
    rng = np.random.default_rng(0)
    batch = x * (1 + 0.01 * rng.normal(size=(4, len(x))))
    values = nll.value(batch)
    np.testing.assert_allclose(values, [nll.value(row) for row in batch], rtol=1e-12)
    values_b, gradients_b = nll.value_and_grad(batch)
    np.testing.assert_allclose(gradients_b[2], nll.value_and_grad(batch[2])[1], rtol=1e-10)
    own = jax.jit(jax.grad(nll.function()))(batch[1])
    np.testing.assert_allclose(own, gradients_b[1], rtol=1e-8)


def test_unconstrained_coordinates(problem):
    _, _, fit, nll = problem
    x = np.array([fit.values[n] for n in nll.names])
    z = nll.to_unconstrained(x)
    np.testing.assert_allclose(nll.from_unconstrained(z), x, rtol=1e-12)
    assert nll.value(z, unconstrained=True) == pytest.approx(nll.value(x), rel=1e-12)
    dtheta_dz = nll._transform.derivative(z)
    np.testing.assert_allclose(nll.value_and_grad(z, unconstrained=True)[1], nll.value_and_grad(x)[1] * dtheta_dz,
                               rtol=1e-8, atol=1e-10)


def test_scipy_finds_the_fits_optimum(problem):
    _, _, fit, nll = problem
    z0 = nll.to_unconstrained(nll.start())
    result = minimize(lambda z: nll.value_and_grad(z, unconstrained=True), z0, jac=True, method="BFGS",
                      options={"gtol": 1e-8, "maxiter": 2000})
    assert -result.fun == pytest.approx(fit.loglik, abs=1e-4)


def test_bad_x_is_named(problem):
    *_, nll = problem
    with pytest.raises(greyid.ModelError, match="free parameters"):
        nll.value(np.zeros(len(nll.names) + 1))


def test_a_sampler_runs_on_the_function(problem):
    """BlackJAX's NUTS on −f(z): the documented sampler example, a few steps from the optimum."""
    blackjax = pytest.importorskip("blackjax")
    _, _, fit, nll = problem
    f = nll.function(unconstrained=True)
    z_hat = nll.to_unconstrained(np.array([fit.values[n] for n in nll.names]))
    mass = np.linalg.inv(nll.hessian(z_hat, unconstrained=True))
    nuts = blackjax.nuts(lambda z: -f(z), step_size=0.5, inverse_mass_matrix=np.diag(mass))
    state = nuts.init(z_hat)
    step = jax.jit(nuts.step)
    keys = jax.random.split(jax.random.key(0), 20)
    draws = []
    for key in keys:
        state, _ = step(key, state)
        draws.append(np.asarray(state.position))
    values = [nll.value(z, unconstrained=True) for z in draws]
    assert np.all(np.isfinite(values)) and max(values) < -fit.loglik + 30


def test_a_fit_with_the_steady_state_finds_the_same_optimum(problem):
    """model.fit(steady_state=True): the fit's programs switch shorter series to the steady state where
    the filter settles — the same estimates, log-likelihood and covariance as stepping through every row,
    the setting kept with the fit for what reruns its filter; with several starts each runs alone."""
    model, data, fit, _ = problem
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        steady = model.fit(data, steady_state=True)
        two = model.fit(data, steady_state=True, starts=2)
    assert steady.settings["steady_state"] is True and fit.settings["steady_state"] is False
    assert steady.converged and steady.loglik == pytest.approx(fit.loglik, abs=1e-8)
    np.testing.assert_allclose(steady.params["estimate"], fit.params["estimate"], rtol=1e-6)
    np.testing.assert_allclose(steady.cov.to_numpy(), fit.cov.to_numpy(), rtol=1e-4,
                               atol=1e-8 * np.abs(fit.cov.to_numpy()).max())
    assert steady._filter_settings()["steady_state"] is True
    assert two.loglik == pytest.approx(fit.loglik, abs=1e-8)
    every_row = model.likelihood(data, steady_state=False)
    x = np.array([fit.values[n] for n in every_row.names])
    assert every_row.value(x) == pytest.approx(-fit.loglik, rel=1e-12)


def test_fleets_and_populations_refuse_the_steady_state(problem):
    model, data, _, _ = problem
    with pytest.raises(greyid.errors.ModelError, match="steady_state=True is for single fits"):
        greyid.fit_many(model, {"a": data, "b": data}, steady_state=True)
    with pytest.raises(greyid.errors.ModelError, match="steady_state=True is for single fits"):
        greyid.fit_population(model, {"a": data, "b": data}, random={model.parameter_names[0]: "normal"},
                              steady_state=True)
    with pytest.raises(greyid.errors.ModelError, match="steady_state must be True or False, got 'yes'"):
        model.fit(data, steady_state="yes")
    with pytest.raises(greyid.errors.ModelError, match="setting 'steady_state' must be true or false"):
        check_options({"steady_state": "yes"})
