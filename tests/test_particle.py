"""Observation distributions and the bootstrap particle filter, against independent references: the exact
Kalman filter (linear Gaussian), a point-mass filter on a grid computed here (Poisson counts), closed-form
densities (SciPy)."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

import greyid
from greyid.errors import DataError, ModelError
from greyid.estimate.approximations import compare_methods, particle_loglik
from greyid.model.distributions import cdf, log_density, moments
from greyid.schema import check_options


def ou_gaussian():
    m = greyid.Model("ou")
    m.add_system("dx = -a*(x - mu)*dt + s*dw1")
    m.add_observation("y = x", variance="r")
    for name, value in dict(a=0.5, mu=1.0, s=0.4, r=0.04).items():
        m.set_parameter(name, init=value, lower=1e-3, upper=10)
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.1]])
    return m


def ou_data(n=60, seed=1):
    rng = np.random.default_rng(seed)
    x, ys = 1.0, []
    for _ in range(n):
        ys.append(x + 0.2 * rng.normal())
        x = 1 + (x - 1) * np.exp(-0.5) + 0.4 * np.sqrt(1 - np.exp(-1.0)) * rng.normal()
    return pd.DataFrame({"t": np.arange(float(n)), "y": ys})


PARAMS = dict(a=0.5, mu=1.0, s=0.4, r=0.04)


def test_the_particle_estimate_lies_within_its_errors_of_the_exact_likelihood_and_its_error_shrinks():
    """Linear Gaussian model: over seeds the estimate lies within 3 Monte Carlo standard errors of the
    Kalman filter's exact value, and the error falls as 1/√P."""
    m, data = ou_gaussian(), ou_data()
    exact = m.loglik(PARAMS, data, method="kalman")
    errors = {}
    for particles in (250, 1000):
        for seed in range(3):
            estimate = particle_loglik(m, PARAMS, data, particles=particles, seed=seed, replicates=8)
            assert abs(estimate.loglik - exact) < 3 * estimate.std_error + 1e-3, (particles, seed, estimate)
            errors.setdefault(particles, []).append(estimate.spread)
    ratio = np.mean(errors[250]) / np.mean(errors[1000])
    assert 1.3 < ratio < 3.2, ratio  # 2 for 1/√P


def test_the_same_seed_gives_the_same_estimate_and_another_seed_another():
    m, data = ou_gaussian(), ou_data(30)
    first = m.loglik(PARAMS, data, method="particle", particles=200, seed=3)
    assert m.loglik(PARAMS, data, method="particle", particles=200, seed=3) == first
    assert m.loglik(PARAMS, data, method="particle", particles=200, seed=4) != first


def poisson_model():
    m = greyid.Model("counts")
    m.add_system("dl = -a*(l - mu)*dt + s*dw1")
    m.add_observation("n = exp(l)", distribution="poisson")
    for name, value in dict(a=0.5, mu=2.0, s=0.5).items():
        m.set_parameter(name, init=value, lower=1e-3, upper=10)
    m.set_initial_state(mean={"l": "mu"}, covariance="stationary")
    return m


def poisson_data(n=40, seed=3, a=0.5, mu=2.0, s=0.5):
    rng = np.random.default_rng(seed)
    level, counts = mu, []
    for _ in range(n):
        counts.append(rng.poisson(np.exp(level)))
        level = mu + (level - mu) * np.exp(-a) + s * np.sqrt((1 - np.exp(-2 * a)) / (2 * a)) * rng.normal()
    return pd.DataFrame({"t": np.arange(float(n)), "n": counts})


def point_mass_grid(a=0.5, mu=2.0, s=0.5, points=3000):
    """The log-rate's grid, its exact Gaussian transition between grid points and its stationary law on them."""
    sd = s / np.sqrt(2 * a)
    grid = np.linspace(mu - 8 * sd, mu + 8 * sd, points)
    step_sd = sd * np.sqrt(1 - np.exp(-2 * a))
    transition = stats.norm.pdf(grid[None, :], mu + (grid[:, None] - mu) * np.exp(-a), step_sd)
    transition /= transition.sum(axis=1, keepdims=True)
    prior = stats.norm.pdf(grid, mu, sd)
    return grid, transition, prior / prior.sum()


def grid_loglik(counts, a=0.5, mu=2.0, s=0.5, points=3000):
    """The point-mass filter: the log-rate on a fine grid, its exact Gaussian transition, Poisson weights."""
    grid, transition, prior = point_mass_grid(a, mu, s, points)
    total = 0.0
    for k, y in enumerate(counts):
        if k > 0:
            prior = prior @ transition
        joint = prior * stats.poisson.pmf(y, np.exp(grid))
        total += np.log(joint.sum())
        prior = joint / joint.sum()
    return total


def test_poisson_counts_on_a_latent_log_rate_match_a_point_mass_filter():
    m, data = poisson_model(), poisson_data()
    reference = grid_loglik(data["n"].to_numpy())
    estimate = particle_loglik(m, dict(a=0.5, mu=2.0, s=0.5), data, particles=2000, seed=0, replicates=8)
    assert abs(estimate.loglik - reference) < 3 * estimate.std_error + 1e-3, (estimate, reference)
    assert estimate.std_error < 0.1


def test_a_gaussian_filter_refuses_counts_and_names_the_methods_that_can():
    m, data = poisson_model(), poisson_data(20)
    with pytest.raises(ModelError, match=r"'n' has the poisson distribution.*'ekf'.*method='particle'"):
        m.loglik(dict(a=0.5, mu=2.0, s=0.5), data)
    with pytest.raises(ModelError, match="'kalman'"):
        m.fit(data, method="kalman")


@pytest.mark.parametrize("bad, message", [(-1, "-1 at row 3"), (2.5, "2.5 at row 3")])
def test_counts_that_are_negative_or_not_whole_are_refused_naming_column_and_row(bad, message):
    m, data = poisson_model(), poisson_data(20)
    data["n"] = data["n"].astype(float)
    data.loc[3, "n"] = bad
    with pytest.raises(DataError, match=f"column 'n' has {message}.*non-negative whole number"):
        m.loglik(dict(a=0.5, mu=2.0, s=0.5), data, method="particle", particles=10)


def test_bad_distribution_declarations_and_settings_are_refused():
    m = greyid.Model("x")
    m.add_system("dx = -x*dt + dw1")
    with pytest.raises(ModelError, match="needs its trials"):
        m.add_observation("y = x", distribution="binomial")
    with pytest.raises(ModelError, match="unknown observation distribution 'gamma'"):
        m.add_observation("y = x", distribution="gamma")
    with pytest.raises(ModelError, match="leave variance out"):
        m.add_observation("y = exp(x)", variance=1.0, distribution="poisson")
    with pytest.raises(ModelError, match="needs its variance"):
        m.add_observation("y = x", distribution={"family": "student_t", "df": "nu"})
    with pytest.raises(ModelError, match="particles must be a positive integer"):
        ou_gaussian().loglik(PARAMS, ou_data(20), method="particle", particles=0)


def test_distributions_travel_through_model_files(tmp_path):
    m = greyid.Model("mixed")
    m.add_system("dx = -a*x*dt + dw1")
    m.add_inputs("trials")
    m.add_observation("k = 1/(1 + exp(-x))", distribution={"family": "binomial", "trials": "trials"})
    m.add_observation("z = x", variance="v", distribution={"family": "student_t", "df": "nu"})
    m.add_observation("c = exp(x)", distribution="poisson")
    m.set_parameter("a", init=1.0)
    m.set_parameter("v", init=0.1)
    m.set_parameter("nu", init=4.0)
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    path = tmp_path / "mixed.toml"
    m.to_toml(path)
    text = path.read_text()
    assert 'k = { equation = "1/(1 + exp(-x))", distribution = { family = "binomial", trials = "trials" } }' in text
    again = greyid.Model.from_toml(path)
    assert again.structure.distributions == ("binomial", "student_t", "poisson")
    assert again.to_dict()["observations"] == m.to_dict()["observations"]


@pytest.mark.parametrize("family, shape, scipy_law", [
    ("normal", 1.0, lambda y, m, v, a: stats.norm.logpdf(y, m, np.sqrt(v))),
    ("student_t", 4.5, lambda y, m, v, a: stats.t.logpdf(y, a, m, np.sqrt(v))),
    ("lognormal", 1.0, lambda y, m, v, a: stats.lognorm.logpdf(y, np.sqrt(v), scale=m)),
    ("poisson", 1.0, lambda y, m, v, a: stats.poisson.logpmf(y, m)),
    ("negative_binomial", 3.0, lambda y, m, v, a: stats.nbinom.logpmf(y, a, a / (a + m))),
    ("binomial", 12.0, lambda y, m, v, a: stats.binom.logpmf(y, a, m)),
])
def test_each_density_and_its_moments_match_scipy(family, shape, scipy_law):
    m = 0.35 if family == "binomial" else 2.7
    variance = 0.3
    for y in (0.0, 1.0, 3.0, 7.0) if family not in ("normal", "student_t", "lognormal") else (0.4, 2.5, 6.0):
        ours = float(log_density(family, y, m, variance, shape))
        assert ours == pytest.approx(scipy_law(y, m, variance, shape), rel=1e-10, abs=1e-12)
    counts = family not in ("normal", "student_t", "lognormal")
    for y in (0.0, 1.0, 3.0, 7.0, 12.0) if counts else (-1.0, 0.4, 2.5, 6.0):
        expected = {"normal": lambda: stats.norm.cdf(y, m, np.sqrt(variance)),
                    "student_t": lambda: stats.t.cdf(y, shape, m, np.sqrt(variance)),
                    "lognormal": lambda: stats.lognorm.cdf(y, np.sqrt(variance), scale=m),
                    "poisson": lambda: stats.poisson.cdf(y, m),
                    "negative_binomial": lambda: stats.nbinom.cdf(y, shape, shape / (shape + m)),
                    "binomial": lambda: stats.binom.cdf(y, shape, m)}[family]()
        assert float(cdf(family, y, m, variance, shape)) == pytest.approx(expected, rel=1e-9, abs=1e-12), y
    mean, var = (float(v) for v in moments(family, m, variance, shape))
    law = {"normal": stats.norm(m, np.sqrt(variance)), "student_t": stats.t(shape, m, np.sqrt(variance)),
           "lognormal": stats.lognorm(np.sqrt(variance), scale=m), "poisson": stats.poisson(m),
           "negative_binomial": stats.nbinom(shape, shape / (shape + m)), "binomial": stats.binom(shape, m)}[family]
    assert (mean, var) == pytest.approx((law.mean(), law.var()), rel=1e-10)


def test_a_particle_fit_of_counts_lands_near_the_simulated_parameters():
    """Common random numbers make the estimate a function of θ that the optimiser can work on."""
    m, data = poisson_model(), poisson_data(200)
    m.set_parameter("a", init=0.3, lower=1e-3, upper=10)
    m.set_parameter("mu", init=1.5, lower=-5, upper=10)
    fit = m.fit(data, method="particle", particles=1000)
    assert fit.settings["method"] == "particle" and fit.settings["particles"] == 1000
    assert abs(fit.values["mu"] - 2.0) < 0.3 and abs(fit.values["s"] - 0.5) < 0.2 and 0.2 < fit.values["a"] < 1.2
    exact_at_start = grid_loglik(data["n"].to_numpy(), a=0.3, mu=1.5, s=0.5)
    assert fit.loglik > exact_at_start + 5  # it climbed


def test_compare_methods_puts_the_gaussian_filters_beside_the_particle_estimate():
    m, data = ou_gaussian(), ou_data()
    table = compare_methods(m, PARAMS, data, methods=["kalman", "ekf", "ukf"], particles=1000)
    assert list(table.index) == ["kalman", "ekf", "ukf", "particle"]
    assert table["agrees"].all(), table  # a linear Gaussian model: every filter is exact
    assert table.loc["kalman", "loglik"] == pytest.approx(m.loglik(PARAMS, data, method="kalman"))
    assert table.loc["particle", "std_error"] > 0


def test_filtering_with_particles_gives_states_and_innovations_close_to_the_kalman_filter():
    m, data = ou_gaussian(), ou_data()
    exact = m.filter(PARAMS, data, method="kalman")
    particles = m.filter(PARAMS, data, method="particle", particles=4000)
    assert np.max(np.abs(particles.filtered["x"] - exact.filtered["x"])) < 0.02
    assert np.max(np.abs(particles.innovations["y"] - exact.innovations["y"])) < 0.02
    # the same random numbers as the likelihood's (whose accuracy the tests above check)
    assert particles.loglik_terms.sum() == pytest.approx(
        m.loglik(PARAMS, data, method="particle", particles=4000), abs=1e-9)


def test_simulated_counts_have_the_poisson_lognormal_mixtures_moments():
    """Counts drawn along a stationary latent log-rate: mean e^{μ+σ²/2}, variance mean + e^{2μ+σ²}(e^{σ²} − 1)."""
    m = poisson_model()
    sim = m.simulate(dict(a=0.5, mu=2.0, s=0.5), np.arange(5.0), n_paths=40_000, seed=2)
    counts = sim.outputs[:, :, 0]
    assert np.all(counts == np.round(counts)) and counts.min() >= 0
    variance = 0.5**2 / (2 * 0.5)
    mean = np.exp(2.0 + variance / 2)
    spread = mean + np.exp(4.0 + variance) * np.expm1(variance)
    assert counts.mean() == pytest.approx(mean, rel=0.02)
    assert counts.var() == pytest.approx(spread, rel=0.05)
    without_noise = m.simulate(dict(a=0.5, mu=2.0, s=0.5), np.arange(5.0), n_paths=3, seed=2, noise=False)
    assert np.allclose(without_noise.outputs[:, :, 0], np.exp(without_noise.states[:, :, 0]))


@pytest.mark.parametrize("family, law, extra", [
    ("negative_binomial", {"family": "negative_binomial", "size": "r"}, dict(r=3.0)),
    ("binomial", {"family": "binomial", "trials": "N"}, {}),
    ("student_t", {"family": "student_t", "df": "nu"}, dict(nu=5.0, v=0.3)),
    ("lognormal", "lognormal", dict(v=0.3)),
])
def test_each_family_simulates_with_its_moments_and_its_particle_likelihood_matches_the_grid(family, law, extra):
    """A latent OU state x; the output's location exp(x) (a probability 1/(1+e^{-x}) for the binomial):
    simulated draws have the family's mean given the states, and the particle filter matches a point-mass
    filter of the same model."""
    m = greyid.Model(family)
    m.add_system("dx = -a*(x - mu)*dt + s*dw1")
    location = "1/(1 + exp(-x))" if family == "binomial" else "exp(x)"
    variance = "v" if family in ("student_t", "lognormal") else None
    m.add_observation(f"y = {location}", variance=variance, distribution=law)
    if family == "binomial":
        m.add_inputs("N")
    m.set_initial_state(mean={"x": "mu"}, covariance="stationary")
    params = dict(a=0.5, mu=0.5, s=0.5, **extra)
    times = np.arange(30.0)
    frame = pd.DataFrame({"t": times, "N": 20.0}) if family == "binomial" else times
    sim = m.simulate(params, frame, n_paths=20_000, seed=5)
    x, y = sim.states[:, :, 0], sim.outputs[:, :, 0]
    place = 1 / (1 + np.exp(-x)) if family == "binomial" else np.exp(x)
    conditional_mean = {"negative_binomial": place, "binomial": 20 * place, "student_t": place,
                        "lognormal": place * np.exp(0.15)}[family]
    residual = (y - conditional_mean).mean()
    assert abs(residual) < 0.05 * np.abs(conditional_mean).mean(), residual
    data = sim.frame(0)[["t", "y"] + (["N"] if family == "binomial" else [])]
    reference = grid_family_loglik(family, data["y"].to_numpy(), params)
    estimate = particle_loglik(m, params, data, particles=2000, seed=1, replicates=8)
    assert abs(estimate.loglik - reference) < 3 * estimate.std_error + 2e-3, (estimate, reference)


def grid_family_loglik(family, ys, p, points=2000):
    a, mu, s = p["a"], p["mu"], p["s"]
    sd = s / np.sqrt(2 * a)
    grid = np.linspace(mu - 8 * sd, mu + 8 * sd, points)
    transition = stats.norm.pdf(grid[None, :], mu + (grid[:, None] - mu) * np.exp(-a), sd * np.sqrt(1 - np.exp(-2 * a)))
    transition /= transition.sum(axis=1, keepdims=True)
    prior = stats.norm.pdf(grid, mu, sd)
    prior /= prior.sum()
    place = np.exp(grid)
    density = {
        "negative_binomial": lambda y: stats.nbinom.pmf(y, p.get("r", 1), p.get("r", 1) / (p.get("r", 1) + place)),
        "binomial": lambda y: stats.binom.pmf(y, 20, 1 / (1 + np.exp(-grid))),
        "student_t": lambda y: stats.t.pdf(y, p.get("nu", 1), place, np.sqrt(p.get("v", 1))),
        "lognormal": lambda y: stats.lognorm.pdf(y, np.sqrt(p.get("v", 1)), scale=place),
    }[family]
    total = 0.0
    for k, y in enumerate(ys):
        if k > 0:
            prior = prior @ transition
        joint = prior * density(y)
        total += np.log(joint.sum())
        prior = joint / joint.sum()
    return total


COUNTS_FILE = """
[model]
name = "counts"
system = ["dl = -a*(l - mu)*dt + s*dw1"]
initial_covariance = "stationary"

[model.observations]
n = { equation = "exp(l)", distribution = "poisson" }

[model.initial_state]
l = "mu"

[parameters]
a = { init = 0.5, lower = 0.001, upper = 10 }
mu = { init = 2.0, lower = -5, upper = 10 }
s = { init = 0.5, lower = 0.001, upper = 10 }

[filter]
method = "METHOD"
"""


@pytest.mark.parametrize("method, bad, message", [
    ("ekf", None, "'n' has the poisson distribution, which the Gaussian filter 'ekf' cannot evaluate"),
    ("particle", -2, "column 'n' has -2 at row 4"),
])
def test_the_command_line_refuses_counts_for_a_gaussian_filter_and_bad_counts_with_exit_2(tmp_path, method, bad,
                                                                                           message):
    from test_bad_input import run_cli

    (tmp_path / "model.toml").write_text(COUNTS_FILE.replace("METHOD", method))
    data = poisson_data(30)
    if bad is not None:
        data.loc[4, "n"] = bad
    data.to_csv(tmp_path / "data.csv", index=False)
    code, printed = run_cli(["fit", str(tmp_path / "model.toml"), str(tmp_path / "data.csv"), "-q"])
    assert code == 2 and message in printed and "Traceback" not in printed, printed


def test_the_ensemble_kalman_filter_converges_to_the_exact_likelihood_as_the_ensemble_grows():
    """Linear Gaussian model: the stochastic EnKF's log-likelihood (fixed random numbers) approaches the Kalman
    filter's as the ensemble grows (the mean error over seeds falls), and its filtered states approach the exact."""
    m, data = ou_gaussian(), ou_data()
    exact = m.loglik(PARAMS, data, method="kalman")
    error = {size: np.mean([abs(m.loglik(PARAMS, data, method="enkf", particles=size, seed=seed) - exact)
                            for seed in range(4)]) for size in (20, 200, 2000)}
    assert error[200] < error[20] and error[2000] < error[200], error
    assert error[2000] < 0.5, error
    states = m.filter(PARAMS, data, method="enkf", particles=2000).filtered["x"]
    assert np.max(np.abs(states - m.filter(PARAMS, data, method="kalman").filtered["x"])) < 0.03


def test_the_ensemble_kalman_filter_refuses_counts_and_bad_settings():
    with pytest.raises(ModelError, match="Gaussian filter 'enkf'"):
        poisson_model().loglik(dict(a=0.5, mu=2.0, s=0.5), poisson_data(20), method="enkf")
    with pytest.raises(ModelError, match="inflation must be a number of at least 1"):
        ou_gaussian().loglik(PARAMS, ou_data(20), method="enkf", inflation=0.5)
    with pytest.raises(ModelError, match="at least 2 members"):
        ou_gaussian().loglik(PARAMS, ou_data(20), method="enkf", particles=1)


def test_a_fit_compares_its_filter_with_the_particle_estimate_at_its_estimates():
    m, data = ou_gaussian(), ou_data()
    fit = m.fit(data, method="kalman")
    table = fit.compare_methods(methods=["kalman", "ekf"], particles=2000)
    assert table.loc["kalman", "loglik"] == pytest.approx(fit.loglik, abs=1e-6)
    assert table["agrees"].all(), table


def test_the_particle_filters_quantile_residuals_are_normal_where_the_model_is_right_and_not_where_it_is_wrong():
    """Randomized probability integral transforms of counts (Dunn & Smyth 1996): under the simulating parameters
    their normal quantiles pass a Kolmogorov–Smirnov test, under a wrong mean level they fail it; a particle
    fit's residuals are these."""
    m, data = poisson_model(), poisson_data(300, seed=11)
    right = m.filter(dict(a=0.5, mu=2.0, s=0.5), data, method="particle", particles=2000).quantile_residuals["n"]
    wrong = m.filter(dict(a=0.5, mu=1.2, s=0.5), data, method="particle", particles=2000).quantile_residuals["n"]
    assert stats.kstest(right, "norm").pvalue > 0.01
    assert stats.kstest(wrong, "norm").pvalue < 1e-3
    assert right.shape == (300,) and right.notna().all()


def test_every_filter_gives_quantile_residuals():
    """A Gaussian filter's (and the ensemble's) predictive law of y_k is N(ŷ, R_k): Φ⁻¹ of its transform is the
    standardized innovation, NaN where unobserved; on a linear Gaussian model the particle filter's agree with
    them up to Monte Carlo error."""
    m, data = ou_gaussian(), ou_data(200, seed=4)
    data.loc[[7, 30], "y"] = np.nan
    exact = m.filter(PARAMS, data, method="kalman")
    pd.testing.assert_frame_equal(exact.quantile_residuals, exact.standardized_innovations)
    assert exact.quantile_residuals["y"].isna().sum() == 2
    ensemble = m.filter(PARAMS, data, method="enkf", particles=500)
    pd.testing.assert_frame_equal(ensemble.quantile_residuals, ensemble.standardized_innovations)
    particles = m.filter(PARAMS, data, method="particle", particles=4000).quantile_residuals["y"]
    # (the particle filter's transforms are of its weighted predicted particles, Monte Carlo error ~ 1/√P)
    assert np.nanmax(np.abs(particles - exact.quantile_residuals["y"])) < 0.1
    assert stats.kstest(exact.quantile_residuals["y"].dropna(), "norm").pvalue > 0.01


@pytest.mark.parametrize("proposal", ["ekf", "ukf"])
def test_a_guided_proposal_keeps_the_exact_likelihood_with_a_fraction_of_the_bootstraps_error(proposal):
    """A sharp observation (r = 4·10⁻⁴) of a linear Gaussian model: the bootstrap's weights degenerate, a
    Gaussian-filter proposal's do not; both estimate the Kalman filter's value."""
    m, data = ou_gaussian(), ou_data()
    sharp = dict(PARAMS, r=4e-4)
    exact = m.loglik(sharp, data, method="kalman")
    bootstrap = particle_loglik(m, sharp, data, particles=200, seed=0, replicates=8)
    for seed in (0, 1):
        guided = particle_loglik(m, sharp, data, particles=200, seed=seed, replicates=8, proposal=proposal)
        assert abs(guided.loglik - exact) < 3 * guided.std_error + 1e-3, (seed, guided, exact)
        assert guided.spread < bootstrap.spread / 10, (guided.spread, bootstrap.spread)


def state_dependent_noise():
    """dx = −a x dt + s √(1 + x²) dω, y = x + e: a diffusion that depends on the state."""
    m = greyid.Model("state-dependent noise")
    m.add_system("dx = -a*x*dt + s*sqrt(1 + x^2)*dw1")
    m.add_observation("y = x", variance="r")
    params = dict(a=0.5, s=0.5, r=0.01)
    for name, value in params.items():
        m.set_parameter(name, init=value)
    m.set_initial_state(mean={"x": 0.5}, covariance=[[0.1]])
    rng = np.random.default_rng(2)
    x, ys = 0.5, []
    for _ in range(40):
        ys.append(x + 0.1 * rng.normal())
        for _ in range(50):
            x += -0.5 * x * 0.02 + 0.5 * np.sqrt(1 + x * x) * np.sqrt(0.02) * rng.normal()
    return m, params, pd.DataFrame({"t": np.arange(40.0), "y": ys})


def euler_grid_loglik(ys, substeps, a=0.5, s=0.5, r=0.01, points=4001):
    """The point-mass filter of the Euler–Maruyama chain with ``substeps`` steps per unit interval."""
    grid = np.linspace(-8, 8, points)
    h = 1 / substeps
    spread = s * np.sqrt(1 + grid**2) * np.sqrt(h)
    step = stats.norm.pdf(grid[None, :], (grid - a * grid * h)[:, None], spread[:, None])
    transition = np.linalg.matrix_power(step * (grid[1] - grid[0]), substeps)
    prior = stats.norm.pdf(grid, 0.5, np.sqrt(0.1)) * (grid[1] - grid[0])
    total = 0.0
    for k, y in enumerate(ys):
        if k > 0:
            prior = prior @ transition
        joint = prior * stats.norm.pdf(y, grid, np.sqrt(r))
        total += np.log(joint.sum())
        prior = joint / joint.sum()
    return total


def test_a_guided_proposal_through_euler_sub_steps_matches_a_grid_filter():
    """Every sub-step guided (a modified diffusion bridge) with a state-dependent diffusion: within its errors
    of the grid filter of the same Euler–Maruyama chain, at a sixth of the bootstrap's spread or less."""
    m, params, data = state_dependent_noise()
    reference = euler_grid_loglik(data["y"].to_numpy(), substeps=4)
    guided = particle_loglik(m, params, data, particles=2000, seed=5, replicates=8, proposal="ekf", substeps=4)
    bootstrap = particle_loglik(m, params, data, particles=2000, seed=5, replicates=8, substeps=4)
    assert abs(guided.loglik - reference) < 3 * guided.std_error + 2e-3, (guided, reference)
    assert guided.spread < bootstrap.spread / 3, (guided.spread, bootstrap.spread)


def test_guided_proposals_on_counts_match_the_point_mass_filter():
    """Poisson counts (the EKF proposal linearises the conditional mean e^l, the UKF's regresses on
    cubature points): both within their errors of the grid filter, with less spread than the bootstrap."""
    m, data = poisson_model(), poisson_data()
    reference = grid_loglik(data["n"].to_numpy())
    params = dict(a=0.5, mu=2.0, s=0.5)
    bootstrap = particle_loglik(m, params, data, particles=500, seed=0, replicates=8)
    for proposal in ("ekf", "ukf"):
        guided = particle_loglik(m, params, data, particles=500, seed=0, replicates=8, proposal=proposal)
        assert abs(guided.loglik - reference) < 3 * guided.std_error + 1e-3, (proposal, guided, reference)
        assert guided.spread < bootstrap.spread, (proposal, guided.spread, bootstrap.spread)


@pytest.mark.filterwarnings("ignore:.*did not converge")
def test_a_proposal_is_a_particle_filter_setting_and_travels_with_a_fit():
    m, data = ou_gaussian(), ou_data(40)
    with pytest.raises(ModelError, match="unknown proposal 'optimal'"):
        m.loglik(PARAMS, data, method="particle", proposal="optimal")
    with pytest.raises(ModelError, match="proposal='ekf' is a setting of the particle filter"):
        m.loglik(PARAMS, data, method="ukf", proposal="ekf")
    with pytest.raises(ModelError, match="setting 'proposal' must be 'bootstrap', 'ekf' or 'ukf', got 'optimal'"):
        check_options({"proposal": "optimal"})  # a model file's [settings] or the command line's
    assert check_options({"proposal": "ekf", "method": "particle"})["proposal"] == "ekf"
    fit = m.fit(data, method="particle", particles=300, proposal="ukf", seed=4)
    assert fit.settings["proposal"] == "ukf" and fit.settings["seed"] == 4
    again = m.loglik(fit.values, data, method="particle", particles=300, proposal="ukf", seed=4)
    assert fit.loglik == pytest.approx(again, abs=1e-9)
    # A profile reruns the fit's own filter (its particles, seed and proposal): at the estimate, the fit's value.
    profile = fit.profile("mu", values=[fit.values["mu"]])
    assert profile["loglik"].iloc[0] == pytest.approx(fit.loglik, abs=1e-6)


@pytest.mark.filterwarnings("ignore:.*did not converge", "ignore:.*at a bound")
@pytest.mark.parametrize("method, settings", [("enkf", dict(particles=300)),
                                              ("particle", dict(particles=300, proposal="ekf"))])
def test_a_fleet_by_the_stochastic_filters_fits_each_member_as_alone(method, settings):
    """fit_many runs the members' programs together; the random numbers come from the seed alone, not from a
    member's place in the fleet, so each member's fit is the one it gets alone."""
    m = ou_gaussian()
    data = [ou_data(60, seed=30 + i) for i in range(2)]
    fleet = greyid.fit_many(m, data, method=method, **settings)
    for name, frame in zip(fleet.table.index, data):
        alone = m.fit(frame, method=method, **settings)
        assert fleet.table.loc[name, "loglik"] == pytest.approx(alone.loglik, abs=1e-6)
        for p in ("a", "mu", "s", "r"):
            assert fleet.table.loc[name, p] == pytest.approx(alone.values[p], rel=1e-4, abs=1e-9)
