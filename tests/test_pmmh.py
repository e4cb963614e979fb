"""Particle marginal Metropolis–Hastings against the exact posterior computed on a grid of the Kalman filter's
likelihood, its diagnostics, and its refusals."""

import dataclasses

import numpy as np
import pytest

import greyid
from greyid.errors import ModelError
from test_particle import PARAMS, ou_data, ou_gaussian


def two_parameter_ou():
    """The Ornstein–Uhlenbeck model of the particle tests with its mean and diffusion free."""
    m = ou_gaussian()
    m.set_parameter("a", init=PARAMS["a"], fixed=True)
    m.set_parameter("r", init=PARAMS["r"], fixed=True)
    return m


def grid_posterior(model, data):
    """The posterior means and standard deviations of (mu, s) under a flat prior, on a grid of the exact
    likelihood."""
    nll = model.likelihood(data, method="kalman")
    assert nll.names == ["mu", "s"]
    mu, s = np.linspace(0.4, 1.4, 101), np.linspace(0.08, 0.6, 105)
    loglik = np.array([[-nll.value(np.array([a, b])) for b in s] for a in mu])
    weights = np.exp(loglik - loglik.max())
    weights /= weights.sum()
    assert weights[[0, -1]].sum() + weights[:, [0, -1]].sum() < 1e-3  # the grid holds the posterior
    out = {}
    for name, axis, values in (("mu", 1, mu), ("s", 0, s)):
        marginal = weights.sum(axis=axis)
        mean = marginal @ values
        out[name] = (mean, np.sqrt(marginal @ (values - mean) ** 2))
    return out


def test_pmmh_draws_the_exact_posterior_from_particle_estimates():
    """A fresh particle estimate at each proposal, the current one kept: the chain's stationary law is the exact
    posterior (Andrieu, Doucet & Holenstein 2010), here the grid's within Monte Carlo error."""
    m, data = two_parameter_ou(), ou_data(60)
    fit = m.fit(data)  # exact; PMMH runs a particle filter of the same model
    posterior = fit.sample(sampler="pmmh", particles=100, proposal="ekf", draws=500, chains=4, warmup=200, seed=1)
    assert posterior.sampler == "pmmh" and posterior.divergences is None
    assert posterior.draws.shape == (2000, 2) and (posterior.r_hat < 1.05).all()
    assert 0.1 < posterior.acceptance < 0.6 and 0 < posterior.loglik_spread < 1.0
    reference = grid_posterior(m, data)
    summary = posterior.summary()
    for name, (mean, sd) in reference.items():
        error = sd / np.sqrt(posterior.ess[name])
        assert abs(summary.loc[name, "mean"] - mean) < 4 * error, (name, summary.loc[name], mean, error)
        assert summary.loc[name, "sd"] == pytest.approx(sd, rel=0.2)


def test_pmmh_warns_where_the_estimate_is_too_noisy_and_refuses_what_it_cannot_do():
    m, data = two_parameter_ou(), ou_data(60)
    m.set_parameter("r", init=4e-4, fixed=True)  # a sharp observation: the bootstrap's weights degenerate
    fit = m.fit(data)
    with pytest.warns(greyid.FitWarning, match=r"varies by .* use more particles \(now 20\) or proposal='ekf'"):
        posterior = fit.sample(sampler="pmmh", particles=20, draws=100, chains=2, warmup=100)
    assert posterior.loglik_spread > 2
    with pytest.raises(ModelError, match="unknown sampler 'gibbs'"):
        fit.sample(sampler="gibbs")
    with pytest.raises(ModelError, match="settings of sampler='pmmh'"):
        fit.sample(particles=100)
    with pytest.raises(ModelError, match="warmup must be an integer of at least 100"):
        fit.sample(sampler="pmmh", warmup=10)
    # (The fit's settings as a particle fit's: the refusal comes before any work.)
    particle_fit = dataclasses.replace(fit, settings=fit.settings.updated(method="particle", particles=50))
    with pytest.raises(ModelError, match="NUTS needs an exact gradient.*sampler='pmmh'"):
        particle_fit.sample(sampler="nuts")
