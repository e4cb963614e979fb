"""The exact Fisher information of a planned experiment on a linear model, in O(N).

For a linear model the observations are jointly Gaussian and so are the
innovations, whence (4.32–4.33, 6.29)

    F_ij = Σ_k E[∂_iε_kᵀ S_k⁻¹ ∂_jε_k] + ½ tr(S_k⁻¹ ∂_iS_k S_k⁻¹ ∂_jS_k).

S_k and its derivatives do not depend on the data.  The sensitivities ∂_iε_k
do: they are affine in the filter's state x̂ and its sensitivities ∂_ix̂, which
are affine in the past observations.  So the true state x, the filter's x̂ and
the p sensitivities ∂x̂ form one linear system driven by the process and
measurement noise; its mean and covariance propagate exactly, step by step, and
E[∂_iεᵀS⁻¹∂_jε] = μ_iᵀS⁻¹μ_j + tr(S⁻¹ Cov(∂_jε, ∂_iε)).  Nothing is sampled.

The filter is the exact Kalman filter of [`greyid.filters.kalman`][greyid.filters.kalman] (the one
estimation uses); its per-step affine maps are taken from it by automatic
differentiation, so the initial transient, irregular sampling, zero- and
first-order holds and missing data are handled as the filter handles them.
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import structure_program
from ..filters.driver import filter_steps
from ..filters.protocol import KALMAN, FilterInputs, FilterOptions
from ..filters.updates import GaussianState
from ..filters.predictors import linearized_observation


def _observation_noise(structure, x, u, t, theta):
    full = structure.observation_covariance
    if full is not None:
        return full(x, u, t, theta)
    return jnp.diag(structure.observation_variance(x, u, t, theta))


def make_exact_information(structure, index: tuple[int, ...]):
    """The function ``information(theta, data) -> F`` (p × p, natural parameters θ[index])."""
    build = filter_steps(structure, FilterOptions(KALMAN, form="plain"))
    n, m, p = structure.n_states, len(structure.output_names), len(index)
    h = structure.observation

    def information(theta, data: FilterInputs):
        directions = jnp.eye(theta.shape[0])[jnp.array(index)]  # tangents along the free parameters
        truth = build(theta, data)
        x0, P0 = truth.initial
        _, (dx0, dP0) = jax.vmap(lambda e: jax.jvp(lambda th: build(th, data).initial, (theta,), (e,)),
                                 out_axes=(None, 0))(directions)
        size = n * (p + 2)  # z = (x, x̂, ∂_1x̂ … ∂_px̂)
        mean = jnp.concatenate([x0, x0, dx0.reshape(-1)])
        cov = jnp.zeros((size, size)).at[:n, :n].set(P0)
        zero_x, zero_y = jnp.zeros(n), jnp.zeros(m)

        # With delayed inputs the rows themselves depend on θ (the extended inputs and the
        # pieces move with τ): their tangents go into each step beside θ's.
        def moving(rows):
            return rows.u_prev, rows.u_cur, rows.pieces

        moving_dot = None
        if structure.delays:
            _, moving_dot = jax.vmap(lambda e: jax.jvp(lambda th: moving(build(th, data).rows), (theta,), (e,)),
                                     out_axes=(None, 0))(directions)
            moving_dot = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, 1), moving_dot)

        def step(carry, inputs):
            row, row_dot = inputs
            mean, cov, P, dP, F = carry

            def filter_step(th, x_hat, P_cov, y, moved):
                parts = build(th, data)
                at = row._replace(u_prev=moved[0], u_cur=moved[1], pieces=moved[2])
                predicted, _ = parts.predict(GaussianState(x_hat, P_cov), at)
                upd, _ = parts.update(predicted, at._replace(y=y))
                return upd.mean, upd.covariance, upd.innovation, upd.innovation_covariance

            def with_tangents(x_hat, y):
                """The filter step and its p tangents (with ∂x̂ = 0: that part is added below)."""
                if row_dot is None:
                    def along(e, dP_j):
                        return jax.jvp(lambda th, P_cov: filter_step(th, x_hat, P_cov, y, moving(row)),
                                       (theta, P), (e, dP_j))

                    return jax.vmap(along, out_axes=(None, 0))(directions, dP)

                def along_moving(e, dP_j, dm_j):
                    return jax.jvp(lambda th, P_cov, m: filter_step(th, x_hat, P_cov, y, m),
                                   (theta, P, moving(row)), (e, dP_j, dm_j))

                return jax.vmap(along_moving, out_axes=(None, 0))(directions, dP, row_dot)

            def random_part(x_hat, y):
                (x_new, _, eps, _), (dx_new, _, d_eps, _) = with_tangents(x_hat, y)
                return x_new, eps, dx_new, d_eps

            (_, P_new, _, S), (_, dP_new, _, dS) = with_tangents(zero_x, zero_y)
            x_c, eps_c, dx_c, deps_c = random_part(zero_x, zero_y)
            # ∂/∂x̂ and ∂/∂y of x̂', ε, ∂x̂' and ∂ε (exact: the step is affine in both).
            (A_x, A_y), (E_x, _), (B_x, B_y), (F_x, F_y) = jax.jacfwd(random_part, argnums=(0, 1))(zero_x, zero_y)

            # The true system over the interval, x' = Φx + c + w, and y = Cx' + d + v.
            (c, Lam), Phi = truth.predict(GaussianState(zero_x, jnp.zeros((n, n))), row)
            d, C = linearized_observation(h, zero_x, row.u_cur, row.t, theta)
            R = _observation_noise(structure, zero_x, row.u_cur, row.t, theta)
            y0 = C @ c + d
            CPhi = C @ Phi

            # z' = T z + t0 + G (w, v), and the innovations' sensitivities ∂ε = K z + k0 + L (w, v).
            T = jnp.zeros((size, size)).at[:n, :n].set(Phi)
            T = T.at[n:2 * n, :n].set(A_y @ CPhi).at[n:2 * n, n:2 * n].set(A_x)
            G = jnp.zeros((size, n + m)).at[:n, :n].set(jnp.eye(n))
            G = G.at[n:2 * n, :n].set(A_y @ C).at[n:2 * n, n:].set(A_y)
            t0 = jnp.concatenate([c, x_c + A_y @ y0, (dx_c + jnp.einsum("jab,b->ja", B_y, y0)).reshape(-1)])
            K = jnp.zeros((p * m, size))
            L = jnp.zeros((p * m, n + m))
            for j in range(p):
                rows = slice(2 * n + j * n, 2 * n + (j + 1) * n)
                T = T.at[rows, :n].set(B_y[j] @ CPhi).at[rows, n:2 * n].set(B_x[j]).at[rows, rows].set(A_x)
                G = G.at[rows, :n].set(B_y[j] @ C).at[rows, n:].set(B_y[j])
                out = slice(j * m, (j + 1) * m)
                K = K.at[out, :n].set(F_y[j] @ CPhi).at[out, n:2 * n].set(F_x[j]).at[out, rows].set(E_x)
                L = L.at[out, :n].set(F_y[j] @ C).at[out, n:].set(F_y[j])
            k0 = (deps_c + jnp.einsum("jab,b->ja", F_y, y0)).reshape(-1)
            Q = jnp.zeros((n + m, n + m)).at[:n, :n].set(Lam).at[n:, n:].set(R)

            d_mean = (K @ mean + k0).reshape(p, m)
            d_cov = (K @ cov @ K.T + L @ Q @ L.T).reshape(p, m, p, m)
            S_inv = jnp.linalg.inv(S)
            W = jnp.einsum("ab,jbc->jac", S_inv, dS)  # S⁻¹ ∂_jS
            F = (F + d_mean @ S_inv @ d_mean.T + jnp.einsum("ab,iajb->ij", S_inv, d_cov)
                 + 0.5 * jnp.einsum("iab,jba->ij", W, W))
            return (T @ mean + t0, T @ cov @ T.T + G @ Q @ G.T, P_new, dP_new, F), None

        carry = (mean, cov, P0, dP0, jnp.zeros((p, p)))
        (_, _, _, _, F), _ = jax.lax.scan(step, carry, (truth.rows, moving_dot))
        return 0.5 * (F + F.T)

    return information


def exact_information(structure, theta: np.ndarray, data: FilterInputs, index: tuple[int, ...]) -> np.ndarray:
    """F for the parameters θ[index] of a linear model on one prepared plan (see the module doc)."""
    program = structure_program(structure, ("exact_information", tuple(index)),
                                lambda: make_exact_information(structure, tuple(index)))
    return np.asarray(program(jnp.asarray(theta, dtype=jnp.float64), data))
