"""Reduced Monte Carlo validations of the estimator (full size in studies/)."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

import greyid
from greyid.datasets import thesis
from greyid.fleet.study import run_study, simulated_series


def check(study, alpha=0.01):
    """No significant bias (|t| test) and estimated variances consistent with the empirical ones.

    With few series the F test has little power, so besides each quantity's F
    test the pooled log-ratio of variances is tested too.
    """
    assert study.converged.all()
    table = study.table()
    n = len(study.estimates)
    t_crit = stats.t.ppf(1 - alpha / 2, n - 1)
    f_lo, f_hi = stats.f.ppf(alpha / 2, n - 1, 1e9), stats.f.ppf(1 - alpha / 2, n - 1, 1e9)
    bad_t = table.index[table.t > t_crit].tolist()
    bad_f = table.index[(table.F < f_lo) | (table.F > f_hi)].tolist()
    assert not bad_t, f"biased: {bad_t}\n{table}"
    assert not bad_f, f"variance mismatch: {bad_f}\n{table}"
    # Pooled over quantities, the mean log F ratio is near 0 (variances neither under- nor over-estimated).
    assert abs(np.mean(np.log(table.F))) < 0.6, table
    return table


def test_test_cell_study_reduced():
    """Table 7.1 with 6 series: unbiased, honest standard errors, white residuals."""
    study = run_study(thesis.test_cell_model(), thesis.TEST_CELL_PARAMETERS, thesis.test_cell_inputs(), 6,
                      report=["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"], derived=thesis.TEST_CELL_DERIVED,
                      seed=11, simulate={"method": "exact"})
    table = check(study)
    assert table.loc["UA", "x_sim"] == pytest.approx(11.082, abs=1e-3)
    assert table.loc["CI", "x_sim"] == pytest.approx(2.2862, abs=1e-3)
    assert abs(study.residual_acf1.mean()) < 0.05
    # The series are fitted together as a fleet: each one's fit is the one model.fit gives alone
    # (the same optimum; estimates and standard errors to the searches' tolerance).
    model = thesis.test_cell_model()
    series = simulated_series(model, thesis.TEST_CELL_PARAMETERS, thesis.test_cell_inputs(), 6, seed=11,
                              method="exact")
    for i in (0, 5):
        alone = model.fit(series[i])
        names = ["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"]
        assert np.allclose(study.estimates.loc[i, names], [alone.values[n] for n in names], rtol=1e-5, atol=0)
        assert np.allclose(study.variances.loc[i, names], alone.params.loc[names, "std_error"] ** 2, rtol=1e-4,
                           atol=0)


def test_a_study_with_the_steady_state_fits_each_series_alone_and_not_on_a_cluster():
    """steady_state=True (given, or the model's own setting) is a single fit's: the series are fitted one
    after the other, equal to model.fit with it; with a cluster it is refused before anything is simulated."""
    model = thesis.test_cell_model()
    with pytest.raises(greyid.ModelError, match="steady_state=True fits the series one after the other"):
        run_study(model, thesis.TEST_CELL_PARAMETERS, thesis.test_cell_inputs(), 2, report=["Hi"],
                  fit={"steady_state": True}, scheduler=object())
    model.set_options(steady_state=True)
    with pytest.raises(greyid.ModelError, match="leave out scheduler"):
        run_study(model, thesis.TEST_CELL_PARAMETERS, thesis.test_cell_inputs(), 2, report=["Hi"],
                  scheduler=object())
    inputs = thesis.test_cell_inputs()
    study = run_study(model, thesis.TEST_CELL_PARAMETERS, inputs, 2, report=["Hi", "Ci"], seed=4,
                      simulate={"method": "exact"})
    alone = model.fit(simulated_series(model, thesis.TEST_CELL_PARAMETERS, inputs, 2, seed=4, method="exact")[1])
    assert alone.settings["steady_state"]
    assert np.array_equal(study.estimates.loc[1, ["Hi", "Ci"]].to_numpy(dtype=float),
                          [alone.values["Hi"], alone.values["Ci"]])


def test_lotka_volterra_study_reduced():
    """Table A.1 with 5 series through the EKF."""
    data = pd.DataFrame({"t": thesis.lotka_volterra_times()})
    study = run_study(thesis.lotka_volterra_model(), thesis.LOTKA_VOLTERRA_PARAMETERS, data, 5,
                      report=["a", "b", "c", "d", "s1", "s2", "m1", "m2"], seed=3,
                      simulate={"method": "milstein", "substeps": 20},
                      fit={"method": "ekf", "substeps": 1})  # one sub-step, as the thesis ran it
    check(study)


def test_table_7_4_study_runs_and_the_step_wins_for_ua(capsys):
    """studies/table_7_4.py on a shorter experiment: both tables print, and the step signal, whose
    power lies at the lowest frequencies, determines the UA-value best (table 7.5's finding)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
    import table_7_4

    table_7_4.main(["--hours", "504"])
    out = capsys.readouterr().out
    assert "Table 7.4" in out and "Table 7.5" in out
    plans = table_7_4.candidates(504)
    from greyid import design

    ranks = design.compare_inputs(thesis.test_cell_model(), thesis.TEST_CELL_PARAMETERS, plans,
                                  criteria={"UA": {"name": "A", "derived": {"UA": table_7_4.PHYSICAL["UA"]}}},
                                  free=["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"])
    assert ranks.loc["step", "UA rank"] == 1
    assert ranks.loc["prbs4", "UA rank"] < ranks.loc["prbs1", "UA rank"]


def test_section_6_5_single_frequency_designs():
    """The scalar example of section 6.5: the local and minimax optimal frequencies come within 0.015
    of the thesis' 0.6606 and 0.8128 (the Bayesian one does not: docs/design.md)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
    import section_6_5

    found = section_6_5.designs(points=400, a_points=13)
    assert found["local"][0] == pytest.approx(0.6606, abs=0.015)
    assert found["minimax"][0] == pytest.approx(0.8128, abs=0.015)
    # The minimax design guards against the worst a, at a higher criterion than the local design's.
    assert found["minimax"][1] > found["local"][1]


def test_passys_window_case_reduced():
    """Case 1 (section 7.4), reduced: the simulated experiments have the thesis' inputs and outputs, the
    models are dimensionally consistent, and the calibration fit hands a prior on the envelope to the
    test experiment (the four fits run in studies/passys_window.py, docs/case-studies.md)."""
    import sys
    import warnings
    from pathlib import Path

    pytest.importorskip("pvlib")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
    import passys_window

    calibration, test = passys_window.experiments(days=4, seed=1)
    assert len(calibration) == len(test) == 96
    assert {"Gdif", "Gdir", "theta", "yTa", "yTs"} <= set(test.columns)
    assert test["Gdir"].max() > 100 and (test["Gdir"] >= 0).all()
    for model in (passys_window.calibration_model(), passys_window.component_model(True),
                  passys_window.component_model(False)):
        assert all(line.endswith("✓") for line in model.check_units())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = passys_window.calibration_model().fit(calibration)
    known = [n for n in passys_window.ENVELOPE if np.isfinite(fit.bse[n])]
    prior = fit.to_prior(names=known)
    assert list(prior["mean"]) == known and "C_a" in known  # the air capacity is always determined
    truth = passys_window.true_characteristics()
    assert truth["UA_tr,e [W/K]"] == pytest.approx(18 * 9 / 27) and truth["alpha_eff"] == 2.0
    ua = fit.derived({"UA": passys_window.CHARACTERISTICS["UA_tr,e [W/K]"]}).loc["UA"]
    assert ua["estimate"] == pytest.approx(1 / (1 / fit.values["H_av"] + 1 / fit.values["H_ve"]))
    assert np.isfinite(ua["std_error"]) and ua["std_error"] > 0


def test_fuel_film_case_reduced():
    """Case 2 (chapter 8), reduced: two of table 8.2's operating points on 1200 samples, fitted in one
    batched call; the delay, time constants, X and k_b come back within 4 standard errors of the table
    and the residuals pass the cumulative periodogram test (all eleven in studies/fuel_film.py)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
    import fuel_film

    points = fuel_film.TABLE_8_2.loc[["s40g4", "s60g4"]]
    datasets = {name: fuel_film.experiment(point, seed=k, samples=1200) for k, (name, point)
                in enumerate(points.iterrows())}
    fleet = fuel_film.fit_points(datasets)
    table = fuel_film.comparison(fleet, points)
    assert table["converged"].all()
    z = table[[f"{p}_z" for p in ("delta_t", "tau_s", "tau_ff", "X", "kb")]].abs()
    assert (z < 4).all().all(), z
    assert (fuel_film.whiteness(fleet, datasets)["p_value"] > 0.01).all()
