"""Experiment design: information of a plan by Monte Carlo against the exact Gaussian information,
optimality criteria against their formulas, local identifiability."""

import numpy as np
import pandas as pd
import pytest

import greyid
from conftest import dense_information, product_model, random_linear_parameters
from greyid import design

NAMES = ["a11", "b11", "g11", "s1", "m1"]


def test_monte_carlo_information_converges_to_the_exact_one(linear_model):
    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    N = 12
    t = np.cumsum(rng.uniform(0.3, 1.0, N))
    U = rng.normal(size=(N, 2))
    plan = pd.DataFrame({"t": t, "u1": U[:, 0], "u2": U[:, 1]})
    info = design.fisher_information(linear_model, params, plan, free=NAMES, method="montecarlo", n_paths=400,
                                     seed=1)
    assert list(info.index) == NAMES and info.attrs["n_paths"] == 400
    exact = dense_information(params, t, U, NAMES)
    error = info.attrs["standard_error"].to_numpy()
    deviation = np.abs(info.to_numpy() - exact)
    assert np.all(deviation < 4.5 * error + 1e-9 * np.abs(exact).max()), deviation / error
    # The estimate is informative: its standard errors are small against the diagonal.
    assert np.all(np.diag(error) < 0.2 * np.diag(exact))


def test_plan_must_not_hold_outputs(linear_model):
    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    plan = pd.DataFrame({"t": [0.0, 1.0], "u1": [0.0, 1.0], "u2": [0.0, 0.0], "y1": [1.0, 2.0]})
    with pytest.raises(greyid.DataError, match="'y1'"):
        design.fisher_information(linear_model, params, plan)
    with pytest.raises(greyid.ModelError, match="unknown method 'dense'"):
        design.fisher_information(linear_model, params, plan.drop(columns="y1"), method="dense")


@pytest.mark.parametrize("hold, foh", [("zoh", 0.0), ("foh", 1.0)])
def test_exact_information_equals_the_dense_gaussian_one(linear_model, hold, foh):
    """The O(N) filter-with-sensitivities information equals ∂μᵀΣ⁻¹∂μ + ½tr(Σ⁻¹∂ΣΣ⁻¹∂Σ) of all stacked
    observations (irregular times, random 3-state model, initial transient included)."""
    for seed in (5, 9):
        rng = np.random.default_rng(seed)
        params, _ = random_linear_parameters(rng)
        N = 12
        t = np.cumsum(rng.uniform(0.3, 1.0, N))
        U = rng.normal(size=(N, 2))
        plan = pd.DataFrame({"t": t, "u1": U[:, 0], "u2": U[:, 1]})
        names = ["a11", "a23", "b11", "c2", "g11", "g21", "h12", "d11", "s1", "s2", "m1", "v11", "v13"]
        info = design.fisher_information(linear_model, params, plan, free=names, hold=hold)
        assert info.attrs["method"] == "exact"
        dense = dense_information(params, t, U, names, foh)
        scale = np.sqrt(np.outer(np.diag(dense), np.diag(dense)))
        np.testing.assert_allclose(info.to_numpy() / scale, dense / scale, atol=1e-6)


def test_exact_information_needs_a_linear_model():
    m = greyid.Model("logistic")
    m.add_system("dx = r*x*(1 - x)*dt + s*dw1")
    m.add_observation("y = x", variance="e")
    m.set_initial_state(mean={"x": "x0"}, covariance=[["p0"]])
    params = dict(r=1.0, s=0.1, e=0.01, x0=0.2, p0=0.01)
    plan = pd.DataFrame({"t": np.arange(5.0)})
    with pytest.raises(greyid.ModelError, match="method='montecarlo'"):
        design.fisher_information(m, params, plan, method="exact")


def test_criteria_equal_their_formulas():
    rng = np.random.default_rng(2)
    B = rng.normal(size=(4, 4))
    M = B @ B.T + 0.5 * np.eye(4)
    names = ["a", "b", "c", "d"]
    info = pd.DataFrame(M, index=names, columns=names)
    theta = {"a": 2.0, "b": -0.5, "c": 4.0, "d": 1.5}
    cov = np.linalg.inv(M)
    assert design.criterion(info, "D") == pytest.approx(-np.log(np.linalg.det(M)))
    assert design.criterion(info, "A") == pytest.approx(np.trace(cov) / 4)
    assert design.criterion(info, "E") == pytest.approx(1 / np.linalg.eigvalsh(M).min())
    t2 = np.array([theta[n] for n in names]) ** 2 / np.diag(cov)
    assert design.criterion(info, "C", params=theta) == pytest.approx(np.mean(1 / t2))
    assert design.criterion(info, "L", k=1) == pytest.approx(design.criterion(info, "A"))
    assert design.criterion(info, "L", k=60) == pytest.approx(design.criterion(info, "E") / 4 ** (1 / 60), rel=1e-3)
    # Ds: the information on (a, b) with c, d as nuisance is the inverse of their covariance block.
    assert design.criterion(info, "Ds", interest=["a", "b"]) == pytest.approx(
        np.log(np.linalg.det(cov[:2, :2])))
    # C is scale-free: expressing a in other units leaves it unchanged.
    S = np.diag([10.0, 1, 1, 1])
    scaled = pd.DataFrame(np.linalg.inv(S) @ M @ np.linalg.inv(S), index=names, columns=names)
    assert design.criterion(scaled, "C", params=dict(theta, a=20.0)) == pytest.approx(
        design.criterion(info, "C", params=theta))
    # Gauss' formula (6.35): the variance of a + 2b is J M⁻¹ Jᵀ.
    J = np.array([1.0, 2.0, 0.0, 0.0])
    assert design.criterion(info, "A", params=theta, derived={"q": "a + 2*b"}) == pytest.approx(J @ cov @ J)
    with pytest.warns(greyid.UndeterminedWarning, match="p1"):
        assert design.criterion(np.diag([1.0, 0.0]), "D") == np.inf
    with pytest.raises(greyid.ModelError, match="unknown criterion"):
        design.criterion(info, "G")


def test_local_identifiability_names_a_product():
    """y depends on a·b only: the information is singular along a ridge that names a and b."""
    m = product_model(dict(a=1.0, b=0.8, s=0.3, r=0.05))
    rng = np.random.default_rng(0)
    plan = pd.DataFrame({"t": np.arange(60) * 0.5, "u": np.repeat(rng.choice([0.0, 1.0], 6), 10)})
    info = design.fisher_information(m, dict(a=1.0, b=0.8, s=0.3, r=0.05), plan, n_paths=20, seed=0)
    flat = design.local_identifiability(info, tolerance=1e-6)
    assert len(flat) == 1 and set(flat["parameters"].iloc[0]) == {"a", "b"}
    assert design.local_identifiability(info.loc[["a", "s", "r"], ["a", "s", "r"]]).empty


def test_cramer_rao_bound_is_the_inverse_information_and_gauss_formula():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(3, 3))
    M = B @ B.T + np.eye(3)
    names = ["a", "b", "c"]
    info = pd.DataFrame(M, index=names, columns=names)
    params = {"a": 2.0, "b": 3.0, "c": 0.5}
    bound = design.cramer_rao_bound(info, params, {"ab": "a*b"})
    cov = np.linalg.inv(M)
    np.testing.assert_allclose(bound[names].to_numpy(), np.diag(cov))
    J = np.array([3.0, 2.0, 0.0])  # ∂(ab)/∂(a, b, c) at the point
    assert bound["ab"] == pytest.approx(J @ cov @ J)
    singular = pd.DataFrame(np.diag([1.0, 0.0]), index=["a", "b"], columns=["a", "b"])
    with pytest.warns(greyid.UndeterminedWarning, match=r"\+1\.000·b"):
        bound = design.cramer_rao_bound(singular)
    assert bound["a"] == 1.0 and np.isinf(bound["b"])  # a is determined, b not at all


def test_compare_inputs_ranks_candidates_by_each_criterion(linear_model):
    """Criteria of each candidate equal the criteria of its own information; ranks order them."""
    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    t = np.arange(10.0)
    plans = {"quiet": pd.DataFrame({"t": t, "u1": 0.01 * rng.normal(size=10), "u2": np.zeros(10)}),
             "loud": pd.DataFrame({"t": t, "u1": 3.0 * rng.normal(size=10), "u2": rng.normal(size=10)})}
    names = ["a11", "b11", "b12", "s1"]
    table = design.compare_inputs(linear_model, params, plans, free=names, interest=["b11", "b12"],
                                  criteria={"D": "D", "Ds": "Ds", "q": {"name": "A", "derived": {"q": "b11*b12"}}})
    for name, plan in plans.items():
        info = design.fisher_information(linear_model, params, plan, free=names)
        assert table.loc[name, "D"] == pytest.approx(design.criterion(info, "D"))
        assert table.loc[name, "Ds"] == pytest.approx(design.criterion(info, "Ds", interest=["b11", "b12"]))
        assert table.loc[name, "q"] == pytest.approx(
            design.criterion(info, "A", params=params, derived={"q": "b11*b12"}))
    # Exciting the inputs tells more about their gains.
    assert table.loc["loud", "Ds rank"] == 1 and table.loc["quiet", "Ds rank"] == 2
    with pytest.raises(greyid.DataError, match="plan 'bad'"):
        design.compare_inputs(linear_model, params, {"bad": plans["loud"].drop(columns="u2")}, free=names)


def test_derived_d_criterion_is_log_det_of_the_derived_covariance():
    M = np.array([[4.0, 1.0], [1.0, 3.0]])
    info = pd.DataFrame(M, index=["a", "b"], columns=["a", "b"])
    params = {"a": 2.0, "b": 1.0}
    J = np.array([[1.0, 1.0], [1.0, 2.0]])  # ∂(a + b, a·b)/∂(a, b) at (2, 1)
    expected = np.log(np.linalg.det(J @ np.linalg.inv(M) @ J.T))
    assert design.criterion(info, "D", params=params, derived={"s": "a + b", "p": "a*b"}) == pytest.approx(expected)


@pytest.fixture(scope="module")
def test_cell():
    from greyid.datasets.thesis import TEST_CELL_PARAMETERS, test_cell_model

    return test_cell_model(), dict(TEST_CELL_PARAMETERS, Ti0=0.0, Tm0=0.0)


def test_frequency_information_is_the_long_experiment_information_per_sample(test_cell):
    """M̄_c + P·M_u(ω) against the exact information of a long sinusoidal experiment divided by its length."""
    model, params = test_cell
    free = ["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"]
    omega, amplitude, N = 0.3, 100.0, 3000
    per_sample = design.frequency_information(model, params, omega, "Qh", 1.0, free=free)
    predicted = per_sample.attrs["input_independent"].to_numpy() + amplitude**2 * per_sample.to_numpy()
    t = np.arange(N, dtype=float)
    plan = pd.DataFrame({"t": t, "Te": 0.0, "Qh": amplitude * np.sqrt(2) * np.cos(omega * t)})
    exact = design.fisher_information(model, params, plan, free=free).to_numpy() / N
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    # The experiment's ends (initial transient, last samples) make an O(1/N) difference.
    np.testing.assert_allclose(exact / scale, predicted / scale, atol=0.02)
    with pytest.raises(greyid.ModelError, match="'Qx' is not an input"):
        design.frequency_information(model, params, omega, "Qx", 1.0)


def test_optimal_multisine_satisfies_the_equivalence_theorem(test_cell):
    """No frequency has a larger directional derivative than the design's support (the design is D-optimal)."""
    model, params = test_cell
    best = design.optimal_multisine(model, params, "Qh", 1.0, free=["Hi", "Hm", "Ci", "Cm"], include_noise=False)
    assert best.weights.sum() == pytest.approx(1.0) and len(best.frequencies) <= 10
    assert best.max_derivative <= best.support_derivative * (1 + 1e-4)
    assert best.support_derivative == pytest.approx(4.0, rel=1e-6)  # = p for D without a fixed part
    # Moving half the power elsewhere is worse.
    single = design.frequency_information(model, params, 0.1, "Qh", 1.0, free=["Hi", "Hm", "Ci", "Cm"])
    mixed = 0.5 * best.information.to_numpy() + 0.5 * single.to_numpy()
    assert -np.linalg.slogdet(mixed)[1] > best.value
    signal = best.signal(np.arange(200.0))
    assert np.mean(signal**2) == pytest.approx(1.0, rel=0.15)


@pytest.fixture(scope="module")
def scalar_example():
    """The scalar model of section 6.5 (6.73)–(6.74): dx = (−a x + b u)dt + √r dw, y = x + e."""
    m = greyid.Model("section_6_5")
    m.add_system("dx = (-a*x + b*u)*dt + sqrt(r)*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r2")
    m.set_initial_state(mean={"x": "0"}, covariance=[["1"]])
    for name in ("a", "b"):
        m.set_parameter(name, init=1.0, lower=0.0, upper=100.0)
    for name in ("r", "r2"):
        m.set_parameter(name, init=1.0, fixed=True)
    return m, dict(a=0.8, b=1.0, r=1.0, r2=0.1)


def _two_sine_values(model, params, points, omegas, weights=np.linspace(0, 1, 41)):
    """Each point's −log det M of every design of one or two sinusoids on a grid (brute force)."""
    M_u, M_c, _ = design.frequency_information_points(model, [dict(params, **p) for p in points], omegas, "u",
                                                      1.0, free=["a", "b"])
    i, j = np.triu_indices(len(omegas))
    M = (M_c[:, None, None] + weights[None, :, None, None, None] * M_u[:, None, i]
         + (1 - weights)[None, :, None, None, None] * M_u[:, None, j])
    return -np.linalg.slogdet(M)[1]  # (points, weights, pairs)


@pytest.mark.slow
def test_bayesian_multisine_beats_every_two_sine_design(scalar_example):
    model, params = scalar_example
    a = np.linspace(0.5, 1.1, 7)
    prior = pd.DataFrame({"a": a, "weight": np.full(7, 1 / 7)})
    best = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"], prior=prior)
    assert best.kind == "Bayesian" and list(best.points.columns) == ["a", "weight", "value"]
    assert best.max_derivative <= best.support_derivative * (1 + 1e-5)
    assert best.value == pytest.approx(best.points.weight @ best.points.value, rel=1e-12)
    brute = _two_sine_values(model, params, [{"a": x} for x in a], np.linspace(0.01, np.pi, 120))
    averaged = brute.mean(axis=0)
    assert best.value <= averaged.min() + 1e-9
    assert best.value >= averaged.min() - 1e-3  # the grid is close to the optimum
    # One point with all the weight is the local design there.
    local = design.optimal_multisine(model, dict(params, a=0.9), "u", 1.0, free=["a", "b"])
    single = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"], prior=pd.DataFrame({"a": [0.9]}))
    assert single.value == pytest.approx(local.value, rel=1e-9)
    np.testing.assert_allclose(single.frequencies, local.frequencies, rtol=1e-6)
    # A Gaussian prior is drawn (seeded).
    drawn = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"],
                                     prior={"mean": {"a": 0.8}, "sd": {"a": 0.1}}, draws=5, seed=3)
    assert len(drawn.points) == 5 and drawn.points["a"].std() > 0


def test_minimax_multisine_is_a_saddle_point(scalar_example):
    model, params = scalar_example
    # Two systems whose worst case changes with the input: a slow one and a fast one with a large gain.
    points = pd.DataFrame({"a": [0.2, 3.0], "b": [0.2, 80.0]})
    best = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"], minimax=points)
    assert best.kind == "minimax" and len(best.frequencies) == 2
    values = best.points["value"].to_numpy()
    assert values.max() == pytest.approx(best.value, rel=1e-12)
    assert abs(values[0] - values[1]) < 1e-6  # an equaliser design
    # The least favourable π certifies it (equivalence theorem of the π-averaged criterion) ...
    pi = best.points["weight"].to_numpy()
    assert np.all(pi > 0.1) and best.max_derivative <= best.support_derivative * (1 + 1e-4)
    # ... and the Bayesian design under π reaches the same value (no duality gap).
    dual = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"], prior=points.assign(weight=pi))
    assert dual.value == pytest.approx(best.value, abs=1e-5)
    brute = _two_sine_values(model, params, points.to_dict("records"),
                             np.concatenate([[0.0], np.linspace(1.8, 2.4, 61)]))
    assert best.value <= brute.max(axis=0).min() + 1e-9
    # A box whose worst corner dominates: the local design at that corner.
    boxed = design.optimal_multisine(model, params, "u", 1.0, free=["a", "b"], minimax={"a": (0.5, 1.1)}, levels=4)
    corner = design.optimal_multisine(model, dict(params, a=1.1), "u", 1.0, free=["a", "b"])
    assert boxed.value == pytest.approx(corner.value, rel=1e-9)
    assert list(boxed.points["weight"]) == [0.0, 0.0, 0.0, 1.0]
    with pytest.raises(greyid.ModelError, match="not both"):
        design.optimal_multisine(model, params, "u", 1.0, prior=points, minimax=points)
    with pytest.raises(greyid.ModelError, match="'c', which is not a parameter"):
        design.optimal_multisine(model, params, "u", 1.0, minimax={"c": (0, 1)})
    with pytest.raises(greyid.ModelError, match="sum to 1"):
        design.optimal_multisine(model, params, "u", 1.0, prior=points.assign(weight=[0.5, 0.6]))


def _example_6_1():
    """The thesis' example 6.1 (6.19) with diagonal process noise and a measurement variance."""
    m = greyid.Model("example61")
    m.add_system("dx1 = (-a*x1 + a*x2)*dt + sqrt(q1)*dw1")
    m.add_system("dx2 = (b*x1 - (b + c)*x2 + d*u)*dt + sqrt(q2)*dw2")
    m.add_inputs("u")
    m.add_observation("y = x2", variance="r")
    m.set_initial_state(mean={"x1": "m1", "x2": "m2"}, covariance=[["v1", 0], [0, "v2"]])
    for name, value in dict(a=1.0, b=0.5, c=0.3, d=2.0, q1=0.1, q2=0.2, r=0.05).items():
        m.set_parameter(name, init=value)
    for name, value in dict(m1=0.0, m2=0.0, v1=1.0, v2=1.0).items():
        m.set_parameter(name, init=value, fixed=True)
    return m


def test_identifiability_reproduces_example_6_1():
    """a, b, c, d globally identifiable from G(p) = d(p + a)/(p² + (a+b+c)p + ac) (6.20); with diagonal
    noise matrices the noise parameters are identifiable too."""
    import sympy as sp

    result = design.identifiability(_example_6_1())
    assert all(result.identifiable.values())
    assert {result.status[n] for n in "abcd"} == {"global"}
    assert {result.status[n] for n in ("q1", "q2", "r")} == {"local"}
    a, b, c, d, p = sp.symbols("a b c d p", real=True)
    expected = d * (p + a) / (p**2 + (a + b + c) * p + a * c)
    G = result.transfer_function.subs({sp.Symbol(n, real=True): s for n, s in zip("abcd", (a, b, c, d))})
    assert sp.simplify(G[0, 0].subs(sp.Symbol("p"), p) - expected) == 0
    assert "global" in result.summary()


def test_identifiability_names_the_identifiable_combinations():
    """y = g·x with x driven by a·b·u: only b·g (and the noise scaled with it) can be determined."""
    m = greyid.Model("scaled")
    m.add_system("dx = (-a*x + a*b*u)*dt + sqrt(q)*dw1")
    m.add_inputs("u")
    m.add_observation("y = g*x", variance="r")
    m.set_initial_state(mean={"x": "0"}, covariance=[["1"]])
    for name, value in dict(a=1.0, b=0.5, g=2.0, q=0.1, r=0.05).items():
        m.set_parameter(name, init=value)
    result = design.identifiability(m)
    assert result.identifiable == {"a": True, "b": False, "q": False, "g": False, "r": True}
    assert "b*g" in result.combinations and "q*g**2" in result.combinations
    direction = result.directions[0]
    assert direction["q"] == pytest.approx(-2 * direction["g"]) and direction["b"] == pytest.approx(-direction["g"])


def test_identifiability_of_a_nonlinear_model_without_a_plan():
    """dx = (−k1·k2·x² + u) dt: only k1·k2 enters.  With no plan, a generic rich plan decides (and the
    result says so): k1 and k2 are not identifiable, k1*k2 is the combination."""
    m = greyid.Model("quadratic")
    m.add_inputs("u")
    m.add_system("dx = (-k1*k2*x^2 + u)*dt + s*dw1")
    m.add_observation("y = x", variance="r^2")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
    for name, value in dict(k1=2.0, k2=0.5, s=0.1, r=0.05).items():
        m.set_parameter(name, init=value, lower=value / 10, upper=value * 10)
    result = design.identifiability(m)
    assert result.status == {"k1": "not identifiable", "k2": "not identifiable", "s": "local", "r": "local"}
    assert result.combinations == ["k1*k2"]
    assert result.directions[0] == pytest.approx({"k1": 1.0, "k2": -1.0})
    assert any("generic plan" in note for note in result.notes)
    # Written with k2 in other units (×1e6), the same verdict and combination.
    m.set_parameter("k2", init=0.5e-6, lower=0.5e-7, upper=0.5e-5)
    m2 = greyid.Model("quadratic_scaled")
    m2.add_inputs("u")
    m2.add_system("dx = (-k1*k2*1000000*x^2 + u)*dt + s*dw1")
    m2.add_observation("y = x", variance="r^2")
    m2.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
    for name, value in dict(k1=2.0, k2=0.5e-6, s=0.1, r=0.05).items():
        m2.set_parameter(name, init=value, lower=value / 10, upper=value * 10)
    again = design.identifiability(m2)
    assert again.status == result.status and again.combinations == ["k1*k2"]


def test_map_average_and_minimax_criteria(linear_model):
    rng = np.random.default_rng(5)
    params, _ = random_linear_parameters(rng)
    t = np.cumsum(rng.uniform(0.3, 1.0, 12))
    plan = pd.DataFrame({"t": t, "u1": rng.normal(size=12), "u2": rng.normal(size=12)})
    names = ["a11", "b11", "s1"]
    model = linear_model
    info = design.fisher_information(model, params, plan, free=names)
    # MAP form (6.53): the prior's precision added to the information.
    prior = {"mean": {"a11": params["a11"], "b11": 0.0}, "sd": {"a11": 0.5, "b11": 2.0}}
    M = info.to_numpy() + np.diag([1 / 0.25, 1 / 4.0, 0.0])
    assert design.criterion(info, "D", prior=prior) == pytest.approx(-np.linalg.slogdet(M)[1])
    # A prior concentrated at a point averages to the criterion at that point.
    tight = {"mean": {"a11": params["a11"]}, "sd": {"a11": 1e-9}}
    average = design.average_criterion(model, plan, "D", tight, draws=3, seed=1, params=params, free=names)
    assert average["value"] == pytest.approx(design.criterion(info, "D"), rel=1e-6)
    spread = design.average_criterion(model, plan, "D", {"mean": {"a11": params["a11"]}, "sd": {"a11": 0.05}},
                                      draws=4, seed=1, params=params, free=names)
    assert spread["standard_error"] > 0 and len(spread["values"]) == 4
    # Minimax (6.39): the worst corner of the box, and no corner is worse.
    box = {"a11": (params["a11"] - 0.05, params["a11"] + 0.05)}
    worst = design.minimax_criterion(model, plan, "D", box, params=params, free=names)
    for a in box["a11"]:
        corner = design.fisher_information(model, dict(params, a11=a), plan, free=names)
        assert design.criterion(corner, "D") <= worst["value"] + 1e-9
    assert worst["at"]["a11"] in box["a11"]
    with pytest.raises(greyid.ModelError, match="'zz'"):
        design.minimax_criterion(model, plan, "D", {"zz": (0, 1)}, params=params, free=names)


def test_sampling_table_aliases_and_joint_design(test_cell):
    """Per sample and per unit time against τ (6.72): a held sinusoid above π/τ is its alias, and at
    every τ the optimal input is at least as good as a fixed one."""
    model, params = test_cell
    free = ["Hi", "Hm", "Ci", "Cm"]
    tau = 4.0
    alias = design.aliased([2.0], tau)[0]
    folded = abs((2.0 + np.pi / tau) % (2 * np.pi / tau) - np.pi / tau)
    assert 0 <= alias <= np.pi / tau and alias == pytest.approx(folded)
    high = design.sampling_table(model, params, "Qh", [tau], frequencies=[2.0], power=100.0, free=free)
    low = design.sampling_table(model, params, "Qh", [tau], frequencies=[alias], power=100.0, free=free)
    assert high["D_per_sample"].iloc[0] == pytest.approx(low["D_per_sample"].iloc[0], rel=1e-9)
    fixed = design.sampling_table(model, params, "Qh", [1.0, 4.0], frequencies=[0.02, 0.6], power=100.0, free=free)
    joint = design.sampling_table(model, params, "Qh", [1.0, 4.0], power=100.0, free=free)
    assert np.all(joint["D_per_sample"].to_numpy() <= fixed["D_per_sample"].to_numpy() + 1e-6)
    np.testing.assert_allclose(fixed["D_per_time"], fixed["D_per_sample"] + 4 * np.log(fixed["interval"]))
