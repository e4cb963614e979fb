"""The Laplace method over the states, against independent references: the exact Kalman filter, the dense
Gaussian likelihood of the Euler–Maruyama discretization, a point-mass filter on a grid, central differences."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats

import greyid
from greyid.errors import ModelError
from greyid.estimate.approximations import particle_loglik
from greyid.filters.api import laplace_residuals
from greyid.report.html import _approximation_section, html_report
from test_correlated_noise import TRUE as CORRELATED
from test_correlated_noise import correlated_model
from test_particle import grid_loglik, point_mass_grid, poisson_data, poisson_model

A, MU, S, R = 0.5, 1.0, 0.4, 0.04
PARAMS = dict(a=A, mu=MU, s=S, r=R)


def ou_model():
    m = greyid.Model("ou")
    m.add_system("dx = -a*(x - mu)*dt + s*dw1")
    m.add_observation("y = x", variance="r")
    for name, value in PARAMS.items():
        m.set_parameter(name, init=value, lower=1e-3, upper=10)
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.1]])
    return m


def ou_data(n=40, seed=1, irregular=False):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n)) if irregular else np.arange(float(n))
    x, ys = 1.0, []
    for k in range(n):
        ys.append(x + np.sqrt(R) * rng.normal())
        step = t[k + 1] - t[k] if k + 1 < n else 1.0
        x = MU + (x - MU) * np.exp(-A * step) + S * np.sqrt((1 - np.exp(-2 * A * step)) / (2 * A)) * rng.normal()
    y = np.array(ys)
    y[[5, 17]] = np.nan  # missing values are integrated over
    return pd.DataFrame({"t": t, "y": y})


def euler_dense_loglik(data, substeps=1, jitter=0.0):
    """The log-density of the observations under x_{j+1} = x_j − a(x_j − μ)Δ + N(0, (s² + jitter)Δ) on the grid of
    ``substeps`` steps per interval, x_0 ~ N(1, 0.1), y = x + N(0, r): one joint Gaussian, written out densely."""
    t = data["t"].to_numpy()
    steps = np.concatenate([np.full(substeps, (t[k + 1] - t[k]) / substeps) for k in range(len(t) - 1)])
    T = len(steps) + 1
    mean = np.empty(T)
    # x_j = c_j + Σ_i M_ji w_i with w_0 ~ N(0, 0.1) the initial deviation and w_i the steps' noise
    M = np.zeros((T, T))
    mean[0], M[0, 0] = 1.0, 1.0
    var = np.concatenate([[0.1], (S**2 + jitter) * steps])
    for j, d in enumerate(steps):
        mean[j + 1] = mean[j] - A * (mean[j] - MU) * d
        M[j + 1] = (1 - A * d) * M[j]
        M[j + 1, j + 1] = 1.0
    cov = (M * var) @ M.T
    at = np.arange(0, T, substeps)
    observed = ~np.isnan(data["y"].to_numpy())
    rows = at[observed]
    return stats.multivariate_normal(mean[rows], cov[np.ix_(rows, rows)] + R * np.eye(len(rows))).logpdf(
        data["y"].to_numpy()[observed])


def test_linear_gaussian_laplace_equals_the_kalman_filter_and_the_dense_euler_likelihood():
    """Exact for a linear Gaussian model: with the exact transition it is the Kalman filter (regular and irregular
    sampling, missing values, sub-steps); with Euler–Maruyama it is the dense likelihood of that discretization."""
    m = ou_model()
    for data in (ou_data(), ou_data(irregular=True)):
        exact = m.loglik(PARAMS, data, method="kalman")
        assert m.loglik(PARAMS, data, method="laplace") == pytest.approx(exact, abs=1e-9)
        assert m.loglik(PARAMS, data, method="laplace", substeps=3) == pytest.approx(exact, abs=1e-9)
        euler = m.loglik(PARAMS, data, method="laplace", scheme="euler")
        assert euler == pytest.approx(euler_dense_loglik(data), abs=1e-9)
        ctsmtmb = m.loglik(PARAMS, data, method="laplace", scheme="ctsmtmb")
        assert ctsmtmb == pytest.approx(euler_dense_loglik(data, jitter=1e-8), abs=1e-9)
        assert abs(euler - exact) > 1e-3  # the discretizations differ


def test_euler_substeps_converge_to_the_exact_likelihood():
    m, data = ou_model(), ou_data()
    exact = m.loglik(PARAMS, data, method="kalman")
    errors = [abs(m.loglik(PARAMS, data, method="laplace", scheme="euler", substeps=k) - exact) for k in (1, 2, 4, 8)]
    assert all(later < 0.7 * earlier for earlier, later in zip(errors, errors[1:])), errors
    assert errors[-1] < 0.15 * errors[0]  # first order: about halved with each doubling
    assert m.loglik(PARAMS, data, method="laplace", scheme="euler", substeps=4) == pytest.approx(
        euler_dense_loglik(data, substeps=4), abs=1e-9)


def test_gradient_and_hessian_are_those_of_the_kalman_filter_for_a_linear_model():
    m, data = ou_model(), ou_data()
    laplace, kalman = m.likelihood(data, method="laplace"), m.likelihood(data, method="kalman")
    x = np.array([PARAMS[n] for n in laplace.names]) * 1.1
    value, gradient = laplace.value_and_grad(x)
    exact_value, exact_gradient = kalman.value_and_grad(x)
    assert value == pytest.approx(exact_value, abs=1e-9)
    np.testing.assert_allclose(gradient, exact_gradient, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(laplace.hessian(x), kalman.hessian(x), rtol=1e-7, atol=1e-8)


def test_poisson_counts_laplace_is_close_to_the_point_mass_filter_and_its_gradient_to_differences():
    """Counts of a few per interval: the Laplace approximation is within 0.1 % of the exact log-likelihood
    (the documented tolerance), and its gradient is the derivative of its value (central differences)."""
    m, data = poisson_model(), poisson_data()
    p = dict(a=0.5, mu=2.0, s=0.5)
    reference = grid_loglik(data["n"].to_numpy())
    value = m.loglik(p, data, method="laplace")
    assert abs(value - reference) < 1e-3 * abs(reference), (value, reference)
    nll = m.likelihood(data, method="laplace")
    x = np.array([p[n] for n in nll.names])
    _, gradient = nll.value_and_grad(x)
    step = 1e-4
    differences = [(nll.value(x + step * e) - nll.value(x - step * e)) / (2 * step) for e in np.eye(len(x))]
    np.testing.assert_allclose(gradient, differences, rtol=1e-6, atol=1e-6)


def test_a_laplace_fit_recovers_the_simulated_parameters_of_counts():
    m, data = poisson_model(), poisson_data(300, seed=8)
    m.set_parameter("mu", init=1.5, lower=-5, upper=10)
    fit = m.fit(data, method="laplace")
    assert fit.converged
    for name, truth in dict(a=0.5, mu=2.0, s=0.5).items():
        estimate, error = fit.values[name], fit.bse[name]
        assert abs(estimate - truth) < 3.5 * error, (name, estimate, error)


def test_an_lbfgs_fit_reaches_newtons_optimum_without_a_hessian_program(monkeypatch):
    """optimizer="lbfgs" (L-BFGS on the value and exact gradient, the Hessian at the optimum by central
    differences of the gradient, as TMB's sdreport), which "auto" takes for the Laplace method: Newton's
    optimum and standard errors, without the exact Hessian's program (what a first Laplace fit by Newton's
    steps spends most of its compilation on)."""
    from greyid.estimate import estimation, objective

    m, data = poisson_model(), poisson_data(300, seed=8)
    m.set_parameter("mu", init=1.5, lower=-5, upper=10)
    newton = m.fit(data, method="laplace", optimizer="newton")

    def refused(*args, **kwargs):
        raise AssertionError("the exact Hessian's programs were asked for")

    monkeypatch.setattr(estimation, "single_programs", refused)
    monkeypatch.setattr(objective.Derivatives, "__init__", refused)
    events = []
    by_default = m.fit(data, method="laplace", progress=events.append)
    lbfgs = m.fit(data, method="laplace", optimizer="lbfgs")
    assert newton.converged and by_default.converged
    assert by_default.loglik == pytest.approx(newton.loglik, abs=1e-7)
    shift = (by_default.params["estimate"] - newton.params["estimate"]) / newton.params["std_error"]
    assert np.max(np.abs(shift)) < 1e-3
    np.testing.assert_allclose(by_default.params["std_error"], newton.params["std_error"], rtol=1e-4)
    np.testing.assert_array_equal(lbfgs.params["estimate"], by_default.params["estimate"])
    steps = [e for e in events if "iteration" in e]
    assert steps and {e["stage"] for e in steps} == {"lbfgs"}
    assert [e["iteration"] for e in steps] == list(range(1, by_default.iterations + 1))
    assert (by_default.settings.optimizer, lbfgs.settings.optimizer) == ("auto", "lbfgs")
    assert by_default.settings.hessian == lbfgs.settings.hessian == "differences"
    assert newton.settings.hessian == "exact"
    assert "covariance: hessian (the Hessian by central differences" in by_default.summary()
    assert "by central differences" not in newton.summary()
    with pytest.raises(greyid.ModelError, match="optimizer='lbfgs' is for single fits"):
        greyid.fit_many(m, {"a": data, "b": data}, method="laplace", optimizer="lbfgs")


def test_the_difference_hessian_does_not_depend_on_the_parameters_scales():
    """Central differences of an exact gradient recover the Hessian at an optimum of a function that is not
    quadratic (Σ cosh of linear combinations), whatever the scale of each coordinate, to 1e-7: the steps are
    taken in each coordinate's own standard deviation (a step of 1e-4 in every coordinate would be a hundred
    standard deviations in one of them)."""
    from greyid.estimate.lbfgs import difference_hessian

    rng = np.random.default_rng(3)
    for scale in (1e-6, 1.0, 1e6):
        A = (rng.normal(size=(3, 3)) + 3 * np.eye(3)) @ np.diag([1.0 / scale, 1.0, scale])
        H = A.T @ A  # cosh''(0) = 1
        scales = 1.0 / np.sqrt(np.diag(H))
        optimum = rng.normal(size=3) * 100 * scales

        def value_and_grad(z):
            u = A @ (z - optimum)
            return np.sum(np.cosh(u)), A.T @ np.sinh(u)

        found = difference_hessian(value_and_grad, optimum, scales)
        norm = np.sqrt(np.outer(np.diag(H), np.diag(H)))
        np.testing.assert_allclose(found / norm, H / norm, atol=1e-7)


def test_the_laplace_method_refuses_what_it_cannot_do():
    m, data = ou_model(), ou_data()
    with pytest.raises(ModelError, match="gives a likelihood, not a filter"):
        m.filter(PARAMS, data, method="laplace")
    with pytest.raises(ModelError, match="unknown scheme 'rk4'"):
        m.loglik(PARAMS, data, method="laplace", scheme="rk4")


def test_a_fleet_of_count_series_fits_by_the_laplace_method_as_each_alone():
    m = poisson_model()
    data = [poisson_data(150, seed=seed) for seed in range(3)]
    fleet = greyid.fit_many(m, data, method="laplace")
    assert fleet.table["converged"].all()
    for name, frame in zip(fleet.table.index, data):
        alone = m.fit(frame, method="laplace")
        assert fleet.table.loc[name, "loglik"] == pytest.approx(alone.loglik, abs=1e-6)
        for p in ("a", "mu", "s"):
            assert fleet.table.loc[name, p] == pytest.approx(alone.values[p], rel=1e-4)


@pytest.mark.filterwarnings("ignore:.*at a bound")  # one Euler step per unit interval leaves r little to explain
def test_a_laplace_fit_keeps_its_scheme_and_its_profile_reruns_it():
    """ctsmTMB's convention travels with the fit: its settings name it, and a profile at the estimate gives the
    fit's own value (not the default scheme's)."""
    m, data = ou_model(), ou_data(150, seed=2)
    fit = m.fit(data, method="laplace", scheme="ctsmtmb")
    assert fit.settings["scheme"] == "ctsmtmb" and fit.settings["substeps"] == 1
    assert fit.loglik == pytest.approx(m.loglik(fit.values, data, **fit.settings.filter_kwargs()), abs=1e-9)
    assert abs(fit.loglik - m.loglik(fit.values, data, method="laplace")) > 1e-3
    profile = fit.profile("mu", values=[fit.values["mu"]])
    assert profile["loglik"].iloc[0] == pytest.approx(fit.loglik, abs=1e-6)


def grid_transforms(counts, uniforms, a=0.5, mu=2.0, s=0.5, points=3000):
    """Each count's exact one-step randomized probability integral transform, from the point-mass filter."""
    grid, transition, prior = point_mass_grid(a, mu, s, points)
    out = []
    for k, (y, v) in enumerate(zip(counts, uniforms)):
        if k > 0:
            prior = prior @ transition
        below, equal = prior @ stats.poisson.cdf(y - 1, np.exp(grid)), prior @ stats.poisson.pmf(y, np.exp(grid))
        out.append(below + v * equal)
        prior = prior * stats.poisson.pmf(y, np.exp(grid))
        prior /= prior.sum()
    return np.array(out)


@pytest.mark.slow
def test_laplace_one_step_residuals_match_the_kalman_filter_and_the_grid_filter():
    """The one-step-ahead residuals on a linear Gaussian model: by the Gaussian predictive (the default, ctsmTMB's)
    the Kalman filter's standardized innovations to rounding; by each tail of y_k given the past by Laplace's
    method ("cdf") within 0.06 of them (the tails' Laplace error, the documented tolerance); missing values NaN.
    For counts (the "cdf" method, their default) within 0.06 of the grid filter's exact randomized transforms
    (the same uniform numbers), normal under the simulating parameters and not under a wrong level."""
    m, data = ou_model(), ou_data(80, seed=4)
    exact = m.filter(PARAMS, data, method="kalman").standardized_innovations["y"]
    gaussian = laplace_residuals(m, PARAMS, data)["y"]
    assert gaussian.isna().tolist() == exact.isna().tolist() and gaussian.isna().sum() == 2
    assert np.nanmax(np.abs(gaussian - exact)) < 1e-9
    residuals = laplace_residuals(m, PARAMS, data, one_step="cdf")["y"]
    assert residuals.isna().tolist() == exact.isna().tolist()
    assert np.nanmax(np.abs(residuals - exact)) < 0.06 and np.nanmean(np.abs(residuals - exact)) < 0.03

    counts_model, counts = poisson_model(), poisson_data(120, seed=11)
    uniforms = np.random.default_rng([0, 0]).uniform(size=(120, 1))[:, 0]
    reference = stats.norm.ppf(grid_transforms(counts["n"].to_numpy(), uniforms))
    right = laplace_residuals(counts_model, dict(a=0.5, mu=2.0, s=0.5), counts)["n"]
    assert np.max(np.abs(right - reference)) < 0.06, np.max(np.abs(right - reference))
    assert stats.kstest(right, "norm").pvalue > 0.01
    wrong = laplace_residuals(counts_model, dict(a=0.5, mu=1.2, s=0.5), counts)["n"]
    assert stats.kstest(wrong, "norm").pvalue < 1e-3


def two_output_model(second_variance: str):
    """One Ornstein–Uhlenbeck state seen by two outputs with independent noise (the second's variance given)."""
    m = greyid.Model("two_outputs")
    m.add_system("dx = -a*(x - mu)*dt + s*dw1")
    m.add_observation("y1 = x", variance="r")
    m.add_observation("y2 = 0.5*x + 1", variance=second_variance)
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.1]])
    return m


def test_the_one_step_residuals_of_two_outputs_trace_the_laplace_value_once(monkeypatch):
    """The outputs in a scan, the rows in batches of one size: the Laplace value of the "cdf" method is traced once,
    not once per output and again for rows left over by the batches.
    Each output given the past and the outputs before it: the Kalman filter's innovations whitened in that order,
    to rounding by the Gaussian predictive, within 0.06 by the tails."""
    from greyid.filters import laplace

    traced, build = [], laplace.build

    def counting(*args):
        built = build(*args)

        def value(*arguments):
            traced.append(1)
            return built.value(*arguments)

        return built._replace(value=value)

    monkeypatch.setattr(laplace, "build", counting)  # (switches the kept programs off: it traces)
    m = two_output_model("r")
    params = dict(a=0.5, mu=1.0, s=0.4, r=0.04)
    data = m.simulate(params, np.arange(21.0), seed=3).frame()[["t", "y1", "y2"]]
    residuals = laplace_residuals(m, params, data, one_step="cdf")
    assert len(traced) == 1
    kalman = m.filter(params, data, method="kalman")
    e, R = kalman.innovations.to_numpy(), kalman.innovation_cov
    first = e[:, 0] / np.sqrt(R[:, 0, 0])
    second = (e[:, 1] - R[:, 1, 0] / R[:, 0, 0] * e[:, 0]) / np.sqrt(R[:, 1, 1] - R[:, 1, 0] ** 2 / R[:, 0, 0])
    assert np.max(np.abs(residuals["y1"] - first)) < 0.06
    assert np.max(np.abs(residuals["y2"] - second)) < 0.06
    gaussian = laplace_residuals(m, params, data)
    assert np.max(np.abs(gaussian["y1"] - first)) < 1e-9 and np.max(np.abs(gaussian["y2"] - second)) < 1e-9


def test_the_one_step_method_is_the_gaussian_predictive_where_it_is_exact_and_checked():
    """By default the Gaussian predictive for a linear model with Gaussian outputs, the tails ("cdf") for a nonlinear
    model or another distribution; a method that is not one, or the Gaussian one for counts, refused by name."""
    from greyid.filters.api import one_step_method

    nonlinear = greyid.Model("double well")
    nonlinear.add_system("dx = (x - x^3)*dt + sigma*dw1")
    nonlinear.add_observation("y = x", variance="e^2")
    nonlinear.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
    from greyid.filters.laplace import gaussian_joint

    # The Gaussian residuals in one pass forward where the joint density is Gaussian, a mode per observation elsewhere.
    assert gaussian_joint(ou_model().structure) and not gaussian_joint(nonlinear.structure)
    assert not gaussian_joint(poisson_model().structure)
    assert one_step_method(ou_model().structure, None) == "gaussian"
    assert one_step_method(nonlinear.structure, None) == "cdf"
    assert one_step_method(nonlinear.structure, "gaussian") == "gaussian"
    assert one_step_method(poisson_model().structure, None) == "cdf"
    with pytest.raises(greyid.ModelError, match="'n' is not: use one_step='cdf'"):
        one_step_method(poisson_model().structure, "gaussian")
    with pytest.raises(greyid.ModelError, match="one_step='tails' is not a one-step method"):
        laplace_residuals(ou_model(), PARAMS, ou_data(), one_step="tails")


def test_row_batches_are_the_fewest_of_one_size():
    from greyid.filters.laplace import row_batches

    assert row_batches(52) == (7, 8) and row_batches(48) == (6, 8) and row_batches(18) == (3, 6)
    for n in range(1, 300):
        count, size = row_batches(n)
        assert size <= 8 and count == -(-n // 8) and 0 <= count * size - n < count


def test_the_one_step_residuals_evaluate_every_row_in_one_vectorised_program():
    """22 rows (a length bucket that no batch of 8 divides): the "cdf" residuals' rows run in batches of one size
    (the last row repeated), so that the program holds the Laplace evaluation once; with batches of 8 and the rest
    vectorised apart (lax.map's remainder), it would hold it twice: a second loop beside the batches' scan.  The
    Gaussian predictive's run one row at a time."""
    import jax
    from jax.extend.core import ClosedJaxpr, Jaxpr

    from greyid.filters import api, laplace

    m, data = ou_model(), ou_data(22, seed=2)
    made, settings = [], []

    def make(structure, options):
        settings.append((structure, options))
        made.append(laplace.one_step_transforms(structure, options))
        return made[-1]

    _, theta, prepared, _ = api._laplace_program(m, PARAMS, data, "t", "zoh", None, "one-step-test", make, {})
    inputs = prepared[0][1]
    assert inputs.t.shape[0] % 8 != 0
    jaxpr = jax.make_jaxpr(made[0])(theta, inputs, np.zeros(inputs.y.shape)).jaxpr
    loops = [eqn.primitive.name for eqn in jaxpr.eqns
             if any(isinstance(value, (ClosedJaxpr, Jaxpr)) for value in eqn.params.values())
             and eqn.primitive.name in ("scan", "while")]
    assert loops == ["scan"]
    # The Gaussian predictive's residuals of this linear Gaussian model: one pass forward, a scan over the rows
    # with no Newton search (while loop) anywhere in it.
    structure, options = settings[0]
    jaxpr = jax.make_jaxpr(laplace.one_step_gaussian(structure, options))(theta, inputs).jaxpr
    lengths = [eqn.params["length"] for eqn in jaxpr.eqns if eqn.primitive.name == "scan"]
    assert lengths.count(inputs.t.shape[0]) == 1 and "while" not in str(jaxpr)
    # Where the joint density is not Gaussian (a nonlinear model asking for the Gaussian predictive) they run the
    # rows one at a time, a Laplace mode each: one scan over the rows, nothing vectorised.
    nonlinear = greyid.Model("double well")
    nonlinear.add_system("dx = (x - x^3)*dt + s*dw1")
    nonlinear.add_observation("y = x", variance="r")
    nonlinear.set_initial_state(mean={"x": 1.0}, covariance=[[0.1]])
    _, theta, prepared, _ = api._laplace_program(nonlinear, dict(s=0.4, r=0.04), data, "t", "zoh", None,
                                                 "one-step-test", make, {})
    inputs = prepared[0][1]
    structure, options = settings[-1]
    jaxpr = jax.make_jaxpr(laplace.one_step_gaussian(structure, options))(theta, inputs).jaxpr
    loops = [eqn for eqn in jaxpr.eqns if any(isinstance(value, (ClosedJaxpr, Jaxpr)) for value in eqn.params.values())]
    assert [eqn.primitive.name for eqn in loops] == ["scan"] and loops[0].params["length"] == inputs.t.shape[0]
    assert "while" in str(loops[0])


def one_pass_and_each_observation(m, params, data, hold, settings):
    """The Gaussian one-step residuals of a two-output model (rows, 2) by the one pass forward
    (``Laplace.one_step``) and by each observation's own Laplace predictive (``Laplace.predictive``)."""
    import jax

    from greyid.filters import api, laplace

    _, theta, prepared, _ = api._laplace_program(m, params, data, "t", hold, None, "one-step-test",
                                                 laplace.one_step_gaussian, settings)
    built = laplace.build(m.structure, api.accurate_options(m.structure, theta, prepared, "laplace", **settings)[0])
    inputs = prepared[0][1]
    one_pass = np.asarray(jax.jit(built.one_step)(theta, inputs))
    each = np.asarray(jax.jit(lambda th, d: laplace.each_observation(
        d, 2, lambda before, k, i: built.predictive(th, before, k, i), 0.0, most=1))(theta, inputs))
    return one_pass[:len(data)], each[:len(data)]


@pytest.mark.parametrize("settings", [dict(scheme="ctsmtmb"), dict(scheme="euler", substeps=3),
                                      dict(substeps=2)])
def test_the_gaussian_one_step_residuals_in_one_pass_are_the_predictive_of_each_observation(settings):
    """Where the joint density is Gaussian the one-step Gaussian residuals come from one pass forward over the grid
    (``Laplace.one_step``): equal to rounding to each observation's predictive from the Laplace mode given the data
    before it (``Laplace.predictive``, what a nonlinear model's residuals run), on two states with an input held by
    first-order hold, correlated output noise, a missing output and an irregular interval, by each scheme."""
    from greyid.filters import laplace

    m, params = correlated_model(), CORRELATED
    t = np.concatenate([np.arange(12.0), [12.7], np.arange(14.0, 30.0)])
    data = pd.DataFrame({"t": t, "u": np.sin(0.4 * t)})
    frame = m.simulate(params, data, seed=5, hold="foh").frame()
    data = data.assign(y1=frame["y1"].to_numpy(), y2=frame["y2"].to_numpy())
    data.loc[7, "y1"] = np.nan
    assert laplace.gaussian_joint(m.structure)
    one_pass, each = one_pass_and_each_observation(m, params, data, "foh", settings)
    assert np.isfinite(one_pass).all() and one_pass[7, 0] == 0.0 and each[7, 0] == 0.0
    np.testing.assert_allclose(one_pass, each, rtol=0, atol=1e-12)
    assert np.max(np.abs(one_pass)) > 0.5


@pytest.mark.parametrize("settings", [dict(scheme="ctsmtmb"), dict(substeps=2)])
def test_the_one_pass_with_independent_noise_takes_each_output_s_own_density(settings):
    """Independent output noise: the pass takes an output's own density term (not the difference of two), equal to
    rounding to each observation's predictive from its Laplace mode, with a missing output and an irregular
    interval."""
    from greyid.filters import laplace

    m = two_output_model("4*r")
    params = dict(a=0.5, mu=1.0, s=0.4, r=0.04)
    t = np.concatenate([np.arange(9.0), [9.4], np.arange(11.0, 20.0)])
    data = m.simulate(params, t, seed=4).frame()[["t", "y1", "y2"]]
    data.loc[5, "y2"] = np.nan
    assert laplace.gaussian_joint(m.structure) and m.structure.observation_covariance is None
    one_pass, each = one_pass_and_each_observation(m, params, data, "zoh", settings)
    assert one_pass[5, 1] == 0.0 and np.isfinite(one_pass).all()
    np.testing.assert_allclose(one_pass, each, rtol=0, atol=1e-12)
    assert np.max(np.abs(one_pass)) > 0.5


def test_the_one_step_searches_stop_sooner_at_the_same_mode():
    """The one-step transforms' Laplace values stop their Newton search at a full step shorter than
    ONE_STEP_TOLERANCE: after the last full step the value equals the likelihood's (whose search runs to
    NEWTON_TOLERANCE) to 1e-10, on Poisson counts, with and without a tail term."""
    import jax

    from greyid.filters import api, laplace

    m, data = poisson_model(), poisson_data(60, seed=3)
    params = dict(a=0.5, mu=2.0, s=0.5)
    _, theta, prepared, _ = api._laplace_program(m, params, data, "t", "zoh", None, "one-step-test",
                                                 laplace.one_step_transforms, dict(substeps=2))
    built = laplace.build(m.structure, api.accurate_options(m.structure, theta, prepared, "laplace", substeps=2)[0])
    inputs = prepared[0][1]
    assert laplace.ONE_STEP_TOLERANCE > 1e3 * laplace.NEWTON_TOLERANCE
    value = float(jax.jit(built.value)(theta, inputs))
    assert value == pytest.approx(float(jax.jit(built.marginal)(theta, inputs)[0]), rel=1e-12, abs=1e-10)
    on = np.zeros(inputs.mask.shape)
    on[30, 0] = 1.0
    tail = float(jax.jit(built.value)(theta, inputs, (on, np.zeros_like(on), np.zeros_like(on))))
    assert np.isfinite(tail) and tail < value  # P(Y < y, past) < p(past)


def test_the_cdf_transforms_vectorised_over_rows_and_parts_are_each_observations_own():
    """The "cdf" transforms, vectorised over rows and their three parts at once (P(Y < y, D), P(Y > y, D),
    P(Y = y, D)), equal the same three Laplace values computed one observation at a time from the data before it
    and combined by hand, to rounding; on Poisson counts with a missing count (0.5 there)."""
    import jax

    from greyid.filters import api, laplace

    m, data = poisson_model(), poisson_data(13, seed=6)
    data.loc[5, "n"] = np.nan
    params = dict(a=0.5, mu=2.0, s=0.5)
    made = []

    def make(structure, options):
        made.append(laplace.build(structure, options))
        return laplace.one_step_transforms(structure, options)

    _, theta, prepared, program = api._laplace_program(m, params, data, "t", "zoh", None, "one-step-test", make, {})
    inputs = prepared[0][1]
    uniforms = np.random.default_rng(3).uniform(size=inputs.y.shape)
    transforms = np.asarray(program(theta, inputs, uniforms))
    value = jax.jit(made[0].value)
    n_rows = len(data)
    for k in range(n_rows):
        if np.isnan(data["n"][k]):
            assert transforms[k, 0] == 0.5
            continue
        rows = np.arange(inputs.t.shape[0])
        before = inputs._replace(dt=np.where(rows > k, 0.0, inputs.dt),
                                 mask=np.where((rows < k)[:, None], inputs.mask, 0.0))
        on, none = np.zeros(inputs.mask.shape), np.zeros(inputs.mask.shape)
        on[k, 0] = 1.0
        below = float(value(theta, before, (on, on, none)))  # P(Y < y): Y ≤ y − 1
        above = float(value(theta, before, (on, none, on)))
        seen = np.array(before.mask)
        seen[k, 0] = 1.0
        point = float(value(theta, before._replace(mask=seen), (none, none, none)))
        p = np.exp(np.array([below, above, point]) - max(below, above, point))
        assert transforms[k, 0] == pytest.approx((p[0] + uniforms[k, 0] * p[2]) / p.sum(), rel=1e-10, abs=1e-13)


@pytest.mark.parametrize("upper", [False, True])
def test_the_laplace_value_with_a_tail_term_is_the_dense_laplace_approximation(upper):
    """Laplace.value with one count's tail among its terms (log P(N < n | l_k) or log P(N > n | l_k), the "cdf"
    transforms' parts, taken at that row alone) against Laplace's approximation computed densely in the test: the
    joint log-density of all states written out (stationary prior, exact OU transitions, Poisson counts before
    row k, the tail at row k, the states after k integrated out exactly), its mode by SciPy, −½ log det of its
    full Hessian; to 1e-8."""
    import jax
    import jax.numpy as jnp
    from jax.scipy.special import gammaincc
    from jax.scipy.stats import norm, poisson
    from scipy import optimize

    from greyid.filters import api, laplace

    m, data = poisson_model(), poisson_data(9, seed=7)
    a, mu, s = 0.5, 2.0, 0.5
    _, theta, prepared, _ = api._laplace_program(m, dict(a=a, mu=mu, s=s), data, "t", "zoh", None, "one-step-test",
                                                 laplace.one_step_transforms, dict(substeps=1))
    options = api.accurate_options(m.structure, theta, prepared, "laplace", substeps=1)[0]
    inputs = prepared[0][1]
    k, counts = 6, data["n"].to_numpy(dtype=float)
    rows = np.arange(inputs.t.shape[0])
    before = inputs._replace(dt=np.where(rows > k, 0.0, inputs.dt),
                             mask=np.where((rows < k)[:, None], inputs.mask, 0.0))
    on, none = np.zeros(inputs.mask.shape), np.zeros(inputs.mask.shape)
    on[k, 0] = 1.0
    cdf = (on, none, on) if upper else (on, on, none)
    value = float(jax.jit(laplace.build(m.structure, options).value)(theta, before, cdf))

    sd, decay = s / np.sqrt(2 * a), np.exp(-a)
    step_sd = sd * np.sqrt(1 - decay**2)

    def joint(x):  # x_0 … x_k: the states after row k integrate to one
        value = norm.logpdf(x[0], mu, sd) + jnp.sum(norm.logpdf(x[1:], mu + (x[:-1] - mu) * decay, step_sd))
        value = value + jnp.sum(poisson.logpmf(counts[:k], jnp.exp(x[:k])))
        below = gammaincc(counts[k], jnp.exp(x[k]))  # P(N ≤ n − 1 | l_k)
        above = 1 - gammaincc(counts[k] + 1, jnp.exp(x[k]))  # P(N > n | l_k)
        return value + jnp.log(above if upper else below)

    negative = jax.jit(lambda x: -joint(x))
    found = optimize.minimize(negative, np.full(k + 1, mu), jac=jax.jit(jax.grad(negative)),
                              hess=jax.jit(jax.hessian(negative)), method="trust-exact", options=dict(gtol=1e-12))
    _, logdet = np.linalg.slogdet(np.asarray(jax.hessian(negative)(found.x)))
    dense = -found.fun + 0.5 * (k + 1) * np.log(2 * np.pi) - 0.5 * logdet
    assert counts[k] > 0 and value == pytest.approx(dense, rel=1e-8, abs=1e-8)


def test_the_newton_search_takes_its_last_full_step_in_its_loop(monkeypatch):
    """The search's last full step is the loop's last pass, not a copy of the step after the loop: tracing
    Laplace.value factorises −H twice (the loop's step, and the value's log-determinant at the mode), and
    Laplace.smoothed twice (the loop's, and the covariances'), where a step after the loop would add a third
    copy of the step to each program.  The value is the likelihood's to rounding."""
    import traceback

    import jax

    from greyid.filters import api, laplace

    m, data = poisson_model(), poisson_data(40, seed=5)
    params = dict(a=0.5, mu=2.0, s=0.5)
    _, theta, prepared, _ = api._laplace_program(m, params, data, "t", "zoh", None, "one-step-test",
                                                 laplace.one_step_transforms, {})
    options = api.accurate_options(m.structure, theta, prepared, "laplace")[0]
    inputs = prepared[0][1]
    places, factor = [], laplace.block_cholesky

    def counting(*args):
        callers = [frame.name for frame in traceback.extract_stack()[:-1]
                   if frame.filename.endswith(str(Path("filters", "laplace.py")))]
        places.append(callers[-1])
        return factor(*args)

    monkeypatch.setattr(laplace, "block_cholesky", counting)
    built = laplace.build(m.structure, options)
    value = float(jax.jit(built.value)(theta, inputs))
    assert places == ["improve", "value_at"]
    places.clear()
    mode, _ = jax.jit(built.smoothed)(theta, inputs)
    assert places == ["improve", "smoothed"]
    assert value == pytest.approx(float(jax.jit(built.marginal)(theta, inputs)[0]), rel=1e-12)


@pytest.mark.filterwarnings("ignore:.*at a bound")  # the Euler fit's diffusion, on 40 rows
def test_a_laplace_fit_of_a_linear_gaussian_model_filters_and_predicts_by_the_exact_kalman_filter():
    """Where the Laplace value is the exact Kalman filter's likelihood (a linear time-invariant model with Gaussian
    outputs and the exact transitions), a Laplace fit's filter() and predict() are that filter's, deterministic;
    with Euler–Maruyama transitions (ctsmTMB's scheme) its likelihood is another model's: the particle filter."""
    from greyid.filters.laplace import exact_kalman

    m, data = ou_model(), ou_data()
    fit = m.fit(data, method="laplace", substeps=2)
    assert exact_kalman(m.structure, "auto") and not exact_kalman(m.structure, "ctsmtmb")
    assert not exact_kalman(poisson_model().structure, None)
    assert fit.filter().method == "kalman"
    np.testing.assert_allclose(fit.filter().filtered.to_numpy(),
                               m.filter(fit.values, data, method="kalman").filtered.to_numpy(), rtol=1e-12)
    pd.testing.assert_frame_equal(fit.predict(steps=2), m.predict(fit.values, data, steps=2, method="kalman"))
    assert fit.loglik == pytest.approx(m.loglik(fit.values, data, method="kalman"), abs=1e-8)
    euler = m.fit(data, method="laplace", scheme="ctsmtmb")
    assert euler._filtering_settings()["method"] == "particle"


@pytest.mark.slow
def test_a_laplace_fit_validates_on_its_one_step_residuals():
    m, data = poisson_model(), poisson_data(150, seed=8)
    fit = m.fit(data, method="laplace")
    expected = laplace_residuals(m, fit.values, data)
    pd.testing.assert_frame_equal(fit.residuals, expected)
    validation = fit.validate()
    tests = validation.tests.set_index("test")
    assert set(tests["output"]) == {"n"}
    assert not tests.loc["ks_normality", "reject"] and not tests.loc["ljung_box", "reject"]
    # The Laplace method has no filter: its fit filters and predicts with the particle filter (named).
    assert fit.filter().method == "particle"
    pd.testing.assert_frame_equal(fit.predict(steps=2),
                                  m.predict(fit.values, data, steps=2, method="particle", particles=1000, seed=0))
    report = html_report(fit, profile=False)
    approximation = report[report.index('<section id="approximation">'):report.index('<section id="parameters">')]
    assert "laplace (the fit&#x27;s)" in approximation and 'class="ok"' in approximation


@pytest.mark.filterwarnings("ignore:.*at a bound")  # the EKF takes the observation noise to its bound here
@pytest.mark.slow
def test_the_report_flags_an_ekf_fit_whose_likelihood_the_particle_filter_contradicts():
    """A double well (bimodal predictive densities): at the EKF fit's estimates its log-likelihood lies far from the
    particle filter's, and the report's approximation section says so."""
    m = greyid.Model("double well")
    m.add_system("dx = (x - x^3)*dt + sigma*dw1")
    m.add_observation("y = x", variance="e^2")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
    rng = np.random.default_rng(1)
    x, ys = 1.0, []
    for _ in range(120):
        ys.append(x + 0.1 * rng.normal())
        for _ in range(100):
            x += (x - x**3) * 0.01 + 0.7 * 0.1 * rng.normal()
    data = pd.DataFrame({"t": np.arange(120.0), "y": ys})
    m.set_parameter("sigma", init=0.7, lower=0.01, upper=5)
    m.set_parameter("e", init=0.1, lower=1e-3, upper=5)
    fit = m.fit(data, method="ekf")
    section = _approximation_section(fit)
    reference = particle_loglik(m, fit.values, data, seed=0, proposal="ekf")
    assert abs(fit.loglik - reference.loglik) > 5 > 10 * reference.std_error  # the EKF's bias, far beyond the error
    assert 'class="warning"' in section and "more than its errors allow" in section


def test_laplace_intervals_cover_the_simulated_parameters_over_replications():
    """40 series of 200 Poisson counts simulated at (a, μ, s) = (0.5, 2, 0.5), each fitted by the Laplace method
    (fit_many): every fit converges, each 95 % Wald interval covers its parameter in at least 34 of 40 series
    (the binomial 1 % bound is 34), the mean level and diffusion are unbiased (t test at 1 %) and the standard
    errors match the estimates' spread (F test at 1 %). The rate a's estimate is biased upward at this length, as
    the maximum-likelihood rate of an Ornstein–Uhlenbeck process is: its coverage is checked, not its mean."""
    m = poisson_model()
    m.set_parameter("mu", init=2.0, lower=-5, upper=10)
    fleet = greyid.fit_many(m, [poisson_data(200, seed=1000 + i) for i in range(40)], method="laplace")
    table = fleet.table
    assert table["converged"].all()
    for name, truth in dict(a=0.5, mu=2.0, s=0.5).items():
        estimate, error = table[name], table[f"{name}_se"]
        covered = ((estimate - 1.96 * error <= truth) & (truth <= estimate + 1.96 * error)).sum()
        assert covered >= 34, (name, covered)
        spread = estimate.std(ddof=1)
        assert stats.f.ppf(0.005, 39, 1e9) < spread**2 / np.mean(error**2) < stats.f.ppf(0.995, 39, 1e9), name
        if name != "a":
            assert abs(estimate.mean() - truth) / (spread / np.sqrt(40)) < stats.t.ppf(0.995, 39), name


def test_the_laplace_smoother_is_the_rauch_tung_striebel_smoother_of_a_linear_gaussian_model():
    """The mode of the states and the diagonal blocks of the inverse Hessian (selected inversion of its block
    Cholesky factor) equal the RTS smoother's means and covariances for a linear Gaussian model (missing values,
    irregular sampling); for counts the mode tracks the grid filter's smoothed log-rate."""
    m = ou_model()
    for data in (ou_data(), ou_data(irregular=True)):
        laplace = m.smooth(PARAMS, data, method="laplace")
        exact = m.smooth(PARAMS, data, method="kalman")
        assert laplace.filter_result is None
        np.testing.assert_allclose(laplace.smoothed["x"], exact.smoothed["x"], atol=1e-9)
        np.testing.assert_allclose(laplace.smoothed_cov, exact.smoothed_cov, atol=1e-9)
    counts_model, counts = poisson_model(), poisson_data(120, seed=11)
    grid, transition, prior = point_mass_grid()
    likelihood = stats.poisson.pmf(counts["n"].to_numpy()[:, None], np.exp(grid)[None, :])
    forward = []
    for k in range(len(counts)):
        prior = (prior @ transition if k else prior) * likelihood[k]
        prior /= prior.sum()
        forward.append(prior)
    backward, mean = np.ones_like(grid), []
    for k in reversed(range(len(counts))):
        posterior = forward[k] * backward
        mean.append(posterior @ grid / posterior.sum())
        backward = transition @ (likelihood[k] * backward)
        backward /= backward.sum()
    mean = np.array(mean[::-1])
    mode = counts_model.smooth(dict(a=0.5, mu=2.0, s=0.5), counts, method="laplace").smoothed["l"].to_numpy()
    assert np.max(np.abs(mode - mean)) < 0.05, np.max(np.abs(mode - mean))


def test_the_derivatives_trace_the_mode_search_once(monkeypatch):
    """Each level of forward differentiation asks for the mode: the Hessian (forward over forward) traces its
    Newton search once, not once in the mode's value and again in its derivative's rule (its value is
    test_gradient_and_hessian_are_those_of_the_kalman_filter_for_a_linear_model's)."""
    import traceback

    from greyid.filters import laplace

    searches = []
    factor = laplace.block_cholesky

    def counting(*args):
        callers = [frame.name for frame in traceback.extract_stack()[:-1]
                   if frame.filename.endswith(str(Path("filters", "laplace.py")))]
        searches.append("improve" in callers)
        return factor(*args)

    monkeypatch.setattr(laplace, "block_cholesky", counting)  # (switches the kept programs off: it traces)
    m = ou_model()
    m.set_initial_state(mean={"x": 1.25}, covariance=[[0.1]])  # a model no other test has traced in this process
    data = ou_data(n=20)
    x = np.array([PARAMS[n] for n in m.likelihood(data).names])
    m.likelihood(data, method="laplace").hessian(x)
    assert sum(searches) == 1


def test_the_selected_inverse_bands_are_the_dense_inverses_blocks():
    """block_inverse_bands: the diagonal blocks of A⁻¹ and those right of them, against numpy's dense inverse of a
    random symmetric positive definite block-tridiagonal A (5 blocks of 3), to 1e-12."""
    from greyid.filters.laplace import block_cholesky, block_inverse_bands

    rng = np.random.default_rng(12)
    T, n = 4, 3
    lower = rng.normal(size=(T, n, n)) * 0.3
    diagonal = np.stack([np.eye(n) * 3 + 0.1 * (a + a.T) for a in rng.normal(size=(T + 1, n, n))])
    dense = np.zeros(((T + 1) * n, (T + 1) * n))
    for j in range(T + 1):
        dense[j * n:(j + 1) * n, j * n:(j + 1) * n] = diagonal[j]
    for j in range(T):
        dense[(j + 1) * n:(j + 2) * n, j * n:(j + 1) * n] = lower[j]
        dense[j * n:(j + 1) * n, (j + 1) * n:(j + 2) * n] = lower[j].T
    inverse = np.linalg.inv(dense)
    inner, crosses = block_inverse_bands(*block_cholesky(diagonal, lower))
    for j in range(T + 1):
        np.testing.assert_allclose(inner[j], inverse[j * n:(j + 1) * n, j * n:(j + 1) * n], atol=1e-12)
    for j in range(T):
        np.testing.assert_allclose(crosses[j], inverse[j * n:(j + 1) * n, (j + 1) * n:(j + 2) * n], atol=1e-12)
