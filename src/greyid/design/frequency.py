"""Information per sample in the frequency domain, and optimal multisine inputs (6.3, 6.47–6.49, 7.49–7.50).

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

from dataclasses import dataclass

from .. import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from scipy import optimize

from ..compiler import jit
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

    structure.cache[key] = (jit(input_information), jit(noise_information))
    return structure.cache[key]


def _setup(model, params, input, free):
    from .information import _free_names

    structure = model.structure
    if not structure.is_linear or structure.kind != "lti":
        raise ModelError(f"the frequency-domain information needs a linear time-invariant model; model "
                         f"'{model.name}' is {structure.kind} (use fisher_information on a plan)")
    if input not in structure.input_names:
        raise ModelError(f"'{input}' is not an input of model '{model.name}' (inputs: {list(structure.input_names)})")
    names = _free_names(model, free)
    all_names = list(structure.parameter_names)
    theta = jnp.asarray(model.parameter_vector(params), dtype=jnp.float64)
    index = tuple(all_names.index(n) for n in names)
    return names, theta, _programs(structure, structure.input_names.index(input), index)


def frequency_information(model, params, omega: float, input: str, sampling_interval: float,
                          free=None) -> pd.DataFrame:
    """Information per sample of a unit-power sinusoid of angular frequency ``omega`` on ``input``.

    ``omega`` in radians per time unit of the model (0 for a constant input of
    unit power), the other inputs held at zero, the model sampled every
    ``sampling_interval``.  A DataFrame over the free parameters (as
    :func:`fisher_information`'s); ``attrs["input_independent"]`` holds M̄_c (6.49),
    the information per sample that no input changes.  See the module doc.
    """
    names, theta, (input_information, noise_information) = _setup(model, params, input, free)
    tau = float(sampling_interval)
    M_u = np.asarray(input_information(theta, tau, jnp.array([float(omega)])))[0]
    info = pd.DataFrame(0.5 * (M_u + M_u.T), index=names, columns=names)
    M_c = np.asarray(noise_information(theta, tau))
    info.attrs["input_independent"] = pd.DataFrame(0.5 * (M_c + M_c.T), index=names, columns=names)
    return info


def frequency_information_grid(model, params, omegas, input: str, sampling_interval: float, free=None):
    """``(M_u, M_c, names)``: :func:`frequency_information` on a grid of frequencies at once.

    ``M_u`` has one p × p matrix per frequency (unit power), ``M_c`` is the
    input-independent part; both NumPy arrays over the parameters ``names``.
    """
    names, theta, (input_information, noise_information) = _setup(model, params, input, free)
    tau = float(sampling_interval)
    M_u = np.asarray(input_information(theta, tau, jnp.asarray(np.asarray(omegas, dtype=np.float64))))
    M_c = np.asarray(noise_information(theta, tau))
    return 0.5 * (M_u + M_u.transpose(0, 2, 1)), 0.5 * (M_c + M_c.T), names


@dataclass
class MultisineDesign:
    """An optimal input: sinusoids at ``frequencies`` (rad per time unit) with power ``weights``."""

    frequencies: np.ndarray
    weights: np.ndarray  # fractions of the total power, summing to 1
    value: float  # the criterion at the design (minimised)
    criterion: str
    power: float
    max_derivative: float  # largest directional derivative over the frequency band
    support_derivative: float  # the design's own (equal at an optimum: equivalence theorem)
    information: pd.DataFrame  # per sample, of the design

    def signal(self, times, offset: float = 0.0, phases="schroeder") -> np.ndarray:
        """The input's time series at ``times`` (a sinusoid at 0 is a constant of its power)."""
        from ..simulate.signals import multisine

        times = np.asarray(times, dtype=np.float64)
        out = np.full(times.shape, float(offset))
        constant = self.frequencies <= 1e-12
        if np.any(constant):
            out += np.sqrt(self.power * self.weights[constant].sum())
        if np.any(~constant):
            share = self.weights[~constant]
            out += multisine(times, self.frequencies[~constant] / (2 * np.pi), power=share,
                             total_power=self.power * share.sum(), phases=phases)
        return out

    def table(self) -> pd.DataFrame:
        return pd.DataFrame({"frequency": self.frequencies, "weight": self.weights})


def _criterion_and_derivatives(M, Ms, kind):
    """Value of the criterion at M and the directional derivative towards each M_u(ω)."""
    M_inv = np.linalg.inv(M)
    if kind == "D":
        return -np.linalg.slogdet(M)[1], np.einsum("ij,lji->l", M_inv, Ms)
    M2 = M_inv @ M_inv
    return np.trace(M_inv) / M.shape[0], np.einsum("ij,lji->l", M2, Ms)


def optimal_multisine(model, params, input: str, sampling_interval: float, criterion: str = "D",
                      power: float = 1.0, band=None, free=None, include_noise: bool = True,
                      grid: int = 400, iterations: int = 5000) -> MultisineDesign:
    """The input of ``power`` (variance) on ``input`` that minimises ``criterion`` per sample (6.3, 7.49).

    Candidate frequencies: 0 and a logarithmic grid up to the Nyquist frequency
    π/τ (or within ``band = (low, high)``).  The weights come from the
    multiplicative algorithm for convex design (a Fedorov–Wynn relative), the
    support is merged and then refined locally in frequency and weight.  The
    information is M̄_c + power·Σ α_l M_u(ω_l), or without M̄_c with
    ``include_noise=False`` (the form of (7.50)).  ``criterion`` is ``"D"`` or
    ``"A"``.  The result's ``max_derivative`` and ``support_derivative`` check the
    general equivalence theorem: no frequency should have a larger directional
    derivative than the design's own.
    """
    if criterion not in ("D", "A"):
        raise ModelError(f"optimal_multisine supports criterion 'D' or 'A', not {criterion!r}")
    if not power > 0:
        raise ModelError(f"the input power must be positive, got {power!r}")
    names, theta, (input_information, noise_information) = _setup(model, params, input, free)
    tau = float(sampling_interval)
    nyquist = np.pi / tau
    low, high = (0.0, nyquist) if band is None else (float(band[0]), min(float(band[1]), nyquist))
    if not 0 <= low < high:
        raise ModelError(f"band must be (low, high) with 0 ≤ low < high ≤ π/τ = {nyquist:.4g}, got {band!r}")
    start = max(low, high * 1e-4)
    omegas = np.unique(np.concatenate([[low], np.geomspace(start, high, grid)]))
    Ms = power * np.asarray(input_information(theta, tau, jnp.asarray(omegas)))
    Ms = 0.5 * (Ms + Ms.transpose(0, 2, 1))
    base = np.asarray(noise_information(theta, tau)) if include_noise else np.zeros(Ms.shape[1:])
    # D is computed in scaled units (the same optimum, better conditioned); A depends on the units.
    scale = np.sqrt(np.maximum(np.einsum("lii->i", Ms) + np.diag(base), 1e-300))
    S = np.diag(1.0 / scale) if criterion == "D" else np.eye(len(scale))
    Ms_s, base_s = S @ Ms @ S, S @ base @ S
    alpha = np.full(len(omegas), 1.0 / len(omegas))
    for _ in range(iterations):
        _, d = _criterion_and_derivatives(base_s + np.einsum("l,lij->ij", alpha, Ms_s), Ms_s, criterion)
        alpha = alpha * d / (alpha @ d)
    # One sinusoid per peak of the weights (its basin's weight summed, between the
    # neighbouring minima), then refined: the algorithm leaves small weights spread
    # around each support point, and merging all of them would average distinct peaks.
    significant = alpha > 1e-3 * alpha.max()
    left = np.concatenate([[-np.inf], alpha[:-1]])
    right = np.concatenate([alpha[1:], [-np.inf]])
    peaks = np.flatnonzero(significant & (alpha >= left) & (alpha >= right))
    bounds = [0] + [int(p0 + np.argmin(alpha[p0:p1 + 1])) for p0, p1 in zip(peaks[:-1], peaks[1:])] + [len(alpha)]
    freq0 = omegas[peaks]
    w0 = np.array([alpha[lo:hi].sum() for lo, hi in zip(bounds[:-1], bounds[1:])])

    def information_of(freqs, weights):
        M_f = power * np.asarray(input_information(theta, tau, jnp.asarray(freqs)))
        return base + np.einsum("l,lij->ij", weights, 0.5 * (M_f + M_f.transpose(0, 2, 1)))

    def objective(x):
        k = len(freq0)
        freqs = np.clip(x[:k], low, high)
        weights = np.exp(x[k:] - x[k:].max())
        weights /= weights.sum()
        value, _ = _criterion_and_derivatives(S @ information_of(freqs, weights) @ S, Ms_s[:1], criterion)
        return value

    x0 = np.concatenate([freq0, np.log(np.maximum(w0, 1e-12))])
    refined = optimize.minimize(objective, x0, method="Nelder-Mead",
                                options=dict(xatol=1e-8, fatol=1e-12, maxiter=4000))
    x = refined.x if refined.fun <= objective(x0) else x0
    k = len(freq0)
    freqs = np.clip(x[:k], low, high)
    weights = np.exp(x[k:] - x[k:].max())
    weights /= weights.sum()
    order = np.argsort(freqs)
    freqs, weights = freqs[order], weights[order]
    M = information_of(freqs, weights)
    # The equivalence check in the units the design was found in; the value in the model's own.
    _, d = _criterion_and_derivatives(S @ M @ S, Ms_s, criterion)
    _, d_support = _criterion_and_derivatives(
        S @ M @ S, S @ (power * np.asarray(input_information(theta, tau, jnp.asarray(freqs)))) @ S, criterion)
    value, _ = _criterion_and_derivatives(M, Ms[:1], criterion)
    return MultisineDesign(freqs, weights, float(value), criterion, float(power), float(d.max()),
                           float(weights @ d_support), pd.DataFrame(M, index=names, columns=names))


def aliased(omegas, sampling_interval: float) -> np.ndarray:
    """The frequencies in [0, π/τ] that sampled (held) sinusoids at ``omegas`` are indistinguishable from."""
    band = 2 * np.pi / sampling_interval
    return np.abs((np.asarray(omegas, dtype=np.float64) + band / 2) % band - band / 2)


def sampling_table(model, params, input: str, intervals, frequencies=None, weights=None, power: float = 1.0,
                   free=None, include_noise: bool = True) -> pd.DataFrame:
    """The D-criterion per sample and per unit time against the sampling interval (section 6.4, (6.72)).

    For each interval τ the information per sample M(τ) = M̄_c(τ) + power·Σ w_l M_u(ω_l; τ)
    of the input design — the given ``frequencies`` (rad per time unit; one above
    the Nyquist frequency π/τ acts as its alias) and power ``weights``, or, without
    ``frequencies``, the D-optimal multisine for that τ (the joint input and
    sampling design of a fixed number of samples) — and the information per
    unit time M(τ)/τ (a fixed experiment time).  Columns ``interval``,
    ``D_per_sample`` = −log det M, ``D_per_time`` = −log det(M/τ), ``frequencies``
    and ``weights`` of the design used.
    """
    rows = []
    for tau in np.asarray(intervals, dtype=np.float64):
        if not tau > 0:
            raise ModelError(f"sampling intervals must be positive, got {tau!r}")
        if frequencies is None:
            best = optimal_multisine(model, params, input, float(tau), power=power, free=free,
                                     include_noise=include_noise)
            freqs, share, M = best.frequencies, best.weights, best.information.to_numpy()
        else:
            freqs = aliased(frequencies, tau)
            share = np.full(len(freqs), 1.0 / len(freqs)) if weights is None else np.asarray(weights, float)
            if share.shape != freqs.shape or np.any(share < 0) or not np.isclose(share.sum(), 1.0):
                raise ModelError("weights must hold one non-negative power fraction per frequency, summing to 1")
            M_u, M_c, _ = frequency_information_grid(model, params, freqs, input, float(tau), free)
            M = (M_c if include_noise else 0.0) + power * np.einsum("l,lij->ij", share, M_u)
        sign, logdet = np.linalg.slogdet(M)
        per_sample = -logdet if sign > 0 else np.inf
        per_time = per_sample + M.shape[0] * np.log(tau) if sign > 0 else np.inf
        rows.append(dict(interval=float(tau), D_per_sample=float(per_sample), D_per_time=float(per_time),
                         frequencies=tuple(np.round(freqs, 6)), weights=tuple(np.round(share, 4))))
    return pd.DataFrame(rows)
