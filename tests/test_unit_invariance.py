"""No answer of design or identifiability depends on the units a model is written in.

The Armadillo house model (pySIP's TwTi_RoRi) in SI units (J/K, K/W, W, seconds) and
in kWh/K, K/kW, kW and hours; and a model whose parameters span 1e-6 to 1e9 against
the same model with every parameter of order one.
"""

import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import design

ROOT = Path(__file__).resolve().parents[1]
MIRROR = Path(os.environ.get("GREYID_DATA_MIRROR", ROOT.parent / "shared" / "data"))  # as conftest.py sets it
DATA = MIRROR / "armadillo_box" / "armadillo_data_H2.csv"

# θ_SI = FACTOR · θ_kWh (time: 3600 s per hour; power: 1000 W per kW).
FACTOR = {"Cw": 3.6e6, "Ci": 3.6e6, "Ri": 1e-3, "Ro": 1e-3, "sigw": 1.0 / 60.0, "sigv": 1.0, "Tw0": 1.0}
# Near the fit of the SI model to the Armadillo data.
POINT_SI = {"Cw": 1.5086e7, "Ri": 1.9866e-3, "Ro": 1.8427e-2, "Ci": 1.6368e6, "sigw": 2.6027e-3, "sigv": 4.8668e-2,
            "Tw0": 26.588}
POINT_KWH = {n: v / FACTOR[n] for n, v in POINT_SI.items()}


def kwh_model():
    text = (ROOT / "examples" / "armadillo.toml").read_text(encoding="utf-8")
    kwh_lines = {  # the same bounds and initial values in K/kW and kWh/K
        "Ro = { init = 0.01, lower = 0.0001, upper = 1.0 }": "Ro = { init = 10.0, lower = 0.1, upper = 1000.0 }",
        "Ri = { init = 0.005, lower = 0.0001, upper = 1.0 }": "Ri = { init = 5.0, lower = 0.1, upper = 1000.0 }",
        "Cw = { init = 1e7, lower = 1e5, upper = 1e9 }": "Cw = { init = 2.78, lower = 0.0278, upper = 278.0 }",
        "Ci = { init = 1e6, lower = 1e4, upper = 1e8 }": "Ci = { init = 0.278, lower = 0.00278, upper = 27.8 }",
        "sigw = { init = 0.001, lower = 1e-6, upper = 1.0 }": "sigw = { init = 0.06, lower = 6e-5, upper = 60.0 }",
    }
    for si, kwh in kwh_lines.items():
        text = text.replace(si, kwh)
    assert text.count("init = ") == 7 and "1e7" not in text
    return greyid.Model.from_toml(text)


@pytest.fixture(scope="module")
def models():
    return greyid.Model.from_toml(ROOT / "examples" / "armadillo.toml"), kwh_model()


@pytest.fixture(scope="module")
def plans():
    if not DATA.is_file():
        pytest.skip(f"shared dataset {DATA} is not available")
    data = pd.read_csv(DATA)
    si = data[["Time", "T_ext", "P_hea"]]
    kwh = si.assign(Time=si["Time"] / 3600.0, P_hea=si["P_hea"] / 1000.0)
    return si, kwh


def test_identifiability_verdicts_do_not_depend_on_units(models):
    si, kwh = models
    a, b = design.identifiability(si), design.identifiability(kwh)
    assert a.status == b.status
    assert a.status == {"Cw": "global", "Ri": "global", "Ro": "global", "Ci": "global", "sigw": "local",
                        "sigv": "local"}
    assert a.combinations == b.combinations == []
    # At the fit's values (what `greyid identifiability fit.json` uses) the same verdicts.
    assert design.identifiability(si, POINT_SI).status == a.status


def spread_model(scale: dict) -> greyid.Model:
    """dx = (−k1·k2·x + g·u) dt + s dω, y = c·x: only k1·k2 is determined, with values scaled by ``scale``."""
    m = greyid.Model("spread")
    m.add_inputs("u")
    m.add_system("dx = (-k1*k2*x + g*u)*dt + s*dw1")
    m.add_observation("y = c*x", variance="e^2")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    base = {"k1": 1e-6, "k2": 1e3, "g": 1e9, "c": 1e-6, "s": 1e-2, "e": 0.1}
    for name, value in base.items():
        v = value * scale.get(name, 1.0)
        m.set_parameter(name, init=v, lower=v * 1e-3, upper=v * 1e3)
    m.fix_parameter("c", base["c"] * scale.get("c", 1.0))
    return m


def test_identifiability_of_a_wide_span_model_names_the_same_combination():
    wide = spread_model({})
    unit = spread_model({"k1": 1e6, "k2": 1e-3, "g": 1e-9, "c": 1e6, "s": 1e2, "e": 10.0})
    a, b = design.identifiability(wide), design.identifiability(unit)
    assert a.status == b.status
    assert a.status["k1"] == a.status["k2"] == "not identifiable"
    assert a.status["g"] != "not identifiable" and a.status["s"] != "not identifiable"
    assert a.combinations == b.combinations == ["k1*k2"]


def test_cramer_rao_bounds_convert_by_the_unit_factors(models, plans):
    (si, kwh), (plan_si, plan_kwh) = models, plans
    info_si = design.fisher_information(si, POINT_SI, plan_si, time="Time", hold="foh")
    info_kwh = design.fisher_information(kwh, POINT_KWH, plan_kwh, time="Time", hold="foh")
    assert np.linalg.cond(info_si.to_numpy()) > 1e18  # from the units alone
    bound_si, bound_kwh = design.cramer_rao_bound(info_si), design.cramer_rao_bound(info_kwh)
    assert np.all(np.isfinite(bound_si))
    factors = pd.Series(FACTOR)[bound_si.index]
    np.testing.assert_allclose(np.sqrt(bound_si), np.sqrt(bound_kwh) * factors, rtol=1e-6)
    # Against a plain inverse of the well-conditioned (kWh) information: the same standard errors.
    np.testing.assert_allclose(bound_kwh, np.diag(np.linalg.inv(info_kwh.to_numpy())), rtol=1e-8)
    # UA = 1/(Ro + Ri), W/K against kW/K.
    ua_si = design.cramer_rao_bound(info_si, POINT_SI, {"UA": "1/(Ro + Ri)"})["UA"]
    ua_kwh = design.cramer_rao_bound(info_kwh, POINT_KWH, {"UA": "1/(Ro + Ri)"})["UA"]
    assert np.sqrt(ua_si) == pytest.approx(1000.0 * np.sqrt(ua_kwh), rel=1e-6)
    # D differs by the log-determinant of the scaling alone: M_SI = D M_kWh D, D = diag(1/factor).
    shift = 2.0 * np.sum(np.log(factors.to_numpy()))
    assert design.criterion(info_si, "D") == pytest.approx(design.criterion(info_kwh, "D") + shift, abs=1e-6)
    for name in ("C", "E"):  # C is scale-free; E of relative errors too
        kw = dict(params=POINT_SI) if name == "C" else dict(V=np.diag(1 / np.array(list(POINT_SI.values()))))
        kw_kwh = dict(params=POINT_KWH) if name == "C" else dict(V=np.diag(1 / np.array(list(POINT_KWH.values()))))
        assert design.criterion(info_si, name, **kw) == pytest.approx(design.criterion(info_kwh, name, **kw_kwh),
                                                                      rel=1e-6)
    assert design.local_identifiability(info_si).empty and design.local_identifiability(info_kwh).empty


def test_a_singular_information_gives_inf_and_names_the_direction():
    names = ["a", "b", "c"]
    # a and b enter only as a + 1e6·b (b in other units): singular along (1e6, −1) in (a, b).
    J = np.array([[1.0, 1e6, 0.0], [0.0, 0.0, 1e-4]])
    info = pd.DataFrame(J.T @ J, index=names, columns=names)
    with pytest.warns(greyid.UndeterminedWarning, match=r"·a.*·b|·b.*·a"):
        assert design.criterion(info, "D") == np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.warns(greyid.UndeterminedWarning):
            bound = design.cramer_rao_bound(info, {"a": 1.0, "b": 1.0, "c": 1.0}, {"sum": "a + 1000000*b"})
    assert np.isinf(bound["a"]) and np.isinf(bound["b"])
    assert bound["c"] == pytest.approx(1e8)  # determined: its own bound
    assert bound["sum"] == pytest.approx(1.0)  # what the data do determine
    flat = design.local_identifiability(info)
    assert len(flat) == 1 and set(flat["parameters"].iloc[0]) == {"a", "b"}
    # A criterion of a determined derived quantity is finite although M is singular.
    assert design.criterion(info, "A", params={"a": 1.0, "b": 1.0, "c": 1.0},
                            derived={"sum": "a + 1000000*b"}) == pytest.approx(1.0)
    for name in ("A", "E", "C"):
        with pytest.warns(greyid.UndeterminedWarning):
            assert design.criterion(info, name, params={"a": 1.0, "b": 1.0, "c": 1.0}) == np.inf
    with pytest.warns(greyid.UndeterminedWarning):
        assert design.criterion(info, "Ds", interest=["a"]) == np.inf
    assert np.isfinite(design.criterion(info, "Ds", interest=["c"]))


def test_optimal_multisine_is_the_same_in_either_unit_system(models):
    si, kwh = models
    # The same input power: 1 kW² = 1e6 W²; sampling every half hour.
    a = design.optimal_multisine(si, POINT_SI, "P_hea", 1800.0, power=1e6, grid=120, iterations=1500)
    b = design.optimal_multisine(kwh, POINT_KWH, "P_hea", 0.5, power=1.0, grid=120, iterations=1500)
    assert list(a.information.index) == ["Cw", "Ri", "Ro", "Ci", "sigw", "sigv"]  # Tw0: not seen per sample
    np.testing.assert_allclose(a.frequencies * 3600.0, b.frequencies, rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(a.weights, b.weights, atol=1e-3)
    factors = np.array([FACTOR[n] for n in a.information.index])
    assert a.value == pytest.approx(b.value + 2.0 * np.sum(np.log(factors)), abs=1e-4)
    assert a.max_derivative == pytest.approx(a.support_derivative, rel=1e-2)


@pytest.mark.parametrize("optimizer", ["auto", "lbfgs"])
def test_a_fit_gives_the_same_answer_in_either_unit_system(models, optimizer):
    """The Armadillo fit in SI and in kWh/K, K/kW, hours: estimates and standard errors convert by the
    unit factors, the log-likelihoods differ by the Jacobian of the time change alone (none here:
    the output is a temperature in both), and the same parameters are flagged; by Newton's steps and by
    L-BFGS with the Hessian by differences of the gradient."""
    if not DATA.is_file():
        pytest.skip(f"shared dataset {DATA} is not available")
    si, kwh = models
    data = pd.read_csv(DATA).iloc[:-1]
    data_kwh = data.assign(Time=data["Time"] / 3600.0, P_hea=data["P_hea"] / 1000.0)
    a = si.fit(data, time="Time", hold="foh", init=POINT_SI, optimizer=optimizer)
    b = kwh.fit(data_kwh, time="Time", hold="foh", init=POINT_KWH, optimizer=optimizer)
    assert a.converged and b.converged
    assert a.loglik == pytest.approx(b.loglik, abs=1e-6)
    factors = pd.Series(FACTOR)[a.params.index]
    np.testing.assert_allclose(a.params["estimate"], b.params["estimate"] * factors, rtol=1e-5)
    np.testing.assert_allclose(a.params["std_error"], b.params["std_error"] * factors, rtol=1e-4)
    assert a.ill_determined == b.ill_determined == []


def test_the_design_command_on_the_si_example(plans, tmp_path, capsys):
    """`greyid design examples/armadillo.toml PLAN`: finite bounds and exit 0 for the data's own plan;
    a plan without heating determines less: exit 1 and the direction named, no inf bound without it."""
    from greyid.cli import main

    plan_si, _ = plans
    good, cold = tmp_path / "plan.csv", tmp_path / "cold.csv"
    plan_si.to_csv(good, index=False)
    plan_si.assign(P_hea=0.0).to_csv(cold, index=False)
    assert main(["design", str(ROOT / "examples" / "armadillo.toml"), str(good)]) == 0
    printed = capsys.readouterr().out
    bounds = printed[printed.index("sd bound"):printed.index("criteria")]
    assert "inf" not in bounds and "not determined by" not in printed
    assert main(["design", str(ROOT / "examples" / "armadillo.toml"), str(cold)]) == 1
    printed = capsys.readouterr().out
    assert "not determined by plan 'cold'" in printed and "inf" in printed
