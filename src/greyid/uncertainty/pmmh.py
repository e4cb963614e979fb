"""Particle marginal Metropolis–Hastings: posterior draws where only a particle estimate of the likelihood exists.

The particle filter's likelihood estimate is unbiased, so a Metropolis–Hastings
chain that uses it in place of the likelihood — a fresh estimate, with new random
numbers, at each proposed point, the current point's estimate kept — has the
exact posterior as its stationary distribution (Andrieu, Doucet & Holenstein
2010).  The target is the fit's criterion as for NUTS
([`sampling`][greyid.uncertainty.sampling]): the log-likelihood with a flat prior
within the bounds, or the log-posterior with the fit's Gaussian prior (3.46), in
the optimiser's unbounded coordinates z with the transforms' Jacobian.

Proposals are Gaussian random-walk steps, N(0, (2.562²/d) Σ) (the scale that
Sherlock, Thiery, Roberts & Rosenthal 2015 find best for a noisy likelihood): Σ
the Laplace covariance at the estimate for the first half of the warm-up, then
the covariance of that half's later draws (all chains pooled).  The chains run in parallel
(``vmap``), a block of steps per compiled call.  How well a chain mixes depends
on the spread of the log-likelihood estimate: where its standard deviation is
well above 1.5 (Doucet, Pitt, Deligiannidis & Kohn 2015) the chains stick at
points whose estimate came out high.  The spread at the estimates is reported
with the draws, and a warning names the remedies (more particles, a guided
proposal) where it exceeds 2.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..estimate.objective import log_prior
from ..estimate.refit import Refit
from ..estimate.results import FitWarning
from ..estimate.transforms import Transform
from ..filters.api import filter_options
from ..filters.driver import filter_steps, scan_rows
from ..filters.protocol import PARTICLE
from .sampling import laplace_z, log_jacobian, posterior_of

#: The random-walk scale, (SCALE² / d) Σ (Sherlock et al. 2015).
SCALE = 2.562
#: Steps per compiled call of the chains.
BLOCK = 50
#: Runs of the particle filter at the estimates behind the reported spread.
SPREAD_RUNS = 16
#: A spread above this warns that the chains will stick.
SPREAD_WARNING = 2.0


class ChainState(NamedTuple):
    """A chain's point in z and its log-target estimate (kept until a proposal is accepted)."""

    z: jnp.ndarray
    log_target: jnp.ndarray


def particle_options(refit: Refit, particles: int | None, proposal: str | None):
    """The fit's particle filter (with ``particles`` and ``proposal`` where given), or, for a fit by another
    method, a particle filter of the same model."""
    options = refit.problem.options
    if options.method == PARTICLE:
        changes = {k: v for k, v in (("particles", particles), ("proposal", proposal)) if v is not None}
        return replace(options, **changes)
    return filter_options(refit.structure, PARTICLE, particles=1000 if particles is None else particles,
                          proposal=proposal)


def log_target(refit: Refit, options):
    """``(z, key, *arguments) -> (log target, log-likelihood)``: one particle estimate with the key's random
    numbers, plus the log-prior (MAP) and the log-Jacobian of z."""
    structure, problem = refit.structure, refit.problem
    build = filter_steps(structure, options)
    kinds = problem.transform.kind

    def target(z, key, base, lower, upper, prior_mean, prior_chol, datasets):
        theta = problem.theta(z, base, Transform(kinds, lower, upper), jnp)
        keys = jax.random.split(key, len(datasets))
        loglik = sum(scan_rows(build(theta, data, key=k), data.t.shape[0], None,
                               accumulate=lambda terms: terms.loglik) for data, k in zip(datasets, keys))
        total = loglik + log_jacobian(kinds, lower, upper)(z)
        if problem.prior is not None:
            total = total + log_prior(theta, problem.prior_index, prior_mean, prior_chol)
        return jnp.where(jnp.isfinite(total), total, -jnp.inf), loglik

    return target


def chain_blocks(target):
    """A jitted ``(states, root, keys, *arguments) -> (states, positions, accepted)``: BLOCK random-walk steps of
    every chain (``keys``: one per chain), proposals root · N(0, I)."""

    def block(states: ChainState, root, keys, *arguments):
        def chain(state: ChainState, key):
            def step(state: ChainState, k):
                k_move, k_filter, k_accept = jax.random.split(k, 3)
                z = state.z + root @ jax.random.normal(k_move, state.z.shape)
                proposed, _ = target(z, k_filter, *arguments)
                accept = jnp.log(jax.random.uniform(k_accept)) < proposed - state.log_target
                state = ChainState(jnp.where(accept, z, state.z), jnp.where(accept, proposed, state.log_target))
                return state, (state.z, accept)

            return jax.lax.scan(step, state, jax.random.split(key, BLOCK))

        states, (positions, accepted) = jax.vmap(chain)(states, keys)
        return states, positions, accepted

    return jax.jit(block)


def random_walk_root(covariance: np.ndarray) -> np.ndarray:
    """The Cholesky factor of (SCALE²/d) · covariance, with a small ridge where it is singular."""
    d = covariance.shape[0]
    covariance = 0.5 * (covariance + covariance.T)
    ridge = 1e-10 * max(float(np.max(np.diag(covariance))), 1e-300)
    return np.linalg.cholesky(SCALE**2 / d * (covariance + ridge * np.eye(d)))


def sample_pmmh(fit, draws: int = 1000, chains: int = 4, seed: int = 0, warmup: int = 500,
                particles: int | None = None, proposal: str | None = None):
    """Particle marginal Metropolis–Hastings draws from the posterior of a fit's criterion.

    Parameters
    ----------
    fit : FitResult
        The fit: its criterion (with its prior, for MAP) is the target, its particle filter (or, for a fit by
        another method, a particle filter of its model) estimates the likelihood.
    draws : int
        Draws kept per chain.
    chains : int
        Chains, run in parallel, each started from a draw of the Laplace approximation.
    seed : int
        The random seed of the chains and of the particle filters' random numbers.
    warmup : int
        Steps before the kept draws (at least 100): the first half's later draws give the proposal's covariance
        for the rest.
    particles : int, optional
        The particle filter's particles (default: the fit's, or 1000).
    proposal : str, optional
        The particle filter's proposal, ``"bootstrap"``, ``"ekf"`` or ``"ukf"`` (default: the fit's, or the
        bootstrap).

    Returns
    -------
    Posterior
        The draws, R-hat, effective sample sizes, the acceptance rate and ``loglik_spread``, the standard
        deviation of the log-likelihood estimate at the estimates (``sampler="pmmh"``).

    Raises
    ------
    ModelError
        A robust or k-step fit (their criteria are not likelihoods), settings out of range, or ArviZ missing.

    Examples
    --------
    >>> posterior = fit.sample(sampler="pmmh", draws=2000)   # doctest: +SKIP
    >>> posterior.summary(), posterior.acceptance, posterior.loglik_spread   # doctest: +SKIP
    """
    for name, value, least in (("draws", draws, 1), ("chains", chains, 1), ("warmup", warmup, 2 * BLOCK)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < least:
            raise ModelError(f"{name} must be an integer of at least {least}, got {value!r}")
    if fit.settings.get("robust") or fit.settings.get("horizon", 1) != 1:
        raise ModelError("PMMH samples a likelihood; this fit's robust or k-step criterion is not one")
    refit = Refit(fit)
    options = particle_options(refit, particles, proposal)
    target = log_target(refit, options)
    arguments = refit.arguments
    key_start, key_spread, key_chains = jax.random.split(jax.random.key(seed), 3)

    # The estimate's spread at the optimum, which decides how well the chains can mix.
    runs = jax.jit(jax.vmap(lambda k: target(jnp.asarray(refit.z_full_hat), k, *arguments)[1]))(
        jax.random.split(key_spread, SPREAD_RUNS))
    spread = float(np.std(np.asarray(runs), ddof=1))
    if not np.isfinite(spread) or spread > SPREAD_WARNING:
        warnings.warn(f"{fit.model.name}: the particle filter's log-likelihood varies by {spread:.3g} (standard "
                      f"deviation over {SPREAD_RUNS} runs) at the estimates; PMMH chains stick where it is well "
                      f"above 1.5: use more particles (now {options.particles}) or proposal='ekf'", FitWarning,
                      stacklevel=2)

    covariance = laplace_z(refit)
    d = covariance.shape[0]
    start = refit.z_full_hat + np.asarray(jax.random.normal(key_start, (chains, d))) @ np.linalg.cholesky(
        covariance + 1e-12 * np.eye(d)).T
    start_keys = jax.random.split(jax.random.fold_in(key_start, 1), chains)
    log_start, _ = jax.jit(jax.vmap(lambda z, k: target(z, k, *arguments)))(jnp.asarray(start), start_keys)
    states = ChainState(jnp.asarray(start), log_start)
    run_block = chain_blocks(target)

    def run(states, root, steps, first_block):
        """``steps`` steps of every chain in blocks numbered from ``first_block`` (whose keys fold in the number)."""
        positions, accepted = [], []
        blocks = -(-steps // BLOCK)
        for number in range(first_block, first_block + blocks):
            keys = jax.random.split(jax.random.fold_in(key_chains, number), chains)
            states, p, a = run_block(states, jnp.asarray(root), keys, *arguments)
            positions.append(np.asarray(p))
            accepted.append(np.asarray(a))
        return (states, np.concatenate(positions, axis=1)[:, :steps], np.concatenate(accepted, axis=1)[:, :steps],
                first_block + blocks)

    # Warm-up: the Laplace covariance, then the first half's draws' covariance (where the chains moved).
    root = random_walk_root(covariance)
    half = warmup // 2
    states, first, _, block = run(states, root, half, 0)
    learnt = np.cov(first[:, half // 2:].reshape(-1, d), rowvar=False).reshape(d, d)
    if np.all(np.isfinite(learnt)) and np.all(np.linalg.eigvalsh(0.5 * (learnt + learnt.T)) > 0):
        root = random_walk_root(learnt)
    states, _, _, block = run(states, root, warmup - half, block)
    states, positions, accepted, _ = run(states, root, draws, block)
    label = "log-posterior" if fit.settings.get("prior") is not None else "log-likelihood (flat prior)"
    return posterior_of(refit, positions, criterion=label, divergences=None, step_size=None,
                        acceptance=float(np.mean(accepted)), sampler="pmmh", loglik_spread=spread)


__all__ = ["sample_pmmh", "particle_options", "log_target", "SCALE"]
