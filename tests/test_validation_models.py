"""Structure tests, criteria, selection, Bayes, simulation checks and fit.validate() on RC models."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure
from scipy import stats

import greyid
from greyid import ModelError
from greyid import validation as v

ONE_STATE_TRUE = dict(Ci=1.0, Ria=8.0, p11=-2.5, e11=-5.0, Ti0=20.0)
TWO_STATE_TRUE = dict(Ci=1.0, Ce=10.0, Rie=1.0, Rea=8.0, p11=-2.5, p22=-3.0, e11=-5.0, Ti0=20.0, Te0=15.0)


def one_state(solar: bool = False) -> greyid.Model:
    m = greyid.Model("Ti_solar" if solar else "Ti")
    gain = " + Aw/Ci*Ps" if solar else ""
    m.add_system(f"dTi = (1/(Ci*Ria)*(Ta-Ti) + Ph/Ci{gain})*dt + exp(p11)*dw1")
    m.add_inputs("Ta", "Ph", "Ps")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0"}, covariance=[[0.1]])
    for name, (init, lo, hi) in dict(Ci=(1.0, 0.01, 100), Ria=(5.0, 0.1, 100), p11=(-2, -20, 5),
                                     e11=(-6, -20, 5), Ti0=(20, 0, 40)).items():
        m.set_parameter(name, init=init, lower=lo, upper=hi)
    if solar:
        m.set_parameter("Aw", init=0.5, lower=-10, upper=10)
    return m


def two_state() -> greyid.Model:
    m = greyid.Model("TiTe")
    m.add_system("dTi = (1/(Ci*Rie)*(Te-Ti) + Ph/Ci)*dt + exp(p11)*dw1")
    m.add_system("dTe = (1/(Ce*Rie)*(Ti-Te) + 1/(Ce*Rea)*(Ta-Te))*dt + exp(p22)*dw2")
    m.add_inputs("Ta", "Ph", "Ps")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0", "Te": "Te0"}, covariance=[[0.1, 0], [0, 0.1]])
    for name, (init, lo, hi) in dict(Ci=(1.0, 0.01, 100), Ce=(5.0, 0.01, 1000), Rie=(1.0, 0.01, 100),
                                     Rea=(5.0, 0.01, 100), p11=(-2, -20, 5), p22=(-2, -20, 5), e11=(-6, -20, 5),
                                     Ti0=(20, 0, 40), Te0=(15, 0, 40)).items():
        m.set_parameter(name, init=init, lower=lo, upper=hi)
    return m


def inputs(n=400, seed=3) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.25
    return pd.DataFrame({"t": t, "Ta": 5 + 3 * np.sin(2 * np.pi * t / 24), "Ph": 2.0 * (rng.random(n) > 0.5),
                         "Ps": np.clip(np.sin(2 * np.pi * (t - 6) / 24), 0, None)})


def simulated(model, params, seed, n=400):
    frame = model.simulate(params, inputs(n), seed=seed, method="exact").frame()
    return frame[["t", "Ta", "Ph", "Ps", "yTi"]]


@pytest.fixture(scope="module")
def models():
    return {"one": one_state(), "solar": one_state(True), "two": two_state()}


@pytest.fixture(scope="module")
def nested(models):
    """One-state fits without and with the solar gain, on data with a small solar effect."""
    data = simulated(models["solar"], dict(ONE_STATE_TRUE, Aw=0.1), seed=4)
    return data, models["one"].fit(data), models["solar"].fit(data)


@pytest.fixture(scope="module")
def one_state_data(models):
    return simulated(models["one"], ONE_STATE_TRUE, seed=2)


@pytest.fixture(scope="module")
def two_state_data(models):
    return simulated(models["two"], TWO_STATE_TRUE, seed=1)


def test_lr_prefers_the_true_larger_model(models, two_state_data, one_state_data):
    small, big = models["one"].fit(two_state_data), models["two"].fit(two_state_data)
    test = v.lr_test(small, big)
    assert test.df == 4 and test.p_value < 1e-6
    small, big = models["one"].fit(one_state_data), models["two"].fit(one_state_data)
    assert v.lr_test(small, big).p_value > 0.05


def test_lr_wald_lm_agree_to_first_order(models, nested):
    data, small, big = nested
    lr = v.lr_test(small, big)
    wald = v.wald_test(big, "Aw")
    lm = v.lm_test(small, models["solar"], at={"Aw": 0.0})
    stats_ = np.array([lr.statistic, wald.statistic, lm.statistic])
    assert lr.df == wald.df == lm.df == 1
    assert np.all(stats_ > stats.chi2.ppf(0.99, 1))
    assert stats_.max() / stats_.min() < 1.5, stats_
    # A single linear restriction: the Wald statistic is the squared t value.
    assert wald.statistic == pytest.approx(big.params.loc["Aw", "t_value"] ** 2, rel=1e-10)
    # "Aw = 0" and "Aw" are the same restriction; a two-row restriction adds up df.
    assert v.wald_test(big, "Aw = 0").statistic == pytest.approx(wald.statistic)
    assert v.wald_test(big, ["Aw", "Ria - 8"]).df == 2


def test_lm_information_kinds_agree_at_the_optimum(models, nested):
    data, small, big = nested
    from greyid.estimate.information import loglik_derivatives

    names = list(small.cov.index)
    fisher = loglik_derivatives(small.model, small.values, data, names, "fisher")
    hessian = loglik_derivatives(small.model, small.values, data, names, "hessian")
    # Observed and expected information differ by sampling error only (12 % at most here); the
    # expected information itself is checked exactly in test_kalman_dense.py.
    np.testing.assert_allclose(np.diag(fisher.information), np.diag(hessian.information), rtol=0.15)
    assert np.max(np.abs(fisher.score * np.sqrt(np.diag(small.cov)))) < 1e-3


def test_cross_validation_and_filter_approximation(models, nested):
    data, small, big = nested
    fresh = simulated(models["solar"], dict(ONE_STATE_TRUE, Aw=0.1), seed=40)
    assert v.cross_validation_test(big, fresh).p_value > 0.05
    shifted = simulated(models["solar"], dict(ONE_STATE_TRUE, Aw=0.1, Ria=6.0), seed=41)
    assert v.cross_validation_test(big, shifted).p_value < 1e-3
    # The exact Kalman filter on a linear model: no approximation to find.
    assert v.approximation_test(big, n_sim=2, seed=5).p_value > 0.05


def test_information_criteria_table(nested):
    data, small, big = nested
    table = v.compare_fits([small, big])
    assert list(table.index) == ["Ti", "Ti_solar"]
    assert table.loc["Ti", "aic"] == pytest.approx(-2 * small.loglik + 2 * 5)
    assert table.loc["Ti_solar", "bic"] == pytest.approx(-2 * big.loglik + 6 * np.log(400))
    eps = small.filter().innovations["yTi"].to_numpy()
    assert table.loc["Ti", "fpe"] == pytest.approx(np.mean(eps**2) * (400 + 5) / (400 - 5), rel=1e-10)
    assert table["delta_aic"].min() == 0.0


def test_structure_tests_reject_bad_use(models, nested, one_state_data):
    data, small, big = nested
    with pytest.raises(ModelError, match="more free parameters"):
        v.lr_test(big, small)
    other = models["one"].fit(one_state_data.iloc[:300])
    with pytest.raises(ModelError, match="same data"):
        v.lr_test(other, big)
    with pytest.raises(ModelError, match="not a parameter"):
        v.wald_test(big, "Qx - 1")
    with pytest.raises(ModelError, match="at=\\{'Aw'"):
        v.lm_test(small, models["solar"])


def test_forward_selection_stops_where_lr_stops(models, two_state_data):
    result = v.select_forward([models["one"], [models["solar"], models["two"]]], two_state_data)
    assert result.chosen.model.name == "TiTe"
    step1 = result.table[result.table["step"] == 1].set_index("model")
    assert step1.loc["TiTe", "chosen"] and not step1.loc["Ti_solar", "chosen"]
    assert step1.loc["TiTe", "p_value"] < 0.05
    # The models not chosen hold no compiled program (released as the selection went on), the chosen one
    # does; a released model computes again, from the kept programs, what its fit found.
    from greyid.runtime.jit import _programs_in

    def compiled(fit):
        return sum(len(program.executables) for program in _programs_in(fit.model.structure.cache))

    assert compiled(result.chosen) > 0
    released = result.fits["Ti_solar"]
    assert compiled(released) == 0 and compiled(result.fits["Ti"]) == 0
    at = released.params["estimate"].to_dict()
    assert released.model.loglik(at, two_state_data) == pytest.approx(released.loglik, rel=1e-12, abs=0)


def test_laplace_marginal_likelihood_is_exact_for_a_gaussian_mean():
    # y_k = μ + e_k with μ ~ N(m0, s0²): the marginal of y is N(m0·1, σ²I + s0²11ᵀ).
    m = greyid.Model("level")
    m.add_system("dx = -x*dt + 1e-6*dw1")
    m.add_observation("y = mu + x", variance="s2")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1e-12]])
    m.set_parameter("mu", init=0.0)
    m.fix_parameter("s2", 0.5)
    rng = np.random.default_rng(8)
    y = 1.3 + np.sqrt(0.5) * rng.normal(size=40)
    data = pd.DataFrame({"t": np.arange(40.0), "y": y})
    prior = {"mean": {"mu": 1.0}, "sd": {"mu": 0.7}}
    fit = m.fit(data, criterion="map", prior=prior)
    exact = stats.multivariate_normal(np.full(40, 1.0), 0.5 * np.eye(40) + 0.49 * np.ones((40, 40))).logpdf(y)
    assert v.log_marginal_likelihood(fit) == pytest.approx(exact, abs=1e-5)
    # Equal marginals: the posterior is the prior, and the losses decide (5.19–5.21).
    comparison = v.posterior_odds(fit, fit, prior_h0=0.2, loss_accept_h1=5.0)
    assert comparison.posterior_h0 == pytest.approx(0.2)
    assert comparison.decision == "H0"  # E(L|accept H0) = 0.8·1 < E(L|accept H1) = 0.2·5
    assert v.posterior_odds(fit, fit, prior_h0=0.2, loss_accept_h1=3.0).decision == "H1"  # 0.8 > 0.6
    with pytest.raises(ModelError, match="no prior"):
        v.log_marginal_likelihood(m.fit(data))


def test_deterministic_simulation_matches_closed_form(models):
    # One-state model with inputs held: x_{k+1} = a x_k + (1 − a)(Ta + R·Ph), a = exp(−τ/RC).
    data = inputs(50).assign(Ta=4.0)
    data["Ps"] = 0.0
    sim = models["one"].simulate(ONE_STATE_TRUE, data, noise=False, method="exact")
    a = np.exp(-0.25 / 8.0)
    x = [20.0]
    for ph in data["Ph"].to_numpy()[:-1]:
        x.append(a * x[-1] + (1 - a) * (4.0 + 8.0 * ph))
    np.testing.assert_allclose(sim.outputs[0, :, 0], x, rtol=1e-10)
    euler = models["one"].simulate(ONE_STATE_TRUE, data, noise=False, method="heun", substeps=20)
    np.testing.assert_allclose(euler.outputs[0, :, 0], x, atol=1e-4)


def test_simulation_check_and_bootstrap(nested):
    data, small, big = nested
    check = v.simulation_check(big, n_paths=200, seed=1)
    assert 0.85 <= check.coverage["yTi"] <= 1.0
    assert check.rmse["yTi"] > 0
    # The deterministic path (simulated as many times as the band's paths, one program for both) is the
    # model's single path without noise, and the band's paths are simulate()'s own.
    alone = big.model.simulate(big.values, data, noise=False, method="exact", substeps=20)
    np.testing.assert_allclose(check.frame["yTi_simulated"], alone.outputs[0, :, 0], rtol=1e-13)
    paths = big.model.simulate(big.values, data, n_paths=200, seed=1, method="exact", substeps=20)
    np.testing.assert_allclose(check.frame["yTi_mean"], paths.outputs[:, :, 0].mean(axis=0), rtol=1e-13)
    boot = v.parameter_bootstrap(big, n_samples=300, seed=2)
    assert boot.samples.shape == (300, 6)
    sd = boot.samples.std().to_numpy()
    np.testing.assert_allclose(sd, np.sqrt(np.diag(big.cov)), rtol=0.15)
    frame = boot.frame
    assert np.all(frame["yTi_lower"] <= frame["yTi_simulated"] + 1e-9)
    assert np.all(frame["yTi_simulated"] <= frame["yTi_upper"] + 1e-9)


def test_validate_flags_a_misspecified_model(models, two_state_data, nested):
    data, small, big = nested
    good = big.validate()
    assert list(good.tests.columns) == ["test", "output", "statistic", "df", "p_value", "reject"]
    assert {"ljung_box", "bispectrum_gaussianity", "input_correlation[Ph]", "coherency"} <= set(good.tests["test"])
    assert good.tests["reject"].sum() <= 2
    wrong = models["one"].fit(two_state_data).validate()
    rejected = set(wrong.rejected["test"])
    assert "ljung_box" in rejected and "cumulative_periodogram" in rejected
    # The same numbers as the plain functions on the fit's residuals.
    res = big.residuals["yTi"]
    row = good.tests.set_index("test").loc["ljung_box"]
    assert row["statistic"] == v.ljung_box(res).statistic


def test_validation_figures(nested):
    data, small, big = nested
    val = big.validate()
    figures = [val.plot(), val.plot_coherency(), val.plot_simulation(n_paths=20), val.plot_bootstrap(n_samples=10),
               val.plot_prediction(steps=4)]
    assert all(isinstance(f, Figure) for f in figures)
    assert len(figures[0].axes) == 7
    with pytest.raises(ModelError, match="no residuals named"):
        val.plot("nope")


def test_fit_from_a_plateau_start_reaches_the_optimum(models, one_state_data):
    """Started with e11 = −3, the BFGS search of earlier versions stopped on a plateau
    (measurement variance → 0) and called it converged; the trust-region Newton search
    reaches the optimum of the default start."""
    m = models["one"]
    best = m.fit(one_state_data)
    fit = m.fit(one_state_data, init={"e11": -3.0})
    assert best.converged and fit.converged
    assert fit.loglik == pytest.approx(best.loglik, abs=1e-6)
    assert fit.loglik >= m.loglik(ONE_STATE_TRUE, one_state_data)
