"""Bayesian comparison of two models with a loss structure (section 5.5).

The marginal likelihood p(y|H) = ∫ p(θ) p(y|θ) dθ (5.23) is approximated by
Laplace's method at the fit: log p(y|θ̂) + log p(θ̂) + (k/2) log 2π + ½ log det Σ̂,
Σ̂ the fit's covariance.  Posterior odds (5.24) are the prior odds times the
ratio of marginal likelihoods; H₀ is accepted when its expected loss is the
smaller (5.19–5.21).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..errors import ModelError
from ..estimate.criteria import GaussianPrior


@dataclass(frozen=True)
class BayesComparison:
    """Marginal likelihoods, posterior odds K₀₁ and the loss-minimising decision."""

    log_marginal: tuple[float, float]
    log_bayes_factor: float  # log p(y|H0) − log p(y|H1)
    posterior_odds: float  # p(H0|y)/p(H1|y)
    posterior_h0: float
    expected_loss_accept_h0: float  # p(H1|y) L(H1, accept H0)  (5.19)
    expected_loss_accept_h1: float  # p(H0|y) L(H0, accept H1)  (5.20)
    decision: str  # "H0" or "H1"


def log_marginal_likelihood(fit, prior=None) -> float:
    """The Laplace approximation of log p(y | H) for a fit.

    Parameters
    ----------
    fit : FitResult
        The fit.
    prior : dict, optional
        The parameter prior, as in ``fit(criterion="map")`` (default: the fit's).

    Returns
    -------
    float
        log p(y | H).
    """
    spec = prior if prior is not None else fit.settings.get("prior")
    if spec is None:
        raise ModelError(f"the fit of '{fit.model.name}' has no prior; the marginal likelihood needs a proper "
                         "prior on every estimated parameter (fit with criterion='map' or pass prior=...)")
    names = list(fit.params.index)
    gp = GaussianPrior.from_spec(spec, names)
    free = list(fit.cov.index)
    lacking = [n for n in free if n not in gp.names]
    if lacking:
        raise ModelError(f"the prior of '{fit.model.name}' says nothing about '{lacking[0]}'; "
                         "the marginal likelihood needs a proper prior on every estimated parameter")
    idx = [gp.names.index(n) for n in free]
    mean, cov_prior = gp.mean[idx], gp.covariance[np.ix_(idx, idx)]
    theta = fit.params.loc[free, "estimate"].to_numpy(dtype=np.float64)
    cov = fit.cov.to_numpy()
    if not np.all(np.isfinite(cov)):
        raise ModelError(f"the fit of '{fit.model.name}' has parameters without covariance (at a bound or not "
                         "determined); the Laplace approximation needs all of them")
    sign, logdet = np.linalg.slogdet(cov)
    if sign <= 0:
        raise ModelError(f"the covariance of the fit of '{fit.model.name}' is not positive definite")
    log_prior = stats.multivariate_normal(mean, cov_prior).logpdf(theta)
    k = len(free)
    return float(fit.loglik + log_prior + 0.5 * k * math.log(2 * math.pi) + 0.5 * logdet)


def posterior_odds(fit0, fit1, prior_h0: float = 0.5, loss_accept_h1: float = 1.0, loss_accept_h0: float = 1.0,
                   prior0=None, prior1=None) -> BayesComparison:
    """Compare two hypotheses by their posterior odds and the Bayes decision (5.16–5.24).

    Parameters
    ----------
    fit0 : FitResult
        The fit under H₀.
    fit1 : FitResult
        The fit under H₁, of the same data.
    prior_h0 : float
        The prior probability of H₀.
    loss_accept_h1 : float
        L(H₀, Ĥ₁), the loss of choosing H₁ when H₀ is true.
    loss_accept_h0 : float
        L(H₁, Ĥ₀), the loss of choosing H₀ when H₁ is true.
    prior0, prior1 : dict, optional
        The parameter priors where the fits were not MAP fits.

    Returns
    -------
    BayesComparison
        ``log_marginal`` (both hypotheses), ``log_bayes_factor``, ``posterior_odds``,
        ``posterior_h0``, the expected losses of each decision (5.19–5.20) and the
        ``decision``, ``"H0"`` or ``"H1"``.
    """
    if not 0 < prior_h0 < 1:
        raise ModelError(f"prior_h0 must lie strictly between 0 and 1, got {prior_h0}")
    if not (loss_accept_h1 > 0 and loss_accept_h0 > 0):
        raise ModelError("the losses of wrong decisions must be positive")
    if fit0.n_obs != fit1.n_obs:
        raise ModelError("the fits use different data; posterior odds compare models of the same data")
    m0, m1 = log_marginal_likelihood(fit0, prior0), log_marginal_likelihood(fit1, prior1)
    log_odds = math.log(prior_h0) - math.log1p(-prior_h0) + m0 - m1
    p0 = 1.0 / (1.0 + math.exp(-log_odds)) if log_odds > -700 else 0.0
    loss0, loss1 = (1 - p0) * loss_accept_h0, p0 * loss_accept_h1
    return BayesComparison((m0, m1), m0 - m1, math.exp(min(log_odds, 700.0)), p0, loss0, loss1,
                           "H0" if loss0 < loss1 else "H1")
