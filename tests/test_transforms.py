"""Lamperti transforms of states (model.transform_state): Itô's formula applied symbolically, checked against
exact filters, closed forms and fine-step simulations of the untransformed equations."""

from __future__ import annotations

import jax
import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.cli import main

GBM = dict(mu=0.05, s=0.2, r=0.01)


def gbm(transform="log", shift=None):
    """Geometric Brownian motion observed on the log scale (shifted by c where ``shift``)."""
    m = greyid.Model("gbm")
    if shift is None:
        m.add_system("dx = mu*x*dt + s*x*dw1").add_observation("y = log(x)", variance="r")
    else:
        m.add_system("dx = mu*(x - c)*dt + s*(x - c)*dw1").add_observation("y = log(x - c)", variance="r")
        m.set_parameter("c", init=shift, fixed=True)
    m.set_initial_state(mean={"x": 2.0 + (shift or 0.0)}, covariance=[[0.04]])
    for name, value in GBM.items():
        m.set_parameter(name, init=value, lower=-1.0 if name == "mu" else 1e-4, upper=2.0)
    if transform:
        m.transform_state("x", transform)
    return m


def log_process():
    """The log of the GBM written out by hand: dz = (μ − s²/2) dt + s dω, P0 = 0.04 / 2² (the delta method)."""
    m = greyid.Model("log gbm").add_system("dz = (mu - s^2/2)*dt + s*dw1")
    m.add_observation("y = z", variance="r")
    m.set_initial_state(mean={"z": "log(2.0)"}, covariance=[[0.01]])
    for name, value in GBM.items():
        m.set_parameter(name, init=value, lower=-1.0 if name == "mu" else 1e-4, upper=2.0)
    return m


@pytest.fixture(scope="module")
def gbm_data():
    return gbm().simulate(GBM, np.arange(0.0, 40.0, 0.5), seed=3).frame(0)[["t", "y"]]


@pytest.mark.parametrize("shift", [None, 1.5])
def test_the_log_transform_makes_gbm_linear_and_its_filter_the_exact_kalman_filter(gbm_data, shift):
    """After the log transform GBM observed on the log scale is linear and time-invariant: the transformed
    model's filter equals the Kalman filter of the log-process written by hand, value and gradient to 1e-10
    (a named transform, and the same through the expression 'log(x - c)')."""
    m = gbm("log" if shift is None else "log(x - c)", shift)
    assert m.structure.kind == "lti"
    params = {**GBM, **({"c": shift} if shift else {})}
    reference = log_process()
    exact = reference.loglik(GBM, gbm_data, method="kalman")
    assert m.loglik(params, gbm_data, method="ekf") == pytest.approx(exact, rel=1e-10, abs=1e-10)
    assert m.loglik(params, gbm_data) == pytest.approx(exact, rel=1e-10, abs=1e-10)

    # States are reported in the user's coordinates: x = c + exp(z), the delta method's variance.
    ours, theirs = m.filter(params, gbm_data), reference.filter(GBM, gbm_data)
    level = np.exp(theirs.filtered["z"].to_numpy())
    np.testing.assert_allclose(ours.filtered["x"].to_numpy(), level + (shift or 0.0), rtol=1e-10)
    np.testing.assert_allclose(ours.filtered_cov[:, 0, 0], theirs.filtered_cov[:, 0, 0] * level**2, rtol=1e-8)
    smoothed, smoothed_ref = m.smooth(params, gbm_data), reference.smooth(GBM, gbm_data)
    np.testing.assert_allclose(smoothed.smoothed["x"].to_numpy(),
                               np.exp(smoothed_ref.smoothed["z"].to_numpy()) + (shift or 0.0), rtol=1e-9)


def test_a_transformed_fit_gives_the_log_process_fit(gbm_data):
    """Estimates and standard errors of the transformed model are those of the hand-written linear model."""
    ours, theirs = gbm().fit(gbm_data), log_process().fit(gbm_data)
    assert ours.loglik == pytest.approx(theirs.loglik, abs=1e-8)
    for column in ("estimate", "std_error"):
        np.testing.assert_allclose(ours.params.loc[list(GBM), column], theirs.params.loc[list(GBM), column],
                                   rtol=1e-5)


def test_simulated_gbm_has_the_closed_form_moments():
    """Paths of the transformed model (exact scheme: it is linear in log x) against GBM's closed form:
    E x_t = x0 e^{μt}, log x_t ~ N(log x0 + (μ − s²/2)t, s²t) from a known start."""
    m = gbm()
    m.set_initial_state(mean={"x": 2.0}, covariance=[[0.0]])
    params = dict(mu=0.1, s=0.3, r=0.01)
    times = np.array([0.0, 1.0, 2.0, 4.0])
    paths = m.simulate(params, times, n_paths=20000, method="exact", seed=5).states[:, :, 0]
    assert np.all(paths > 0)
    for k, t in enumerate(times[1:], start=1):
        logs = np.log(paths[:, k])
        assert abs(logs.mean() - (np.log(2.0) + (0.1 - 0.045) * t)) < 4 * 0.3 * np.sqrt(t / 20000)
        assert logs.std() == pytest.approx(0.3 * np.sqrt(t), rel=0.03)
        mean, sd = paths[:, k].mean(), paths[:, k].std()
        assert abs(mean - 2.0 * np.exp(0.1 * t)) < 4 * sd / np.sqrt(20000)
    deterministic = m.simulate(params, times, method="heun", noise=False, substeps=50).states[0, :, 0]
    np.testing.assert_allclose(deterministic, 2.0 * np.exp(0.1 * times), rtol=1e-6)  # dx = μx dt, no Itô term
    with pytest.raises(greyid.ModelError, match="noise=False.*method='heun'"):
        m.simulate(params, times, method="exact", noise=False)
    with pytest.raises(greyid.ModelError, match="Itô equations"):
        m.simulate(params, times, calculus="stratonovich")


def _fine_euler(drift, diffusion, x0, times, paths, seed, steps=400):
    """Euler–Maruyama of the untransformed equation on a fine grid (``steps`` per unit time)."""
    rng = np.random.default_rng(seed)
    x, out, t = np.full(paths, x0), [np.full(paths, x0)], 0.0
    for target in times[1:]:
        n = int(round((target - t) * steps))
        h = (target - t) / n
        for _ in range(n):
            x = x + drift(x) * h + diffusion(x) * np.sqrt(h) * rng.normal(size=paths)
        out.append(x.copy())
        t = target
    return np.array(out).T


@pytest.mark.parametrize("case", ["logistic/log", "cir/sqrt", "proportion/logit", "proportion/arcsine"])
def test_transformed_simulation_matches_a_fine_step_simulation_of_the_original_equation(case):
    """Each named transform: the transformed model's paths (Euler in z, 100 sub-steps) have the mean and
    quartiles of a fine-step (400 per unit) Euler simulation of the original equation, within Monte Carlo
    error; CIR's mean also against its closed form."""
    model, transform = case.split("/")
    equations = {
        "logistic": ("dx = r*x*(1 - x/K)*dt + s*x*dw1", dict(r=0.8, K=10.0, s=0.3), 1.0,
                     lambda x: 0.8 * x * (1 - x / 10), lambda x: 0.3 * x),
        "cir": ("dx = a*(m - x)*dt + s*sqrt(x)*dw1", dict(a=0.7, m=2.0, s=0.3), 0.5,
                lambda x: 0.7 * (2.0 - x), lambda x: 0.3 * np.sqrt(np.maximum(x, 0.0))),
        "proportion": ("dx = a*(m - x)*dt + s*x*(1 - x)*dw1" if transform == "logit" else
                       "dx = a*(m - x)*dt + s*sqrt(x*(1 - x))*dw1", dict(a=1.0, m=0.6, s=0.4), 0.3,
                       lambda x: 1.0 * (0.6 - x),
                       (lambda x: 0.4 * x * (1 - x)) if transform == "logit" else
                       (lambda x: 0.4 * np.sqrt(np.clip(x * (1 - x), 0.0, None)))),
    }
    text, params, x0, drift, diffusion = equations[model]
    m = greyid.Model(model).add_system(text).add_observation("y = x", variance="v")
    m.set_initial_state(mean={"x": x0}, covariance=[[0.0]])
    m.transform_state("x", transform)
    times = np.array([0.0, 0.5, 1.5, 3.0])
    paths = 8000
    ours = m.simulate({**params, "v": 0.01}, times, n_paths=paths, substeps=100, seed=11).states[:, :, 0]
    fine = _fine_euler(drift, diffusion, x0, times, paths, seed=12)
    for k in range(1, len(times)):
        sd = np.sqrt((ours[:, k].var() + fine[:, k].var()) / paths)
        assert abs(ours[:, k].mean() - fine[:, k].mean()) < 4 * sd, (case, times[k])
        for q in (0.25, 0.5, 0.75):
            assert abs(np.quantile(ours[:, k], q) - np.quantile(fine[:, k], q)) < 6 * sd, (case, times[k], q)
    if model == "cir":
        closed = 2.0 + (x0 - 2.0) * np.exp(-0.7 * times[1:])
        spread = ours[:, 1:].std(axis=0) / np.sqrt(paths)
        assert np.all(np.abs(ours[:, 1:].mean(axis=0) - closed) < 4 * spread)
    if model == "proportion":
        assert np.all((ours > 0) & (ours < 1))


def test_the_laplace_method_fits_multiplicative_noise_after_the_log_transform():
    """Logistic growth with noise s·x: the Laplace method's transitions are Gaussian in log x, so its value is
    finite and lies within 0.5 of the particle filter's estimate (EKF proposal, 4 × 1000 particles), as it
    does not on x itself."""
    from greyid.estimate.approximations import particle_loglik

    rng = np.random.default_rng(2)
    x, ys = 10.0, []
    for _ in range(60):
        ys.append(x + 2.0 * rng.normal())
        for _ in range(100):
            x = x + 0.3 * x * (1 - x / 100) * 0.01 + 0.3 * x * 0.1 * rng.normal()
    data = pd.DataFrame({"t": np.arange(60.0), "y": ys})
    m = greyid.Model("logistic").add_system("dx = r*x*(1 - x/K)*dt + s*x*dw1")
    m.add_observation("y = x", variance="v").set_initial_state(mean={"x": 10.0}, covariance=[[1.0]])
    params = dict(r=0.3, K=100.0, s=0.3, v=4.0)
    m.transform_state("x", "log")
    laplace = m.loglik(params, data, method="laplace")
    reference = particle_loglik(m, params, data, particles=1000, seed=0, replicates=4, proposal="ekf")
    assert np.isfinite(laplace)
    assert abs(laplace - reference.loglik) < max(0.5, 3 * reference.std_error)


def test_transforms_round_trip_through_model_files_and_saved_fits(gbm_data, tmp_path):
    m = gbm()
    again = greyid.Model.from_toml(m.to_toml())
    assert "[model.transforms]" in m.to_toml()
    assert again.loglik(GBM, gbm_data) == pytest.approx(m.loglik(GBM, gbm_data), abs=1e-12)
    assert greyid.Model.from_dict(m.to_dict()).structure.fingerprint == m.structure.fingerprint
    assert gbm(None).structure.fingerprint != m.structure.fingerprint


@pytest.mark.parametrize("system, transform, culprit", [
    ("dx = -a*x*dt + s*dw1", "log", "does not match the diffusion of state 'x'.*proportional to the state"),
    ("dx = -a*x*dt + 0*dw1", "log", "'x' has no noise term"),
    ("dx = -a*x*dt + s*x*dw1 + s*dw2", "log", "state 'x' has 2 noise terms \\(dw1, dw2\\)"),
    ("dx = -a*x*dt + s*x*dw1", "x^2", "has 2 inverse"),
    ("dx = -a*x*dt + s*x*dw1", "log(a)", "neither one of arcsine, log, logit, sqrt nor an expression of 'x'"),
    ("dx = -a*x*dt + s*x*dw1", "lg(x", "transform of state 'x'"),
])
def test_transforms_that_cannot_apply_are_refused_by_name(system, transform, culprit):
    m = greyid.Model().add_system(system).add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.1]])
    with pytest.raises(greyid.ModelError, match=culprit):
        m.transform_state("x", transform)
        m.structure  # noqa: B018  (built here)


def test_transform_state_checks_its_arguments():
    m = greyid.Model().add_system("dx = -a*x*dt + s*x*dw1")
    with pytest.raises(greyid.ModelError, match="'z' is not a state"):
        m.transform_state("z", "log")
    m.transform_state("x", "log")
    with pytest.raises(greyid.ModelError, match="already transformed"):
        m.transform_state("x", "sqrt")
    with pytest.raises(greyid.ModelError, match="two strings"):
        greyid.Model().add_system("dx = 0*dt + s*x*dw1").transform_state("x", 3)


def test_a_model_file_with_a_transform_that_does_not_match_exits_2(tmp_path, capsys):
    (tmp_path / "data.csv").write_text("t,y\n0,1\n1,1.1\n2,1.2\n")
    (tmp_path / "model.toml").write_text(
        '[model]\nsystem = ["dx = -a*x*dt + s*dw1"]\ninitial_covariance = [[0.1]]\n'
        '[model.observations]\ny = { equation = "x", variance = "r" }\n'
        '[model.transforms]\nx = "log"\n[model.initial_state]\nx = 1.0\n'
        '[parameters]\na = { init = 0.5 }\ns = { init = 0.1 }\nr = { init = 0.1 }\n')
    assert main(["fit", str(tmp_path / "model.toml"), str(tmp_path / "data.csv")]) == 2
    err = capsys.readouterr().err
    assert "does not match the diffusion of state 'x'" in err and "Traceback" not in err
    (tmp_path / "bad.toml").write_text((tmp_path / "model.toml").read_text().replace('x = "log"', "x = 3"))
    assert main(["fit", str(tmp_path / "bad.toml"), str(tmp_path / "data.csv")]) == 2
    assert "[model.transforms] must be a table" in capsys.readouterr().err


def test_jax_sees_one_program_per_transformed_structure(gbm_data):
    """The transform is symbolic: the compiled functions are ordinary structure functions (traceable)."""
    s = gbm().structure
    x = jax.numpy.array([np.log(2.0)])
    theta = jax.numpy.asarray(gbm().parameter_vector(GBM))
    np.testing.assert_allclose(s.drift(x, jax.numpy.zeros(0), 0.0, theta), [0.05 - 0.02])
    np.testing.assert_allclose(s.diffusion(x, jax.numpy.zeros(0), 0.0, theta), [[0.2]])
