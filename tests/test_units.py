"""Physical units: every equation checked for dimensions (Pint) before a fit, offending terms named, scale
mismatches caught, units carried through model files, parameter tables, summaries and derived quantities."""

import pytest

import greyid
from greyid import library

UNITS = {"t": "h", "Ti": "K", "Te": "K", "Ta": "K", "yTi": "K", "Ph": "kW", "Ps": "kW/m^2", "Ci": "kWh/K",
         "Ce": "kWh/K", "Rie": "K/kW", "Rea": "K/kW", "Aw": "m^2", "p11": "K/h^0.5",
         "p22": "K/h^0.5", "e11": "K^2"}


def house():
    m = greyid.Model("TiTe")
    m.add_system("dTi = ((Te - Ti)/(Rie*Ci) + Ph/Ci + Aw*Ps/Ci)*dt + exp(p11)*dw1",
                 "dTe = ((Ti - Te)/(Rie*Ce) + (Ta - Te)/(Rea*Ce))*dt + exp(p22)*dw2")
    m.add_inputs("Ta", "Ph", "Ps")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0", "Te": "Te0"})
    return m


def test_consistent_equations_pass_with_a_line_per_term():
    m = house().set_units(UNITS)
    lines = m.check_units()
    assert "in dTi (drift): term Ph/Ci has unit K·kW/kWh = K/h, expected K/h ✓" in lines
    assert any(line.startswith("in dTi (dw1): term exp(p11) has unit K/h⁰⋅⁵") for line in lines)
    report = m.unit_report()
    assert report["ok"].all() and len(report) == 9


def test_inconsistent_terms_are_named():
    m = house().set_units(dict(UNITS, Aw="m"))  # an area given as a length
    with pytest.raises(greyid.ModelError, match=r"in dTi \(drift\): term Aw\*Ps/Ci has unit .* expected K/h ✗"):
        m.check_units()
    # Same dimension, another scale: J/K for a capacity with kW and hours is 3.6e6 times off.
    m = house().set_units(dict(UNITS, Ci="J/K"))
    with pytest.raises(greyid.ModelError, match="a factor 3.6e\\+06 apart"):
        m.check_units()
    # A sum of unlike quantities inside a term, and a name without a unit.
    m = house().set_units({k: v for k, v in UNITS.items() if k != "p22"})
    with pytest.raises(greyid.ModelError, match="p22 has no unit: taken as dimensionless"):
        m.check_units()
    odd = greyid.Model("odd").add_system("dx = (u - x*k)*dt + s*dw1").add_inputs("u")
    odd.add_observation("y = x", variance="r").set_initial_state(mean={"x": "0"}, covariance=[[1.0]])
    odd.set_units({"t": "s", "x": "m", "u": "m/s", "k": "1/s", "s": "m/s^0.5", "r": "m^2", "y": "m"})
    with pytest.raises(greyid.ModelError, match="term -k\\*x has unit m/h = 0.000277778 m/s, expected m/s ✗"):
        odd.set_units({"k": "1/h"}).check_units()
    inside = greyid.Model("inside").add_system("dx = k*(u - x)*dt + s*dw1").add_inputs("u")
    inside.add_observation("y = x", variance="r").set_initial_state(mean={"x": "0"}, covariance=[[1.0]])
    inside.set_units({"t": "s", "x": "m", "u": "m/s", "k": "1/s", "s": "m/s^0.5", "r": "m^2", "y": "m"})
    with pytest.raises(greyid.ModelError, match="'-x' has unit m but 'u' beside it has m/s"):
        inside.check_units()
    with pytest.raises(greyid.ModelError, match="unknown unit 'furlongz' for 'x'"):
        odd.set_units({"x": "furlongz"})
    with pytest.raises(greyid.ModelError, match="units given for 'q', which is not a name"):
        odd.set_units({"q": "m"}).check_units()
    with pytest.raises(greyid.ModelError, match="the argument 'x' of exp has unit m"):
        greyid.Model("e").add_system("dx = -exp(x)*dt + s*dw1").add_observation("y = x", variance="r") \
            .set_initial_state(mean={"x": "0"}, covariance=[[1.0]]) \
            .set_units({"t": "s", "x": "m", "y": "m", "s": "m/s^0.5", "r": "m^2"}).check_units()


def test_a_fit_refuses_inconsistent_units_and_carries_consistent_ones(tmp_path):
    from greyid.datasets import building_model, load_building_data

    m = building_model()
    assert m.units["Ci"] == "kWh/K"
    data = load_building_data()
    fit = m.fit(data)
    assert fit.params.loc["Ci", "unit"] == "kWh/K" and fit.params.loc["Ti0", "unit"] == "degC"
    assert "[kWh/K]" in fit.summary()
    derived = fit.derived()
    assert derived.loc["UA [kW/K]", "unit"] == "kW/K" and derived.loc["C_total [kWh/K]", "unit"] == "kWh/K"
    # The units travel with the model file and the saved fit.
    again = greyid.Model.from_toml(m.to_toml())
    assert again.units == m.units
    fit.save(tmp_path / "fit.json")
    assert greyid.load_fit(tmp_path / "fit.json").params.loc["Riw", "unit"] == "K/kW"
    figure = fit.validate().plot_prediction()
    assert figure.axes[0].get_ylabel() == "yTi [°C]" and figure.axes[-1].get_xlabel() == "t [h]"
    from greyid.report.html import _parameters_section

    section = _parameters_section(fit)
    assert "<th>unit</th>" in section and "<td>kWh/K</td>" in section
    assert "<td>m²</td>" in section and "<td>°C</td>" in section  # as a reader writes them
    wrong = building_model().set_units({"Aw": "m"})
    with pytest.raises(greyid.ModelError, match="not dimensionally consistent"):
        wrong.fit(data)


def test_every_library_model_with_units_is_consistent():
    for name in (*library.BUILDING_MODELS, "test_cell", "fuel_film"):
        model = library.load_model(name)
        assert model.units and all(line.endswith("✓") for line in model.check_units()), name


def test_celsius_offsets_cancel_in_differences():
    m = greyid.Model("c").add_system("dT = (Ta - T)/tau*dt + s*dw1").add_inputs("Ta")
    m.add_observation("y = T + 273.15", variance="r").set_initial_state(mean={"T": "0"}, covariance=[[1.0]])
    m.set_units({"t": "min", "T": "degC", "Ta": "degC", "tau": "min", "s": "K/min^0.5", "y": "K", "r": "K^2"})
    assert all(line.endswith("✓") for line in m.check_units())


def test_the_thesis_test_cell_carries_units_and_hand_conversions_get_none():
    from greyid.datasets.thesis import test_cell_model

    m = test_cell_model()
    assert all(line.endswith("✓") for line in m.check_units())
    from greyid.model.units import derived_unit

    assert derived_unit(m, m.units, "Hi*Hm/(Hi+Hm)") == "W/K"
    assert derived_unit(m, m.units, "(Ci + Hi*Cm/(Hm+Hi))*3600/1e6") == ""  # a conversion to MJ/K by hand


def test_units_are_shown_as_a_reader_writes_them():
    """Figures' axis labels and the report's tables write units alike: superscripts, °C, √h."""
    from greyid.model.units import pretty
    from greyid.validation.plots import labelled

    assert pretty("kW/m^2") == "kW/m²" and pretty("degC") == "°C" and pretty("K/h^0.5") == "K/√h"
    assert pretty("K^2") == "K²" and pretty("not a unit at all") == "not a unit at all"
    assert pretty("log(K/kW)") == "log(K/kW)"
    assert labelled("Ps", {"Ps": "kW/m^2"}) == "Ps [kW/m²]" and labelled("Ta", {}) == "Ta"
