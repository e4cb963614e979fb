"""Covariance propagation and measurement updates in plain and square-root form.

A filter carries the state covariance either as the matrix P ("plain", with
the Joseph-form update) or as a square root L with P = L Lᵀ ("sqrt").  The
square-root measurement update is Potter's, one scalar observation at a time,
and never subtracts covariances, so P stays positive semi-definite (the role of
the LDLᵀ updates of A.1.2 and A.3); the time update refactorises Φ P Φᵀ + Λ, a
sum of positive semi-definite terms, by the guarded Cholesky factorisation of
[`small.cholesky()`][greyid.filters.small.cholesky] (zero pivots give zero columns).  It is not an array
(QR) algorithm.

Unobserved elements of y_k are masked: their row of C is zeroed, their
innovation set to 0 and their variance to 1, so they add nothing to the
likelihood (3.18) and the Gaussian constant counts only observed elements.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
from . import small

LOG_2PI = math.log(2.0 * math.pi)
PLAIN = "plain"
SQRT = "sqrt"
FORMS = (PLAIN, SQRT)


class GaussianState(NamedTuple):
    """The state of a Gaussian filter: a mean and a covariance (in the carried form)."""

    mean: jnp.ndarray
    covariance: jnp.ndarray  # P or its factor, see to_matrix


class Update(NamedTuple):
    """Result of one measurement update at t_k."""

    mean: jnp.ndarray  # x_{k|k}
    covariance: jnp.ndarray  # P_{k|k} (or its factor)
    innovation: jnp.ndarray  # ε_k (0 where unobserved)
    innovation_covariance: jnp.ndarray  # R_{k|k-1} (identity rows where unobserved)
    terms: "StepTerms"  # what this step adds to the criterion
    #: 1 where the update's plain covariance P − K R Kᵀ was not positive semi-definite and the
    #: guarded (Joseph) form replaced it (the moment-based updates of the UKF and second-order filters).
    guarded: jnp.ndarray | float = 0.0

    @property
    def state(self) -> GaussianState:
        """The filtered state the filter carries on to the next row."""
        return GaussianState(self.mean, self.covariance)


class StepTerms(NamedTuple):
    """One step's contribution to (3.18): whitened innovation, log det R_k, count."""

    whitened: jnp.ndarray  # R_k^{-1/2} ε_k (0 where unobserved)
    logdet: jnp.ndarray
    n_obs: jnp.ndarray

    @property
    def loglik(self):
        return -0.5 * (self.n_obs * LOG_2PI + self.logdet + jnp.sum(self.whitened**2, axis=-1))


class DensityTerms(NamedTuple):
    """One step's contribution to the log-likelihood where it is not a Gaussian innovation's: log p(y_k |
    y_1..k−1) itself (the particle filter's estimate of it), and the count of observed elements."""

    loglik: jnp.ndarray
    n_obs: jnp.ndarray


def symmetrize(P: jnp.ndarray) -> jnp.ndarray:
    return 0.5 * (P + P.T)


def to_matrix(cov: jnp.ndarray, form: str) -> jnp.ndarray:
    """P from the carried representation."""
    return cov @ cov.T if form == SQRT else cov


def from_matrix(P: jnp.ndarray, form: str) -> jnp.ndarray:
    """The carried representation from P."""
    return small.cholesky(symmetrize(P)) if form == SQRT else symmetrize(P)


def propagate(cov: jnp.ndarray, transition: jnp.ndarray, noise: jnp.ndarray, form: str) -> jnp.ndarray:
    """Φ P Φᵀ + Λ (4.35, A.33, A.50) in the carried representation."""
    if form == SQRT:
        FL = small.mm(transition, cov)
        return small.cholesky(symmetrize(small.mm(FL, FL.T) + noise))
    return symmetrize(small.mm(small.mm(transition, cov), transition.T) + noise)


def gaussian_term(innovation, chol_R, mask) -> StepTerms:
    """log N(ε; 0, R) over the observed elements, from a Cholesky factor of R."""
    z = small.solve_lower(chol_R, innovation)
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
        # Potter's square-root update, one scalar observation at a time (S is
        # diagonal): L⁺ = L (I − γ f fᵀ) with f = Lᵀcᵢ.  Processing the elements in
        # turn factorises R_k, so the scaled innovations are R_k^{-1/2} ε_k.
        x, L = mean, cov
        whitened, logdet = [], jnp.zeros(())
        for i in range(s):
            c = C[i]
            f = small.mm(L.T, c)
            alpha = jnp.sum(f * f) + S[i]
            e = innovation[i] - jnp.sum(c * (x - mean))
            Lf = small.mm(L, f)
            x = x + Lf * (e / alpha)
            L = L - jnp.outer(Lf, f) / (alpha + jnp.sqrt(alpha * S[i]))
            whitened.append(e / jnp.sqrt(alpha))
            logdet = logdet + jnp.log(alpha)
        R = symmetrize(C @ cov @ cov.T @ C.T + jnp.diag(S))
        terms = StepTerms(jnp.stack(whitened), logdet, jnp.sum(mask))
        return Update(x, L, innovation, R, terms)
    PCt = cov @ C.T
    R = symmetrize(C @ PCt + jnp.diag(S))
    chol_R = small.cholesky(R)
    gain = small.cho_solve(chol_R, PCt.T).T
    new_mean = mean + gain @ innovation
    IKC = jnp.eye(n) - gain @ C
    new_cov = symmetrize(IKC @ cov @ IKC.T + (gain * S) @ gain.T)  # Joseph form
    return Update(new_mean, new_cov, innovation, R, gaussian_term(innovation, chol_R, mask))


def observed_root(S_full, mask):
    """The Cholesky factor L of the observed outputs' noise covariance, an identity block for the unobserved
    ones: L⁻¹ makes the observed outputs' noise independent with unit variances."""
    return small.cholesky(symmetrize(S_full * mask[:, None] * mask[None, :] + jnp.diag(1.0 - mask)))


def whiten(L, mask, v):
    """L⁻¹ v over the observed elements of v (the unobserved ones 0)."""
    return small.solve_lower(L, jnp.where(mask > 0, v, 0.0))


def correlated_update(mean, cov, y, mask, y_pred, C, S_full, form: str, update=None) -> Update:
    """The update with correlated measurement noise S (a full matrix).

    The observed elements are decorrelated by the Cholesky factor L of their noise
    covariance (unobserved ones get an identity block): with y', ŷ', C' = L⁻¹(y, ŷ, C)
    the noise is white with unit variances, so the scalar updates apply; log det R
    gains 2 log det L, and the innovations and R are returned in the outputs' own
    coordinates.  ``update`` is [`linear_update()`][greyid.filters.updates.linear_update] or a filter's variant of it.
    """
    update = update or linear_update
    m = mask
    L = observed_root(S_full, m)
    white = update(mean, cov, whiten(L, m, y), m, whiten(L, m, y_pred), small.solve_lower(L, C * m[:, None]),
                   jnp.ones_like(y), form)
    terms = white.terms._replace(logdet=white.terms.logdet + 2.0 * jnp.sum(jnp.log(jnp.diag(L))))
    innovation = jnp.where(m > 0, y - y_pred, 0.0)
    R = symmetrize(small.mm(small.mm(L, white.innovation_covariance), L.T))
    return Update(white.mean, white.covariance, innovation, R, terms)
