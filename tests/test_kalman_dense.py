"""The Kalman log-likelihood equals the dense Gaussian likelihood of all observations."""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from conftest import dense_reference, random_linear_model_spec, random_linear_parameters


def random_data(rng, N=40, nu=2, ny=2, missing=0.2):
    t = np.cumsum(rng.uniform(0.2, 1.5, N)) + 3.0
    U = rng.normal(size=(N, nu))
    Y = rng.normal(size=(N, ny)) * 2.0
    Y[rng.random((N, ny)) < missing] = np.nan
    df = pd.DataFrame({"t": t, **{f"u{j + 1}": U[:, j] for j in range(nu)},
                       **{f"y{i + 1}": Y[:, i] for i in range(ny)}})
    return df, t, U, Y


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_kalman_equals_dense_gaussian(linear_model, seed, hold):
    rng = np.random.default_rng(seed)
    params, mats = random_linear_parameters(rng)
    df, t, U, Y = random_data(rng)
    assert linear_model.kind == "lti"
    ref, _, _ = dense_reference(mats, t, U, Y, foh=1.0 if hold == "foh" else 0.0)
    for form in ("sqrt", "plain"):
        ll = linear_model.loglik(params, df, hold=hold, form=form)
        assert ll == pytest.approx(ref, rel=1e-8), form


def test_smoother_equals_dense_conditional_mean(linear_model):
    rng = np.random.default_rng(42)
    params, mats = random_linear_parameters(rng)
    df, t, U, Y = random_data(rng, N=30)
    _, xs_ref, Ps_ref = dense_reference(mats, t, U, Y, foh=0.0)
    sm = linear_model.smooth(params, df)
    np.testing.assert_allclose(sm.smoothed.to_numpy(), xs_ref, rtol=1e-7, atol=1e-8)
    n = 3
    var_ref = np.array([np.diag(Ps_ref[k * n:(k + 1) * n, k * n:(k + 1) * n]) for k in range(len(t))])
    np.testing.assert_allclose(np.diagonal(sm.smoothed_cov, axis1=1, axis2=2), var_ref, rtol=1e-6, atol=1e-9)
    ekf = linear_model.smooth(params, df, method="ekf")
    np.testing.assert_allclose(ekf.smoothed.to_numpy(), xs_ref, rtol=1e-7, atol=1e-8)


def test_several_experiments_add_up(linear_model):
    rng = np.random.default_rng(7)
    params, _ = random_linear_parameters(rng)
    a, _, _, _ = random_data(rng, N=25)
    b, _, _, _ = random_data(rng, N=33)
    total = linear_model.loglik(params, [a, b])
    assert total == pytest.approx(linear_model.loglik(params, a) + linear_model.loglik(params, b), rel=1e-12)
    results = linear_model.filter(params, [a, b])
    assert len(results) == 2 and results[1].innovations.shape == (33, 2)


def test_data_sets_of_one_shape_run_through_one_vectorised_filter():
    """Data sets of one shape are evaluated together (jax.vmap, one filter in the program): the value, gradient
    and Hessian of three data sets (two of one shape) equal the sums over each data set alone."""
    from greyid.estimate.objective import summed_over_datasets

    rng = np.random.default_rng(8)
    params, _ = random_linear_parameters(rng)
    model = random_linear_model_spec()
    for name, value in params.items():
        model.set_parameter(name, init=value, fixed=name not in ("b11", "c1", "s1", "a22"))
    frames = [random_data(rng, N=25)[0], random_data(rng, N=25, missing=0.2)[0], random_data(rng, N=300)[0]]
    together = model.likelihood(frames, steady_state=False)
    x = np.array([params[name] for name in together.names])
    assert len(x) == 4
    f, g = together.value_and_grad(x)
    parts = [model.likelihood(frame, steady_state=False) for frame in frames]
    assert f == pytest.approx(sum(part.value(x) for part in parts), rel=1e-12)
    np.testing.assert_allclose(g, sum(part.value_and_grad(x)[1] for part in parts), rtol=1e-10,
                               atol=1e-12 * np.abs(g).max())
    H = together.hessian(x)
    np.testing.assert_allclose(H, sum(part.hessian(x) for part in parts), rtol=1e-9, atol=1e-12 * np.abs(H).max())
    # The grouping itself: one call of the criterion per shape, the same sum.
    calls = []

    def criterion(theta, data):
        calls.append(np.shape(data))
        return theta * jnp.sum(data)

    shaped = [jnp.ones(3), 2 * jnp.ones(3), jnp.ones(5)]
    assert float(summed_over_datasets(criterion, 2.0, shaped)) == 2.0 * (3 + 6 + 5)
    assert len(calls) == 2


def test_unobserved_elements_are_skipped(linear_model):
    rng = np.random.default_rng(3)
    params, _ = random_linear_parameters(rng)
    df, *_ = random_data(rng, N=30, missing=0.3)
    res = linear_model.filter(params, df)
    observed = df[["y1", "y2"]].notna().to_numpy()
    assert np.array_equal(res.innovations.notna().to_numpy(), observed)
    assert res.n_obs == observed.sum()
    assert res.loglik == pytest.approx(linear_model.loglik(params, df), rel=1e-12)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("case", ["known_initial_state", "tiny_variances"])
def test_singular_covariances_stay_finite_and_exact(linear_model, seed, case):
    """Noise-free states, P0 = 0 or 1e-18, and chains of 1e-5 intervals: both forms equal
    the dense Gaussian (the square-root form's factorisation met 0/0 pivots here)."""
    rng = np.random.default_rng(seed)
    params, mats = random_linear_parameters(rng)
    noisy = [0] if case == "tiny_variances" else []
    for i in range(3):
        if i not in noisy:
            mats["G"][i] = 0.0
            for j in range(2):
                params[f"g{i + 1}{j + 1}"] = 0.0
    mats["P0"] = np.eye(3) * (1e-18 if case == "tiny_variances" else 0.0)
    for i in range(3):
        for j in range(i, 3):
            params[f"v{i + 1}{j + 1}"] = mats["P0"][i, j]
    N = 30
    t = 3.0 + np.cumsum(np.where(np.arange(N) % 2, 1e-5, 0.5))
    U, Y = rng.normal(size=(N, 2)), rng.normal(size=(N, 2))
    df = pd.DataFrame({"t": t, "u1": U[:, 0], "u2": U[:, 1], "y1": Y[:, 0], "y2": Y[:, 1]})
    ref, _, _ = dense_reference(mats, t, U, Y, foh=0.0)
    for form in ("sqrt", "plain"):
        assert linear_model.loglik(params, df, form=form) == pytest.approx(ref, rel=1e-9), form


def test_indefinite_initial_covariance_is_refused(linear_model):
    import greyid

    rng = np.random.default_rng(0)
    params, _ = random_linear_parameters(rng)
    params.update(v11=1.0, v12=2.0, v22=1.0)
    df, *_ = random_data(rng)
    with pytest.raises(greyid.ModelError, match="positive semi-definite"):
        linear_model.loglik(params, df)


def test_fisher_information_equals_dense_gaussian_formula(linear_model):
    """For parameters of the mean (inputs, offsets, initial state) the innovations' derivatives
    do not depend on the data, and the information through the filter equals the Gaussian
    formula on the stacked observations, ∂μᵀΣ⁻¹∂μ (+ ½tr(Σ⁻¹∂ΣΣ⁻¹∂Σ) = 0), ∂μ by differences."""
    from conftest import dense_information
    from greyid.estimate.information import loglik_derivatives

    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    df, t, U, Y = random_data(rng, N=15, missing=0.0)
    names = ["b11", "b22", "c1", "d21", "m2", "m3"]
    fisher = loglik_derivatives(linear_model, params, df, names, "fisher").information
    expected = dense_information(params, t, U, names)
    np.testing.assert_allclose(fisher, expected, rtol=1e-5, atol=1e-8 * np.abs(expected).max())


@pytest.mark.parametrize("method", ["iekf", "ukf", "ekf2"])
def test_every_filter_smooths_and_is_exact_on_linear_models(linear_model, method):
    rng = np.random.default_rng(43)
    params, mats = random_linear_parameters(rng)
    df, t, U, Y = random_data(rng, N=25)
    _, xs_ref, _ = dense_reference(mats, t, U, Y, foh=0.0)
    sm = linear_model.smooth(params, df, method=method)
    np.testing.assert_allclose(sm.smoothed.to_numpy(), xs_ref, rtol=1e-6, atol=1e-7)
