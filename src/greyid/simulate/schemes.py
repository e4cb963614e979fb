"""Time-discrete approximations of Itô SDEs dx = f dt + G dω (section 2.5).

* Euler–Maruyama (2.41): strong order 1/2, weak order 1.
* Milstein (2.46–2.47): strong order 1 for commutative noise; with several
  non-commuting noise terms the Lévy areas are neglected (order 1/2 then).
* Heun (2.49–2.50): converges to the Stratonovich solution, i.e. to the Itô
  equation with drift f + ½ c, c_i = Σ_jk G_kj ∂G_ij/∂x_k (2.48, λ = ½).

The model is read as an Itô equation (``calculus="ito"``): Heun is then given
the drift f − ½ c so that it converges to the Itô solution.  With
``calculus="stratonovich"`` the model is read as a Stratonovich equation and
Euler and Milstein get the drift f + ½ c instead.
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

SCHEMES = ("euler", "milstein", "heun")
CALCULI = ("ito", "stratonovich")


def _directional(diffusion, x, u, t, theta):
    """D[:, :, j] = (∂G/∂x) G[:, j], the derivatives L^j G of the Milstein scheme."""
    g = diffusion(x, u, t, theta)
    cols = jax.vmap(lambda v: jax.jvp(lambda z: diffusion(z, u, t, theta), (x,), (v,))[1], in_axes=1, out_axes=2)(g)
    return g, cols


def _correction(diffusion, x, u, t, theta):
    """c_i = Σ_j (L^j G)_{ij}, the Itô–Stratonovich drift difference times 2."""
    _, d = _directional(diffusion, x, u, t, theta)
    return jnp.einsum("ijj->i", d) if d.shape[1] else jnp.zeros(x.shape[0])


def make_step(drift, diffusion, method: str, calculus: str):
    """One step x_i → x_{i+1} of the chosen scheme, ``step(x, u, t, h, dW, theta)``."""
    if method not in SCHEMES:
        raise ValueError(f"unknown simulation method '{method}'; use one of {list(SCHEMES) + ['exact']}")
    if calculus not in CALCULI:
        raise ValueError(f"unknown calculus '{calculus}'; use 'ito' or 'stratonovich'")

    def drift_ito(x, u, t, theta):
        if calculus == "stratonovich":
            return drift(x, u, t, theta) + 0.5 * _correction(diffusion, x, u, t, theta)
        return drift(x, u, t, theta)

    def drift_strat(x, u, t, theta):
        if calculus == "ito":
            return drift(x, u, t, theta) - 0.5 * _correction(diffusion, x, u, t, theta)
        return drift(x, u, t, theta)

    def euler(x, u, t, h, dW, theta):
        return x + drift_ito(x, u, t, theta) * h + diffusion(x, u, t, theta) @ dW

    def milstein(x, u, t, h, dW, theta):
        g, d = _directional(diffusion, x, u, t, theta)
        m = dW.shape[0]
        # ∫∫ dW_j dW_l ≈ ½(ΔW_j ΔW_l − δ_jl h) (2.47), exact for j = l.
        double = 0.5 * (jnp.outer(dW, dW) - h * jnp.eye(m))
        return x + drift_ito(x, u, t, theta) * h + g @ dW + jnp.einsum("ilj,jl->i", d, double)

    def heun(x, u, t, h, dW, theta):
        a0, g0 = drift_strat(x, u, t, theta), diffusion(x, u, t, theta)
        pred = x + a0 * h + g0 @ dW
        a1, g1 = drift_strat(pred, u, t + h, theta), diffusion(pred, u, t + h, theta)
        return x + 0.5 * (a0 + a1) * h + 0.5 * (g0 + g1) @ dW

    return {"euler": euler, "milstein": milstein, "heun": heun}[method]


def make_integrator(drift, diffusion, method: str, calculus: str = "ito"):
    """``integrate(theta, x0, times, inputs, increments) -> states (K+1, n)``.

    ``times`` is the grid (K+1,), ``inputs`` the inputs at the grid points held
    over each step (K+1, nu), ``increments`` the Wiener increments (K, m).
    """
    step = make_step(drift, diffusion, method, calculus)

    def integrate(theta, x0, times, inputs, increments):
        def body(x, k):
            x_next = step(x, inputs[k], times[k], times[k + 1] - times[k], increments[k], theta)
            return x_next, x_next

        _, xs = jax.lax.scan(body, x0, jnp.arange(increments.shape[0]))
        return jnp.concatenate([x0[None, :], xs], axis=0)

    return integrate
