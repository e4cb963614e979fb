"""The model library: every model builds, RC names, and models that recover what they simulate."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from greyid import ModelError, library
from greyid.simulate.signals import prbs

EXPECTED_KIND = {"logistic_growth": "nonlinear", "lotka_volterra": "nonlinear",
                 "test_cell": "lti"}


@pytest.mark.parametrize("name", library.names())
def test_library_model_builds(name):
    m = library.load_model(name)
    assert m.description
    assert m.kind == EXPECTED_KIND.get(name, "lti")
    free = [n for n in m.parameter_names if not m.parameters[n].fixed]
    assert all(m.parameters[n].init is not None for n in free)  # ready to fit


def test_rc_names_in_any_order():
    a, b = library.load_model("TiThTeTs"), library.load_model("TiTeThTs")
    assert a.to_dict() == b.to_dict()
    assert a.state_names == ("Ti", "Te", "Th", "Ts")
    assert a.output_names == ("yTi",)
    assert 'yTi = { equation = "Ts"' in a.to_toml()
    with pytest.raises(ModelError, match="no model 'TiTx'"):
        library.load_model("TiTx")


def test_rc_network_heat_balance():
    """At steady state with Ph and Ps zero, every temperature equals Ta (no heat source)."""
    m = library.load_model("TiTeThTm")
    p = m.initial_values()
    n = len(m.state_names)
    f = m.structure.drift
    x = np.full(n, 7.5)
    assert np.allclose(np.asarray(f(x, np.array([7.5, 0.0, 0.0]), 0.0, m.parameter_vector(p))), 0.0)
    # UA of the one-state model is 1/Ria
    ua = library.load_model("Ti").derived["UA [kW/K]"]
    assert ua == "1/Ria"


def test_fuel_film_recovers_time_constants_and_delay():
    """Simulate the fuel-film model (8.1)–(8.3) with a PRBS on the injected fuel and fit it back."""
    m = library.load_model("fuel_film")
    truth = {"tau_s": 0.15, "tau_ff": 1.2, "X": 0.35, "delta_t": 0.07, "kb": 14.67 / 20.0, "s1f": 2e-4,
             "s1ff": 1e-4, "s2": 2e-4, "mf0": 1.4, "mff0": 0.49}
    n = 800
    t = np.arange(n) * 0.0125 * 4  # the thesis' sampling, every 4th sample
    mfi = prbs(6, clock=10, levels=(1.2, 1.6), length=n)
    data = pd.DataFrame({"t": t, "mfi": mfi})
    sim = m.simulate(truth, data, method="exact", seed=4)
    data["phi"] = sim.outputs[0, :, 0]
    fit = m.fit(data)
    assert fit.converged
    for name in ("tau_s", "tau_ff", "X", "delta_t", "kb"):
        est, se = fit.params.loc[name, ["estimate", "std_error"]]
        assert abs(est - truth[name]) < 4 * se, name
    assert fit.loglik >= m.loglik(truth, data) - 1e-6


def test_logistic_growth_tends_to_capacity():
    m = library.load_model("logistic_growth")
    p = dict(m.initial_values(), rho=1.0, K=50.0, x0=5.0, sigma=0.05)
    times = np.linspace(0, 15, 61)
    expected = 50.0 / (1 + (50.0 / 5.0 - 1) * np.exp(-1.0 * times))  # the closed-form logistic curve
    errors = {}
    for method in ("euler", "milstein", "heun"):
        sim = m.simulate(p, times, noise=False, substeps=50, method=method)
        errors[method] = np.max(np.abs(sim.states[0, :, 0] / expected - 1))
    # Without noise every scheme solves the ODE: first order (Euler, Milstein), second order (Heun).
    assert errors["euler"] < 3e-3 and errors["milstein"] == pytest.approx(errors["euler"], rel=1e-9)
    assert errors["heun"] < 1e-5
