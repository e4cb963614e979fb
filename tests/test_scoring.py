"""Fisher scoring and its hand-over to exact Newton steps, stalls on ridges, step safeguards."""

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.estimate import trust_region as optimize
from greyid.estimate.objective import Derivatives, Problem, combine_scoring, compiled
from greyid.estimate.transforms import Transform
from greyid.filters.api import filter_options, prepare_datasets
from test_estimation import TRUE, ou_model, regression_model


@pytest.fixture(scope="module")
def ou_data():
    m = ou_model()
    rng = np.random.default_rng(11)
    t = np.arange(200) * 0.5
    df = pd.DataFrame({"t": t, "u": np.repeat(rng.choice([0.0, 1.0], 20), 10)})
    df["y"] = m.simulate(TRUE, df, method="exact", seed=2).outputs[0, :, 0]
    df.loc[[5, 60, 61], "y"] = np.nan  # missing values carry no information
    return m, df


def _problem(m, df, prior=None):
    structure = m.structure
    names = list(structure.parameter_names)
    free = tuple(range(len(names)))
    lower = [m.parameters[n].lower for n in names]
    upper = [m.parameters[n].upper for n in names]
    problem = Problem(filter_options(structure, None), None, 1, free, Transform.from_bounds(lower, upper), prior,
                      () if prior is None else tuple(names.index(n) for n in prior.names))
    theta = np.array([TRUE[n] for n in names])
    datasets = [inputs for _, inputs in prepare_datasets(structure, theta, [df], "t", "zoh", None)]
    return problem, theta, datasets


def test_scoring_matrix_is_the_innovations_information_by_differences(ou_data):
    """F = Σ ∂εᵀR⁻¹∂ε + ½ tr(R⁻¹∂R R⁻¹∂R) in z, against central differences of the filter's
    innovations and their covariances (NumPy, no automatic differentiation); g is the gradient."""
    m, df = ou_data
    problem, theta, datasets = _problem(m, df)
    args = problem.arguments(theta)
    z = problem.transform.to_z(theta) + np.array([0.1, -0.2, 0.05, 0.1, 0.3])  # away from the optimum
    programs = compiled(m.structure, problem)
    with Derivatives(programs.scoring, len(z), (*args, datasets), combine=combine_scoring) as scoring:
        f, g, F = scoring(z)
    _, g_exact = programs.value_and_grad(z, *args, datasets)
    np.testing.assert_allclose(g, g_exact, rtol=1e-9)
    assert f == pytest.approx(-m.loglik(dict(zip(m.structure.parameter_names, problem.theta(z, theta))), df))

    observed = df["y"].notna().to_numpy()

    def innovations(zz):
        out = m.filter(dict(zip(m.structure.parameter_names, problem.theta(zz, theta))), df)
        return out.innovations["y"].to_numpy()[observed], out.innovation_cov[observed, 0, 0]

    eps, R = innovations(z)
    h = 1e-5
    d_eps, d_R = [], []
    for i in range(len(z)):
        step = np.zeros(len(z))
        step[i] = h
        (e1, r1), (e0, r0) = innovations(z + step), innovations(z - step)
        d_eps.append((e1 - e0) / (2 * h))
        d_R.append((r1 - r0) / (2 * h))
    d_eps, d_R = np.array(d_eps), np.array(d_R)
    reference = (d_eps / R) @ d_eps.T + 0.5 * (d_R / R) @ (d_R / R).T
    np.testing.assert_allclose(F, reference, rtol=1e-5, atol=1e-8)
    assert np.linalg.eigvalsh(F)[0] > 0


def test_scoring_matrix_adds_the_exact_prior_hessian():
    """With a Gaussian prior (MAP), F gains the prior's Hessian in z: for a linear regression with
    flat bounds the criterion is quadratic and F is its exact Hessian."""
    m = regression_model()
    rng = np.random.default_rng(4)
    u = rng.normal(size=30)
    df = pd.DataFrame({"t": np.arange(30.0), "u": u, "y": 1.0 + 2.0 * u + 0.5 * rng.normal(size=30)})
    prior = {"mean": {"a": 0.0, "b": 1.0}, "sd": {"a": 0.5, "b": 0.4}, "corr": {("a", "b"): 0.3}}
    scored = m.fit(df, criterion="map", prior=prior, optimizer="scoring")
    exact = m.fit(df, criterion="map", prior=prior, optimizer="newton")
    np.testing.assert_allclose(scored.params["estimate"], exact.params["estimate"], rtol=1e-9)
    assert scored.iterations <= 2  # a quadratic criterion: one scoring step lands on the mode


@pytest.mark.parametrize("method", ["kalman", "ekf"])
def test_scoring_and_newton_reach_the_same_optimum(ou_data, method):
    m, df = ou_data
    scored = m.fit(df, method=method, optimizer="scoring")
    exact = m.fit(df, method=method, optimizer="newton")
    assert scored.converged and exact.converged
    assert scored.loglik == pytest.approx(exact.loglik, abs=1e-6)
    np.testing.assert_allclose(scored.params["estimate"], exact.params["estimate"], rtol=1e-4, atol=1e-8)
    np.testing.assert_allclose(scored.bse, exact.bse, rtol=1e-4)  # the exact Hessian at the end


def test_robust_criterion_has_no_scoring_matrix(ou_data):
    """Robust and k-step criteria are not Gaussian likelihoods: they take exact Newton steps only."""
    m, df = ou_data
    problem, theta, datasets = _problem(m, df)
    from dataclasses import replace

    assert compiled(m.structure, replace(problem, robust=("huber", 2.0))).scoring is None
    assert compiled(m.structure, replace(problem, horizon=2)).scoring is None
    fit = m.fit(df, robust=("huber", 2.0), optimizer="scoring")
    assert fit.converged


def test_unknown_optimizer_is_named(ou_data):
    m, df = ou_data
    with pytest.raises(greyid.ModelError, match="unknown optimizer 'bfgs'"):
        m.fit(df, optimizer="bfgs")
    with pytest.raises(greyid.ModelError, match="setting 'optimizer'"):
        m.set_options(optimizer="bfgs")


def _quadratic(center, curvature):
    def evaluate(z):
        d = z - center
        return 0.5 * d @ curvature @ d, curvature @ d, curvature

    return evaluate


def test_scoring_hands_over_and_reports_the_exact_hessian():
    """Scoring with a wrong (but positive definite) matrix still ends at the minimum, and the
    optimum carries the exact Hessian, not the scoring matrix."""
    H = np.array([[4.0, 1.0], [1.0, 3.0]])
    exact = _quadratic(np.array([1.0, -2.0]), H)

    def scoring(z):
        f, g, _ = exact(z)
        return f, g, np.diag([2.0, 6.0])

    best = optimize.newton_trust_region(exact, np.array([8.0, 5.0]), scoring=scoring)
    assert best.converged
    np.testing.assert_allclose(best.z, [1.0, -2.0], atol=1e-5)
    np.testing.assert_allclose(best.hessian, H)


def test_a_crawl_along_a_flat_ridge_stops_as_stalled():
    """f = z₁² − 1e-4·z₂ (z₂ a log coordinate, so steps of at most MAX_STEP): no minimum, each
    step gains a little along a direction of zero curvature. The search stops as stalled (not
    converged) within a few dozen steps, with the well-determined coordinate at its optimum up to
    less than the stall threshold."""
    def evaluate(z):
        return z[0] ** 2 - 1e-4 * z[1], np.array([2 * z[0], -1e-4]), np.diag([2.0, 0.0])

    best = optimize.newton_trust_region(evaluate, np.array([1.0, 0.0]), step_limit=optimize.MAX_STEP)
    assert not best.converged
    assert best.message.startswith("stalled")
    assert best.iterations <= 3 * optimize.STALL_STEPS
    assert best.z[0] ** 2 < optimize.STALL_GAIN  # what is left to gain in z₁ is below the threshold


def test_no_step_along_a_direction_without_slope_or_curvature():
    """The trust-region subproblem with a singular, positive semi-definite matrix and no slope in
    its null direction: the step does not wander along that direction (it used to fill the region)."""
    w, V = np.array([0.0, 2.0]), np.eye(2)
    p = optimize.trust_region_step(w, V, np.array([0.0, 1.0]), radius=100.0)
    np.testing.assert_allclose(p, [0.0, -0.5])
    # Negative curvature is still followed to the edge of the region.
    p = optimize.trust_region_step(np.array([-1.0, 2.0]), V, np.array([0.0, 1.0]), radius=2.0)
    assert np.linalg.norm(p) == pytest.approx(2.0)


def test_one_step_moves_a_coordinate_at_most_max_step():
    """A nearly flat model proposes huge steps; none moves a (log or logistic) coordinate by more
    than the limit estimation gives those coordinates."""
    moves = []

    def evaluate(z):
        moves.append(z.copy())
        return 1e-3 * np.log1p(np.exp(-z[0])) + z[1] ** 2, np.array(
            [-1e-3 / (1 + np.exp(z[0])), 2 * z[1]]), np.diag([1e-12, 2.0])

    optimize.newton_trust_region(evaluate, np.array([0.0, 1.0]), maxiter=20, step_limit=optimize.MAX_STEP)
    steps = np.abs(np.diff(np.array(moves), axis=0))
    assert steps.max() <= 2 * optimize.MAX_STEP + 1e-9  # extrapolation jumps are capped at twice


def test_auto_starts_repeat_the_initial_values_with_newton_steps(ou_data, monkeypatch):
    """Where "auto" scores, the first extra start repeats the initial values with Newton steps only
    (scoring can settle in another basin); both reach this model's single optimum."""
    import greyid.estimate.estimation as estimation

    m, df = ou_data
    monkeypatch.setattr(estimation, "SCORING_WORK", 0)
    fit = m.fit(df, starts=3, seed=2)
    assert [s["start"] for s in fit.starts] == ["initial values", "initial values, Newton steps", "space-filling"]
    assert fit.starts[0]["criterion"] == pytest.approx(fit.starts[1]["criterion"], abs=1e-6)
    assert fit.start_spread().startswith("3, 3 reached the best value")
    forced = m.fit(df, starts=3, seed=2, optimizer="scoring")
    assert [s["start"] for s in forced.starts] == ["initial values", "space-filling", "space-filling"]


@pytest.mark.parametrize("robust", [None, ("huber", 1.5)])
def test_long_series_criterion_summed_in_the_scan_equals_the_stacked_one(ou_data, robust):
    """Past LONG_SERIES rows the criterion is summed in the filter's scan (nothing kept per step);
    value, gradient and Hessian equal those from the per-step terms."""
    from dataclasses import replace

    m, df = ou_data
    problem, theta, datasets = _problem(m, df)
    problem = replace(problem, robust=robust)
    args = problem.arguments(theta)
    z = problem.transform.to_z(theta) + 0.1
    rows = np.eye(len(z))
    stacked = compiled(m.structure, replace(problem, long_series=False)).derivatives(z, rows, *args, datasets)
    summed = compiled(m.structure, replace(problem, long_series=True)).derivatives(z, rows, *args, datasets)
    for a, b in zip(summed, stacked):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("m_out", [1, 2, 3])
def test_whitened_sensitivities_give_the_gaussian_information(m_out):
    """MMᵀ = Σ_k ∂ε_kᵀR_k⁻¹∂ε_k + ½ tr(R_k⁻¹∂_iR_k R_k⁻¹∂_jR_k) (4.32–4.33), against NumPy's
    inverses, for correlated outputs too."""
    from greyid.estimate.objective import whitened_sensitivities

    rng = np.random.default_rng(3)
    steps, directions = 7, 4
    roots = rng.normal(size=(steps, m_out, m_out))
    R = roots @ np.swapaxes(roots, 1, 2) + 0.5 * np.eye(m_out)
    d_eps = rng.normal(size=(directions, steps, m_out))
    d_R = rng.normal(size=(directions, steps, m_out, m_out))
    d_R = d_R + np.swapaxes(d_R, 2, 3)
    M = np.asarray(whitened_sensitivities(R, d_eps, d_R))
    R_inv = np.linalg.inv(R)
    reference = np.zeros((directions, directions))
    for i in range(directions):
        for j in range(directions):
            for k in range(steps):
                reference[i, j] += d_eps[i, k] @ R_inv[k] @ d_eps[j, k]
                reference[i, j] += 0.5 * np.trace(R_inv[k] @ d_R[i, k] @ R_inv[k] @ d_R[j, k])
    np.testing.assert_allclose(M @ M.T, reference, rtol=1e-12, atol=1e-12)
