"""Uncertainty beyond the Hessian: profile likelihoods against fits with the parameter fixed, profile
intervals on the χ² threshold, NUTS against closed-form and Laplace posteriors, prediction intervals
against brute-force mixtures and their coverage."""

import warnings

import numpy as np
import pandas as pd
import pytest
from scipy import stats

import greyid
from greyid import uncertainty
from test_estimation import TRUE, ou_model

THRESHOLD = stats.chi2.ppf(0.95, 1)


def ou_data(n=300, seed=5, r=TRUE["r"]):
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"t": np.arange(n) * 0.5, "u": np.repeat(rng.choice([0.0, 1.0], n // 10 + 1), 10)[:n]})
    df["y"] = ou_model().simulate(dict(TRUE, r=r), df, method="exact", seed=seed).outputs[0, :, 0]
    return df


@pytest.fixture(scope="module")
def ou_fit():
    m = ou_model()
    df = ou_data()
    return m, df, m.fit(df)


def fixed_fit(df, name, value, model=None):
    m = model or ou_model()
    m.set_parameter(name, init=value, fixed=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return m.fit(df)


def test_profile_equals_fits_with_the_parameter_fixed(ou_fit):
    m, df, fit = ou_fit
    a_hat = fit.params.loc["a", "estimate"]
    table = fit.profile("a", values=[0.6, a_hat, 1.0])
    assert list(table.columns) == ["a", "loglik", "b", "s", "r", "x0", "converged", "deviance"]
    assert table["converged"].all()
    assert table.loc[1, "deviance"] == pytest.approx(0.0, abs=1e-8)
    for row in (0, 2):
        other = fixed_fit(df, "a", table.loc[row, "a"])
        assert table.loc[row, "loglik"] == pytest.approx(other.loglik, abs=1e-6)
        for name in ("b", "s", "r", "x0"):
            assert table.loc[row, name] == pytest.approx(other.params.loc[name, "estimate"], rel=1e-4, abs=1e-7)
    grid = fit.profile("s", n=11, span=2)
    se = fit.params.loc["s", "std_error"]
    np.testing.assert_allclose(grid["s"], np.linspace(-2, 2, 11) * se + fit.params.loc["s", "estimate"])
    # Near the optimum the profile is the Wald parabola; further out the noise intensity's is skewed.
    near = grid.iloc[4:7]
    np.testing.assert_allclose(near["deviance"], ((near["s"] - fit.params.loc["s", "estimate"]) / se) ** 2,
                               rtol=0.15, atol=1e-9)
    assert grid["deviance"].iloc[0] > grid["deviance"].iloc[-1]
    assert grid.attrs["threshold"] == pytest.approx(THRESHOLD)
    with pytest.raises(greyid.ModelError, match="outside its bounds"):
        fit.profile("s", values=[-0.1, 0.4])
    with pytest.raises(greyid.ModelError, match="'q' is neither a parameter nor a derived quantity"):
        fit.profile("q")


def test_profile_intervals_sit_on_the_chi2_threshold(ou_fit):
    m, df, fit = ou_fit
    ci = fit.conf_int(method="profile")
    wald = fit.conf_int()
    for name in ("a", "s"):
        for end in ("lower", "upper"):
            deviance = 2 * (fit.loglik - fixed_fit(df, name, ci.loc[name, end]).loglik)
            assert deviance == pytest.approx(THRESHOLD, abs=1e-4)
        width = ci.loc[name, "upper"] - ci.loc[name, "lower"]
        assert width == pytest.approx(wald.loc[name, "upper"] - wald.loc[name, "lower"], rel=0.15)
    # A variance that the data cannot tell from 0: the interval's lower end is the bound, said so.
    small = ou_data(r=1e-5)
    fit_small = ou_model().fit(small)
    with pytest.warns(greyid.FitWarning, match="lower end of the profile interval of 'r' runs into its bound 0"):
        bounded = fit_small.conf_int(method="profile")
    assert bounded.loc["r", "lower"] == 0.0 and bounded.loc["r", "upper"] > fit_small.params.loc["r", "estimate"]
    assert 2 * (fit_small.loglik - fixed_fit(small, "r", bounded.loc["r", "upper"]).loglik) == pytest.approx(
        THRESHOLD, abs=1e-4)
    with pytest.raises(greyid.ModelError, match="method='wald' or 'profile'"):
        fit.conf_int(method="bootstrap")


def test_the_threshold_is_scipy_s_chi2_quantile():
    """The profile's χ²₁ quantile without importing scipy.stats: the same number to the last bit."""
    import sys

    module = sys.modules["greyid.uncertainty.profile"]
    for level in (0.5, 0.683, 0.8, 0.9, 0.95, 0.99, 0.999, 1 - 1e-9):
        assert module._chi2_quantile(level) == stats.chi2.ppf(level, 1)


def test_newton_ends_agree_with_the_secant_search_and_sit_on_the_threshold(ou_fit, monkeypatch):
    """The ends by Newton's method on the end's equations (Venzon and Moolgavkar) against the secant search
    along the profile (forced by a Newton solver that gives up) and against fits with the parameter fixed:
    on the threshold to 1e-7 where the search stops within 4e-5, and each of the ten ends found by Newton."""
    import sys

    module = sys.modules["greyid.uncertainty.profile"]
    m, df, fit = ou_fit
    solved = []
    newton_end = module._newton_end

    def counted(*args):
        end = newton_end(*args)
        solved.append(end is not None)
        return end

    monkeypatch.setattr(module, "_newton_end", counted)
    newton = uncertainty.profile_intervals(fit)
    assert solved == [True] * 10
    # Newton's method where the fit's Hessian is the Kalman filter's forward over forward, refits elsewhere.
    from types import SimpleNamespace as Problem
    for method, free, long_series, pays in (("kalman", 10, False, True), ("kalman", 11, False, False),
                                            ("kalman", 5, True, False), ("ekf", 5, False, False),
                                            ("laplace", 5, False, False)):
        problem = Problem(options=Problem(method=method), free=tuple(range(free)), long_series=long_series)
        assert module._newton_pays(problem) is pays
    monkeypatch.setattr(module, "_newton_end", lambda *args: None)
    secant = uncertainty.profile_intervals(fit)
    se = fit.params["std_error"]
    for end in ("lower", "upper"):
        assert np.all(np.abs(newton[end] - secant[end]) < 1e-4 * se), end
    for name in ("a", "r"):
        for end in ("lower", "upper"):
            deviance = 2 * (fit.loglik - fixed_fit(df, name, newton.loc[name, end]).loglik)
            assert deviance == pytest.approx(THRESHOLD, abs=1e-7)


def test_an_unbounded_parameter_far_from_zero_has_its_interval(ou_fit, monkeypatch):
    """An unbounded parameter is its own optimiser coordinate: an end beyond 35 is no bound (the input in
    hundredths puts the gain b near 100), by Newton's method and by the secant search alike."""
    import sys

    module = sys.modules["greyid.uncertainty.profile"]
    _, df, _ = ou_fit
    scaled = df.assign(u=df["u"] / 100.0)
    fit = ou_model().fit(scaled)
    b = fit.params.loc["b", "estimate"]
    assert b > 50
    with warnings.catch_warnings():
        warnings.simplefilter("error", greyid.FitWarning)
        newton = uncertainty.profile_interval(fit, "b")
        monkeypatch.setattr(module, "_newton_end", lambda *args: None)
        secant = uncertainty.profile_interval(fit, "b")
    assert newton[0] < b < newton[1] and newton[0] > 35
    np.testing.assert_allclose(newton, secant, rtol=0, atol=1e-4 * fit.params.loc["b", "std_error"])
    for end in newton:
        assert 2 * (fit.loglik - fixed_fit(scaled, "b", end).loglik) == pytest.approx(THRESHOLD, abs=1e-6)


def test_profile_of_a_derived_quantity_equals_the_reparametrised_fit(ou_fit):
    """The static gain g = b/a profiled under the constraint equals a model written in (a, g) with g fixed."""
    m, df, fit = ou_fit
    g_hat = fit.params.loc["b", "estimate"] / fit.params.loc["a", "estimate"]
    table = fit.profile("gain", expression="b/a", values=[0.9 * g_hat, g_hat, 1.15 * g_hat])
    assert table["converged"].all() and table.loc[1, "deviance"] == pytest.approx(0.0, abs=1e-7)
    for row in (0, 2):
        reparametrised = greyid.Model("ou_gain")
        reparametrised.add_system("dx = (-a*x + g*a*u)*dt + s*dw1")
        reparametrised.add_inputs("u")
        reparametrised.add_observation("y = x", variance="r")
        reparametrised.set_initial_state(mean={"x": "x0"}, covariance=[[0.1]])
        for name, spec in dict(a=dict(init=0.5, lower=0.0, upper=10.0), s=dict(init=0.3, lower=0.0),
                               r=dict(init=0.1, lower=0.0), x0=dict(init=0.0)).items():
            reparametrised.set_parameter(name, **spec)
        other = fixed_fit(df, "g", table.loc[row, "gain"], model=reparametrised)
        assert table.loc[row, "loglik"] == pytest.approx(other.loglik, abs=1e-5)
        assert table.loc[row, "a"] == pytest.approx(other.params.loc["a", "estimate"], rel=1e-3)


def test_nuts_matches_the_closed_form_posterior_of_a_variance():
    """y_k ~ N(0, r), flat prior on r > 0: r | y is inverse gamma (N/2 − 1, S/2)."""
    m = greyid.Model("white")
    m.add_system("dx = -x*dt + q*dw1")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": "0"}, covariance=[[1e-14]])
    m.set_parameter("q", init=1e-9, fixed=True)
    m.set_parameter("r", init=1.0, lower=0.0)
    y = np.random.default_rng(3).normal(0.0, 1.5, 12)
    fit = m.fit(pd.DataFrame({"t": np.arange(12.0), "y": y}))
    posterior = fit.sample(draws=1500, chains=4, warmup=400, seed=2)
    exact = stats.invgamma(a=12 / 2 - 1, scale=np.sum(y ** 2) / 2)
    draws = posterior.draws["r"].to_numpy()
    assert posterior.divergences == 0 and posterior.r_hat["r"] < 1.02 and posterior.ess["r"] > 1000
    error = exact.std() / np.sqrt(posterior.ess["r"])
    assert abs(draws.mean() - exact.mean()) < 4 * error
    for p in (0.1, 0.5, 0.9):
        assert np.quantile(draws, p) == pytest.approx(exact.ppf(p), rel=0.05)
    # Skewed: the posterior mean lies well above the maximum-likelihood estimate S/N.
    assert draws.mean() > 1.15 * fit.params.loc["r", "estimate"]


def test_nuts_agrees_with_importance_sampling_and_the_laplace_spread(ou_fit):
    """The posterior means against self-normalised importance sampling of the exact likelihood (a
    Student-t proposal around the estimates); the spread against the Laplace approximation."""
    m, df, fit = ou_fit
    posterior = fit.sample(draws=500, chains=2, warmup=300, seed=1)
    assert posterior.draws.shape == (1000, 5) and posterior.chains == 2
    assert posterior.divergences == 0 and (posterior.r_hat < 1.05).all()
    names = list(m.parameter_names)
    estimate = fit.params.loc[names, "estimate"].to_numpy()
    proposal = stats.multivariate_t(loc=estimate, shape=1.5 * fit.cov.loc[names, names].to_numpy(), df=5)
    points = proposal.rvs(1500, random_state=np.random.default_rng(0))
    inside = (points[:, 0] > 0) & (points[:, 0] < 10) & (points[:, 2] > 0) & (points[:, 3] > 0)
    loglik = np.array([m.loglik(dict(zip(names, x)), df) if ok else -np.inf for x, ok in zip(points, inside)])
    weights = np.exp(loglik - proposal.logpdf(points) - np.max(loglik - proposal.logpdf(points)))
    weights /= weights.sum()
    reference = pd.Series(weights @ points, index=names)
    reference_ess = 1 / np.sum(weights ** 2)
    assert reference_ess > 500
    summary = posterior.summary()
    for name in names:
        se = fit.params.loc[name, "std_error"]
        monte_carlo = summary.loc[name, "sd"] * np.sqrt(1 / posterior.ess[name] + 1 / reference_ess)
        assert abs(summary.loc[name, "mean"] - reference[name]) < 4 * monte_carlo
        assert summary.loc[name, "sd"] == pytest.approx(se, rel=0.2)
    # The posterior of the rate a is skewed: its mean lies above the maximum-likelihood estimate.
    assert summary.loc["a", "mean"] > fit.params.loc["a", "estimate"] + 0.2 * fit.params.loc["a", "std_error"]
    idata = posterior.to_inference_data()
    assert idata.posterior["a"].shape == (2, 500)
    with pytest.raises(greyid.ModelError, match="draws must be an integer"):
        fit.sample(draws=0)


def test_prediction_intervals_are_the_mixture_of_the_parameter_draws(ou_fit):
    m, df, fit = ou_fit
    out = fit.predict(steps=5, parameter_uncertainty=True, draws=50, seed=4)
    from greyid.uncertainty.intervals import parameter_draws

    thetas = parameter_draws(fit, 50, seed=4)
    names = list(m.parameter_names)
    predictions = [m.predict(dict(zip(names, th)), df, steps=5) for th in thetas]
    means = np.array([p["y"].to_numpy() for p in predictions])
    sds = np.array([p["y_sd"].to_numpy() for p in predictions])
    np.testing.assert_allclose(out["y"], means.mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(out["y_sd"] ** 2, (sds ** 2).mean(axis=0) + means.var(axis=0), rtol=1e-9)
    # The mixture's quantiles, from samples of the mixture itself.
    rng = np.random.default_rng(0)
    pick = rng.integers(0, 50, 40_000)
    samples = means[pick, 100] + sds[pick, 100] * rng.standard_normal(40_000)
    assert out.loc[100, "y_lower"] == pytest.approx(np.quantile(samples, 0.025), abs=0.01)
    assert out.loc[100, "y_upper"] == pytest.approx(np.quantile(samples, 0.975), abs=0.01)
    plain = fit.predict(steps=5, interval=0.9)
    np.testing.assert_allclose(plain["y_upper"] - plain["y"], stats.norm.ppf(0.95) * plain["y_sd"])
    np.testing.assert_allclose(out["y_sd_noise"], plain["y_sd"], rtol=1e-9)


def test_forecast_intervals_with_parameter_uncertainty_cover(ou_fit):
    """Fits on short series, 20-step forecasts of the next 40 samples: the parameter-aware 90 % intervals
    cover about 90 % of the future outputs, more than the plug-in ones."""
    m = ou_model()
    covered = {True: [], False: []}
    for replication in range(12):
        full = ou_data(n=100, seed=100 + replication)
        train, future = full.iloc[:60], full.iloc[60:]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = m.fit(train)
        ahead = pd.concat([train, future.assign(y=np.nan)])
        for uncertain in (True, False):
            p = fit.predict(ahead, steps=20, interval=0.9, parameter_uncertainty=uncertain, draws=100,
                            seed=replication).iloc[60:]
            covered[uncertain].append(((future["y"] >= p["y_lower"]) & (future["y"] <= p["y_upper"])).to_numpy())
    with_parameters, plug_in = np.mean(covered[True]), np.mean(covered[False])
    assert 0.85 <= with_parameters <= 0.97
    assert with_parameters > plug_in


def test_simulation_bands_with_parameter_uncertainty_are_wider(ou_fit):
    m, df, fit = ou_fit
    with_parameters = fit.simulate(n_paths=100, parameter_uncertainty=True, seed=3)
    plain = fit.simulate(n_paths=100, interval=0.95, seed=3)
    assert list(with_parameters.columns) == ["t", "y", "y_lower", "y_upper"]
    width = (with_parameters["y_upper"] - with_parameters["y_lower"]).mean()
    assert width > (plain["y_upper"] - plain["y_lower"]).mean()
    # Coverage of the fitted data by the 95 % simulation band (the model is right).
    inside = ((df["y"] >= with_parameters["y_lower"]) & (df["y"] <= with_parameters["y_upper"])).mean()
    assert 0.88 <= inside <= 1.0
    figure = uncertainty.plot_intervals(with_parameters, df)
    line = figure.axes[0].lines[0]
    np.testing.assert_allclose(line.get_ydata(), with_parameters["y"])
    with pytest.raises(greyid.ModelError, match="no <output>_lower"):
        uncertainty.plot_intervals(fit.predict())


def test_plot_profile_returns_the_figure_of_the_profile(ou_fit):
    """plot_profile draws the profile's deviance and the χ² threshold and returns the Figure, as the other
    plot methods do; on a given Axes it draws there (and returns that Axes' Figure)."""
    from matplotlib.figure import Figure

    _, _, fit = ou_fit
    figure = fit.plot_profile("a", n=5)
    assert isinstance(figure, Figure)
    ax = figure.axes[0]
    table = fit.profile("a", n=5)
    np.testing.assert_allclose(ax.lines[0].get_ydata(), table["deviance"], rtol=1e-8)
    assert any(np.allclose(line.get_ydata(), THRESHOLD) for line in ax.lines)
    given = Figure().subplots()
    assert fit.plot_profile("a", ax=given, n=5) is given.figure
