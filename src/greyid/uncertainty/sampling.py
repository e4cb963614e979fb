"""Posterior sampling with the No-U-Turn sampler on the fit's exact log-posterior.

The target is the fit's criterion — the log-likelihood (3.18) or, for MAP,
the log-posterior with its Gaussian prior (3.46) — with a flat prior on the
natural parameters within their bounds for parameters without a prior.  The
sampler moves in the optimiser's unbounded coordinates z (θ = l + e^z, the
logistic map between two bounds), so the density carries the Jacobian
log|dθ/dz|.  NUTS is BlackJAX's (Hoffman & Gelman 2014, multinomial variant
with Stan's window adaptation of the step size and a dense mass matrix seeded
with the Laplace covariance at the optimum).  Why BlackJAX: it samples any
JAX log-density function, which is what greyid's compiled criterion is, without
re-expressing the model in a probabilistic programming language (NumPyro's
model syntax would wrap the same function and add nothing), it is maintained
and its kernels are pure functions that ``vmap`` runs as parallel chains.

The gradient is the forward-mode one of the estimator (one tangent per
parameter through the filter, nothing kept per step), attached as the
criterion's derivative: on the Armadillo model it makes sampling 1.2–1.6 times
faster than reverse mode through the filter's scan (benchmarks/uncertainty.py).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ..errors import ModelError
from ..estimate.objective import compiled, forward_value_and_grad
from ..estimate.optimize import EXACT
from ..estimate.refit import Refit
from ..estimate.transforms import BOTH, NONE


@dataclass
class Posterior:
    """Draws of the free parameters from the posterior of a fit, with convergence diagnostics."""

    draws: pd.DataFrame  # one column per free parameter (natural units), index (chain, draw)
    r_hat: pd.Series  # rank-normalised split R-hat per parameter (ArviZ)
    ess: pd.Series  # bulk effective sample size per parameter (ArviZ)
    divergences: int | None  # NUTS: divergent transitions after warm-up, all chains (None for PMMH)
    step_size: np.ndarray | None  # NUTS: adapted step size per chain (None for PMMH)
    acceptance: float  # mean acceptance rate after warm-up
    criterion: str  # "log-likelihood (flat prior)" or "log-posterior"
    _idata: object = field(default=None, repr=False)
    sampler: str = "nuts"  # "nuts" or "pmmh" (particle marginal Metropolis–Hastings)
    #: PMMH: the standard deviation of the particle filter's log-likelihood at the estimates (chains stick
    #: where it is well above 1.5).
    loglik_spread: float | None = None

    @property
    def chains(self) -> int:
        return int(self.draws.index.get_level_values("chain").nunique())

    def summary(self, level: float = 0.95) -> pd.DataFrame:
        """The posterior per parameter: mean, standard deviation, equal-tailed interval, R-hat and ESS.

        Parameters
        ----------
        level : float
            The interval's probability.

        Returns
        -------
        pandas.DataFrame
            One row per free parameter.
        """
        tail = (1 - level) / 2
        return pd.DataFrame({"mean": self.draws.mean(), "sd": self.draws.std(ddof=1),
                             f"{tail:.3g}": self.draws.quantile(tail), f"{1 - tail:.3g}": self.draws.quantile(1 - tail),
                             "r_hat": self.r_hat, "ess": self.ess})

    def to_inference_data(self):
        """The draws as ArviZ ``InferenceData`` (the posterior group, chains × draws).

        Returns
        -------
        arviz.InferenceData
            The draws.
        """
        if self._idata is None:
            self._idata = _inference_data(self.draws)
        return self._idata


def _arviz():
    with warnings.catch_warnings():  # ArviZ announces its refactor on import
        warnings.simplefilter("ignore", FutureWarning)
        import arviz

    return arviz


def _inference_data(draws: pd.DataFrame):
    arviz = _arviz()
    chains = draws.index.get_level_values("chain").nunique()
    values = {name: draws[name].to_numpy().reshape(chains, -1) for name in draws.columns}
    return arviz.from_dict(posterior=values)


def log_jacobian(kind, lower, upper):
    """z ↦ Σ log|dθ_i/dz_i| of the bound transforms (see estimate.transforms)."""
    kind, lower, upper = jnp.asarray(kind), jnp.asarray(lower), jnp.asarray(upper)
    width = jnp.where(kind == BOTH, upper - lower, 1.0)

    def of(z):
        logistic = jnp.log(width) - jax.nn.softplus(-z) - jax.nn.softplus(z)
        return jnp.sum(jnp.where(kind == NONE, 0.0, jnp.where(kind == BOTH, logistic, z)))

    return of


def log_density(refit: Refit):
    """z ↦ the fit's criterion at θ(z) plus the log-Jacobian, differentiated in forward mode."""
    value = compiled(refit.structure, refit.problem).value
    arguments = refit.arguments

    def negative(z):
        return value(z, *arguments)

    forward = forward_value_and_grad(negative)

    @jax.custom_vjp
    def criterion(z):
        return -negative(z)

    def criterion_forward(z):
        v, g = forward(z)
        return -v, -g

    criterion.defvjp(criterion_forward, lambda g, cotangent: (cotangent * g,))
    transform = refit.parameters.transform
    jacobian = log_jacobian(transform.kind, transform.lower, transform.upper)
    return lambda z: criterion(z) + jacobian(z)


def laplace_z(refit: Refit) -> np.ndarray:
    """The covariance of the Laplace approximation in z: the inverse exact Hessian at the optimum.

    Directions with no curvature (a parameter at a bound, an ill-determined
    combination) get a unit variance in z instead, so chains can start and the
    mass matrix can adapt.
    """
    _, _, H = refit.programs()[EXACT](refit.z_full_hat)
    refit.close()
    H = 0.5 * (np.asarray(H) + np.asarray(H).T)
    w, V = np.linalg.eigh(H)
    floor = 1e-10 * max(w.max(), 1e-300)
    inverse = np.where(w > floor, 1.0 / np.where(w > floor, w, 1.0), 1.0)
    return (V * inverse) @ V.T


def sample(fit, draws: int = 1000, chains: int = 4, seed: int = 0, warmup: int = 500,
           target_accept: float = 0.8) -> Posterior:
    """NUTS draws from the posterior of a fit's criterion (BlackJAX).

    Parameters
    ----------
    fit : FitResult
        The fit: its criterion (with its prior, for MAP) is the log-density, in the
        optimiser's coordinates with the transforms' Jacobian.
    draws : int
        Draws kept per chain.
    chains : int
        Chains, run in parallel (``vmap``), each started from a draw of the Laplace approximation.
    seed : int
        The random seed.
    warmup : int
        Adaptation steps before the kept draws.
    target_accept : float
        The step-size adaptation's target acceptance rate.

    Returns
    -------
    Posterior
        Draws, R-hat, effective sample sizes and divergences; ArviZ's
        ``InferenceData`` through ``to_inference_data()``.

    Raises
    ------
    ModelError
        BlackJAX or ArviZ is not installed (``pip install "greyid[sampling]"``).
    """
    try:
        import blackjax
    except ImportError:
        raise ModelError("posterior sampling needs BlackJAX and ArviZ: pip install \"greyid[sampling]\"") from None

    for name, value, least in (("draws", draws, 1), ("chains", chains, 1), ("warmup", warmup, 10)):
        if not isinstance(value, (int, np.integer)) or value < least:
            raise ModelError(f"{name} must be an integer of at least {least}, got {value!r}")
    if not 0 < target_accept < 1:
        raise ModelError(f"target_accept must lie between 0 and 1, got {target_accept!r}")
    refit = Refit(fit)
    density = log_density(refit)
    covariance = laplace_z(refit)
    key_start, key_chains = jax.random.split(jax.random.key(seed))
    start = (refit.z_full_hat + np.asarray(jax.random.normal(key_start, (chains, len(refit.z_full_hat))))
             @ np.linalg.cholesky(covariance).T)
    adaptation = blackjax.window_adaptation(blackjax.nuts, density, is_mass_matrix_diagonal=False,
                                            initial_inverse_mass_matrix=covariance,
                                            target_acceptance_rate=target_accept)

    def chain(key, position):
        key_warmup, key_draws = jax.random.split(key)
        (state, parameters), _ = adaptation.run(key_warmup, position, num_steps=warmup)
        kernel = blackjax.nuts(density, **parameters)

        def step(state, k):
            state, info = kernel.step(k, state)
            return state, (state.position, info.is_divergent, info.acceptance_rate)

        _, (positions, divergent, accepted) = jax.lax.scan(step, state, jax.random.split(key_draws, draws))
        return positions, divergent, accepted, parameters["step_size"]

    positions, divergent, accepted, step_size = jax.jit(jax.vmap(chain))(
        jax.random.split(key_chains, chains), jnp.asarray(start))
    label = "log-posterior" if fit.settings.get("prior") is not None else "log-likelihood (flat prior)"
    return posterior_of(refit, np.asarray(positions), criterion=label, divergences=int(np.asarray(divergent).sum()),
                        step_size=np.asarray(step_size), acceptance=float(np.asarray(accepted).mean()))


def posterior_of(refit: Refit, positions: np.ndarray, **diagnostics) -> Posterior:
    """The [`Posterior`][greyid.uncertainty.sampling.Posterior] of draws in z (chains, draws, free parameters):
    the draws in natural units, R-hat and effective sample sizes (ArviZ), and the sampler's ``diagnostics``."""
    chains, draws = positions.shape[:2]
    z = positions.reshape(chains * draws, -1)
    theta = np.asarray(refit.parameters.transform.to_theta(z, np))
    free_names = [refit.names[i] for i in refit.parameters.free]
    index = pd.MultiIndex.from_product([range(chains), range(draws)], names=["chain", "draw"])
    table = pd.DataFrame(theta, columns=free_names, index=index)
    idata = _inference_data(table)
    arviz = _arviz()
    r_hat = arviz.rhat(idata) if chains > 1 else None
    ess = arviz.ess(idata)
    return Posterior(
        draws=table,
        r_hat=pd.Series({n: float(r_hat[n]) if r_hat is not None else np.nan for n in free_names}, name="r_hat"),
        ess=pd.Series({n: float(ess[n]) for n in free_names}, name="ess"), _idata=idata, **diagnostics)
