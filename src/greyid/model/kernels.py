"""Gaussian-process kernels as linear SDEs, for latent forces (Hartikainen & Särkkä 2010; Solin & Särkkä 2014).

A stationary Gaussian process f(t) with kernel k(τ) is, exactly or to a stated order, the output f = H z of a
linear SDE dz = F z dt + G dω started in its stationary law N(0, P∞).  Each kernel gives (F, G, P∞, H) as SymPy
matrices of its hyperparameters, which are ordinary model parameters (or numbers):

| kernel | k(τ) | states | exact |
|---|---|---|---|
| ``matern12`` | σ² e^{−λ|τ|}, λ = 1/ℓ | 1 | yes |
| ``matern32`` | σ² (1 + λ|τ|) e^{−λ|τ|}, λ = √3/ℓ | 2 | yes |
| ``matern52`` | σ² (1 + λ|τ| + λ²τ²/3) e^{−λ|τ|}, λ = √5/ℓ | 3 | yes |
| ``periodic`` | σ² exp(−2 sin²(πτ/p) / w²) | 2J + 1 | to order J |
| ``quasiperiodic`` | periodic × Matérn-3/2 of lengthscale ℓ | 2(2J + 1) | to order J |

σ is ``scale`` (a standard deviation in the force's unit), ℓ ``lengthscale`` and p ``period`` in the time unit,
w ``smoothness`` (the periodic kernel's own lengthscale, dimensionless).  The periodic kernel is its cosine
series e^{−1/w²} e^{cos(ωτ)/w²} = Σ_j q_j² cos(jωτ), ω = 2π/p, q_0² = e^{−x} I_0(x), q_j² = 2 e^{−x} I_j(x),
x = w⁻² (modified Bessel functions), truncated after harmonic J (``order``, default 6): each harmonic is an
undamped oscillator, and the truncation error is σ²(1 − Σ_{j≤J} q_j²) at τ = 0, the largest over τ
([`periodic_truncation_error`][greyid.model.kernels.periodic_truncation_error]).  Sums stack the state spaces;
products take Kronecker products (F₁ ⊗ I + I ⊗ F₂, P∞₁ ⊗ P∞₂, H₁ ⊗ H₂, the noise from the stationary
Lyapunov equation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import sympy as sp

from ..errors import ModelError

#: The named kernels and the hyperparameters each takes (besides ``order`` for the periodic ones).
KERNELS = {
    "matern12": ("scale", "lengthscale"),
    "matern32": ("scale", "lengthscale"),
    "matern52": ("scale", "lengthscale"),
    "periodic": ("scale", "period", "smoothness"),
    "quasiperiodic": ("scale", "lengthscale", "period", "smoothness"),
}
#: Hyperparameters that must be positive (a lengthscale or period of zero has no meaning).
POSITIVE = ("lengthscale", "period", "smoothness")
DEFAULT_ORDER = 6


class ScaledBesselI(sp.Function):
    """e^{−x} I_j(x), the exponentially scaled modified Bessel function of the first kind of integer order j
    (its JAX form is [`scaled_besseli`][greyid.model.kernels.scaled_besseli])."""

    nargs = 2


def scaled_besseli(order, x):
    """e^{−x} I_j(x) in JAX by its power series, summed in logarithms (400 terms: to double precision for
    x ≤ 250, i.e. a periodic smoothness w ≥ 0.064), differentiable in x."""
    import jax.numpy as jnp
    from jax.scipy.special import gammaln

    k = jnp.arange(400.0)
    x = jnp.asarray(x, dtype=jnp.float64)
    logs = (2 * k + order) * jnp.log(x / 2) - gammaln(k + 1) - gammaln(k + order + 1) - x
    return jnp.sum(jnp.exp(logs))


@dataclass(frozen=True)
class StateSpace:
    """A kernel's SDE: dz = F z dt + G dω, z(t₀) ~ N(0, P∞), f = H z (SymPy matrices)."""

    F: sp.Matrix
    G: sp.Matrix
    P: sp.Matrix
    H: sp.Matrix

    @property
    def size(self) -> int:
        return self.F.shape[0]


class Kernel:
    """A kernel; ``+`` and ``*`` combine them."""

    def __add__(self, other: Kernel) -> Kernel:
        return Sum((self, other))

    def __mul__(self, other: Kernel) -> Kernel:
        return Product((self, other))

    def state_space(self, value) -> StateSpace:
        """(F, G, P∞, H) with each hyperparameter read by ``value(name, given)`` into SymPy."""
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError

    def hyperparameters(self) -> list[tuple[str, object]]:
        """``[(role, value), ...]`` of this kernel and its parts."""
        raise NotImplementedError


@dataclass(frozen=True)
class Named(Kernel):
    """One of the named kernels (``matern12``, ``matern32``, ``matern52``, ``periodic``, ``quasiperiodic``)
    with its hyperparameters (names, expressions or numbers) and, for the periodic kernels, the truncation
    order J."""

    kind: str
    values: tuple
    order: int = DEFAULT_ORDER

    def hyperparameters(self):
        return list(zip(KERNELS[self.kind], self.values))

    def to_dict(self) -> dict:
        out = {"kernel": self.kind, **dict(self.hyperparameters())}
        if self.kind in ("periodic", "quasiperiodic"):
            out["order"] = self.order
        return out

    def state_space(self, value) -> StateSpace:
        given = {role: value(role, v) for role, v in self.hyperparameters()}
        if self.kind.startswith("matern"):
            return matern(self.kind, given["scale"], given["lengthscale"])
        periodic = periodic_state_space(given["scale"], given["period"], given["smoothness"], self.order)
        if self.kind == "periodic":
            return periodic
        return product(periodic, matern("matern32", sp.Integer(1), given["lengthscale"]))


@dataclass(frozen=True)
class Combined(Kernel):
    """Kernels combined: their hyperparameters and dict form, the combination named by ``kind``."""

    parts: tuple
    kind = "combined"

    def hyperparameters(self):
        return [h for p in self.parts for h in p.hyperparameters()]

    def to_dict(self) -> dict:
        return {"kernel": self.kind, "parts": [p.to_dict() for p in self.parts]}


class Sum(Combined):
    """k₁ + k₂ + …: the parts' state spaces stacked (block-diagonal F, G, P∞; H side by side)."""

    kind = "sum"

    def state_space(self, value) -> StateSpace:
        spaces = [p.state_space(value) for p in self.parts]
        return StateSpace(sp.diag(*[s.F for s in spaces]), sp.diag(*[s.G for s in spaces]),
                          sp.diag(*[s.P for s in spaces]), sp.Matrix.hstack(*[s.H for s in spaces]))


class Product(Combined):
    """k₁ · k₂ · …: Kronecker products of the parts' state spaces ([`product`][greyid.model.kernels.product])."""

    kind = "product"

    def state_space(self, value) -> StateSpace:
        spaces = [p.state_space(value) for p in self.parts]
        out = spaces[0]
        for s in spaces[1:]:
            out = product(out, s)
        return out


def matern(kind: str, scale, lengthscale) -> StateSpace:
    """The Matérn kernels' companion forms (Hartikainen & Särkkä 2010), P∞ in closed form."""
    s2 = scale ** 2
    if kind == "matern12":
        lam = 1 / lengthscale
        return StateSpace(sp.Matrix([[-lam]]), sp.Matrix([[scale * sp.sqrt(2 * lam)]]), sp.Matrix([[s2]]),
                          sp.Matrix([[1]]))
    if kind == "matern32":
        lam = sp.sqrt(3) / lengthscale
        F = sp.Matrix([[0, 1], [-lam ** 2, -2 * lam]])
        G = sp.Matrix([[0], [2 * scale * lam * sp.sqrt(lam)]])  # q = 4 λ³ σ²
        return StateSpace(F, G, sp.diag(s2, lam ** 2 * s2), sp.Matrix([[1, 0]]))
    lam = sp.sqrt(5) / lengthscale
    F = sp.Matrix([[0, 1, 0], [0, 0, 1], [-lam ** 3, -3 * lam ** 2, -3 * lam]])
    G = sp.Matrix([[0], [0], [4 * scale * lam ** 2 * sp.sqrt(lam) / sp.sqrt(3)]])  # q = 16/3 λ⁵ σ²
    k = lam ** 2 * s2 / 3
    P = sp.Matrix([[s2, 0, -k], [0, k, 0], [-k, 0, lam ** 4 * s2]])
    return StateSpace(F, G, P, sp.Matrix([[1, 0, 0]]))


def periodic_weights(smoothness, order: int) -> list:
    """q_j² / σ² for j = 0..J: e^{−x} I_0(x) and 2 e^{−x} I_j(x), x = w⁻² (SymPy)."""
    x = smoothness ** -2
    return [ScaledBesselI(0, x)] + [2 * ScaledBesselI(j, x) for j in range(1, order + 1)]


def periodic_state_space(scale, period, smoothness, order: int) -> StateSpace:
    """Solin & Särkkä's (2014) periodic kernel: the constant and J undamped oscillators of frequency j·2π/p."""
    weights = periodic_weights(smoothness, order)
    omega = 2 * sp.pi / period
    F, P, H = [sp.zeros(1, 1)], [sp.Matrix([[scale ** 2 * weights[0]]])], [sp.Matrix([[1]])]
    for j in range(1, order + 1):
        F.append(sp.Matrix([[0, -j * omega], [j * omega, 0]]))
        P.append(scale ** 2 * weights[j] * sp.eye(2))
        H.append(sp.Matrix([[1, 0]]))
    size = 2 * order + 1
    return StateSpace(sp.diag(*F), sp.zeros(size, 0), sp.diag(*P), sp.Matrix.hstack(*H))


def product(a: StateSpace, b: StateSpace) -> StateSpace:
    """The state space of the product of two kernels: F = F_a ⊗ I + I ⊗ F_b, P∞ = P_a ⊗ P_b, H = H_a ⊗ H_b,
    and G Gᵀ = P_a ⊗ G_b G_bᵀ + G_a G_aᵀ ⊗ P_b (the stationary Lyapunov equation's noise), G from the
    Cholesky factors of P_a and P_b."""
    kron = sp.kronecker_product
    F = kron(a.F, sp.eye(b.size)) + kron(sp.eye(a.size), b.F)
    columns = []
    if b.G.shape[1]:
        columns.append(kron(_cholesky(a.P), b.G))
    if a.G.shape[1]:
        columns.append(kron(a.G, _cholesky(b.P)))
    G = sp.Matrix.hstack(*columns) if columns else sp.zeros(a.size * b.size, 0)
    # Columns that are zero (a harmonic's sine state has no noise of its own) are no noise at all.
    G = sp.Matrix.hstack(*[G[:, j] for j in range(G.shape[1]) if any(e != 0 for e in G[:, j])]) \
        if any(e != 0 for e in G) else sp.zeros(a.size * b.size, 0)
    return StateSpace(F, G, kron(a.P, b.P), kron(a.H, b.H))


def _cholesky(P: sp.Matrix) -> sp.Matrix:
    if P.is_diagonal():
        return sp.diag(*[sp.sqrt(P[i, i]) for i in range(P.shape[0])])
    return P.cholesky(hermitian=False)


def periodic_truncation_error(smoothness: float, order: int = DEFAULT_ORDER) -> float:
    """1 − Σ_{j≤J} q_j²/σ²: the periodic kernel's truncation error relative to σ² (its largest, at τ = 0)."""
    from scipy.special import ive

    x = smoothness ** -2.0
    return float(1.0 - ive(0, x) - 2.0 * sum(ive(j, x) for j in range(1, order + 1)))


def kernel_of(spec, where: str) -> Kernel:
    """A [`Kernel`][greyid.model.kernels.Kernel] from a kernel object or its dict form (checked)."""
    if isinstance(spec, Kernel):
        return spec
    if not isinstance(spec, Mapping) or "kernel" not in spec:
        raise ModelError(f"{where}: a kernel is a table {{ kernel = \"matern32\", scale = ..., lengthscale = ... }} "
                         f"or a greyid.model.kernels object, got {spec!r}")
    kind = spec["kernel"]
    if kind in ("sum", "product"):
        unknown = sorted(set(spec) - {"kernel", "parts"})
        parts = spec.get("parts")
        if unknown or not isinstance(parts, (list, tuple)) or len(parts) < 2:
            raise ModelError(f"{where}: a {kind} kernel takes parts = [two or more kernels]"
                             + (f"; unknown key '{unknown[0]}'" if unknown else ""))
        made = tuple(kernel_of(p, f"{where}, part {i + 1}") for i, p in enumerate(parts))
        return Sum(made) if kind == "sum" else Product(made)
    if kind not in KERNELS:
        raise ModelError(f"{where}: unknown kernel '{kind}'; use one of {', '.join([*KERNELS, 'sum', 'product'])}")
    roles = KERNELS[kind]
    periodic = kind in ("periodic", "quasiperiodic")
    unknown = sorted(set(spec) - {"kernel", *roles, *(["order"] if periodic else [])})
    if unknown:
        raise ModelError(f"{where}: the {kind} kernel takes {', '.join(roles)}" + (", order" if periodic else "")
                         + f"; unknown key '{unknown[0]}'")
    missing = [r for r in roles if r not in spec]
    if missing:
        raise ModelError(f"{where}: the {kind} kernel needs its {missing[0]} (a parameter name, expression or "
                         "number)")
    order = spec.get("order", DEFAULT_ORDER)
    if periodic and (not isinstance(order, (int, np.integer)) or isinstance(order, bool) or order < 1):
        raise ModelError(f"{where}: the {kind} kernel's order must be a positive whole number, got {order!r}")
    return Named(kind, tuple(spec[r] for r in roles), int(order))
