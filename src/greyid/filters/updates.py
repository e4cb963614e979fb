"""Covariance propagation and measurement updates in plain and square-root form.

A filter carries the state covariance either as the matrix P ("plain") or as
a lower Cholesky factor L with P = L Lᵀ ("sqrt").  The square-root measurement
update is the array (QR) form, which never subtracts covariances and so keeps
P positive definite (the role of the LDLᵀ updates of A.1.2 and A.3).

Unobserved elements of y_k are masked: their row of C is zeroed, their
innovation set to 0 and their variance to 1, so they add nothing to the
likelihood (3.18) and the Gaussian constant counts only observed elements.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax.scipy.linalg import cho_solve, solve_triangular

LOG_2PI = float(jnp.log(2.0 * jnp.pi))
PLAIN = "plain"
SQRT = "sqrt"
FORMS = (PLAIN, SQRT)


class Update(NamedTuple):
    """Result of one measurement update at t_k."""

    mean: jnp.ndarray  # x_{k|k}
    covariance: jnp.ndarray  # P_{k|k} (or its factor)
    innovation: jnp.ndarray  # ε_k (0 where unobserved)
    innovation_covariance: jnp.ndarray  # R_{k|k-1} (identity rows where unobserved)
    terms: "StepTerms"  # what this step adds to the criterion


class StepTerms(NamedTuple):
    """One step's contribution to (3.18): whitened innovation, log det R_k, count."""

    whitened: jnp.ndarray  # R_k^{-1/2} ε_k (0 where unobserved)
    logdet: jnp.ndarray
    n_obs: jnp.ndarray

    @property
    def loglik(self):
        return -0.5 * (self.n_obs * LOG_2PI + self.logdet + jnp.sum(self.whitened**2, axis=-1))


def symmetrize(P: jnp.ndarray) -> jnp.ndarray:
    return 0.5 * (P + P.T)


def to_matrix(cov: jnp.ndarray, form: str) -> jnp.ndarray:
    """P from the carried representation."""
    return cov @ cov.T if form == SQRT else cov


def from_matrix(P: jnp.ndarray, form: str) -> jnp.ndarray:
    """The carried representation from P."""
    return jnp.linalg.cholesky(symmetrize(P)) if form == SQRT else symmetrize(P)


def propagate(cov: jnp.ndarray, transition: jnp.ndarray, noise: jnp.ndarray, form: str) -> jnp.ndarray:
    """Φ P Φᵀ + Λ (4.35, A.33, A.50) in the carried representation."""
    if form == SQRT:
        FL = transition @ cov
        return jnp.linalg.cholesky(symmetrize(FL @ FL.T + noise))
    return symmetrize(transition @ cov @ transition.T + noise)


def gaussian_term(innovation, chol_R, mask) -> StepTerms:
    """log N(ε; 0, R) over the observed elements, from a Cholesky factor of R."""
    z = solve_triangular(chol_R, innovation, lower=True)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diag(chol_R))))
    return StepTerms(z, logdet, jnp.sum(mask))


def mask_observation(y, y_pred, C, S, mask):
    """Innovation, observation matrix and noise variances with unobserved rows neutral."""
    innovation = jnp.where(mask > 0, y - y_pred, 0.0)
    C = C * mask[:, None]
    S = jnp.where(mask > 0, S, 1.0)
    return innovation, C, S


def linear_update(mean, cov, y, mask, y_pred, C, S, form: str) -> Update:
    """Kalman update (4.27–4.29, 4.33) with output prediction y_pred and Jacobian C."""
    innovation, C, S = mask_observation(y, y_pred, C, S, mask)
    s, n = C.shape
    if form == SQRT:
        # Pre-array [[√S, C L], [0, L]] → lower-triangular [[R^½, 0], [K̄, L⁺]].
        pre = jnp.block([[jnp.diag(jnp.sqrt(S)), C @ cov], [jnp.zeros((n, s)), cov]])
        post = jnp.linalg.qr(pre.T)[1].T
        chol_R, gain_bar, new_cov = post[:s, :s], post[s:, :s], post[s:, s:]
        new_mean = mean + gain_bar @ solve_triangular(chol_R, innovation, lower=True)
        R = chol_R @ chol_R.T
        # Cholesky factors from QR may carry negative diagonals; the product is unaffected.
        new_cov = new_cov * jnp.where(jnp.diag(new_cov) < 0, -1.0, 1.0)[None, :]
    else:
        PCt = cov @ C.T
        R = symmetrize(C @ PCt + jnp.diag(S))
        chol_R = jnp.linalg.cholesky(R)
        gain = cho_solve((chol_R, True), PCt.T).T
        new_mean = mean + gain @ innovation
        IKC = jnp.eye(n) - gain @ C
        new_cov = symmetrize(IKC @ cov @ IKC.T + (gain * S) @ gain.T)  # Joseph form
    return Update(new_mean, new_cov, innovation, R, gaussian_term(innovation, chol_R, mask))
