"""Model specification: parsing, classification, Python-function models, compile-once."""

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import DataError, ModelError


def two_state(**kw):
    m = greyid.Model("TiTw")
    m.add_system("dTi = (1/(Ci*Riw)*(Tw-Ti) + Aw/Ci*Gv + Qi/Ci)*dt + exp(p11)*dw1")
    m.add_system("dTw = (1/(Cw*Riw)*(Ti-Tw) + 1/(Cw*Rwe)*(Te-Tw))*dt + exp(p22)*dw2")
    m.add_inputs("Te", "Gv", "Qi")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0", "Tw": 31.0}, **kw)
    return m


def test_names_and_classification():
    m = two_state()
    assert m.state_names == ("Ti", "Tw")
    assert m.input_names == ("Te", "Gv", "Qi")
    assert set(m.parameter_names) == {"Ci", "Riw", "Aw", "p11", "Cw", "Rwe", "p22", "e11", "Ti0"}
    assert m.kind == "lti"
    ltv = greyid.Model("ltv")
    ltv.add_system("dx = -k*(1 + u)*x*dt + s*dw1")
    ltv.add_inputs("u")
    ltv.add_observation("y = x", variance="r")
    ltv.set_initial_state(mean={"x": 0.0})
    assert ltv.kind == "ltv"
    tv = greyid.Model("time")
    tv.add_system("dx = (-k*x + sin(t))*dt + s*dw1")
    tv.add_observation("y = x", variance="r")
    tv.set_initial_state(mean={"x": 0.0})
    assert tv.kind == "ltv"
    nl = greyid.Model("nl")
    nl.add_system("dx = -k*x*dt + s*sqrt(abs(x))*dw1")
    nl.add_observation("y = x", variance="r")
    nl.set_initial_state(mean={"x": 1.0})
    assert nl.kind == "nonlinear"


def test_algebraic_definitions_functions_and_piecewise():
    m = greyid.Model("alg")
    m.add_algebraic("theta = exp(logtheta)")
    m.add_system("dx = (-theta*x + max(u, 0) + Piecewise((1, t < 2), (0, True)))*dt + exp(ls)*dw1")
    m.add_inputs("u")
    m.add_observation("y = tanh(x) + x^2", variance="exp(le)")
    m.set_initial_state(mean={"x": 0.5}, covariance=[[0.1]])
    assert set(m.parameter_names) == {"logtheta", "ls", "le"}
    assert m.kind == "nonlinear"
    s = m.structure
    theta = jnp.asarray(m.parameter_vector({"logtheta": np.log(2.0), "ls": 0.0, "le": 0.0}))
    f = s.drift(jnp.array([1.0]), jnp.array([-3.0]), 1.0, theta)
    assert float(f[0]) == pytest.approx(-2.0 + 0.0 + 1.0)
    h = s.observation(jnp.array([0.5]), jnp.array([0.0]), 0.0, theta)
    assert float(h[0]) == pytest.approx(np.tanh(0.5) + 0.25)


def test_singular_and_correlated_noise_and_state_dependent_diffusion():
    m = greyid.Model("noise")
    m.add_system("dx1 = (-x1 + x2)*dt + s*dw1")
    m.add_system("dx2 = -0.5*x2*dt + q*dw1 + 0.1*x2*dw2")  # dw1 shared, dw2 state dependent
    m.add_system("dx3 = (x1 - x3)*dt")  # no noise
    m.add_observation("y1 = x1", variance="r")
    m.add_observation("y2 = x3", variance="r")
    m.set_initial_state(mean={"x1": 1.0, "x2": 0.0, "x3": 0.0}, covariance=[0.1, 0.1, 0.1])
    s = m.structure
    assert s.noise_names == ("dw1", "dw2") and m.kind == "nonlinear"
    theta = jnp.asarray(m.parameter_vector({"s": 1.0, "q": 2.0, "r": 0.1}))
    G = np.asarray(s.diffusion(jnp.array([0.0, 3.0, 0.0]), jnp.zeros(0), 0.0, theta))
    np.testing.assert_allclose(G, [[1.0, 0.0], [2.0, 0.3], [0.0, 0.0]])
    df = pd.DataFrame({"t": np.arange(20.0), "y1": np.sin(np.arange(20.0)), "y2": np.nan})
    df.loc[::3, "y2"] = 0.5
    for method in ("ekf", "ukf", "iekf"):
        assert np.isfinite(m.loglik({"s": 1.0, "q": 2.0, "r": 0.1}, df, method=method))


def test_python_function_model_equals_equation_model():
    eq = greyid.Model("eq")
    eq.add_system("dx = (-a*x + b*u)*dt + s*dw1")
    eq.add_inputs("u")
    eq.add_observation("y = x", variance="r")
    eq.set_initial_state(mean={"x": "x0"}, covariance=[[0.5]])
    fn = greyid.Model.from_functions(
        states=["x"], inputs=["u"], outputs=["y"], parameters=["a", "b", "s", "r", "x0"],
        drift=lambda x, u, t, p: jnp.array([-p["a"] * x[0] + p["b"] * u[0]]),
        diffusion=lambda x, u, t, p: jnp.array([[p["s"]]]),
        observation=lambda x, u, t, p: x,
        observation_variance=lambda x, u, t, p: jnp.array([p["r"]]),
        kind="lti",
    )
    fn.set_initial_state(mean={"x": "x0"}, covariance=[[0.5]])
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"t": np.cumsum(rng.uniform(0.5, 1, 30)), "u": rng.normal(size=30), "y": rng.normal(size=30)})
    p = dict(a=0.7, b=1.2, s=0.4, r=0.2, x0=0.3)
    assert fn.loglik(p, df) == pytest.approx(eq.loglik(p, df), rel=1e-12)
    assert fn.loglik(p, df, method="ekf") == pytest.approx(eq.loglik(p, df), rel=1e-10)


@pytest.mark.parametrize("inputs", [2, 0])
def test_linear_drift_is_the_drift(inputs):
    """(A, B, c) of a linear time-invariant model, from the symbolic derivatives: f(x, u) = A x + B u + c."""
    from conftest import random_linear_model_spec, random_linear_parameters

    model = random_linear_model_spec(nu=inputs) if inputs else greyid.Model("no_inputs")
    if not inputs:
        model.add_system("dx1 = (-a*x1 + k*x2 + c)*dt + s*dw1", "dx2 = (x1 - b*x2)*dt + s*dw2")
        model.add_observation("y = x1", variance="r")
        model.set_initial_state(mean={"x1": 0.0, "x2": 0.0}, covariance=[[1.0, 0.0], [0.0, 1.0]])
        params = dict(a=0.7, k=0.2, b=1.1, c=0.4, s=0.3, r=0.1)
    else:
        params, _ = random_linear_parameters(np.random.default_rng(3), nu=inputs)
    structure = model.structure
    theta = jnp.asarray(model.parameter_vector(params))
    A, B, c = structure.linear_drift(theta)
    assert B.shape == (structure.n_states, inputs)
    rng = np.random.default_rng(4)
    for _ in range(3):
        x, u = jnp.asarray(rng.normal(size=structure.n_states)), jnp.asarray(rng.normal(size=inputs))
        np.testing.assert_allclose(A @ x + B @ u + c, structure.drift(x, u, 0.0, theta), rtol=1e-12, atol=1e-12)
    nonlinear = greyid.Model("logistic")
    nonlinear.add_system("dx = r*x*(1 - x/K)*dt + s*dw1")
    nonlinear.add_observation("y = x", variance="v")
    nonlinear.set_initial_state(mean={"x": 1.0}, covariance=[[1.0]])
    assert nonlinear.structure.linear_drift is None


def test_compiles_once_per_structure_across_data_and_parameters():
    traces = []

    def drift(x, u, t, p):
        traces.append(1)  # runs only while JAX traces
        return -p["a"] * x

    m = greyid.Model.from_functions(
        states=["x"], outputs=["y"], parameters=["a", "s"], drift=drift,
        diffusion=lambda x, u, t, p: jnp.array([[p["s"]]]), observation=lambda x, u, t, p: x,
        observation_variance=lambda x, u, t, p: jnp.array([0.1]), kind="lti")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    rng = np.random.default_rng(1)

    def data(n):
        return pd.DataFrame({"t": np.cumsum(rng.uniform(0.5, 1.5, n)), "y": rng.normal(size=n)})

    m.loglik({"a": 1.0, "s": 1.0}, data(1000))
    count = len(traces)
    for n, a in [(1010, 2.0), (1020, 0.5), (1024, 3.0)]:
        m.loglik({"a": a, "s": 0.7}, data(n))
    assert len(traces) == count  # same length bucket: no new trace
    assert m.structure.cache  # compiled functions kept on the structure


# ---------------------------------------------------------------- errors that name the problem
@pytest.mark.parametrize("equation, match", [
    ("dx = (-a*x*dt + s*dw1", "cannot parse"),
    ("dx = foo(x)*dt + s*dw1", "unknown function 'foo'"),
    ("dx = -a*x + s*dw1", "no '\\*dt' term"),
    ("dx = -a*x*dt + s*dw1 + 1", "without dt or dw"),
    ("x = -a*x*dt", "must be 'd<state>'"),
    ("dx = -a*x*dt*dt", "not linear in dt"),
])
def test_bad_system_equations(equation, match):
    with pytest.raises(ModelError, match=match):
        greyid.Model().add_system(equation)


def test_zero_drift_as_the_error_message_suggests():
    """'0*dt' is what the missing-dt error tells the user to write: it must parse (to drift 0)."""
    m = greyid.Model().add_system("dx = 0*dt + s*dw1")
    m.add_observation("y = x", variance="r").set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    assert m.structure.equations["drift"][0] == 0


def test_structural_errors():
    m = greyid.Model()
    m.add_system("dx = -a*x*dt + s*dw1")
    with pytest.raises(ModelError, match="state 'x' is defined twice"):
        m.add_system("dx = -b*x*dt")
    with pytest.raises(ModelError, match="contains 'dw1'"):
        m.add_observation("y = x + dw1", variance="r")
    with pytest.raises(ModelError, match="no observation equation"):
        m.structure
    m.add_observation("y = x", variance="r")
    with pytest.raises(ModelError, match="no initial state"):
        m.structure
    with pytest.raises(ModelError, match="not a state"):
        m.set_initial_state(mean={"x": 0.0, "z": 1.0}).structure
    with pytest.raises(ModelError, match="must be 1x1"):
        m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0, 0.0], [0.0, 1.0]]).structure
    with pytest.raises(ModelError, match="unknown initial covariance"):
        m.set_initial_state(mean={"x": 0.0}, covariance="huge")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    with pytest.raises(ModelError, match="lower bound 2.0 must be below upper bound 1.0"):
        m.set_parameter("a", init=1.5, lower=2.0, upper=1.0)
    with pytest.raises(ModelError, match="initial value 5.0 is outside its bounds"):
        m.set_parameter("a", init=5.0, lower=0.0, upper=1.0)
    df = pd.DataFrame({"t": [0.0, 1.0, 2.0], "y": [0.0, 1.0, 0.5]})
    with pytest.raises(ModelError, match="parameter 's' is used in the model but given no value"):
        m.loglik({"a": 1.0, "r": 0.1}, df)
    with pytest.raises(ModelError, match="'b' is not a parameter"):
        m.loglik({"a": 1.0, "s": 1.0, "r": 0.1, "b": 2.0}, df)
    with pytest.raises(ModelError, match="variance of observation 'y' is -0.1 at row 0"):
        m.loglik({"a": 1.0, "s": 1.0, "r": -0.1}, df)
    # fit checks only when the criterion is not finite at the start, and then says why
    m.set_parameter("s", init=1.0)
    m.set_parameter("r", init=-0.1)
    longer = pd.DataFrame({"t": np.arange(6.0), "y": [0.0, 1.0, 0.5, 0.2, 0.4, 0.1]})
    with pytest.raises(ModelError, match="variance of observation 'y' is -0.1 at row 0"):
        m.fit(longer, init={"a": 0.5})
    with pytest.raises(greyid.DataError, match="3 observed output value.* for 3 free parameters"):
        m.fit(df, init={"a": 0.5})
    m.set_parameter("r", init=0.1)
    with pytest.raises(ModelError, match="unknown filter method 'pf'"):
        m.loglik({"a": 1.0, "s": 1.0, "r": 0.1}, df, method="pf")
    m.fix_parameter("s", 0.5)
    assert np.isfinite(m.loglik({"a": 1.0, "r": 0.1}, df))
    with pytest.raises(ModelError, match="unknown simulation method 'rk4'"):
        m.simulate({"a": 1.0, "r": 0.1}, [0.0, 1.0], method="rk4")


def test_nonlinear_model_refuses_exact_kalman():
    m = greyid.Model()
    m.add_system("dx = -a*x^3*dt + s*dw1")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    df = pd.DataFrame({"t": [0.0, 1.0], "y": [0.0, 1.0]})
    with pytest.raises(ModelError, match="needs a linear model"):
        m.loglik({"a": 1.0, "s": 1.0, "r": 0.1}, df, method="kalman")


@pytest.fixture(scope="module")
def small():
    m = greyid.Model("small")
    m.add_system("dx = (-a*x + u)*dt + s*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    return m, {"a": 1.0, "s": 1.0, "r": 0.1}


GOOD = pd.DataFrame({"t": [0.0, 1.0, 2.0], "u": [0.0, 1.0, 0.5], "y": [0.0, 1.0, 0.5]})


@pytest.mark.parametrize("data, match", [
    (GOOD.drop(columns="t"), "time column 't' not found"),
    (GOOD.drop(columns="u"), "input column 'u' not found"),
    (GOOD.drop(columns="y"), "output column 'y' not found"),
    (GOOD.assign(u=["a", "b", "c"]), "input column 'u' is not numeric: row 0"),
    (GOOD.assign(t=["a", "b", "c"]), "time column 't' is not numeric: row 0"),
    (GOOD.assign(y=[0.0, "x", 1.0]), "output column 'y' is not numeric: row 1"),
    (GOOD.assign(t=[0.0, 2.0, 1.0]), "not increasing: row 2"),
    (GOOD.assign(t=[0.0, 1.0, 1.0]), "duplicated time 1.0 at row 2"),
    (GOOD.assign(u=[0.0, np.nan, 1.0]), "input 'u' has a missing or infinite value at row 1"),
    (GOOD.assign(u=[0.0, np.inf, 1.0]), "input 'u' has a missing or infinite value at row 1"),
    (GOOD.assign(y=[0.0, np.inf, 1.0]), "output 'y' has an infinite value at row 1"),
    (GOOD.assign(y=np.nan), "output column 'y' has no observation"),
    (GOOD.iloc[:0], "empty"),
    ([], "list of data sets is empty"),
    ("data.csv", "must be a pandas DataFrame"),
])
def test_bad_data(small, data, match):
    m, p = small
    with pytest.raises(DataError, match=match):
        m.loglik(p, data)


def test_bad_hold_and_datetimes(small):
    m, p = small
    with pytest.raises(DataError, match="unknown hold 'spline'"):
        m.loglik(p, GOOD, hold="spline")
    dated = GOOD.assign(t=pd.to_datetime(["2024-01-01 00:00", "2024-01-01 01:00", "2024-01-01 02:00"]))
    assert m.loglik(p, dated, time_unit="h") == pytest.approx(m.loglik(p, GOOD), rel=1e-12)
    assert m.loglik(p, GOOD.assign(t=GOOD.t * 3600.0)) != pytest.approx(m.loglik(p, GOOD))
