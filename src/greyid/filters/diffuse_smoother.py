"""Smoothing after a diffuse start, exactly: the diffuse part of x₀ integrated out under its flat prior.

With x₀ = a + E δ (E the diffuse states' columns of I) and the other part of x₀ ~ N(·, P*), the
filter and the Rauch–Tung–Striebel smoother started from (a + E δ, P*) are linear in δ: the smoothed
means m_k(δ) = m_k(0) + J_k δ, their covariances P_k|N free of δ, and the log-likelihood ℓ(δ) a
quadratic.  A flat prior on δ (κ → ∞) makes δ | y ~ N(δ̂, (−∇²ℓ)⁻¹), δ̂ = −(∇²ℓ)⁻¹ ∇ℓ(0), so

    x_k|N = m_k(δ̂),   P_k|N + J_k (−∇²ℓ)⁻¹ J_kᵀ

(de Jong's augmented smoother, 1991, in the form of a derivative): the gradient, Hessian and J by JAX,
each exact because the functions are linear or quadratic in δ.  It needs P_k|k−1 invertible from row 1
on (process noise on every state), as the smoother itself does.
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import jit
from ..model.structure import Structure
from .driver import filter_steps, scan_rows, state_moments
from .protocol import FilterInputs, FilterOptions
from .smoother import rts_smooth
from .updates import GaussianState


def make_diffuse_smoother(structure: Structure, options: FilterOptions):
    """A jitted ``run(theta, data) -> (smoothed means, smoothed covariances)`` of a model with diffuse states."""
    build = filter_steps(structure, options)
    columns = np.eye(structure.n_states)[:, list(structure.initial_covariance.diffuse)]

    def from_known_start(theta, data: FilterInputs, delta):
        """The ordinary filter from (a + E δ, P*): its log-likelihood and what the smoother needs."""
        parts = build(theta, data)
        start = GaussianState(parts.initial.mean + columns @ delta, parts.initial.covariance)
        parts = parts._replace(initial=start, diffuse=None, steady=None)

        def collect(predicted, transition, upd, y_pred):
            return upd.terms.loglik, (*state_moments(predicted, options.form), *state_moments(upd.state, options.form),
                                      transition)

        loglik, (x_pred, P_pred, x_filt, P_filt, transitions) = scan_rows(parts, data.t.shape[0], collect)
        return jnp.sum(loglik), (x_filt, P_filt, x_pred, P_pred, transitions)

    def smoothed_mean(theta, data, delta):
        _, (x_filt, P_filt, x_pred, P_pred, transitions) = from_known_start(theta, data, delta)
        return rts_smooth(x_filt, P_filt, x_pred, P_pred, transitions)

    def run(theta, data: FilterInputs):
        zero = jnp.zeros(columns.shape[1])

        def loglik(delta):
            return from_known_start(theta, data, delta)[0]

        gradient, hessian = jax.grad(loglik)(zero), jax.hessian(loglik)(zero)
        information = -0.5 * (hessian + hessian.T)
        delta = jnp.linalg.solve(information, gradient)
        means, covariances = smoothed_mean(theta, data, delta)
        sensitivity = jax.jacfwd(lambda d: smoothed_mean(theta, data, d)[0])(delta)  # (N, n, d)
        spread = jnp.einsum("kia,ab,kjb->kij", sensitivity, jnp.linalg.inv(information), sensitivity)
        return means, covariances + spread

    return jit(run)
