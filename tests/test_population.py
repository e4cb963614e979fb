"""Population (mixed-effects) fits: the Laplace marginal likelihood against independent references."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from scipy import optimize
from scipy.stats import multivariate_normal

import greyid
from test_crosscheck import shared
from conftest import dense_moments, matrices_from_parameters, random_linear_model_spec, random_linear_parameters
from greyid.population import PopulationWarning, fit_population
from greyid.population.fit import Outer
from greyid.population.members import population_filter, population_programs, prepare_members
from greyid.population import laplace
from greyid.estimate.batch import _member
from greyid.population.spec import make_spec
from greyid.filters.api import filter_options
from greyid.datasets.reference import theophylline_model


# ---------------------------------------------------------------- methods of each member's likelihood
# First in the module and alone: their programs are the largest (nested derivatives of the Laplace method
# over the states and of the ensemble filter), and they hold no fixture, so they run before the module's
# fixtures keep the fitted models' programs, while the other test worker waits (a run's peak memory).
@pytest.mark.slow
@pytest.mark.alone
def test_a_population_by_the_ensemble_kalman_filter_approaches_the_exact_one_and_particles_are_refused():
    """The EnKF's fixed random numbers make each member's likelihood smooth in θ, so the random effects integrate by
    Laplace's method as with the exact filter: on a linear Gaussian population the two fits agree to the ensemble's
    error. The particle filter's estimate is not smooth (resampling): refused, naming what to use."""
    from test_particle import ou_data, ou_gaussian

    m = ou_gaussian()
    data = {f"m{i}": ou_data(60, seed=20 + i) for i in range(5)}
    exact = greyid.fit_population(m, data, random={"mu": "normal"}, method="kalman")
    ensemble = greyid.fit_population(m, data, random={"mu": "normal"}, method="enkf", particles=1000)
    assert ensemble.converged
    assert ensemble.loglik == pytest.approx(exact.loglik, abs=1.0)
    for name in ("a", "mu", "s", "r"):
        estimate, error = exact.params.loc[name, "estimate"], exact.params.loc[name, "std_error"]
        assert abs(ensemble.params.loc[name, "estimate"] - estimate) < 0.5 * error, name
    with pytest.raises(greyid.ModelError, match="particle filter's estimate has none.*'laplace', 'enkf'"):
        greyid.fit_population(m, data, random={"mu": "normal"}, method="particle")


@pytest.mark.slow
@pytest.mark.alone
def test_a_population_by_the_laplace_method_over_the_states_equals_the_kalman_filters():
    """Laplace's method over the states (exact transitions of a linear Gaussian model) gives each member the
    Kalman filter's likelihood exactly, so the nested Laplace over the random effects must reproduce the
    Kalman population fit: log-likelihood to 1e-6, estimates and standard errors to 1e-4 relative."""
    from test_particle import ou_data, ou_gaussian

    m = ou_gaussian()
    m.set_initial_state(mean={"x": 1.0}, covariance=[[4.0]])  # the members start near their own levels
    data = {}
    for i, level in enumerate((-0.8, 0.0, 0.9)):
        frame = ou_data(60, seed=30 + i)
        data[f"m{i}"] = frame.assign(y=frame["y"] + level)
    exact = greyid.fit_population(m, data, random={"mu": "normal"}, method="kalman")
    marginal = greyid.fit_population(m, data, random={"mu": "normal"}, method="laplace")
    assert exact.converged and marginal.converged
    assert (marginal.call["hessian"], exact.call["hessian"]) == ("differences", "differences")
    assert exact.params.loc["omega_mu", "estimate"] > 0.1  # a real random effect, not one at its bound
    assert marginal.loglik == pytest.approx(exact.loglik, abs=1e-6)
    for column in ("estimate", "std_error"):
        np.testing.assert_allclose(marginal.params[column], exact.params[column], rtol=1e-4)
    np.testing.assert_allclose(marginal.random_effects.to_numpy(float), exact.random_effects.to_numpy(float),
                               rtol=1e-4, atol=1e-8)


# ---------------------------------------------------------------- real data: theophylline
# Early too, before the fixtures below keep their models' programs: its own take 0.5-0.7 GB.
def closed_form_laplace(frame, lke, lka, lcl, s2, omega_ka, omega_cl):
    """The Laplace approximation written out with the closed-form concentration (SSfol), modes by SciPy,
    the Hessian by central differences: a reference independent of greyid's filter and derivatives."""
    total = 0.0
    for _, subject in frame.groupby("Subject", sort=False):
        t, dose, y = subject["Time"].to_numpy(), subject["Dose"].to_numpy(), subject["conc"].to_numpy()

        def g(u):
            ke, ka, cl = np.exp(lke), np.exp(lka + omega_ka * u[0]), np.exp(lcl + omega_cl * u[1])
            c = dose * ke * ka / (cl * (ka - ke)) * (np.exp(-ke * t) - np.exp(-ka * t))
            return 0.5 * np.sum(np.log(2 * np.pi * s2) + (y - c) ** 2 / s2) + 0.5 * u @ u

        u = optimize.minimize(g, np.zeros(2), method="BFGS", options=dict(gtol=1e-10)).x
        u = optimize.minimize(g, u, method="Nelder-Mead", options=dict(xatol=1e-12, fatol=1e-14)).x
        h, E = 1e-4, np.eye(2)
        H = np.array([[(g(u + h * (E[i] + E[j])) - g(u + h * (E[i] - E[j])) - g(u - h * (E[i] - E[j]))
                        + g(u - h * (E[i] + E[j]))) / (4 * h * h) for j in range(2)] for i in range(2)])
        total += g(u) + 0.5 * np.log(np.linalg.det(H))
    return -total


def test_theophylline_laplace_equals_the_closed_form_reference():
    """On the classic data set, at R nlme's ML estimates (run side by side, docs/population.md), greyid's
    Laplace marginal equals the same approximation computed from the closed-form solution."""
    frame = pd.read_csv(shared("theophylline/Theoph.csv"))
    model = theophylline_model()
    data = {str(k): g[["Time", "Dose", "conc"]].reset_index(drop=True)
            for k, g in frame.groupby("Subject", sort=False)}
    nlme = dict(lKe=-2.4547026, lKa=0.4657295, lCl=-3.2272222, s2=0.7092536 ** 2, omega_ka=0.643583,
                omega_cl=0.166928)
    spec, raw = make_spec(model, {"lKa": "normal", "lCl": "normal"}, None, None, "diagonal", list(data))
    members = prepare_members(model, list(data), list(data.values()), spec, raw, "Time", "zoh", None, None)
    options = population_filter(model, spec, members, None, "Time", "zoh", None, {})
    outer = Outer(population_programs(model.structure, spec, options), members, spec)
    assert spec.phi_names() == ["lCl", "lKa", "lKe", "s2", "omega_lKa", "omega_lCl"]
    phi = np.array([nlme["lCl"], nlme["lKa"], nlme["lKe"], np.log(nlme["s2"]), np.log(nlme["omega_ka"]),
                    np.log(nlme["omega_cl"])])
    ours = -outer.value(phi)[0]
    reference = closed_form_laplace(frame, nlme["lKe"], nlme["lKa"], nlme["lCl"], nlme["s2"], nlme["omega_ka"],
                                    nlme["omega_cl"])
    outer.close()
    assert ours == pytest.approx(reference, abs=2e-4)


# ---------------------------------------------------------------- exact case: an input gain
FREE = ("b11", "c1", "s1")


@pytest.fixture(scope="module")
def gain_problem():
    """A linear model whose random effect (b11, an input gain) enters the outputs linearly; six members
    with their own inputs and lengths, simulated with b11 drawn around its typical value."""
    rng = np.random.default_rng(12)
    params, _ = random_linear_parameters(rng)
    model = random_linear_model_spec()
    model.name = "gain"
    for name, value in params.items():
        model.set_parameter(name, init=value, fixed=name not in FREE, lower=0 if name == "s1" else None)
    datasets = {}
    for k in range(6):
        N = 25 + 3 * k
        t = np.cumsum(rng.uniform(0.3, 1.2, N))
        U = rng.normal(size=(N, 2))
        member = dict(params, b11=params["b11"] + 0.6 * rng.normal())
        frame = pd.DataFrame({"t": t, "u1": U[:, 0], "u2": U[:, 1]})
        sim = model.simulate(member, frame, seed=k)
        frame["y1"], frame["y2"] = sim.outputs[0, :, 0], sim.outputs[0, :, 1]
        frame.loc[frame.index[::7], "y2"] = np.nan
        datasets[f"unit{k}"] = frame
    return model, params, datasets


def dense_marginal(params, datasets, b11, c1, s1, omega):
    """Σ_i log N(y_i; μ_i(b11), S_i + ω² g_i g_iᵀ), g_i = ∂μ_i/∂b11 (μ is linear in b11: exact)."""
    total = 0.0
    for frame in datasets.values():
        t, U = frame["t"].to_numpy(), frame[["u1", "u2"]].to_numpy()
        Y = frame[["y1", "y2"]].to_numpy().reshape(-1)
        p = dict(params, b11=b11, c1=c1, s1=s1)
        _, _, _, mean, cov = dense_moments(matrices_from_parameters(p), t, U, 0.0)
        shifted = dense_moments(matrices_from_parameters(dict(p, b11=b11 + 1.0)), t, U, 0.0)[3]
        g = shifted - mean
        cov = cov + omega ** 2 * np.outer(g, g)
        seen = ~np.isnan(Y)
        total += multivariate_normal(mean[seen], cov[np.ix_(seen, seen)]).logpdf(Y[seen])
    return total


GAIN_FIT_EVENTS: list = []  # what the gain fit's progress callable received


@pytest.fixture(scope="module")
def gain_fit(gain_problem):
    model, _, datasets = gain_problem
    return fit_population(model, datasets, {"b11": "normal"}, progress=GAIN_FIT_EVENTS.append)


def test_progress_reaches_a_callable_phase_by_phase_and_step_by_step(gain_fit):
    """The phases in their order (the pooled start, the members' programs, the search), then one dict per
    accepted step with its log-likelihood, rising to the fit's."""
    phases = [event["phase"] for event in GAIN_FIT_EVENTS if "phase" in event]
    assert phases == ["start", "programs", "search"]
    assert "first 6 of the 6 members" in GAIN_FIT_EVENTS[0]["message"]
    steps = [event for event in GAIN_FIT_EVENTS if "iteration" in event]
    assert len(steps) >= 2 and set(steps[0]) == {"iteration", "stage", "value", "max_gradient"}
    values = np.array([step["value"] for step in steps])
    assert np.all(np.diff(values) >= -1e-9 * np.abs(values[:-1]))  # accepted steps never lose likelihood
    assert values[-1] == pytest.approx(gain_fit.loglik, rel=1e-8)


@pytest.fixture(scope="module")
def dense_curvature(gain_problem, gain_fit):
    """``(x0, gradient, Hessian)`` of the dense marginal's negative log-likelihood at the fit's
    estimates, by central differences (h = 1e-3; b11, c1 directly, s1 and ω through their logarithms)."""
    _, params, datasets = gain_problem
    est = gain_fit.params["estimate"]
    x0 = np.array([est["b11"], est["c1"], np.log(est["s1"]), np.log(est["omega_b11"])])
    values = {}

    def f(x):
        key = tuple(np.round(x - x0, 12))
        if key not in values:
            values[key] = -dense_marginal(params, datasets, x[0], x[1], np.exp(x[2]), np.exp(x[3]))
        return values[key]

    h = 1e-3
    E = np.eye(4) * h
    H = np.zeros((4, 4))
    for i in range(4):
        for j in range(i, 4):
            H[i, j] = H[j, i] = (f(x0 + E[i] + E[j]) - f(x0 + E[i] - E[j]) - f(x0 - E[i] + E[j])
                                 + f(x0 - E[i] - E[j])) / (4 * h * h)
    gradient = np.array([(f(x0 + 2 * E[i]) - f(x0 - 2 * E[i])) / (4 * h) for i in range(4)])
    return x0, gradient, H


def test_laplace_is_exact_for_a_random_input_gain(gain_problem, gain_fit, dense_curvature):
    """Where η enters the outputs linearly in a linear Gaussian model the Laplace approximation is the
    marginal likelihood: it equals the dense Gaussian with covariance S_i + ω² g_i g_iᵀ, and the
    estimates maximise that dense likelihood (a Newton step on it from them moves them by less than
    2e-4 and gains less than 1e-6)."""
    _, params, datasets = gain_problem
    fit = gain_fit
    assert fit.converged, fit.message
    est = fit.params["estimate"]
    at_estimates = dense_marginal(params, datasets, est["b11"], est["c1"], est["s1"], est["omega_b11"])
    assert fit.loglik == pytest.approx(at_estimates, rel=1e-8)
    _, gradient, H = dense_curvature
    assert np.all(np.linalg.eigvalsh(H) > 0)  # a minimum of the negative log-likelihood
    step = -np.linalg.solve(H, gradient)
    assert np.max(np.abs(step)) < 2e-4
    assert -(gradient @ step + 0.5 * step @ H @ step) < 1e-6


def test_standard_errors_are_the_dense_likelihoods_curvature(gain_fit, dense_curvature):
    """The standard errors come from the exact Hessian of the marginal: the same as the dense
    likelihood's by central differences (b11, c1 directly; s1 and ω through their logarithms)."""
    est = gain_fit.params["estimate"]
    _, _, H = dense_curvature
    se_log = np.sqrt(np.diag(np.linalg.inv(H)))
    se = gain_fit.params["std_error"]
    np.testing.assert_allclose([se["b11"], se["c1"], se["s1"] / est["s1"], se["omega_b11"] / est["omega_b11"]],
                               se_log, rtol=2e-3)


def test_the_hessian_by_differences_of_the_members_slopes_equals_the_exact_one(gain_problem, gain_fit, monkeypatch):
    """By default (``hessian="differences"``: the members' second derivatives by central differences of their
    exact first derivatives) the fit compiles no Hessian program of the filter, says so, and ends at the exact
    Hessian's optimum (``hessian="exact"``) with its standard errors to 1e-8 relative; an unknown setting is
    named."""
    model, _, datasets = gain_problem
    assert gain_fit.call["hessian"] == "differences"
    assert "from the Hessian with the members' second derivatives by differences" in gain_fit.summary()
    exact = fit_population(model, datasets, {"b11": "normal"}, hessian="exact")
    assert exact.call["hessian"] == "exact" and "from the exact Hessian" in exact.summary()
    assert gain_fit.loglik == pytest.approx(exact.loglik, abs=1e-9)
    np.testing.assert_allclose(gain_fit.params["estimate"], exact.params["estimate"], rtol=1e-7)
    np.testing.assert_allclose(gain_fit.params["std_error"], exact.params["std_error"], rtol=1e-8)
    called, ahead = [], laplace.MemberPrograms.compile_ahead

    def recorded(self, phi, u, hessian=False):
        called.append(("ahead", hessian))
        return ahead(self, phi, u, hessian)

    monkeypatch.setattr(laplace.MemberPrograms, "compile_ahead", recorded)
    monkeypatch.setattr(laplace.MemberPrograms, "hessian", lambda *args: called.append("hessian"))
    again = fit_population(model, datasets, {"b11": "normal"})
    assert called == [("ahead", False)] and again.loglik == pytest.approx(gain_fit.loglik, abs=1e-9)
    with pytest.raises(greyid.ModelError, match="hessian is 'numeric'; use 'exact'.*'differences'"):
        fit_population(model, datasets, {"b11": "normal"}, hessian="numeric")
    with pytest.raises(greyid.ModelError, match="does not take 'hesian'.*progress, hessian and"):
        fit_population(model, datasets, {"b11": "normal"}, hesian="exact")


def test_random_effects_are_the_conditional_means(gain_problem, gain_fit):
    """In the exact case the conditional mode of b11 is its conditional mean given the member's data,
    E[b | y] = b + ω² gᵀ(S + ω²ggᵀ)⁻¹(y − μ), with variance ω² − ω⁴ gᵀ(S + ω²ggᵀ)⁻¹g."""
    _, params, datasets = gain_problem
    est = gain_fit.params["estimate"]
    omega = est["omega_b11"]
    for name, frame in datasets.items():
        t, U = frame["t"].to_numpy(), frame[["u1", "u2"]].to_numpy()
        Y = frame[["y1", "y2"]].to_numpy().reshape(-1)
        p = dict(params, b11=est["b11"], c1=est["c1"], s1=est["s1"])
        _, _, _, mean, cov = dense_moments(matrices_from_parameters(p), t, U, 0.0)
        g = dense_moments(matrices_from_parameters(dict(p, b11=est["b11"] + 1.0)), t, U, 0.0)[3] - mean
        seen = ~np.isnan(Y)
        g, total = g[seen], cov[np.ix_(seen, seen)] + omega ** 2 * np.outer(g[seen], g[seen])
        solved = np.linalg.solve(total, np.column_stack([Y[seen] - mean[seen], g]))
        expected = est["b11"] + omega ** 2 * g @ solved[:, 0]
        variance = omega ** 2 - omega ** 4 * g @ solved[:, 1]
        row = gain_fit.random_effects.loc[name]
        assert row["b11"] == pytest.approx(expected, rel=1e-7, abs=1e-9)
        assert row["b11_se"] == pytest.approx(np.sqrt(variance), rel=1e-6)


# The fits on a Dask cluster: early in the module, while its process holds the gain model's programs alone
# (with the cluster's worker process, the run's peak memory), and on one worker process each.
@pytest.mark.slow
@pytest.mark.alone
def test_population_on_a_dask_cluster_equals_the_local_fit(gain_problem, gain_fit, capsys):
    """Chunks of members (two, of three) on a LocalCluster's worker process: the same estimates and loglik, with
    either Hessian."""
    distributed = pytest.importorskip("distributed")
    model, _, datasets = gain_problem
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        fit = fit_population(model, datasets, {"b11": "normal"}, scheduler=client, chunk_size=3, progress=True)
        # (the Hessian by default with the members' second derivatives by differences, their steps coming back
        # with each chunk's Hessian; then the exact one)
        exact = fit_population(model, datasets, {"b11": "normal"}, scheduler=client, chunk_size=3, hessian="exact")
    assert fit.loglik == pytest.approx(gain_fit.loglik, rel=1e-10)
    np.testing.assert_allclose(fit.params["estimate"], gain_fit.params["estimate"], rtol=1e-7)
    np.testing.assert_allclose(fit.params["std_error"], gain_fit.params["std_error"], rtol=1e-6)
    assert "population step 1: log-likelihood" in capsys.readouterr().err
    assert (fit.call["hessian"], exact.call["hessian"]) == ("differences", "exact")
    np.testing.assert_allclose(exact.params["estimate"], gain_fit.params["estimate"], rtol=1e-7)
    np.testing.assert_allclose(exact.params["std_error"], gain_fit.params["std_error"], rtol=1e-6)


@pytest.mark.slow
@pytest.mark.alone
def test_a_lost_worker_loses_no_chunk(gain_problem):
    """The worker killed after the chunks were scattered (its nanny starts a fresh one): its chunks are sent
    again and the evaluation equals the in-process one."""
    import os
    import signal

    distributed = pytest.importorskip("distributed")
    from greyid.filters.api import filter_options
    from greyid.population.distributed import ClusterEvaluator, evaluate

    model, _, datasets = gain_problem
    names = list(datasets)
    spec, raw = make_spec(model, {"b11": "normal"}, None, None, "diagonal", names)
    members = prepare_members(model, names, list(datasets.values()), spec, raw, "t", "zoh", None, None)
    options = filter_options(model.structure, None)
    local = laplace.MemberPrograms(laplace.build(model.structure, spec, options), members.x, spec.base(),
                                   members.data, 1)
    phi, u0 = spec.phi0(), np.zeros((len(names), 1))
    expected = evaluate(local, phi, u0, "gradient")
    local.close()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        evaluator = ClusterEvaluator(client, model, spec, options, members, 3, 60.0)
        holders = client.who_has([future for _, future in evaluator.chunks])
        victim = next(iter(holders.values()))[0]
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)  # the nanny starts a fresh worker, without the chunk's data
        _, values, gradients, _, path = evaluator(phi, u0, "gradient")
    np.testing.assert_allclose(values, laplace.laplace_values(expected[0]), rtol=1e-12)
    np.testing.assert_allclose(gradients, expected[2], rtol=1e-10)
    for chunked, alone in zip(path, expected[4]):  # the Hessian's T and λ, put together in the members' order
        np.testing.assert_allclose(chunked, alone, rtol=1e-10, atol=1e-14)


# Before the general case's fixtures below add their models' programs: its own fit's take about 1 GB.
def test_a_member_that_cannot_be_fitted_is_left_out_with_a_warning(gain_problem):
    model, _, datasets = gain_problem
    broken = dict(datasets)
    broken["empty"] = datasets["unit0"].assign(y1=np.nan, y2=np.nan)
    with pytest.warns(PopulationWarning, match="data set 'empty' is left out"):
        fit = fit_population(model, broken, {"b11": "normal"})
    assert "empty" in fit.left_out and "empty" not in fit.random_effects.index
    assert "left out: data set 'empty'" in fit.summary()


# ---------------------------------------------------------------- derivatives of the general case
@pytest.fixture(scope="module")
def nonlinear_problem():
    """dx = (−a·x + b·u)dt + s·dω with a lognormal, b normal, correlated, a covariate effect on b:
    the random effects enter the likelihood nonlinearly (a through the dynamics)."""
    m = greyid.Model("decay")
    m.add_system("dx = (-a*x + b*u)*dt + s*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[0.1]])
    m.set_parameter("a", init=0.5, lower=0)
    m.set_parameter("b", init=1.0)
    m.set_parameter("s", init=0.3, lower=0)
    m.set_parameter("r", init=0.05, lower=0)
    rng = np.random.default_rng(3)
    t = np.arange(40.0)
    data, area = {}, []
    for i in range(7):
        u = np.sign(np.sin(t / 4 + i))
        area.append(100 + 30 * i)
        member = dict(a=0.5 * np.exp(0.3 * rng.normal()), b=1.0 + 0.004 * (area[-1] - 190) + 0.3 * rng.normal(),
                      s=0.3, r=0.05)
        sim = m.simulate(member, pd.DataFrame({"t": t, "u": u}), seed=i)
        data[f"h{i}"] = pd.DataFrame({"t": t, "u": u, "y": sim.outputs[0, :, 0]})
    covariates = pd.DataFrame({"area": area}, index=list(data))
    spec, raw = make_spec(m, {"a": "lognormal", "b": "normal"}, covariates, {"b": ["area"]}, "full", list(data))
    members = prepare_members(m, list(data), list(data.values()), spec, raw, "t", "zoh", None, None)
    programs = laplace.build(m.structure, spec, filter_options(m.structure, None))
    return m, data, covariates, spec, Outer(programs, members, spec)


@pytest.mark.slow
def test_outer_gradient_and_hessian_against_central_differences(nonlinear_problem):
    """The envelope-theorem gradient (with the mode's implicit derivative in the log-determinant) and
    the exact Hessian equal central differences of the Laplace value, its modes solved anew."""
    *_, spec, outer = nonlinear_problem
    phi = spec.phi0() + np.array([0.05, -0.1, 0.02, -0.03, 0.2, 0.1, -0.2, 0.3])
    f, g, H = outer.exact(phi)
    assert np.isfinite(f) and f == pytest.approx(outer.value(phi)[0], rel=1e-10)
    h = 1e-5
    numeric = np.array([(outer.value(phi + h * e)[0] - outer.value(phi - h * e)[0]) / (2 * h)
                        for e in np.eye(len(phi))])
    np.testing.assert_allclose(g, numeric, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    numeric_H = np.array([(outer.exact(phi + 1e-4 * e)[1] - outer.exact(phi - 1e-4 * e)[1]) / 2e-4
                          for e in np.eye(len(phi))])
    np.testing.assert_allclose(H, numeric_H, rtol=1e-4, atol=1e-5 * np.abs(H).max())
    # Where the search's last gradient was taken at φ, its modes' tangents and multipliers give the Hessian:
    # the same one as the Hessian computed with everything anew.
    outer.value_and_gradient(phi)
    assert outer.last_gradient[4] is not None
    f_kept, g_kept, H_kept = outer.exact(phi)
    assert f_kept == pytest.approx(f, rel=1e-10)  # the modes solved again from another start: to their tolerance
    np.testing.assert_allclose(g_kept, g, rtol=1e-7, atol=1e-9 * np.abs(g).max())
    np.testing.assert_allclose(H_kept, H, rtol=1e-7, atol=1e-9 * np.abs(H).max())


def test_the_hessian_with_second_derivatives_by_differences_equals_the_exact_one(nonlinear_problem):
    """Off the optimum, with lognormal and correlated random effects and a covariate effect: the Hessian with
    each member's second derivatives by central differences of its exact slopes equals the exact one to 1e-8
    (its steps found at the first call, then kept), and the value and gradient are the exact ones."""
    *_, spec, outer = nonlinear_problem
    differenced = Outer(outer.programs.programs, outer.members, spec, hessian="differences")
    for shift in (0.0, 1e-3):
        phi = spec.phi0() + np.array([0.05, -0.1, 0.02, -0.03, 0.2, 0.1, -0.2, 0.3]) + shift
        f, g, H = outer.exact(phi)
        f_d, g_d, H_d = differenced.exact(phi)
        assert f_d == pytest.approx(f, rel=1e-12) and np.all(np.isfinite(differenced.steps))
        np.testing.assert_allclose(g_d, g, rtol=1e-10, atol=1e-12 * np.abs(g).max())
        np.testing.assert_allclose(H_d, H, rtol=1e-7, atol=1e-8 * np.abs(H).max())
        np.testing.assert_allclose(np.linalg.inv(H_d), np.linalg.inv(H), rtol=1e-7,
                                   atol=1e-8 * np.abs(np.linalg.inv(H)).max())


def _derivatives_through_z(m, spec):
    """``(phi, u, x, base, data) -> (ℓ_i', T_i, λ_i)`` of one member by forward derivatives of g_i(u, φ) itself,
    through θ_i(φ, u), in z = (u, φ) (laplace's module doc, first part): the reference for the gradient's
    program, which takes the filter's derivatives in the member's parameter scales ψ instead."""
    import jax

    from greyid.estimate.criteria import log_criterion
    from greyid.filters.api import compiled_filter

    run = compiled_filter(m.structure, filter_options(m.structure, None), keep_outputs=False)
    q = spec.n_random

    def derivatives(phi, u_hat, x, base, data):
        def g(u, ph):
            return -log_criterion(run(spec.theta(ph, u, x, base), data)[0]) + 0.5 * jnp.sum(u ** 2)

        def parts(z):
            u, ph = z[:q], z[q:]
            H = jax.jacfwd(jax.jacfwd(g))(u, ph)
            return g(u, ph) + 0.5 * jnp.linalg.slogdet(H)[1], jax.jacfwd(g)(u, ph)

        Fz, Gz = jax.jacfwd(parts)(jnp.concatenate([u_hat, phi]))
        H = Gz[:, :q]
        T = jnp.concatenate([-jnp.linalg.solve(H, Gz[:, q:]), jnp.eye(len(phi))])
        return Fz @ T, T, -jnp.linalg.solve(H, Fz[:q])

    return jax.jit(derivatives)


def test_outer_gradient_through_the_parameter_scales_equals_that_through_z(nonlinear_problem):
    """The gradient program's ℓ_i', T_i and λ_i (the filter differentiated in the member's free parameters'
    scales ψ, F and G from P(ψ) = (K, ∇_R K, ∇²_R K) and its first derivatives) equal forward derivatives of
    g_i itself in (u, φ), for a lognormal and a normal random effect, a covariate effect and a full Ω.  (The
    Hessian's program, which adds P's second derivatives, is checked against central differences of this
    gradient in test_outer_gradient_and_hessian_against_central_differences.)"""
    m, _, _, spec, outer = nonlinear_problem
    phi = spec.phi0() + np.array([0.05, -0.1, 0.02, -0.03, 0.2, 0.1, -0.2, 0.3])
    u = outer.modes(phi).u
    _, gradients, tangents, multipliers = outer.programs.gradient(phi, u)
    members, reference = outer.members, _derivatives_through_z(m, spec)
    for i in (0, 3, 6):
        expected = reference(jnp.asarray(phi), jnp.asarray(u[i]), jnp.asarray(members.x[i]),
                             tuple(jnp.asarray(b) for b in spec.base()), _member(members.data, i))
        for got, want in zip((gradients[i], tangents[i], multipliers[i]), map(np.asarray, expected)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())


def test_nested_layouts_share_the_filters_programs(nonlinear_problem):
    """A diagonal Ω without the covariate effect, nested in the fixture's full Ω with one, has the same programs
    of the filter (the same keys; the closed forms' differ): compiled for it, they serve the full layout in
    the same process, whose gradient still equals forward derivatives of g_i through z."""
    m, data, _, spec, outer = nonlinear_problem
    options = filter_options(m.structure, None)
    diagonal, raw = make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "diagonal", list(data))
    nested, full = laplace.build(m.structure, diagonal, options), laplace.build(m.structure, spec, options)
    for name in [f for f in laplace.LaplacePrograms._fields if f != "shaped"]:
        shared = name in ("likelihood", "on_random", "slopes", "curvatures")
        assert (getattr(nested, name).key == getattr(full, name).key) == shared, name
    nested_members = prepare_members(m, list(data), list(data.values()), diagonal, raw, "t", "zoh", None, None)
    first = laplace.MemberPrograms(nested, nested_members.x, diagonal.base(), nested_members.data, 1)
    second = laplace.MemberPrograms(full, outer.members.x, spec.base(), outer.members.data, 1)
    try:
        first.gradient(diagonal.phi0(), np.zeros((len(data), 2)))
        phi = spec.phi0() + np.array([0.05, -0.1, 0.02, -0.03, 0.2, 0.1, -0.2, 0.3])
        u = outer.modes(phi).u
        _, gradients, tangents, multipliers = second.gradient(phi, u)
    finally:
        first.close()
        second.close()
    assert list(full.slopes.executables.values()) == list(nested.slopes.executables.values())  # the same one
    # What the Hessian's closed form is compiled for ahead of the filter's program: shaped as that program gives.
    (slopes,) = full.slopes.executables.values()
    _, like = full.shaped(len(data), 1)
    shapes = [[a.shape for a in jax.tree_util.tree_leaves(tree)] for tree in (like, slopes.out_info)]
    assert shapes[0] == shapes[1]
    reference = _derivatives_through_z(m, spec)
    for i in (0, 6):
        expected = reference(jnp.asarray(phi), jnp.asarray(u[i]), jnp.asarray(outer.members.x[i]),
                             tuple(jnp.asarray(b) for b in spec.base()), _member(outer.members.data, i))
        for got, want in zip((gradients[i], tangents[i], multipliers[i]), map(np.asarray, expected)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())


def test_the_outer_gradient_s_programs_compile_ahead_and_give_the_same_gradients(nonlinear_problem):
    """``compile_ahead`` compiles the filter's programs of the outer gradient (and of the exact Hessian) in the
    background: they are there before the first gradient, which compiles none of them again and equals the
    gradient of members' programs that compiled as they went."""
    m, data, _, spec, outer = nonlinear_problem
    programs = laplace.build(m.structure, spec, filter_options(m.structure, None))
    members, u = outer.members, np.zeros((len(data), spec.n_random))
    phi = spec.phi0() + 0.05
    ahead = laplace.MemberPrograms(programs, members.x, spec.base(), members.data, 1)
    plain = laplace.MemberPrograms(programs, members.x, spec.base(), members.data, 1)
    try:
        ahead.compile_ahead(spec.phi0(), u, hessian=True)
        assert set(ahead._pending) == {"gradient", "hessian"}
        for pending in list(ahead._pending.values()):
            pending.result()
        assert len(programs.slopes.executables) == 1 and len(programs.curvatures.executables) == 1
        slopes = dict(programs.slopes.executables)
        first = ahead.gradient(phi, u)
        assert "gradient" not in ahead._pending and programs.slopes.executables == slopes
        for got, want in zip(first, plain.gradient(phi, u)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    finally:
        ahead.close()
        plain.close()


def test_parameter_map_by_hand(nonlinear_problem):
    """θ_i from φ, u and the standardised covariate, written out: a lognormal, b normal + β·area, Ω = LLᵀ."""
    *_, spec, _ = nonlinear_problem
    assert spec.phi_names() == ["a", "b", "s", "r", "beta_b_area", "omega_a", "omega_b", "corr_b_a"]
    phi = np.array([np.log(0.4), 1.2, np.log(0.3), np.log(0.05), 0.7, np.log(0.2), np.log(0.5), 0.6])
    u, x = np.array([0.3, -1.1]), np.array([0.8])
    theta = np.asarray(spec.theta(jnp.asarray(phi), jnp.asarray(u), jnp.asarray(x),
                                  tuple(jnp.asarray(b) for b in spec.base())))
    row = np.array([0.6, 1.0]) / np.hypot(0.6, 1.0)
    L = np.array([[0.2, 0.0], [0.5 * row[0], 0.5 * row[1]]])
    eta = L @ u
    names = list(spec.names)
    assert theta[names.index("a")] == pytest.approx(0.4 * np.exp(eta[0]))
    assert theta[names.index("b")] == pytest.approx(1.2 + 0.7 * 0.8 + eta[1])
    assert theta[names.index("r")] == pytest.approx(0.05) and theta[names.index("s")] == pytest.approx(0.3)


@pytest.fixture(scope="module")
def correlated_fit(nonlinear_problem):
    m, data, covariates, *_ = nonlinear_problem
    return fit_population(m, data, {"a": "lognormal", "b": "normal"}, covariates=covariates,
                          effects={"b": "area"}, omega="full")


def test_population_fit_recovers_a_correlated_nonlinear_population(nonlinear_problem, correlated_fit):
    """The fit converges; the covariate effect is reported per unit of the covariate; Ω is positive definite."""
    _, data, *_ = nonlinear_problem
    fit = correlated_fit
    assert fit.converged, fit.message
    beta = fit.params.loc["beta_b_area"]
    assert beta["ci_lower"] < 0.004 < beta["ci_upper"]
    assert np.linalg.eigvalsh(fit.omega.to_numpy()).min() > 0
    assert -1 < fit.params.loc["corr_b_a", "estimate"] < 1
    assert list(fit.random_effects.index) == list(data)
    assert fit.aic == pytest.approx(-2 * fit.loglik + 2 * 8)
    assert fit.bic == pytest.approx(-2 * fit.loglik + 8 * np.log(7 * 40))


def test_the_results_tables_come_from_one_program(correlated_fit):
    """A full Ω and a covariate effect: each member's θ_i is spec.theta's, evaluated in NumPy; the estimates are
    φ mapped back by hand (exp of the log-scale typical value and of log ω, the covariate effect per unit of
    its covariate, the correlation of Ω = L Lᵀ); the standard errors go through ∂ρ/∂φ, checked by central
    differences.  Building the tables lowers one program (then loaded or compiled): op by op, as they were
    computed, each small operation was a program of its own, lowered and compiled (or loaded) in every
    process."""
    from greyid.population.result import PopulationResult, _reporting
    from greyid.runtime.jit import release_compiled

    fit, spec = correlated_fit, correlated_fit.spec
    members, modes = fit._members, fit._modes
    base = spec.base()
    for k, name in enumerate(fit.names):
        theta = spec.theta(fit.phi, modes.u[k], members.x[k], base, xp=np)
        np.testing.assert_allclose(fit.individual.loc[name].to_numpy(), theta, rtol=1e-13, atol=0)

    names = spec.phi_names()
    phi = dict(zip(names, fit.phi))
    L = spec.cholesky(fit.phi, xp=np)
    omega = L @ L.T
    sd = np.asarray(spec.covariate_sd, dtype=float)[spec.covariates.index("area")]
    by_hand = {"a": np.exp(phi["a"]), "b": phi["b"], "beta_b_area": phi["beta_b_area"] / sd,
               "omega_a": np.exp(phi["omega_a"]), "omega_b": np.exp(phi["omega_b"]),
               "corr_b_a": omega[1, 0] / np.sqrt(omega[0, 0] * omega[1, 1])}
    for name, value in by_hand.items():
        assert fit.params.loc[name, "estimate"] == pytest.approx(value, rel=1e-13), name

    rho_of, value_of = _reporting(spec)
    sd_effects = np.array([sd])

    def rho(v):
        return np.asarray(rho_of(jnp.asarray(v), sd_effects))

    step = 1e-6
    J = np.stack([(rho(fit.phi + step * e) - rho(fit.phi - step * e)) / (2 * step) for e in np.eye(len(fit.phi))],
                 axis=1)
    r = rho(fit.phi)
    h = 1e-6 * np.maximum(np.abs(r), 1.0)
    slope = (value_of(r + h) - value_of(r - h)) / (2 * h)
    se = np.abs(slope) * np.sqrt(np.diag(J @ fit.cov_phi @ J.T))
    np.testing.assert_allclose(fit.params["std_error"].to_numpy(), se, rtol=1e-7)

    release_compiled()  # what a later process starts from: the programs in the cache folder, none in memory
    lowered = []  # every program JAX builds, loaded or compiled after it (an operation run alone is one too)

    def listener(event, duration, **_):
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            lowered.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        again = PopulationResult(fit.model, spec, members, fit.phi, fit.hessian, modes, fit.call, fit.converged,
                                 fit.message, fit.iterations)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert len(lowered) == 1
    pd.testing.assert_frame_equal(again.params, fit.params)
    pd.testing.assert_frame_equal(again.individual, fit.individual)


@pytest.mark.slow
def test_likelihood_ratio_with_a_variance_on_the_boundary(nonlinear_problem, correlated_fit):
    """Adding b's random effect (its variance and correlation) is tested against ½χ²₁ + ½χ²₂."""
    from greyid.population import likelihood_ratio

    m, data, covariates, *_ = nonlinear_problem
    restricted = fit_population(m, data, {"a": "lognormal"}, covariates=covariates, effects={"b": "area"})
    test = likelihood_ratio(restricted, correlated_fit)
    assert test.statistic == pytest.approx(2 * (correlated_fit.loglik - restricted.loglik))
    assert test.df == 2 and test.variances == 1
    from scipy.stats import chi2

    assert test.p_value == pytest.approx(0.5 * chi2.sf(test.statistic, 1) + 0.5 * chi2.sf(test.statistic, 2))
    assert "boundary" in repr(test) and "Self & Liang" in repr(test)
    with pytest.raises(ValueError, match="must hold every population parameter"):
        likelihood_ratio(correlated_fit, restricted)


def test_member_is_a_fit_at_the_individual_parameters(gain_problem, gain_fit):
    model, _, datasets = gain_problem
    member = gain_fit.member("unit3")
    values = gain_fit.individual.loc["unit3"].to_dict()
    assert member.values["b11"] == pytest.approx(gain_fit.random_effects.loc["unit3", "b11"])
    assert member.loglik == pytest.approx(model.loglik(values, datasets["unit3"]), rel=1e-12)
    assert member.params.loc["b11", "std_error"] == gain_fit.random_effects.loc["unit3", "b11_se"]
    assert member.params.loc["c1", "std_error"] == gain_fit.params.loc["c1", "std_error"]
    assert len(member.residuals) == len(datasets["unit3"])
    assert member.validate() is not None
    with pytest.raises(KeyError, match="'nobody' is not a member"):
        gain_fit.member("nobody")


# ---------------------------------------------------------------- bad input
def test_bad_population_input_is_named(gain_problem):
    model, _, datasets = gain_problem
    with pytest.raises(greyid.ModelError, match="'a11', which is fixed"):
        fit_population(model, datasets, {"a11": "normal"})
    with pytest.raises(greyid.ModelError, match="'zz', which is not a parameter"):
        fit_population(model, datasets, {"zz": "normal"})
    with pytest.raises(greyid.ModelError, match="'gamma'"):
        fit_population(model, datasets, {"b11": "gamma"})
    with pytest.raises(greyid.ModelError, match="lognormal.*may be negative|initial value"):
        fit_population(model, datasets, {"c1": "lognormal"})
    covariates = pd.DataFrame({"area": np.arange(6.0)}, index=list(datasets))
    with pytest.raises(greyid.DataError, match="no row for data set 'unit5'"):
        fit_population(model, datasets, {"b11": "normal"}, covariates=covariates.iloc[:5], effects={"b11": "area"})
    with pytest.raises(greyid.DataError, match="'floor' .* not a column"):
        fit_population(model, datasets, {"b11": "normal"}, covariates=covariates, effects={"b11": ["floor"]})
    gappy = covariates.copy()
    gappy.loc["unit2", "area"] = np.nan
    with pytest.raises(greyid.DataError, match="'area' is missing or not a number for data set 'unit2'"):
        fit_population(model, datasets, {"b11": "normal"}, covariates=gappy, effects={"b11": "area"})
    with pytest.raises(greyid.DataError, match="too few"):
        fit_population(model, {"one": datasets["unit0"]}, {"b11": "normal"})
    with pytest.raises(greyid.ModelError, match="omega is 'block'"):
        fit_population(model, datasets, {"b11": "normal"}, omega="block")
    with pytest.raises(greyid.ModelError, match="omega_init of 'b11' is -1"):
        fit_population(model, datasets, {"b11": "normal"}, omega_init={"b11": -1.0})


def test_a_full_omega_start_is_checked_and_used(nonlinear_problem):
    """omega_init as Ω itself: not positive definite, not symmetric, mislabelled or correlated under a
    diagonal Ω are named; a valid one is φ's start (Ω from φ0 equals it)."""
    m, data, *_ = nonlinear_problem
    names = list(data)
    labels = ["a", "b"]
    given = pd.DataFrame([[0.09, 0.06], [0.06, 0.25]], index=labels, columns=labels)
    spec, _ = make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "full", names, omega_init=given)
    L = np.asarray(spec.cholesky(spec.phi0()))
    np.testing.assert_allclose(L @ L.T, given.to_numpy(), rtol=1e-12)
    bad = pd.DataFrame([[0.09, 0.2], [0.2, 0.25]], index=labels, columns=labels)
    with pytest.raises(greyid.ModelError, match="not positive definite"):
        make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "full", names, omega_init=bad)
    with pytest.raises(greyid.ModelError, match="not a symmetric"):
        make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "full", names,
                  omega_init=pd.DataFrame([[0.09, 0.0], [0.06, 0.25]], index=labels, columns=labels))
    with pytest.raises(greyid.ModelError, match="rows and columns named"):
        make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "full", names,
                  omega_init=given.rename(index={"a": "x"}))
    with pytest.raises(greyid.ModelError, match="use omega='full'"):
        make_spec(m, {"a": "lognormal", "b": "normal"}, None, None, "diagonal", names, omega_init=given)


def test_saved_fit_loads_with_the_same_tables(gain_problem, gain_fit, tmp_path):
    """save/load keeps the estimates, standard errors, random effects and the summary; member() needs
    the data back where they were DataFrames, and says so; a damaged file is named."""
    from greyid.population import load_population

    model, _, datasets = gain_problem
    path = tmp_path / "population.json"
    gain_fit.save(path)
    loaded = load_population(path)
    pd.testing.assert_frame_equal(loaded.params, gain_fit.params)
    pd.testing.assert_frame_equal(loaded.random_effects, gain_fit.random_effects)
    assert loaded.loglik == gain_fit.loglik and loaded.summary() == gain_fit.summary()
    with pytest.raises(KeyError, match="not in the saved fit"):
        loaded.member("unit2")
    again = load_population(path, data=datasets)
    assert again.member("unit2").loglik == pytest.approx(gain_fit.member("unit2").loglik, rel=1e-12)
    path.write_text('{"format": "greyid population fit", "version": 1}')
    with pytest.raises(greyid.DataError, match="damaged population fit file"):
        load_population(path)
    with pytest.raises(greyid.DataError, match="not found"):
        load_population(tmp_path / "missing.json")


@pytest.mark.slow
def test_command_line_population(nonlinear_problem, tmp_path, capsys):
    """`greyid population MODEL FOLDER --random ... --covariates ... --effect ...`: the summary, the files
    of --out; bad input exits 2 with the problem named."""
    from greyid.cli import main

    m, data, covariates, *_ = nonlinear_problem
    model_file = tmp_path / "decay.toml"
    model_file.write_text(m.to_toml())
    folder = tmp_path / "houses"
    folder.mkdir()
    for name, frame in data.items():
        frame.to_csv(folder / f"{name}.csv", index=False)
    table = tmp_path / "covariates.csv"
    covariates.rename_axis("house").to_csv(table)
    out = tmp_path / "out"
    code = main(["population", str(model_file), str(folder), "--random", "a:lognormal", "--covariates", str(table),
                 "--effect", "b:area", "--out", str(out), "--report"])
    printed, told = capsys.readouterr()
    assert code == 0 and "omega_a" in printed and "beta_b_area" in printed
    # What the fit is doing while it compiles and searches, on standard error (-q: nothing).
    for line in ("population: the start", "population: the members' programs", "population step 1: log-likelihood",
                 "fitted in"):
        assert line in told, line
    assert {p.name for p in out.iterdir()} >= {"population.json", "summary.txt", "parameters.csv",
                                                "random_effects.csv", "report.html"}
    assert '<section id="members">' in (out / "report.html").read_text(encoding="utf-8")
    from greyid.population import load_population

    loaded = load_population(out / "population.json")
    assert loaded.member("h3").n_obs == 40  # the members' CSV paths are kept
    assert main(["population", str(model_file), str(folder), "--random", "a:gamma", "-q"]) == 2
    assert "'gamma'" in capsys.readouterr().err
    assert main(["population", str(model_file), str(tmp_path / "none"), "--random", "a:lognormal", "-q"]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["population", str(model_file), str(folder), "--random", "a:lognormal", "--effect", "b:area",
                 "-q"]) == 2
    assert "--effect needs --covariates" in capsys.readouterr().err
    assert main(["population", str(model_file), str(folder), "--random", "a:lognormal", "--report", "-q"]) == 2
    assert "--report needs --out" in capsys.readouterr().err
    assert main(["population", str(model_file), str(folder), "--random", "a:lognormal", "--hessian", "numeric",
                 "-q"]) == 2
    assert "hessian is 'numeric'" in capsys.readouterr().err
    # The same settings from the model file's [population] table (covariates relative to the file).
    m.set_population(random={"a": "lognormal"}, effects={"b": ["area"]}, covariates="covariates.csv")
    with_table = tmp_path / "decay_population.toml"
    with_table.write_text(m.to_toml())
    assert "[population]" in with_table.read_text()
    # ... with the exact Hessian: the same optimum, the same standard errors.
    code = main(["population", str(with_table), str(folder), "--out", str(tmp_path / "again"), "--hessian",
                 "exact", "-q"])
    assert code == 0
    assert "from the exact Hessian" in (tmp_path / "again" / "summary.txt").read_text()
    assert "second derivatives by differences" in (out / "summary.txt").read_text()
    first = pd.read_csv(out / "parameters.csv", index_col=0)
    again = pd.read_csv(tmp_path / "again" / "parameters.csv", index_col=0)
    np.testing.assert_allclose(again["estimate"], first["estimate"], rtol=1e-7)
    np.testing.assert_allclose(again["std_error"], first["std_error"], rtol=1e-7)
    m.population.clear()


def test_predict_a_new_data_set_with_the_population_as_prior(gain_problem, gain_fit):
    """A data set given anew gets the conditional mode and SE its member has in the fit (same φ, same data),
    and a FitResult that predicts."""
    _, _, datasets = gain_problem
    new = gain_fit.predict(datasets["unit2"], name="again")
    row = gain_fit.random_effects.loc["unit2"]
    assert new.values["b11"] == pytest.approx(row["b11"], rel=1e-9, abs=1e-12)
    assert new.params.loc["b11", "std_error"] == pytest.approx(row["b11_se"], rel=1e-9)
    assert new.loglik == pytest.approx(gain_fit.member("unit2").loglik, rel=1e-10)
    assert len(new.predict()) == len(datasets["unit2"])
    with pytest.raises(greyid.DataError, match="cannot be used"):
        gain_fit.predict(datasets["unit2"].drop(columns="u1"))


def test_population_report(nonlinear_problem, correlated_fit, tmp_path):
    """The report holds every section; its tables are the fit's (Ω, β, random effects); the members' test
    table holds each member's own residual tests; it survives save/load with the data given back."""
    import re

    from greyid.population import load_population
    from greyid.report.population import POPULATION_SECTIONS, _covariate_table, member_tests

    _, data, covariates, *_ = nonlinear_problem
    fit = correlated_fit
    path = tmp_path / "report.html"
    text = fit.report(path, level=0.05)
    assert path.read_text(encoding="utf-8") == text
    for sid in POPULATION_SECTIONS:
        assert f'<section id="{sid}">' in text
    assert text.count("<img") == 2  # η against covariates, Q-Q plot
    assert f"{fit.params.loc['omega_a', 'estimate']:.4g}" in text
    assert f"{fit.params.loc['beta_b_area', 'estimate']:.5g}" in text
    assert "corr_b_a" in text and "b_i = b + β_area·(area − mean area) + η_b,i" in text
    tests = member_tests(fit)
    assert list(tests.index) == list(data)
    own = fit.member("h2").validate().tests
    np.testing.assert_allclose(tests.loc["h2", list(own["test"])].to_numpy(dtype=float),
                               own["p_value"].to_numpy(dtype=float), rtol=1e-12)
    assert (tests["rejects"] == (tests.drop(columns="rejects") < 0.05).sum(axis=1)).all()
    rows = re.findall(r'<tr><td class="name">(h\d)</td>', text)
    assert rows[-len(data):] == list(data)
    # The covariates table is kept (columns the model does not use included) and saved.
    assert list(_covariate_table(fit).columns) == ["area"]
    fit.save(tmp_path / "population.json")
    loaded = load_population(tmp_path / "population.json", data=data)
    pd.testing.assert_frame_equal(loaded.covariates, fit.covariates, check_dtype=False)
    again = loaded.report(members=False)
    assert '<section id="members">' not in again and '<section id="omega">' in again


def test_member_programs_compile_a_program_once_then_run_the_chunks_side_by_side():
    """A program is compiled once, for the first chunk, before the chunks run (threads started together would
    each trace and compile it); then the chunks run side by side on the threads, on the first call as on later
    ones (a chunk run alone first kept one core idle in every fit), and the members come back in their order."""
    import threading
    import time

    class Recorded:
        """A program whose ``executable`` compiles once per signature (0.2 s), its runs recorded."""

        def __init__(self, kind):
            self.kind, self.executables, self.compiled, self.runs = kind, {}, [], []
            self.lock = threading.Lock()

        def dynamic(self, args):
            return args

        def __call__(self, *args):  # as a Program's call
            return self.executable(*args)(*self.dynamic(args))

        def executable(self, u, phi, x, base, data):
            signature = (np.shape(u), np.shape(x))
            if signature not in self.executables:  # no lock: threads asking together would each compile
                start = time.perf_counter()
                time.sleep(0.2)
                self.compiled.append((threading.get_ident(), start, time.perf_counter()))
                self.executables[signature] = self.run
            return self.executables[signature]

        def run(self, u, phi, x, base, data):
            start = time.perf_counter()
            time.sleep(0.2)
            with self.lock:
                self.runs.append((int(x[0, 0]), start, time.perf_counter()))
            return np.asarray(x)[:, 0] * 2.0

    value, inner = Recorded("value"), Recorded("inner")
    programs = laplace.LaplacePrograms(**dict.fromkeys(laplace.LaplacePrograms._fields))
    x = np.arange(6.0)[:, None]
    members = laplace.MemberPrograms(programs, x, (np.zeros(1),), {"y": np.zeros((6, 3))}, workers=3)

    def run(program):
        u = np.zeros((6, 1))
        return members._run([(program, lambda part, _: (u[part[1]], np.zeros(2), part[2], members.base, part[3]))])

    try:
        for _ in range(2):  # the first call, then a later one
            value.runs.clear()
            np.testing.assert_array_equal(run(value), 2.0 * np.arange(6.0))
            assert len(value.compiled) == 1 and value.compiled[0][0] == threading.get_ident()  # once, here
            assert sorted(member for member, _, _ in value.runs) == [0, 2, 4]  # three chunks of two
            assert min(start for _, start, _ in value.runs) >= value.compiled[0][2]  # after the compilation
            assert max(start for _, start, _ in value.runs) < min(end for _, _, end in value.runs)  # side by side
        np.testing.assert_array_equal(run(inner), 2.0 * np.arange(6.0))
        assert len(inner.compiled) == 1  # another program: compiled once too
        assert max(start for _, start, _ in inner.runs) < min(end for _, _, end in inner.runs)
    finally:
        members.close()
