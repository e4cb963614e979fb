"""FitResult as statsmodels users read it; covariance types; forecasting past the data."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from test_estimation import TRUE, ou_model

FREE = ["a", "b", "s", "r", "x0"]


@pytest.fixture(scope="module")
def ou_case():
    m = ou_model()
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"t": np.arange(300) * 0.5, "u": np.repeat(rng.choice([0.0, 1.0], 30), 10)})
    df["y"] = m.simulate(TRUE, df, method="exact", seed=5).outputs[0, :, 0]
    return m, df, m.fit(df)


def test_statsmodels_names(ou_case):
    m, df, fit = ou_case
    assert fit.llf == fit.loglik and fit.nobs == fit.n_obs == 300
    assert isinstance(fit.bse, pd.Series) and isinstance(fit.tvalues, pd.Series) and isinstance(fit.pvalues, pd.Series)
    est = fit.params["estimate"]
    np.testing.assert_allclose(fit.tvalues[FREE], est[FREE] / fit.bse[FREE])
    k, n = 5, 300
    np.testing.assert_allclose(fit.pvalues[FREE], 2 * stats.t.sf(np.abs(fit.tvalues[FREE]), n - k))
    assert fit.hqic == pytest.approx(-2 * fit.llf + 2 * k * np.log(np.log(n)))
    pd.testing.assert_frame_equal(fit.cov_params(), fit.cov)
    assert fit.cov_type == "hessian"


def test_conf_int_is_a_student_t_wald_interval(ou_case):
    m, df, fit = ou_case
    ci = fit.conf_int(0.9)
    q = stats.t.ppf(0.95, fit.nobs - 5)
    est, se = fit.params["estimate"], fit.bse
    np.testing.assert_allclose(ci.loc[FREE, "lower"], est[FREE] - q * se[FREE])
    np.testing.assert_allclose(ci.loc[FREE, "upper"], est[FREE] + q * se[FREE])
    assert (fit.conf_int(0.99)["upper"] - fit.conf_int(0.99)["lower"] > ci["upper"] - ci["lower"])[FREE].all()
    with pytest.raises(Exception, match="level"):
        fit.conf_int(1.5)


def test_summary_shows_intervals_and_bounds_apart(ou_case):
    m, df, fit = ou_case
    text = fit.summary()
    assert "[0.025" in text and "0.975]" in text and "covariance: hessian" in text
    header, bounds = text.split("bounds", 1)
    a_line = next(line for line in header.splitlines() if line.startswith("a "))
    ci = fit.conf_int().loc["a"]
    assert f"{ci['lower']:.5g}" in a_line and f"{ci['upper']:.5g}" in a_line
    assert "10" not in a_line.split()[-1]  # the upper bound of a is no longer in the estimate's row
    assert any(line.split()[:3] == ["a", "0", "10"] for line in bounds.splitlines())
    assert list(fit.params.columns[:7]) == ["estimate", "std_error", "t_value", "p_value", "lower_bound",
                                            "upper_bound", "fixed"]


def test_p_values_read_alike_in_the_summary_and_the_report(ou_case):
    """A p-value below double precision's resolution reads "< 1e-16" in both, not 0 in one of them; others
    print with three digits in both."""
    from greyid.estimate.results import p_value_text
    from greyid.report.html import _p_value

    m, df, fit = ou_case
    assert p_value_text(0.0) == "< 1e-16" and p_value_text(0.012345) == "0.0123"
    for p in (0.0, 3e-20, 0.012345, 0.5):
        assert _p_value(p) == p_value_text(p)
    lines = fit.summary().splitlines()
    for name in FREE:
        p = fit.params.loc[name, "p_value"]
        if not np.isfinite(p) or not fit.tests_against_zero.get(name, True):
            continue
        row = next(line for line in lines if line.startswith(f"{name} "))
        assert p_value_text(p) in row, row


def test_sandwich_equals_finite_difference_scores(ou_case):
    """H⁻¹JH⁻¹ with J from central differences of the filter's per-step log-likelihood terms."""
    m, df, fit = ou_case
    sandwich = m.fit(df, cov_type="sandwich")
    opg = m.fit(df, cov_type="opg")
    theta = fit.values
    scores = []
    for name in FREE:
        h = 1e-6 * max(abs(theta[name]), 1.0)
        up = m.filter(dict(theta, **{name: theta[name] + h}), df).loglik_terms.to_numpy()
        down = m.filter(dict(theta, **{name: theta[name] - h}), df).loglik_terms.to_numpy()
        scores.append((up - down) / (2 * h))
    S = np.array(scores).T
    J = S.T @ S
    cov_h = fit.cov.loc[FREE, FREE].to_numpy()
    expected = cov_h @ J @ cov_h
    np.testing.assert_allclose(sandwich.cov.loc[FREE, FREE].to_numpy(), expected, rtol=2e-4,
                               atol=1e-6 * np.max(np.abs(expected)))
    np.testing.assert_allclose(opg.cov.loc[FREE, FREE].to_numpy(), np.linalg.inv(J), rtol=2e-4)
    assert sandwich.cov_type == "sandwich" and "covariance: sandwich" in sandwich.summary()
    # x0 is informed by the first observations only: its score-based SE is flagged.
    assert not sandwich.params.loc["x0", "reliable"] and any("'x0'" in w for w in sandwich.warnings)
    with pytest.raises(Exception, match="cov_type"):
        m.fit(df, cov_type="robust")


def test_k_step_sandwich_is_calibrated():
    """Monte Carlo (small; studies/table_7_1.py --horizon 4 at full size): with the 4-step
    criterion the Hessian's standard errors are too small, the sandwich's are right."""
    m = ou_model()
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"t": np.arange(600) * 0.5, "u": np.repeat(rng.choice([0.0, 1.0], 60), 10)})
    n = 30
    sims = m.simulate(TRUE, df, method="exact", seed=11, n_paths=n).outputs[:, :, 0]
    estimates, se_sandwich, se_hessian = [], [], []
    for i in range(n):
        data = df.assign(y=sims[i])
        fit = m.fit(data, horizon=4)
        assert fit.cov_type == "sandwich"
        estimates.append(fit.params["estimate"])
        se_sandwich.append(fit.bse)
        se_hessian.append(m.fit(data, horizon=4, cov_type="hessian", init=fit.values).bse)
    spread = pd.DataFrame(estimates).std()
    def rms(se):
        return np.sqrt((pd.DataFrame(se) ** 2).mean())
    for name in ("a", "b"):
        assert 0.7 < spread[name] / rms(se_sandwich)[name] < 1.3, name
        assert spread[name] / rms(se_hessian)[name] > 1.2, name


def test_forecast_past_the_data_equals_closed_form(ou_case):
    """Rows with inputs but no outputs are forecast from the last observation (OU closed form)."""
    m, df, fit = ou_case
    future = pd.DataFrame({"t": df["t"].iloc[-1] + 0.5 * np.arange(1, 21), "u": 1.0, "y": np.nan})
    extended = pd.concat([df, future], ignore_index=True)
    forecast = fit.predict(extended)
    same = m.predict(fit.values, extended, steps=1)
    pd.testing.assert_frame_equal(forecast, same)
    last = fit.filter(df)
    x, P = last.filtered["x"].iloc[-1], last.filtered_cov[-1, 0, 0]
    p = fit.values
    h = future["t"].to_numpy() - df["t"].iloc[-1]
    decay = np.exp(-p["a"] * h)
    mean = decay * x + p["b"] / p["a"] * (1 - decay)
    var = decay**2 * P + p["s"] ** 2 / (2 * p["a"]) * (1 - decay**2) + p["r"]
    tail = forecast.iloc[len(df):]
    np.testing.assert_allclose(tail["y"].to_numpy(), mean, rtol=1e-9)
    np.testing.assert_allclose(tail["y_sd"].to_numpy(), np.sqrt(var), rtol=1e-9)
    # Within the data the forecast frame holds the usual one-step predictions.
    np.testing.assert_allclose(forecast["y"].iloc[:len(df)], fit.predict(df)["y"], rtol=1e-12)


def test_nearly_flat_parameter_is_flagged():
    """A noise intensity the data cannot see (true exp(p) = 6e-6 under measurement noise 0.2)
    drifts with a huge standard error: flagged unreliable with a warning, not silently 'reliable'."""
    import greyid

    m = greyid.Model("ou_flat")
    m.add_system("dx = (-a*x + b*u)*dt + exp(p)*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[0.1]])
    for name, init, lower in [("a", 0.5, 0.0), ("b", 1.0, None), ("p", -3.0, None), ("r", 0.1, 0.0)]:
        m.set_parameter(name, init=init, lower=lower)
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"t": np.arange(300) * 0.5, "u": np.repeat(rng.choice([0.0, 1.0], 30), 10)})
    df["y"] = m.simulate(dict(a=0.8, b=1.5, p=-12.0, r=0.04), df, method="exact", seed=5).outputs[0, :, 0]
    fit = m.fit(df)
    assert not fit.params.loc["p", "reliable"] and fit.params.loc["a", "reliable"]
    assert any("nearly flat in 'p'" in w for w in fit.warnings)
    assert fit.message.startswith("converged")


def test_loaded_fit_reads_its_data_file(ou_case, tmp_path):
    import greyid

    m, df, fit = ou_case
    df.to_csv(tmp_path / "data.csv", index=False)
    fit.data_file = str(tmp_path / "data.csv")
    fit.save(tmp_path / "fit.json")
    loaded = greyid.load_fit(tmp_path / "fit.json")
    assert loaded.data is None
    np.testing.assert_allclose(loaded.residuals["y"].to_numpy(), fit.residuals["y"].to_numpy(), rtol=1e-8)
    assert "<html" in loaded.report(steps=2)[:200].lower()
    (tmp_path / "data.csv").unlink()
    again = greyid.load_fit(tmp_path / "fit.json")
    with pytest.raises(greyid.DataError, match="not there any more"):
        again.validate()


def test_predict_gives_time_and_states(ou_case):
    m, df, fit = ou_case
    pred = fit.predict(states=True)
    assert list(pred.columns) == ["t", "y", "y_sd", "x", "x_sd"]
    np.testing.assert_allclose(pred["t"], df["t"])
    filtered = fit.filter()
    np.testing.assert_allclose(pred["x"], filtered.predicted["x"], rtol=1e-10)
    np.testing.assert_allclose(pred["x_sd"], np.sqrt(filtered.predicted_cov[:, 0, 0]), rtol=1e-10)
    # The output's variance is the state's plus the measurement noise (y = x + e).
    np.testing.assert_allclose(pred["y_sd"] ** 2, pred["x_sd"] ** 2 + fit.values["r"], rtol=1e-9)


def test_fit_settings_are_typed_read_as_a_mapping_and_survive_files_old_and_new(ou_case, tmp_path):
    """A fit's settings are a FitSettings: read by key as before (``fit.settings["method"]``), saved and
    loaded unchanged; a file written before a setting existed loads with its default, one with a
    population member's random effects (``omega``) loads without them, an ``optimizer="lbfgs"`` fit's with its
    Hessian by differences, and an unknown setting or a missing one without a default is refused with the file
    named."""
    import json

    import greyid
    from greyid.estimate.settings import FitSettings

    m, df, fit = ou_case
    s = fit.settings
    assert isinstance(s, FitSettings) and s["method"] == s.method == "kalman" and s.get("robust") is None
    assert dict(s)["hold"] == s.hold and set(s) == set(FitSettings._names()) and len(s) == len(set(s))
    assert s.filter_kwargs() == {"time": "t", "hold": s.hold, "method": "kalman", "form": s.form,
                                 "substeps": s.substeps, "iterations": s.iterations}
    with pytest.raises(KeyError):
        s["no_such_setting"]
    fit.save(tmp_path / "fit.json")
    assert greyid.load_fit(tmp_path / "fit.json").settings == s
    document = json.loads((tmp_path / "fit.json").read_text())
    old = dict(document, settings={k: v for k, v in document["settings"].items()
                                   if k not in ("steady_state", "start_labels", "substeps_accurate", "hessian")})
    old["settings"]["omega"] = {"a": 0.1}
    (tmp_path / "old.json").write_text(json.dumps(old))
    loaded = greyid.load_fit(tmp_path / "old.json")
    assert loaded.settings == s.updated(start_labels=(), substeps_accurate=None) and "omega" not in loaded.settings
    assert loaded.loglik == fit.loglik
    # A file of an optimizer="lbfgs" fit written before the Hessian's kind was kept: its Hessian was by differences.
    old["settings"]["optimizer"] = "lbfgs"
    (tmp_path / "old_lbfgs.json").write_text(json.dumps(old))
    assert (loaded.settings.hessian, greyid.load_fit(tmp_path / "old_lbfgs.json").settings.hessian) == (
        "exact", "differences")
    for name, settings, message in [
            ("unknown.json", dict(document["settings"], colour="red"), "unknown setting 'colour'"),
            ("missing.json", {k: v for k, v in document["settings"].items() if k != "hold"}, "no setting 'hold'")]:
        (tmp_path / name).write_text(json.dumps(dict(document, settings=settings)))
        with pytest.raises(greyid.ModelError, match=f"{name}.*{message}"):
            greyid.load_fit(tmp_path / name)


def test_a_fit_result_is_constructed_in_one_place():
    """FitResult objects come from FitResult.of only: a fit's optimum, a saved file and a population
    member each give it their Estimates (no other call of the FitResult constructor in greyid)."""
    import ast
    from pathlib import Path

    source = Path(__file__).resolve().parents[1] / "src" / "greyid"
    calls = [f"{path.relative_to(source)}:{node.lineno}" for path in sorted(source.rglob("*.py"))
             for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
             if isinstance(node, ast.Call) and "FitResult" in (getattr(node.func, "id", None),
                                                                getattr(node.func, "attr", None))]
    assert calls == []
