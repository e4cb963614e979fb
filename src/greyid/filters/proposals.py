"""Gaussian-filter proposals for the particle filter: each particle's last move drawn with an eye on y_k.

The bootstrap filter moves a particle by the dynamics alone, blind to the row's
observation; where the observation is sharp most moves land where p(y_k | x) is
negligible and the weights degenerate.  A guided filter draws the last move from
an approximation of p(x_k | x_{k−1}, y_k) instead (Doucet, Godsill & Andrieu 2000;
the EKF and UKF proposals of van der Merwe et al. 2001) and corrects the weight by
prior / proposal.

Each move is Gaussian in standard normal numbers w: x → m + C w, w ~ N(0, I) — the
exact transition (C the root of Λ, (4.36)–(4.39)), or each Euler–Maruyama sub-step
(C = G √h).  Working in w, not in x, keeps the densities proper where C is singular
(fewer noises than states).  A sub-step j of s looks ahead to t_k as Golightly &
Wilkinson's (2008) modified diffusion bridge does: the particle would reach
x_k ≈ e + C w + D v, with e = x + f·(t_k − t_j) (the drift held), D = G √(t_k − t_j − h)
the later sub-steps' noise and v ~ N(0, I).  The observation is linearised in w,

    y ≈ ŷ + B w + ε,  ε ~ N(0, Ω),

* ``"ekf"``: about w = v = 0 — ŷ = E[y | e], B = H C with H = ∂E[y | x]/∂x at e,
  Ω = diag Var[y | e] + H D (H D)ᵀ (the family's conditional mean and variance: a
  count's too);
* ``"ukf"``: by statistical linear regression on the cubature points ±√q e_i of
  (w, v) (Arasaratnam & Haykin 2009: 2q points of equal positive weight) — ŷ and B
  the points' mean and covariance with w, Ω what w leaves of their covariance plus
  the mean conditional variance.

The proposal is then the exact posterior of w in that linear Gaussian model,
N(μ, P⁻¹) with P = I + BᵀΩ⁻¹B and μ = P⁻¹BᵀΩ⁻¹(y − ŷ), and a draw w = μ + P^{-1/2} e from the
row's fixed normals e changes the particle's log-weight by

    log N(w; 0, I) − log N(w; μ, P⁻¹) = −½ wᵀw + ½ eᵀe − log|L_P|.

For a linear model with Gaussian observations the ``"ekf"`` proposal is the optimal
one (the weights no longer depend on the draw); for any model the estimate stays
unbiased, only its variance depends on how good the proposal is.  Unobserved
outputs, and outputs without a finite variance (Student-t with ≤ 2 degrees of
freedom), do not guide the draw.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

from . import small

BOOTSTRAP, EKF_PROPOSAL, UKF_PROPOSAL = "bootstrap", "ekf", "ukf"
#: The particle filter's proposals: the dynamics alone, or guided by a Gaussian filter's update.
PROPOSALS = (BOOTSTRAP, EKF_PROPOSAL, UKF_PROPOSAL)


class Linearised(NamedTuple):
    """y ≈ y_hat + B w + ε, ε ~ N(0, Omega), for one particle's last move."""

    y_hat: jnp.ndarray  # (m,)
    B: jnp.ndarray  # (m, d)
    Omega: jnp.ndarray  # (m, m)


def linearise(kind: str, conditional: Callable, end, scale, rest=None) -> Linearised:
    """The observation's linearisation in w for x_k = end + scale · w + rest · v, w and v ~ N(0, I)
    (``rest`` None: no v), see the module doc.

    ``conditional(x) -> (E[y | x], Var[y | x])`` gives each output's mean and variance.
    """
    if kind == EKF_PROPOSAL:
        y_hat, variance = conditional(end)
        H = jax.jacfwd(lambda x: conditional(x)[0])(end)
        Omega = jnp.diag(variance)
        if rest is not None:
            Omega = Omega + (H @ rest) @ (H @ rest).T
        return Linearised(y_hat, H @ scale, Omega)
    d = scale.shape[1]
    joint = scale if rest is None else jnp.concatenate([scale, rest], axis=1)
    size = joint.shape[1]
    points = jnp.sqrt(size) * jnp.concatenate([jnp.eye(size), -jnp.eye(size)])  # (2D, D)
    values, variances = jax.vmap(lambda p: conditional(end + joint @ p))(points)
    y_hat = jnp.mean(values, axis=0)
    spread = values - y_hat
    B = spread.T @ points[:, :d] / (2 * size)  # Cov(y, w), w's covariance being I
    Omega = spread.T @ spread / (2 * size) - B @ B.T + jnp.diag(jnp.mean(variances, axis=0))
    return Linearised(y_hat, B, 0.5 * (Omega + Omega.T))


def guided_draw(linearised: Linearised, y, mask, normals):
    """``(w, log_correction)``: w from N(μ, P⁻¹) by the normals e, and log N(w; 0, I) − log q(w)."""
    y_hat, B, Omega = linearised
    variance = jnp.diag(Omega)
    guiding = (mask > 0) & jnp.isfinite(variance) & (variance > 0)
    both = guiding[:, None] & guiding[None, :]
    Omega = jnp.where(both, Omega, jnp.eye(Omega.shape[0]))
    B = jnp.where(guiding[:, None], B, 0.0)
    residual = jnp.where(guiding, y - y_hat, 0.0)
    L = small.cholesky(Omega)
    B_white, r_white = small.solve_lower(L, B), small.solve_lower(L, residual)
    precision = jnp.eye(B.shape[1]) + B_white.T @ B_white
    L_P = small.cholesky(precision)
    mu = small.cho_solve(L_P, B_white.T @ r_white)
    w = mu + small.solve_upper_transposed(L_P, normals)
    log_correction = -0.5 * w @ w + 0.5 * normals @ normals - jnp.sum(jnp.log(jnp.diag(L_P)))
    return w, log_correction
