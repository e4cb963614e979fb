"""Rauch–Tung–Striebel fixed-interval smoother, after any of greyid's filters.

Running backwards over the filter's output,

    J_k = P_{k|k} Φ_{k+1}ᵀ P_{k+1|k}⁻¹,
    x_{k|N} = x_{k|k} + J_k (x_{k+1|N} − x_{k+1|k}),
    P_{k|N} = P_{k|k} + J_k (P_{k+1|N} − P_{k+1|k}) J_kᵀ,

where Φ_{k+1} is the transition matrix of the interval (t_k, t_{k+1}]: exact
for the Kalman filter; for the EKF family (EKF, IEKF, EKF2) the product of the
sub-step Jacobians of A.49; for the UKF the product of the sub-steps'
statistically linearized transitions (A = Cov(x, f) P⁻¹, 4.48), so that
P_{k|k}Φᵀ is the sigma points' state cross-covariance to first order — the
statistically linearized (unscented) RTS smoother.  All are exact on linear
models.
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve

from ..runtime.jit import jit


@jit
def rts_smooth(filtered_mean, filtered_cov, predicted_mean, predicted_cov, transitions):
    """Smoothed means and covariances, arrays shaped like the filtered ones."""

    def step(carry, k):
        xs_next, Ps_next = carry
        Pf, xf = filtered_cov[k], filtered_mean[k]
        Pp, xp, phi = predicted_cov[k + 1], predicted_mean[k + 1], transitions[k + 1]
        J = cho_solve(cho_factor(0.5 * (Pp + Pp.T), lower=True), phi @ Pf).T
        xs = xf + J @ (xs_next - xp)
        Ps = Pf + J @ (Ps_next - Pp) @ J.T
        Ps = 0.5 * (Ps + Ps.T)
        return (xs, Ps), (xs, Ps)

    last = (filtered_mean[-1], filtered_cov[-1])
    ks = jnp.arange(filtered_mean.shape[0] - 2, -1, -1)
    _, (xs, Ps) = jax.lax.scan(step, last, ks)
    xs = jnp.concatenate([xs[::-1], filtered_mean[-1:]], axis=0)
    Ps = jnp.concatenate([Ps[::-1], filtered_cov[-1:]], axis=0)
    return xs, Ps
