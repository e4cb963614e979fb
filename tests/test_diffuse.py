"""The exact diffuse initialisation against statsmodels' exact diffuse filter and Koopman's analytic first steps.

statsmodels' filters are run here on the same models: its own local level model, and for the continuous
models a ``KalmanSmoother`` given the exact discretisation computed in the test (Van Loan's matrix exponential,
SciPy), so that neither side's discretisation is shared.
"""

import warnings

import numpy as np
import pandas as pd
import pytest
import scipy.linalg
from statsmodels.tsa.statespace.initialization import Initialization
from statsmodels.tsa.statespace.kalman_smoother import KalmanSmoother
from statsmodels.tsa.statespace.structural import UnobservedComponents

import greyid
from greyid.filters.api import laplace_residuals
from greyid.cli import main
from greyid.errors import DataError, ModelError

NILE = np.array([1120, 1160, 963, 1210, 1160, 1160, 813, 1230, 1370, 1140, 995, 935, 1110, 994, 1020, 960, 1180,
                 799, 958, 1140, 1100, 1210, 1150, 1250, 1260, 1220, 1030, 1100, 774, 840, 874, 694, 940, 833, 701,
                 916, 692, 1020, 1050, 969, 831, 726, 456, 824, 702, 1120, 1100, 832, 764, 821, 768, 845, 864, 862,
                 698, 845, 744, 796, 1040, 759, 781, 865, 845, 944, 984, 897, 822, 1010, 771, 676, 649, 846, 812,
                 742, 801, 1040, 860, 874, 848, 890, 744, 749, 838, 1050, 918, 986, 797, 923, 975, 815, 1020, 906,
                 901, 1170, 912, 746, 919, 718, 714, 740], dtype=float)
LEVEL = {"sig": np.sqrt(1469.1), "s2": 15099.0}


def local_level(form_mean=None):
    return (greyid.Model().add_system("dx = 0*dt + sig*dw").add_observation("y = x", variance="s2")
            .set_parameter("sig", init=30.0, lower=1.0, upper=500.0)
            .set_parameter("s2", init=1e4, lower=10.0, upper=1e6)
            .set_initial_state(mean={} if form_mean is None else form_mean, diffuse=["x"]))


def frame(y, dt=1.0):
    return pd.DataFrame({"t": dt * np.arange(len(y)), "y": y})


def trend_model(sb_fixed=None):
    """A continuous local linear trend: level x1 with slope x2, both diffuse."""
    m = (greyid.Model().add_system("dx1 = x2*dt + s1*dw1").add_system("dx2 = 0*dt + sb*dw2")
         .add_observation("y = x1", variance="s2")
         .set_parameter("s1", init=1.0, lower=1e-3, upper=10).set_parameter("s2", init=1.0, lower=1e-3, upper=10))
    m = m.set_parameter("sb", init=sb_fixed, fixed=True) if sb_fixed is not None else m.set_parameter(
        "sb", init=0.3, lower=1e-3, upper=10)
    return m.set_initial_state(mean={}, diffuse=["x1", "x2"])


def van_loan(A, GGt, dt):
    """Φ = e^{A dt} and Λ = ∫₀^dt e^{As} G Gᵀ e^{Aᵀs} ds."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A, GGt, A.T
    E = scipy.linalg.expm(M * dt)
    Phi = E[n:, n:].T
    return Phi, Phi @ E[:n, n:]


def statsmodels_filter(y, T, Q, Z, H, init):
    """statsmodels' exact diffuse filter and smoother of y_k = Z x_k + e_k, x_{k+1} = T x_k + η_k."""
    y = np.asarray(y, dtype=float).reshape(len(y), -1)
    n, p = T.shape[0], y.shape[1]
    ssm = KalmanSmoother(k_endog=p, k_states=n, k_posdef=n, tolerance=0.0)  # never hold the covariance
    ssm.bind(y)
    ssm.initialize(init)
    ssm["design"], ssm["obs_cov"], ssm["transition"] = Z, H, T
    ssm["selection"], ssm["state_cov"] = np.eye(n), Q
    return ssm.smooth()


@pytest.mark.parametrize("form", ["sqrt", "plain"])
def test_local_level_equals_statsmodels(form):
    ref = UnobservedComponents(NILE, "llevel", use_exact_diffuse=True).smooth([LEVEL["s2"], LEVEL["sig"] ** 2])
    m = local_level()
    data = frame(NILE)
    assert m.loglik(LEVEL, data, time="t", form=form) == pytest.approx(ref.llf, rel=1e-12, abs=1e-9)
    res = m.filter(LEVEL, data, time="t", form=form)
    np.testing.assert_allclose(res.loglik_terms.to_numpy(), ref.llf_obs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.filtered["x"].to_numpy(), ref.filtered_state[0], rtol=1e-10)
    np.testing.assert_allclose(res.filtered_cov[:, 0, 0], ref.filtered_state_cov[0, 0], rtol=1e-10)
    np.testing.assert_allclose(res.predicted_cov[1:, 0, 0], ref.predicted_state_cov[0, 0, 1:-1], rtol=1e-10)
    # The first prediction has an infinite variance: no innovation, no standardized residual.
    assert np.isinf(res.predicted_cov[0, 0, 0]) and np.isnan(res.innovations["y"].iloc[0])
    np.testing.assert_allclose(res.innovations["y"].to_numpy()[1:], ref.forecasts_error[0, 1:], rtol=1e-10)
    assert res.standardized_innovations["y"].notna().sum() == len(NILE) - 1
    smooth = m.smooth(LEVEL, data, time="t", form=form)
    np.testing.assert_allclose(smooth.smoothed["x"].to_numpy(), ref.smoothed_state[0], rtol=1e-9)
    np.testing.assert_allclose(smooth.smoothed_cov[:, 0, 0], ref.smoothed_state_cov[0, 0], rtol=1e-8)


def test_local_level_koopman_analytic():
    """Koopman (1997): the first update takes the level to y₁ with variance σ²_y, its term −½ log 2π."""
    y1, s2y, s2mu = 10.2394, 1.993, 8.253
    y = np.r_[y1, [1.0] * 9]
    params = {"sig": np.sqrt(s2mu), "s2": s2y}
    res = local_level().filter(params, frame(y), time="t")
    assert res.filtered["x"].iloc[0] == pytest.approx(y1, rel=1e-14)
    assert res.filtered_cov[0, 0, 0] == pytest.approx(s2y, rel=1e-13)
    assert res.predicted["x"].iloc[1] == pytest.approx(y1, rel=1e-14)
    assert res.predicted_cov[1, 0, 0] == pytest.approx(s2y + s2mu, rel=1e-13)
    assert res.loglik_terms.iloc[0] == pytest.approx(-0.5 * np.log(2 * np.pi), rel=1e-14)
    # The diffuse state's mean does not matter.
    other = local_level({"x": 123.0}).loglik(params, frame(y), time="t")
    assert other == pytest.approx(res.loglik, rel=1e-13)


def test_local_linear_trend_koopman_analytic():
    """Koopman (1997) for the trend without slope noise: after two observations the predicted state at t₃ is
    (2y₂ − y₁, y₂ − y₁) with covariance σ²_y [[5 + 2q, 3 + q], [3 + q, 2 + q]], q = σ²_μ/σ²_y."""
    y1, y2 = 10.2394, 4.2039
    s1, s2 = 1.3, 0.7
    y = np.r_[y1, y2, 6.123123, [1.0] * 7]
    res = trend_model(sb_fixed=0.0).filter({"s1": s1, "s2": s2, "sb": 0.0}, frame(y), time="t")
    np.testing.assert_allclose(res.predicted.iloc[2].to_numpy(), [2 * y2 - y1, y2 - y1], rtol=1e-12)
    q = s1**2 / s2
    expected = s2 * np.array([[5 + 2 * q, 3 + q], [3 + q, 2 + q]])
    np.testing.assert_allclose(res.predicted_cov[2], expected, rtol=1e-11)
    # Both states are diffuse at t₂ (P∞ = [[1, 1], [1, 1]]), the slope still after y₁.
    assert np.all(np.isinf(res.predicted_cov[1])) and np.isinf(res.filtered_cov[0, 1, 1])
    # F∞ = 1 at both diffuse observations: each term is −½ log 2π.
    np.testing.assert_allclose(res.loglik_terms.iloc[:2].to_numpy(), [-0.5 * np.log(2 * np.pi)] * 2, rtol=1e-13)


@pytest.mark.parametrize("form", ["sqrt", "plain"])
@pytest.mark.parametrize("missing", [False, True])
def test_continuous_trend_equals_statsmodels(form, missing):
    """Sampled every 0.5: the exact discretisation's T and Q (with the slope's noise in the level) handed to
    statsmodels; a value missing during the diffuse period moves it on by a row."""
    rng = np.random.default_rng(3)
    dt, s1, sb, s2 = 0.5, 0.4, 0.15, 0.3
    params = {"s1": s1, "sb": sb, "s2": s2}
    y = np.cumsum(np.cumsum(rng.normal(0, 0.2, 60))) * 0.1 + rng.normal(0, np.sqrt(s2), 60)
    if missing:
        y[1] = np.nan
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    T, Q = van_loan(A, np.diag([s1**2, sb**2]), dt)
    ref = statsmodels_filter(y, T, Q, np.array([[1.0, 0.0]]), np.array([[s2]]),
                             Initialization(2, initialization_type="diffuse"))
    assert ref.nobs_diffuse == (3 if missing else 2)
    m = trend_model()
    data = frame(y, dt)
    res = m.filter(params, data, time="t", form=form)
    assert res.loglik == pytest.approx(ref.llf, rel=1e-12)
    np.testing.assert_allclose(res.loglik_terms.to_numpy(), ref.llf_obs, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(res.filtered.to_numpy(), ref.filtered_state.T, rtol=1e-10, atol=1e-11)
    later = ref.nobs_diffuse
    np.testing.assert_allclose(res.filtered_cov[later:], np.moveaxis(ref.filtered_state_cov, -1, 0)[later:],
                               rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(res.predicted_cov[later:], np.moveaxis(ref.predicted_state_cov, -1, 0)[later:-1],
                               rtol=1e-10, atol=1e-13)
    smooth = m.smooth(params, data, time="t", form=form)
    np.testing.assert_allclose(smooth.smoothed.to_numpy(), ref.smoothed_state.T, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(smooth.smoothed_cov, np.moveaxis(ref.smoothed_state_cov, -1, 0), rtol=1e-9,
                               atol=1e-11)


@pytest.mark.parametrize("correlated", [False, True])
def test_mixed_diffuse_and_stationary_equals_statsmodels(correlated):
    """A diffuse random-walk level beside a stationary Ornstein–Uhlenbeck deviation (its own block's stationary
    covariance, as statsmodels' mixed initialisation), both seen through one output, with a second output of the
    deviation alone; the first output missing at the start; the outputs' noise independent or correlated
    (statsmodels then diagonalises it by its Cholesky factor, as greyid does)."""
    rng = np.random.default_rng(11)
    dt, sl, a, so, r1, r2, c = 1.0, 0.3, 0.8, 0.5, 0.2, 0.1, 0.08 if correlated else 0.0
    n = 80
    y = np.column_stack([np.cumsum(rng.normal(0, sl, n)) + rng.normal(0, 0.6, n), rng.normal(0, 0.6, n)])
    y[0, 0] = np.nan
    y[5, 1] = np.nan
    m = (greyid.Model().add_system("dL = 0*dt + sl*dw1").add_system("dD = -a*D*dt + so*dw2")
         .add_observation("y1 = L + D", variance="r1").add_observation("y2 = D", variance="r2")
         .set_parameter("sl", init=sl).set_parameter("a", init=a).set_parameter("so", init=so)
         .set_parameter("r1", init=r1).set_parameter("r2", init=r2)
         .set_initial_state(mean={"D": 0.0}, covariance="stationary", diffuse=["L"]))
    params = {"sl": sl, "a": a, "so": so, "r1": r1, "r2": r2}
    if correlated:
        m = m.set_observation_covariance([["r1", "c"], ["c", "r2"]]).set_parameter("c", init=c)
        params["c"] = c
    A = np.array([[0.0, 0.0], [0.0, -a]])
    T, Q = van_loan(A, np.diag([sl**2, so**2]), dt)
    init = Initialization(2)
    init.set(0, "diffuse")
    init.set(1, "stationary")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # statsmodels' note on its diagonalised disturbances
        ref = statsmodels_filter(y, T, Q, np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[r1, c], [c, r2]]), init)
    data = pd.DataFrame({"t": dt * np.arange(n), "y1": y[:, 0], "y2": y[:, 1]})
    res = m.filter(params, data, time="t")
    assert res.loglik == pytest.approx(ref.llf, rel=1e-12)
    np.testing.assert_allclose(res.loglik_terms.to_numpy(), ref.llf_obs, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(res.filtered.to_numpy(), ref.filtered_state.T, rtol=1e-10, atol=1e-11)
    smooth = m.smooth(params, data, time="t")
    np.testing.assert_allclose(smooth.smoothed.to_numpy(), ref.smoothed_state.T, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(smooth.smoothed_cov, np.moveaxis(ref.smoothed_state_cov, -1, 0), rtol=1e-9,
                               atol=1e-11)


def test_laplace_method_with_a_flat_prior_is_the_diffuse_likelihood():
    """The Laplace method integrates the diffuse states out under a flat prior: less ½ log 2π per diffuse state it
    is Koopman and Durbin's diffuse log-likelihood (exact here, the models being linear and Gaussian), its smoother
    the exact diffuse smoother, its fit the Kalman filter's."""
    m, data = local_level(), frame(NILE)
    missing = NILE.copy()
    missing[:2] = np.nan
    for series in (data, frame(missing)):
        assert m.loglik(LEVEL, series, time="t", method="laplace") == pytest.approx(
            m.loglik(LEVEL, series, time="t"), rel=1e-13)
    rng = np.random.default_rng(3)
    y = np.cumsum(np.cumsum(rng.normal(0, 0.2, 60))) * 0.1 + rng.normal(0, 0.5, 60)
    trend, params = trend_model(), {"s1": 0.4, "sb": 0.15, "s2": 0.3}
    assert trend.loglik(params, frame(y, 0.5), time="t", method="laplace") == pytest.approx(
        trend.loglik(params, frame(y, 0.5), time="t"), rel=1e-12)
    # Its one-step residuals (the Gaussian predictive's, a Laplace mode per observation: a diffuse state's density is
    # not Gaussian) are the diffuse filter's standardized innovations, with none at the first row, whose level
    # nothing before it determines.
    from greyid.filters.laplace import gaussian_joint

    assert not gaussian_joint(m.structure)
    residuals = laplace_residuals(m, LEVEL, data.iloc[:30], time="t")["y"]
    innovations = m.filter(LEVEL, data.iloc[:30], time="t").standardized_innovations["y"]
    assert np.isnan(residuals.iloc[0]) and np.isnan(innovations.iloc[0])
    np.testing.assert_allclose(residuals.iloc[1:], innovations.iloc[1:], rtol=0, atol=1e-9)
    laplace, kalman = (m.smooth(LEVEL, data, time="t", method=method) for method in ("laplace", "kalman"))
    np.testing.assert_allclose(laplace.smoothed.to_numpy(), kalman.smoothed.to_numpy(), rtol=1e-12)
    np.testing.assert_allclose(laplace.smoothed_cov, kalman.smoothed_cov, rtol=1e-9)
    fit = m.fit(data, time="t", method="laplace")
    assert fit.loglik == pytest.approx(m.fit(data, time="t").loglik, rel=1e-10)


def test_predictions_from_a_diffuse_start():
    """One-step predictions equal the filter's; k-step ones from a state with a diffuse part are unknown (infinite
    standard deviation); later ones are the ordinary k-step predictions of the filtered state."""
    m = local_level()
    data = frame(NILE)
    res = m.filter(LEVEL, data, time="t")
    one = m.predict(LEVEL, data, time="t", steps=1)
    np.testing.assert_allclose(one["y"].to_numpy(), res.output_predictions["y"].to_numpy(), rtol=1e-12)
    sd = np.sqrt(res.innovation_cov[:, 0, 0])
    np.testing.assert_allclose(one["y_sd"].to_numpy(), sd, rtol=1e-12)
    assert np.isinf(one["y_sd"].iloc[0])
    three = m.predict(LEVEL, data, time="t", steps=3)
    assert np.all(np.isinf(three["y_sd"].iloc[:3]))
    # The level is a random walk: three steps from row k − 3 add 2 σ² to the one-step variance.
    np.testing.assert_allclose(three["y"].to_numpy()[3:], res.filtered["x"].to_numpy()[:-3], rtol=1e-12)
    np.testing.assert_allclose(three["y_sd"].to_numpy()[3:] ** 2,
                               res.filtered_cov[:-3, 0, 0] + 3 * LEVEL["sig"] ** 2 + LEVEL["s2"], rtol=1e-10)


def test_gradient_exact_and_fit_equals_statsmodels():
    m = local_level()
    data = frame(NILE)
    L = m.likelihood(data, time="t")
    x = np.array([1.3 * LEVEL[n] for n in L.names])  # away from the optimum: a gradient well above rounding
    value, gradient = L.value_and_grad(x)
    step = 1e-5 * np.abs(x)
    numeric = [(L.value(x + step[i] * np.eye(2)[i]) - L.value(x - step[i] * np.eye(2)[i])) / (2 * step[i])
               for i in range(2)]
    np.testing.assert_allclose(gradient, numeric, rtol=1e-6)
    fit = m.fit(data, time="t")
    # Durbin & Koopman (2012, §2.10.3): σ²_ε = 15099, σ²_η = 1469.1 (exact diffuse maximum likelihood).
    assert fit.values["s2"] == pytest.approx(15099.0, rel=1e-4)
    assert fit.values["sig"] ** 2 == pytest.approx(1469.1, rel=1e-3)
    # statsmodels' own optimiser stops a little short of the maximum (its gradient 6e-4 there).
    ref = UnobservedComponents(NILE, "llevel", use_exact_diffuse=True).fit(disp=False)
    assert ref.llf - 1e-4 < ref.llf <= fit.loglik + 1e-9 and fit.loglik - ref.llf < 1e-3


def test_fleet_members_equal_their_fits_alone():
    """fit_many pads the members' diffuse periods to the longest (a member whose first values are missing)."""
    y = NILE.copy()
    y[50:53] = np.nan
    sets = {"a": frame(y[:50]), "b": frame(y[50:]), "c": frame(y[20:90])}
    m = local_level()
    fleet = greyid.fit_many(m, sets, time="t")
    for name, data in sets.items():
        alone = m.fit(data, time="t")
        assert fleet.fits[name].loglik == pytest.approx(alone.loglik, rel=1e-9)
        for key, value in alone.values.items():
            assert fleet.fits[name].values[key] == pytest.approx(value, rel=1e-4)


def test_long_series_with_steady_state():
    """A series long enough for the steady-state switch after its diffuse period."""
    rng = np.random.default_rng(5)
    y = np.cumsum(rng.normal(0, 1.0, 400)) + rng.normal(0, 2.0, 400)
    params = {"sig": 1.0, "s2": 4.0}
    ref = UnobservedComponents(y, "llevel", use_exact_diffuse=True).filter([4.0, 1.0])
    m = local_level()
    L = m.likelihood(frame(y), time="t")
    assert -L.value([params[n] for n in L.names]) == pytest.approx(ref.llf, rel=1e-10)
    assert m.loglik(params, frame(y), time="t", steady_state=False) == pytest.approx(ref.llf, rel=1e-11)


def test_refusals():
    with pytest.raises(ModelError, match="'x' is diffuse but the initial covariance gives it"):
        local_level().set_initial_state(mean={}, covariance=[[2.0]], diffuse=["x"])
    with pytest.raises(ModelError, match="cannot be estimated"):
        local_level().set_initial_state(mean={"x": "x0"}, diffuse=["x"])
    with pytest.raises(ModelError, match="'z' is not a state"):
        local_level().set_initial_state(mean={}, diffuse=["z"])
    with pytest.raises(ModelError, match="named twice"):
        local_level().set_initial_state(mean={}, diffuse=["x", "x"])
    with pytest.raises(ModelError, match="needs a linear model"):
        (greyid.Model().add_system("dx = -k*x**3*dt + s*dw").add_observation("y = x", variance="r")
         .set_initial_state(mean={}, diffuse=["x"])).structure
    for method in ("ukf", "particle"):
        with pytest.raises(ModelError, match="started exactly by the Kalman filter .* and the Laplace method"):
            local_level().loglik(LEVEL, frame(NILE), time="t", method=method)
    with pytest.raises(DataError, match="1 observed rows of the outputs that see the diffuse initial states, fewer "
                                        "than the model's 2"):
        trend_model().loglik({"s1": 1.0, "s2": 1.0, "sb": 0.3}, frame(np.r_[1.0, [np.nan] * 9]), time="t")
    # A diffuse state no output sees, and one the output sees with a zero gain at the given parameters.
    hidden = (greyid.Model().add_system("dx = 0*dt + s*dw1").add_system("dz = 0*dt + s*dw2")
              .add_observation("y = x", variance="r").set_initial_state(mean={}, diffuse=["x", "z"]))
    with pytest.raises(ModelError, match=r"diffuse state 'z' is seen by no output"):
        hidden.structure
    unseen = (greyid.Model().add_system("dx = 0*dt + s*dw1").add_observation("y = c*x", variance="r")
              .set_initial_state(mean={}, diffuse=["x"]))
    with pytest.raises(ModelError, match=r"not all determined by the outputs of the first 1 rows"):
        unseen.loglik({"s": 1.0, "r": 1.0, "c": 0.0}, frame(NILE / 100), time="t")


def test_model_file_round_trip_and_cli(tmp_path, capsys):
    m = local_level()
    text = m.to_toml()
    assert 'initial_diffuse = ["x"]' in text
    back = greyid.Model.from_toml(text)
    assert back.loglik(LEVEL, frame(NILE), time="t") == pytest.approx(m.loglik(LEVEL, frame(NILE), time="t"),
                                                                       rel=1e-14)
    frame(NILE).to_csv(tmp_path / "data.csv", index=False)
    # Without an [model.initial_state] table: every state diffuse.
    (tmp_path / "model.toml").write_text(
        '[model]\nsystem = ["dx = 0*dt + sig*dw1"]\ninitial_diffuse = ["x"]\n'
        '[model.observations]\ny = { equation = "x", variance = "s2" }\n'
        '[parameters]\nsig = { init = 30, lower = 1, upper = 500 }\ns2 = { init = 1e4, lower = 10, upper = 1e6 }\n'
        '[data]\ntime = "t"\n')
    assert greyid.Model.from_toml(tmp_path / "model.toml").loglik(LEVEL, frame(NILE), time="t") == pytest.approx(
        m.loglik(LEVEL, frame(NILE), time="t"), rel=1e-14)
    assert main(["fit", str(tmp_path / "model.toml"), str(tmp_path / "data.csv")]) == 0
    capsys.readouterr()
    (tmp_path / "bad.toml").write_text((tmp_path / "model.toml").read_text().replace('["x"]', '["q"]'))
    assert main(["fit", str(tmp_path / "bad.toml"), str(tmp_path / "data.csv")]) == 2
    err = capsys.readouterr().err
    assert "diffuse state 'q' is not a state" in err and "Traceback" not in err
    (tmp_path / "bad.toml").write_text((tmp_path / "model.toml").read_text().replace('["x"]', '"x"'))
    assert main(["fit", str(tmp_path / "bad.toml"), str(tmp_path / "data.csv")]) == 2
    assert "initial_diffuse must be a list of strings" in capsys.readouterr().err
