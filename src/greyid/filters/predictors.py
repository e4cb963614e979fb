"""Time updates: from (x_{k-1|k-1}, P_{k-1|k-1}) to (x_{k|k-1}, P_{k|k-1}).

* linear: the exact discretization (4.34)–(4.39) of a linear model;
* extended: the sub-sampled local linearization of appendix A.4 (A.46–A.50),
  exact for linear models;
* unscented: the moment equations (4.19)–(4.20) with the expectations of
  f and G Gᵀ taken over sigma points, i.e. the statistically linearized drift
  (4.47)–(4.48), integrated with the same exponential sub-steps as the EKF, so
  that it too is exact for linear models and stable for stiff ones.

Inputs are held (hold="zoh") or interpolated linearly (hold="foh", 4.37); the
``foh`` flag is 0.0 or 1.0 so that both share one compiled function.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

from . import small
from .discretize import discretize
from .updates import Update, from_matrix, gaussian_term, propagate, symmetrize, to_matrix


class Interval(NamedTuple):
    """What a time update needs to know of one sampling interval."""

    t_prev: jnp.ndarray
    dt: jnp.ndarray
    u_prev: jnp.ndarray
    u_cur: jnp.ndarray
    foh: jnp.ndarray


def linear_predict(mean, cov, disc, b_prev, b_cur, foh, form):
    """x = Φx + Γb_k + Υ(b_{k+1} − b_k), P = ΦPΦᵀ + Λ (4.34, 4.35, 4.38)."""
    mean = (small.mm(disc.transition, mean) + small.mm(disc.input_gain, b_prev)
            + foh * small.mm(disc.ramp_gain, b_cur - b_prev))
    return mean, propagate(cov, disc.transition, disc.noise_covariance, form)


def _input_rate(drift, x, u, t, theta, u_rate):
    """∂f/∂u · du/dt + ∂f/∂t, the drift's change along the interpolated inputs and in time."""
    t = jnp.asarray(t, dtype=jnp.float64)
    return jax.jvp(lambda v, s: drift(x, v, s, theta), (u, t), (u_rate, jnp.ones_like(t)))[1]


def second_order_term(fn, x, P, *args):
    """½ Σ_ij P_ij ∂²fn/∂x_i∂x_j, the bias correction of (4.58) and (4.60)."""
    hess = jax.hessian(fn, argnums=0)(x, *args)
    return 0.5 * jnp.einsum("kij,ij->k", hess, P)


def extended_predict(mean, cov, interval: Interval, theta, drift, diffusion, substeps: int, form: str,
                     bias_correction: bool = False, noise_correction: bool = False):
    """Sub-sampled local linearization (A.46–A.50); returns mean, cov and the interval's Φ.

    With ``bias_correction`` the mean follows (4.58), f + ½ P ∂²f/∂x², while the
    covariance keeps the first-order equation (the "first order filter with bias
    correction" of section 4.2.2).  With ``noise_correction`` the covariance
    follows (4.59) with the second-order expectation of GGᵀ, GGᵀ + ½ P ∂²(GGᵀ)/∂x²
    (the second-order filters; exact for a diffusion linear in x).
    """
    h = interval.dt / substeps
    du = (interval.u_cur - interval.u_prev) * interval.foh
    u_rate = jnp.where(interval.dt > 0, du / jnp.where(interval.dt > 0, interval.dt, 1.0), 0.0)
    jac = jax.jacfwd(drift, argnums=0)

    def substep(j, state):
        x, c, phi_total = state
        t = interval.t_prev + j * h
        u = interval.u_prev + du * (j / substeps)
        f = drift(x, u, t, theta)
        if bias_correction:
            f = f + second_order_term(drift, x, to_matrix(c, form), u, t, theta)
        g = diffusion(x, u, t, theta)
        Q = small.mm(g, g.T)
        if noise_correction:
            def noise(xx):
                gg = diffusion(xx, u, t, theta)
                return (gg @ gg.T).reshape(-1)

            Q = Q + second_order_term(noise, x, to_matrix(c, form)).reshape(Q.shape)
        disc = discretize(jac(x, u, t, theta), Q, h)
        # x_{j+1} = x_j + Γ f_j + ∫(h−s)e^{As}ds (∂f/∂u u̇ + ∂f/∂t)  (A.49 with the input ramp)
        x = x + small.mm(disc.input_gain, f) + h * small.mm(disc.ramp_gain, _input_rate(drift, x, u, t, theta, u_rate))
        c = propagate(c, disc.transition, disc.noise_covariance, form)
        return x, c, small.mm(disc.transition, phi_total)

    n = mean.shape[0]
    return jax.lax.fori_loop(0, substeps, substep, (mean, cov, jnp.eye(n)))


class SigmaWeights(NamedTuple):
    mean: jnp.ndarray
    cov: jnp.ndarray
    spread: float
    #: A negative covariance weight (the central point's): the sigma points' joint covariance need
    #: not be positive semi-definite, and the update's may go negative (see moment_update).
    negative: bool = False


def sigma_weights(n: int, alpha: float, beta: float, kappa: float) -> SigmaWeights:
    """Weights of the scaled unscented transform with 2n+1 points."""
    lam = alpha**2 * (n + kappa) - n
    wm = jnp.full(2 * n + 1, 1.0 / (2.0 * (n + lam)))
    wc = wm
    wm = wm.at[0].set(lam / (n + lam))
    wc = wc.at[0].set(lam / (n + lam) + 1.0 - alpha**2 + beta)
    central = lam / (n + lam) + 1.0 - alpha**2 + beta
    return SigmaWeights(wm, wc, float(jnp.sqrt(n + lam)), bool(central < 0 or n + lam < 0))


def sigma_points(mean, P, weights: SigmaWeights):
    # The guarded factor: a known initial state or a noise-free state (P singular) gives sigma
    # points that coincide in those directions instead of NaN.
    L = small.cholesky(0.5 * (P + P.T))
    offsets = weights.spread * L.T  # rows are scaled columns of L
    return jnp.concatenate([mean[None, :], mean + offsets, mean - offsets], axis=0)


def statistical_linearization(P, cross, jacobian):
    """A = Cov(x, f) P⁻¹ (4.48); along a direction of the state that P does not spread (zero
    variance: a known or noise-free state) the sigma points say nothing, and A takes the Jacobian
    there, the limit of the statistical slope as the spread goes to 0."""
    P = 0.5 * (P + P.T)
    diagonal = jnp.diag(P)
    flat = diagonal <= small.PIVOT_ROUNDING * jnp.max(jnp.abs(diagonal))
    scale = jnp.where(flat, 1e-12 * jnp.max(jnp.abs(diagonal)) + 1e-300, 0.0)
    # The Jacobian only where some direction is flat (a known state, a noise-free one).
    J = jax.lax.cond(jnp.any(flat), jacobian, lambda: jnp.zeros((cross.shape[1], P.shape[0])))
    return jnp.linalg.solve(P + jnp.diag(scale), cross + scale[:, None] * J.T).T


def unscented_predict(mean, cov, interval: Interval, theta, drift, diffusion, substeps: int, form: str,
                      weights: SigmaWeights):
    """Sigma-point moment propagation with statistically linearized drift (4.47–4.53)."""
    h = interval.dt / substeps
    du = (interval.u_cur - interval.u_prev) * interval.foh
    u_rate = jnp.where(interval.dt > 0, du / jnp.where(interval.dt > 0, interval.dt, 1.0), 0.0)

    def substep(j, state):
        x, c, phi_total = state
        t = interval.t_prev + j * h
        u = interval.u_prev + du * (j / substeps)
        P = to_matrix(c, form)
        X = sigma_points(x, P, weights)
        F = jax.vmap(lambda xi: drift(xi, u, t, theta))(X)
        f_mean = weights.mean @ F
        cross = (X - x).T @ (weights.cov[:, None] * (F - f_mean))  # Cov(x, f)
        A = statistical_linearization(P, cross, lambda: jax.jacfwd(drift, argnums=0)(x, u, t, theta))  # (4.48)
        Gs = jax.vmap(lambda xi: diffusion(xi, u, t, theta))(X)
        Q = jnp.einsum("i,ijk,ilk->jl", weights.mean, Gs, Gs)
        rate = weights.mean @ jax.vmap(lambda xi: _input_rate(drift, xi, u, t, theta, u_rate))(X)
        disc = discretize(A, Q, h)
        x = x + disc.input_gain @ f_mean + h * disc.ramp_gain @ rate
        c = from_matrix(disc.transition @ P @ disc.transition.T + disc.noise_covariance, form)
        return x, c, disc.transition @ phi_total

    n = mean.shape[0]
    return jax.lax.fori_loop(0, substeps, substep, (mean, cov, jnp.eye(n)))


def unscented_update(mean, cov, y, mask, u, t, theta, observation, variance, form, weights: SigmaWeights):
    """Unscented measurement update: ŷ, R and the state–output cross covariance from sigma points.

    P⁺ = P − K R Kᵀ subtracts, as every unscented update does; in the square-root
    form P⁺ is refactorised by the guarded Cholesky ([`small.cholesky()`][greyid.filters.small.cholesky]).
    """
    P = to_matrix(cov, form)
    X = sigma_points(mean, P, weights)
    Y = jax.vmap(lambda xi: observation(xi, u, t, theta))(X)
    y_pred = weights.mean @ Y
    dY = Y - y_pred
    S = variance  # the outputs' noise: variances (a vector) or a full covariance matrix
    noise = jnp.diag(S) if S.ndim == 1 else S
    R = dY.T @ (weights.cov[:, None] * dY) + noise
    cross = (X - mean).T @ (weights.cov[:, None] * dY)
    return moment_update(mean, P, y, mask, y_pred, cross, R, form, noise, weights.negative), y_pred


def moment_update(mean, P, y, mask, y_pred, cross, R, form, noise, guard: bool) -> Update:
    """The update from the first two moments of the output: ŷ, R = Cov(y) and Cov(x, y) (4.21–4.22
    with Gaussian approximations); unobserved elements are masked out.

    P − K R Kᵀ is a covariance only if the moments are those of a joint distribution, which the
    approximations do not guarantee: the truncated second-order filter's R neglects fourth moments
    and can fall below Cov(x, y)ᵀ P⁻¹ Cov(x, y), giving a negative variance.  Where the plain form
    is not positive semi-definite the Joseph form (I − K H) P (I − K H)ᵀ + K S Kᵀ, with
    H = Cov(x, y)ᵀ P⁻¹ and the outputs' noise S, replaces it (never negative), and the update says
    so (``guarded``).  ``guard`` says whether the approximation can go negative at all (the
    Gaussian second-order filter and the UKF with non-negative weights cannot): the check costs
    an eigen-decomposition per step, and is left out where it cannot act.
    """
    m = mask
    R = R * m[:, None] * m[None, :] + jnp.diag(1.0 - m)
    cross = cross * m[None, :]
    innovation = jnp.where(m > 0, y - y_pred, 0.0)
    chol_R = jnp.linalg.cholesky(symmetrize(R))
    gain = jax.scipy.linalg.cho_solve((chol_R, True), cross.T).T
    new_mean = mean + gain @ innovation
    new_P = symmetrize(P - gain @ R @ gain.T)
    terms = gaussian_term(innovation, chol_R, m)
    if not guard:
        return Update(new_mean, from_matrix(new_P, form), innovation, R, terms)
    P = symmetrize(P)
    lowest = jnp.linalg.eigvalsh(new_P)[0]
    negative = lowest < -1e-10 * jnp.maximum(jnp.max(jnp.abs(jnp.diag(P))), 1e-300)
    n = P.shape[0]
    H = statistical_linearization(P, cross, lambda: jnp.zeros((cross.shape[1], n)))  # Cov(x, y)ᵀ P⁻¹
    I_KH = jnp.eye(n) - gain @ H
    joseph = symmetrize(I_KH @ P @ I_KH.T + gain @ (noise * m[:, None] * m[None, :]) @ gain.T)
    new_P = jnp.where(negative, joseph, new_P)
    return Update(new_mean, from_matrix(new_P, form), innovation, R, terms, jnp.where(negative, 1.0, 0.0))


def linearized_observation(observation: Callable, x, u, t, theta):
    """h(x) and C = ∂h/∂x (A.41)."""
    return observation(x, u, t, theta), jax.jacfwd(observation, argnums=0)(x, u, t, theta)


def second_order_update(mean, cov, y, mask, u, t, theta, observation, noise, form, gaussian: bool):
    """The measurement update of the modified second-order filters (section 4.2.2).

    With δ = x − x̂ and h expanded to second order, ŷ = h + ½b, b_k = tr(∂²h_k P)
    (4.60), Cov(x, y) = P Hᵀ (odd moments vanish), and
    Cov(y) = H P Hᵀ + S + ¼(E[δᵀh_k''δ δᵀh_l''δ] − b_k b_l): the truncated filter
    neglects the fourth moments (−¼ b bᵀ), the Gaussian one takes them from (4.57)
    (+½ tr(h_k'' P h_l'' P)).  The covariance is then updated from these moments
    (4.61–4.62 with b₁ = 0, the "modified" filters).
    """
    P = to_matrix(cov, form)
    h_value, H = linearized_observation(observation, mean, u, t, theta)
    hess = jax.hessian(observation, argnums=0)(mean, u, t, theta)  # (s, n, n)
    b = jnp.einsum("kij,ji->k", hess, P)
    y_pred = h_value + 0.5 * b
    if gaussian:
        HP = jnp.einsum("kij,jl->kil", hess, P)
        fourth = 0.5 * jnp.einsum("kij,lji->kl", HP, HP)
    else:
        fourth = -0.25 * jnp.outer(b, b)
    S = noise if noise.ndim == 2 else jnp.diag(noise)
    R = H @ P @ H.T + S + fourth
    # The truncated filter's R leaves out fourth moments and can fall below H P Hᵀ + S: guarded.
    return moment_update(mean, P, y, mask, y_pred, P @ H.T, R, form, S, guard=not gaussian), y_pred
