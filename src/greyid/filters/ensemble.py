"""The stochastic ensemble Kalman filter (``method="enkf"``), for models with many states.

The filter carries an ensemble of P members instead of a mean and a covariance.
Row k moves each member by the model's dynamics with fixed random numbers (as the
particle filter does: [`sampled_dynamics()`][greyid.filters.particle.sampled_dynamics]),
spreads the predicted members about their mean by ``inflation`` (≥ 1, against the
ensemble's underestimated spread), and updates them with perturbed observations
(Evensen 1994; Burgers, van Leeuwen & Evensen 1998):

    ŷ = mean of h(xⁱ),  R_k = cov of h(xⁱ) + S,  K = cov(xⁱ, h(xⁱ)) R_k⁻¹,
    xⁱ ← xⁱ + K (y_k + √S eⁱ − h(xⁱ)),

the step adding the Gaussian log-likelihood of the innovation y_k − ŷ with
covariance R_k (3.18).  No covariance matrix of the states is formed, so the cost
grows with P·n rather than n³.  The random numbers are fixed by ``seed``, so the
estimate is a smooth function of θ: the ensemble estimate converges to the exact
filter's likelihood for linear Gaussian models as P grows.
"""

from __future__ import annotations

from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..model.structure import Structure
from . import small
from .particle import sampled_dynamics
from .protocol import FilterInputs, FilterOptions, FilterSteps, Row, series_rows
from .updates import StepTerms

#: The observations' perturbations are drawn from the seed's key folded with this tag and the row's number.
_PERTURB = 3


class EnsembleState(NamedTuple):
    """The members (P, n) and the number of rows done."""

    members: jnp.ndarray
    step: jnp.ndarray

    def moments(self):
        """The ensemble's mean and covariance."""
        mean = jnp.mean(self.members, axis=0)
        centred = self.members - mean
        return mean, centred.T @ centred / (self.members.shape[0] - 1)


class EnsembleUpdate(NamedTuple):
    """One row's update: the members carried on, the step's Gaussian terms, the innovation and its covariance."""

    state: EnsembleState
    terms: StepTerms
    innovation: jnp.ndarray
    innovation_covariance: jnp.ndarray
    guarded: float = 0.0


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data, key=None) -> FilterSteps`` of the stochastic ensemble Kalman filter."""
    size, inflation, seed = options.particles, options.inflation, options.seed
    if size < 2:
        raise ModelError(f"an ensemble needs at least 2 members, got particles={size}")
    h, variance_of = structure.observation, structure.observation_variance
    n_out = len(structure.output_names)
    full = structure.observation_covariance
    zeros = np.zeros(structure.n_states)

    def steps(theta, data: FilterInputs, key=None) -> FilterSteps:
        base = jax.random.PRNGKey(seed) if key is None else key
        series = series_rows(structure, theta, data)
        dynamics = sampled_dynamics(structure, options, theta, series.data, base, size, series.delays)
        perturb_key = jax.random.fold_in(base, _PERTURB)

        def predict(state: EnsembleState, row: Row):
            moved = dynamics.advance(state.members, row, state.step)
            return state._replace(members=moved), jnp.eye(structure.n_states)

        def update(state: EnsembleState, row: Row, mask=None):
            mask = row.mask if mask is None else mask
            X = state.members
            mean = jnp.mean(X, axis=0)
            X = mean + inflation * (X - mean)
            Y = jax.vmap(lambda x: h(x, row.u_cur, row.t, theta))(X)
            S = jnp.mean(jax.vmap(lambda x: variance_of(x, row.u_cur, row.t, theta))(X), axis=0)
            # The noise's covariance: its variances, or where the outputs' noise is correlated its matrix
            # (which does not depend on the state).
            noise = jnp.diag(S) if full is None else full(zeros, row.u_cur, row.t, theta)
            y_pred = jnp.mean(Y, axis=0)
            A, B = X - mean, Y - y_pred
            both = mask[:, None] * mask[None, :]
            # Unobserved outputs: their rows and columns of R_k are the identity's, their innovation 0.
            R = jnp.where(both > 0, B.T @ B / (size - 1) + noise, jnp.eye(n_out))
            cross = A.T @ B / (size - 1) * mask[None, :]
            innovation = jnp.where(mask > 0, row.y - y_pred, 0.0)
            L = small.cholesky(R)
            terms = StepTerms(small.solve_lower(L, innovation), 2 * jnp.sum(jnp.log(jnp.diag(L))), jnp.sum(mask))
            gain = small.cho_solve(L, cross.T).T  # K = cov(x, y) R⁻¹
            normals = jax.random.normal(jax.random.fold_in(perturb_key, state.step), (size, n_out))
            perturbation = normals * jnp.sqrt(S) if full is None else normals @ small.cholesky(noise).T
            discrepancy = jnp.where(mask > 0, row.y + perturbation - Y, 0.0)
            members = X + discrepancy @ gain.T
            return EnsembleUpdate(EnsembleState(members, state.step + 1), terms, innovation, R), y_pred

        initial = EnsembleState(dynamics.initial, jnp.zeros((), jnp.int32))
        return FilterSteps(initial, series.rows, predict, update)

    return steps
