"""Discretization of dx = (A x + b(t)) dt + G dω over one sampling interval.

For an interval of length τ we need (4.36), (4.39), (A.51):

    Φ = e^{Aτ},  Γ = ∫₀^τ e^{As} ds,  Υ = (1/τ) ∫₀^τ e^{As}(τ − s) ds,
    Λ = ∫₀^τ e^{As} G Gᵀ e^{Aᵀs} ds,

so that with b linear in time over the interval (first-order hold, 4.37)

    x(t+τ) = Φ x(t) + Γ b(t) + Υ (b(t+τ) − b(t)),   Cov = Φ P Φᵀ + Λ.

Γ and Υ are taken without the input matrix B so that any affine input term b
(B u plus constants) is handled the same way.  The integrals come from Van
Loan's block matrix exponentials (A.55–A.58) evaluated on τ/2ʲ, where the blocks
are benign even for stiff A, followed by j doubling steps (van Loan, 1978) that
only add positive semi-definite terms to Λ.  This keeps Λ accurate and positive
semi-definite for building models whose time constants span minutes to weeks.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

from .small import mm

#: Largest number of doublings: handles ‖A‖τ up to about 2⁴⁰.
MAX_DOUBLINGS = 40
TAYLOR_ORDER = 16


class Discretization(NamedTuple):
    """Φ, Γ, Υ and Λ of one interval (4.36, 4.39)."""

    transition: jnp.ndarray  # Φ
    input_gain: jnp.ndarray  # Γ (without B)
    ramp_gain: jnp.ndarray  # Υ (without B)
    noise_covariance: jnp.ndarray  # Λ


def _small_interval(A: jnp.ndarray, Q: jnp.ndarray, h: jnp.ndarray):
    """Φ, Γ, Γ₂ = τΥ and Λ on an interval with ‖A‖h ≤ 1/2, by their Taylor series (A.55–A.58).

    Van Loan's block exponentials, written out block by block: with X = Ah,

        Φ = Σ X^k/k!,   Γ = h Σ X^k/(k+1)!,   Γ₂ = h² Σ X^k/(k+2)!,
        Λ = h Σ N_k/(k+1)!  with N₀ = Q, N_k = X N_{k−1} + N_{k−1} Xᵀ,

    summed to k = TAYLOR_ORDER: the truncation error is of order (1/2)^K/K!
    relative (for Λ 1/(K+2)!), below double precision for K = 16.  Only n × n
    products: a ninth of the work of the 3n × 3n and 2n × 2n block exponentials,
    and about three fifths of their cost in a Hessian (``benchmarks/likelihood.py``).
    """
    n, order = A.shape[0], TAYLOR_ORDER
    X = A * h
    inverse_factorials = jnp.asarray([1.0 / math.factorial(k) for k in range(order + 3)])

    # A loop rather than unrolled products: the programs that differentiate this twice then
    # trace one step instead of TAYLOR_ORDER (a model's first fit would compile for longer).
    def term(k, sums):  # the k-th terms of Φ, Γ/h, Γ₂/h² and Λ/h
        power, phi, gamma, gamma2, N, lam = sums
        power = mm(X, power)
        XN = mm(X, N)
        N = XN + XN.T  # N stays symmetric: N Xᵀ = (X N)ᵀ
        return (power, phi + power * inverse_factorials[k], gamma + power * inverse_factorials[k + 1],
                gamma2 + power * inverse_factorials[k + 2], N, lam + N * inverse_factorials[k + 1])

    eye = jnp.eye(n)
    _, phi, gamma, gamma2, _, lam = jax.lax.fori_loop(1, order + 1, term, (eye, eye, eye, 0.5 * eye, Q, Q))
    lam = h * lam
    return phi, h * gamma, h * h * gamma2, 0.5 * (lam + lam.T)


def discretize(A: jnp.ndarray, Q: jnp.ndarray, tau: jnp.ndarray) -> Discretization:
    """Φ, Γ, Υ, Λ for drift matrix A, diffusion covariance Q = G Gᵀ and step τ ≥ 0."""
    tau = jnp.asarray(tau, dtype=jnp.float64)
    norm = jnp.max(jnp.sum(jnp.abs(A), axis=0)) * tau
    doublings = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.5)), 0, MAX_DOUBLINGS)
    doublings = jax.lax.stop_gradient(doublings)
    h = tau / 2.0**doublings
    phi, gamma, gamma2, lam = _small_interval(A, Q, h)

    def double(state):
        phi, gamma, gamma2, lam, h = state
        return (
            mm(phi, phi),
            gamma + mm(phi, gamma),
            gamma2 + h * gamma + mm(phi, gamma2),
            mm(mm(phi, lam), phi.T) + lam,
            2.0 * h,
        )

    # A branch per iteration keeps the work (and its reverse-mode cost) to the
    # doublings actually needed; most sub-sampled EKF intervals need none.
    def doubled(state):
        return jax.lax.fori_loop(
            0, MAX_DOUBLINGS, lambda i, st: jax.lax.cond(i < doublings, double, lambda x: x, st), state)

    state = jax.lax.cond(doublings > 0, doubled, lambda x: x, (phi, gamma, gamma2, lam, h))
    phi, gamma, gamma2, lam, _ = state
    safe_tau = jnp.where(tau > 0, tau, 1.0)
    # Υ = Γ₂/τ → τ/2·I as τ → 0: the limit keeps Υ's derivative in τ where a piece has length 0.
    ramp = jnp.where(tau > 0, gamma2 / safe_tau, 0.5 * tau * jnp.eye(A.shape[0]))
    return Discretization(phi, gamma, ramp, 0.5 * (lam + lam.T))


def discretize_each(A: jnp.ndarray, Q: jnp.ndarray, taus: jnp.ndarray) -> Discretization:
    """[`discretize()`][greyid.filters.discretize.discretize] for each of the steps ``taus`` (leading axis of the
    result).

    One step after the other rather than vectorized: the number of doublings
    then stays a scalar, so each step runs only the doublings it needs, and the
    zero-length steps that pad ``taus`` cost next to nothing: they take the
    second-order Taylor polynomials in τ, which are exactly (I, 0, 0, 0) at τ = 0
    and keep the first and second derivatives in τ (a delay's piece of length 0
    still moves with the delay: ∂Φ/∂τ = A there, not 0).
    """
    n = A.shape[0]
    eye = jnp.eye(n)

    def at_zero(A, Q, tau):
        AQ = mm(A, Q)
        return Discretization(eye + tau * A + 0.5 * tau**2 * mm(A, A), tau * eye + 0.5 * tau**2 * A,
                              0.5 * tau * eye + tau**2 / 6.0 * A, tau * Q + 0.5 * tau**2 * (AQ + AQ.T))

    return jax.lax.map(lambda tau: jax.lax.cond(tau > 0, discretize, at_zero, A, Q, tau), taus)


def stationary_covariance(A: jnp.ndarray, Q: jnp.ndarray) -> jnp.ndarray:
    """Solution P of A P + P Aᵀ + Q = 0 (stable A), by the Kronecker form."""
    n = A.shape[0]
    eye = jnp.eye(n)
    lyap = jnp.kron(eye, A) + jnp.kron(A, eye)
    P = jnp.linalg.solve(lyap, -Q.reshape(-1)).reshape(n, n)
    return 0.5 * (P + P.T)


class AffineStep(NamedTuple):
    """x(t+τ) = Φ x(t) + c, Cov = Φ P Φᵀ + Λ over one interval of a time-varying linear model."""

    transition: jnp.ndarray  # Φ
    offset: jnp.ndarray  # c
    noise_covariance: jnp.ndarray  # Λ


def time_varying_step(matrices, offset, t_prev, tau, u_prev, u_cur, foh, substeps: int) -> AffineStep:
    """Φ, c and Λ of dx = (A(t)x + b(t))dt + G(t)dω over [t_prev, t_prev + τ] (4.19–4.20).

    ``matrices(u, t) -> (A, G Gᵀ)`` and ``offset(u, t) -> b``.  The interval is
    cut into ``substeps`` pieces; on each, A and GGᵀ are frozen at its midpoint
    (the exponential midpoint rule, second order: the error falls fourfold per
    doubling of ``substeps``) and b is taken linear between the piece's ends, so
    each piece is discretized exactly as in [`discretize()`][greyid.filters.discretize.discretize].  The inputs are
    held (``foh`` = 0) or interpolated (``foh`` = 1) inside the interval.
    """
    h = tau / substeps
    du = (u_cur - u_prev) * foh

    def at(s):  # inputs and time at fraction s of the interval
        return u_prev + du * s, t_prev + tau * s

    def piece(j, state):
        phi_total, c, lam = state
        A, Q = matrices(*at((j + 0.5) / substeps))
        b_start, b_end = offset(*at(j / substeps)), offset(*at((j + 1.0) / substeps))
        disc = discretize(A, Q, h)
        c = mm(disc.transition, c) + mm(disc.input_gain, b_start) + mm(disc.ramp_gain, b_end - b_start)
        lam = mm(mm(disc.transition, lam), disc.transition.T) + disc.noise_covariance
        return mm(disc.transition, phi_total), c, 0.5 * (lam + lam.T)

    n = offset(u_prev, t_prev).shape[0]
    start = (jnp.eye(n), jnp.zeros(n), jnp.zeros((n, n)))
    return AffineStep(*jax.lax.fori_loop(0, substeps, piece, start))
