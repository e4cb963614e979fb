"""Information per sample in the frequency domain (6.47–6.49, 6.76–6.81 generalised).

For a linear time-invariant model sampled every τ with the input held between
samples, the stationary Kalman filter gives the innovations form

    y_k = G₁(q) u_k + G₂(q) ε_k,   ε_k white with covariance Σ,

G₁(z) = C(zI − Φ)⁻¹Γ + D and G₂(z) = I + C(zI − Φ)⁻¹K (K the stationary
predictor gain; the sampled form of (6.76–6.81), for n states and several
outputs).  Per sample, the information of a long experiment is

    M = M̄_c + Σ_l P_l M_u(ω_l),   M_u(ω) = Re[W(ω)ᴴ Σ⁻¹ W(ω)],  W = G₂⁻¹ ∂G₁/∂θ at z = e^{iωτ},

for an input of sinusoids of powers P_l at angular frequencies ω_l (6.47–6.48),
and M̄_c = ½ tr(Σ⁻¹∂Σ Σ⁻¹∂Σ) + (1/2π)∮ tr(Σ⁻¹ H_j Σ H_iᴴ), H_i = G₂⁻¹∂_iG₂, the
part no input changes (6.49).  Derivatives are exact (automatic
differentiation through the discretisation and the Riccati iteration).
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ..runtime.jit import jit
from ..errors import ModelError
from ..filters.discretize import discretize

#: Iterations of the Riccati recursion towards its stationary solution.
RICCATI_STEPS = 400
#: Points on the unit circle for the input-independent part's integral.
CIRCLE_POINTS = 256


def _programs(structure, input_index: int, index: tuple[int, ...]):
    """``(input_information(theta, tau, omegas), noise_information(theta, tau))``, compiled once."""
    key = ("frequency_information", input_index, index)
    if key in structure.cache:
        return structure.cache[key]
    n, nu = structure.n_states, len(structure.input_names)
    f, h = structure.drift, structure.observation
    zeros_x, zeros_u, t0 = np.zeros(n), np.zeros(nu), 0.0
    selected = jnp.array(index)

    def innovations_form(theta, tau):
        A = jax.jacfwd(f, argnums=0)(zeros_x, zeros_u, t0, theta)
        B = jax.jacfwd(f, argnums=1)(zeros_x, zeros_u, t0, theta)[:, input_index]
        C = jax.jacfwd(h, argnums=0)(zeros_x, zeros_u, t0, theta)
        D = jax.jacfwd(h, argnums=1)(zeros_x, zeros_u, t0, theta)[:, input_index]
        g = structure.diffusion(zeros_x, zeros_u, t0, theta)
        full = structure.observation_covariance
        R = (full(zeros_x, zeros_u, t0, theta) if full is not None
             else jnp.diag(structure.observation_variance(zeros_x, zeros_u, t0, theta)))
        disc = discretize(A, g @ g.T, tau)
        Phi, Gamma, Lam = disc.transition, disc.input_gain @ B, disc.noise_covariance

        def riccati(P, _):
            S = C @ P @ C.T + R
            K = Phi @ P @ C.T @ jnp.linalg.inv(S)
            return Phi @ P @ Phi.T + Lam - K @ S @ K.T, None

        P, _ = jax.lax.scan(riccati, Lam, None, length=RICCATI_STEPS)
        S = C @ P @ C.T + R
        return Phi, Gamma, C, D, Phi @ P @ C.T @ jnp.linalg.inv(S), S

    def transfer(theta_free, theta, tau, z):
        full = theta.at[selected].set(theta_free)
        Phi, Gamma, C, D, K, S = innovations_form(full, tau)
        resolvent = jnp.linalg.inv(z * jnp.eye(n) - Phi)
        G1 = C @ resolvent @ Gamma + D
        G2 = jnp.eye(C.shape[0]) + C @ resolvent @ K
        return G1, G2, S

    def split(fun):
        """∂fun/∂θ_free of a complex-valued fun, through its real and imaginary parts."""
        def parts(x, *args):
            out = fun(x, *args)
            return jnp.real(out), jnp.imag(out)

        def jac(x, *args):
            re, im = jax.jacfwd(parts)(x, *args)
            return re + 1j * im

        return jac

    def input_information(theta, tau, omegas):
        free = theta[selected]

        def at(omega):
            z = jnp.exp(1j * omega * tau)
            _, G2, S = transfer(free, theta, tau, z)
            dG1 = split(lambda x: transfer(x, theta, tau, z)[0])(free)  # (m, p)
            W = jnp.linalg.solve(G2, dG1)
            return jnp.real(W.conj().T @ jnp.linalg.solve(S, W))

        return jax.vmap(at)(omegas)

    def noise_information(theta, tau):
        free = theta[selected]
        S_of = lambda x: transfer(x, theta, tau, 1.0 + 0j)[2]  # noqa: E731
        S = S_of(free)
        dS = jnp.moveaxis(jax.jacfwd(S_of)(free), -1, 0)  # (p, m, m)
        W = jnp.einsum("ab,jbc->jac", jnp.linalg.inv(S), dS)
        part = 0.5 * jnp.einsum("iab,jba->ij", W, W)

        def at(omega):
            z = jnp.exp(1j * omega)
            _, G2, _ = transfer(free, theta, tau, z)
            dG2 = jnp.moveaxis(split(lambda x: transfer(x, theta, tau, z)[1])(free), -1, 0)  # (p, m, m)
            H = jnp.linalg.solve(G2[None], dG2)
            S_inv = jnp.linalg.inv(S)
            return jnp.real(jnp.einsum("ab,jbc,cd,ida->ij", S_inv, H, S, H.conj().transpose(0, 2, 1)))

        circle = 2 * jnp.pi * jnp.arange(CIRCLE_POINTS) / CIRCLE_POINTS
        return part + jnp.mean(jax.vmap(at)(circle), axis=0)

    structure.cache[key] = (jit(input_information), jit(noise_information),
                            jit(jax.vmap(input_information, in_axes=(0, None, None))),
                            jit(jax.vmap(noise_information, in_axes=(0, None))))
    return structure.cache[key]


def _setup(model, params, input, free, several: bool = False):
    from ..model.parameters import in_dynamics
    from .information import _free_names

    structure = model.structure
    if not structure.is_linear or structure.kind != "lti":
        raise ModelError(f"the frequency-domain information needs a linear time-invariant model; model "
                         f"'{model.name}' is {structure.kind} (use fisher_information on a plan)")
    if structure.delays:
        raise ModelError(f"the frequency-domain information does not handle delayed inputs yet ("
                         f"{', '.join(d.name for d in structure.delays)} in model '{model.name}'); "
                         "fisher_information on a plan (time domain) does")
    if input not in structure.input_names:
        raise ModelError(f"'{input}' is not an input of model '{model.name}' (inputs: {list(structure.input_names)})")
    # Per sample, a stationary experiment says nothing of the initial state's parameters: by default
    # they are left out (an explicit free= keeps them, and its information is singular along them).
    names = _free_names(model, free) if free is not None else in_dynamics(structure, _free_names(model, None))
    all_names = list(structure.parameter_names)
    vectors = [model.parameter_vector(p) for p in (params if several else [params])]
    theta = jnp.asarray(np.array(vectors) if several else vectors[0], dtype=jnp.float64)
    index = tuple(all_names.index(n) for n in names)
    programs = _programs(structure, structure.input_names.index(input), index)
    return names, theta, programs[2:] if several else programs[:2]


def frequency_information(model, params, omega: float, input: str, sampling_interval: float,
                          free=None) -> pd.DataFrame:
    """The information per sample of a unit-power sinusoid on one input (6.47–6.49).

    Parameters
    ----------
    model : Model
        A linear time-invariant model.
    params : mapping of str to float
        The assumed parameter values.
    omega : float
        The angular frequency in radians per time unit of the model (0: a constant
        input of unit power).
    input : str
        The input carrying the sinusoid (the others held at zero).
    sampling_interval : float
        The time between samples.
    free : sequence of str, optional
        The parameters (default: the free ones that enter the equations; those of
        the initial state only are not seen per sample).

    Returns
    -------
    pandas.DataFrame
        Over the parameters; ``attrs["input_independent"]`` holds M̄_c (6.49), the
        information per sample that no input changes.
    """
    names, theta, (input_information, noise_information) = _setup(model, params, input, free)
    tau = float(sampling_interval)
    M_u = np.asarray(input_information(theta, tau, jnp.array([float(omega)])))[0]
    info = pd.DataFrame(0.5 * (M_u + M_u.T), index=names, columns=names)
    M_c = np.asarray(noise_information(theta, tau))
    info.attrs["input_independent"] = pd.DataFrame(0.5 * (M_c + M_c.T), index=names, columns=names)
    return info


def frequency_information_grid(model, params, omegas, input: str, sampling_interval: float, free=None):
    """[`frequency_information()`][greyid.design.frequency.frequency_information] on a grid of frequencies at once.

    Parameters
    ----------
    model : Model
        A linear time-invariant model.
    params : mapping of str to float
        The assumed parameter values.
    omegas : array_like
        The angular frequencies.
    input : str
        The input carrying the sinusoid.
    sampling_interval : float
        The time between samples.
    free : sequence of str, optional
        The parameters.

    Returns
    -------
    tuple
        ``(M_u, M_c, names)``: one p × p matrix per frequency (unit power), the
        input-independent part, and the parameters' names (NumPy arrays).
    """
    names, theta, (input_information, noise_information) = _setup(model, params, input, free)
    tau = float(sampling_interval)
    M_u = np.asarray(input_information(theta, tau, jnp.asarray(np.asarray(omegas, dtype=np.float64))))
    M_c = np.asarray(noise_information(theta, tau))
    return 0.5 * (M_u + M_u.transpose(0, 2, 1)), 0.5 * (M_c + M_c.T), names


def frequency_information_points(model, points, omegas, input: str, sampling_interval: float, free=None,
                                 input_independent: bool = True):
    """[`frequency_information_grid()`][greyid.design.frequency.frequency_information_grid] at several points at once.

    Parameters
    ----------
    model : Model
        A linear time-invariant model.
    points : sequence of mapping
        The parameter points.
    omegas : array_like
        The angular frequencies.
    input : str
        The input carrying the sinusoid.
    sampling_interval : float
        The time between samples.
    free : sequence of str, optional
        The parameters.
    input_independent : bool
        Also M̄_c at each point (it costs more than a few frequencies' M_u).

    Returns
    -------
    tuple
        ``(M_u, M_c, names)``: shapes (points, frequencies, p, p) and (points, p, p),
        M_c None without ``input_independent``.
    """
    names, thetas, (input_information, noise_information) = _setup(model, points, input, free, several=True)
    tau = float(sampling_interval)
    M_u = np.asarray(input_information(thetas, tau, jnp.asarray(np.asarray(omegas, dtype=np.float64))))
    M_u = 0.5 * (M_u + M_u.transpose(0, 1, 3, 2))
    if not input_independent:
        return M_u, None, names
    M_c = np.asarray(noise_information(thetas, tau))
    return M_u, 0.5 * (M_c + M_c.transpose(0, 2, 1)), names
