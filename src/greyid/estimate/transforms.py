"""Smooth maps from unbounded optimisation variables z to bounded parameters θ.

Bounds are handled as in CTSM by transformation: θ = l + e^z (lower bound
only), θ = u − e^z (upper bound only), θ = l + (u − l)/(1 + e^{−z}) (both), θ = z
(none).  dθ/dz maps gradients and Hessians back to θ.
"""

from __future__ import annotations

from dataclasses import dataclass

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
import numpy as np
from scipy import special

NONE, LOWER, UPPER, BOTH = 0, 1, 2, 3
#: |z| of a doubly bounded parameter within 1e-12 of its span from a bound (to_z's clip).
EDGE_Z = float(np.log((1 - 1e-12) / 1e-12))


@dataclass(frozen=True)
class Transform:
    """Element-wise bound transforms for a vector of free parameters."""

    kind: np.ndarray  # int codes per parameter
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def from_bounds(cls, lower, upper) -> "Transform":
        lo = np.array([np.nan if v is None else v for v in lower], dtype=np.float64)
        hi = np.array([np.nan if v is None else v for v in upper], dtype=np.float64)
        kind = np.where(np.isnan(lo), np.where(np.isnan(hi), NONE, UPPER), np.where(np.isnan(hi), LOWER, BOTH))
        return cls(kind.astype(int), np.nan_to_num(lo), np.nan_to_num(hi))

    def to_theta(self, z, xp=jnp):
        """θ at z; ``xp`` is the array module (``jax.numpy`` in compiled code, or NumPy)."""
        z = xp.asarray(z)
        width = self.upper - self.lower
        with np.errstate(over="ignore"):  # NumPy: e^z = inf gives the bound, as in JAX
            return xp.select(
                [self.kind == NONE, self.kind == LOWER, self.kind == UPPER],
                [z, self.lower + xp.exp(z), self.upper - xp.exp(z)],
                self.lower + width / (1.0 + xp.exp(-z)),
            )

    def to_z(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=np.float64)
        width = np.where(self.kind == BOTH, self.upper - self.lower, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.clip((theta - self.lower) / width, 1e-12, 1 - 1e-12)
            return np.select(
                [self.kind == NONE, self.kind == LOWER, self.kind == UPPER],
                [theta, np.log(np.maximum(theta - self.lower, 1e-300)), np.log(np.maximum(self.upper - theta, 1e-300))],
                np.log(frac) - np.log1p(-frac),
            )

    def derivative(self, z) -> np.ndarray:
        """dθ/dz at z."""
        z = np.asarray(z, dtype=np.float64)
        width = np.where(self.kind == BOTH, self.upper - self.lower, 1.0)  # not ∞·0 where a bound is missing
        s = special.expit(z)  # 1/(1 + e^−z) without overflow (and its warning) for z far below 0
        e = np.exp(np.clip(z, -700, 700))
        return np.select([self.kind == NONE, self.kind == LOWER, self.kind == UPPER], [np.ones_like(z), e, -e],
                         width * s * (1 - s))

    def at_bound(self, z, gradient, curvature, step: float = 0.5) -> np.ndarray:
        """True where the optimum in z lies against a bound, judged in z itself.

        Near a bound θ − l ≈ e^z (log and logistic transforms alike), so for a
        criterion f with slope g_θ there, ∂f/∂z ≈ g_θ e^z and ∂²f/∂z² ≈ g_θ e^z +
        e^{2z} ∂²f/∂θ²: the marginal Newton step in z, −(∂f/∂z)/(∂²f/∂z²), tends to
        one unit *towards* the bound when the bound holds the estimate back, and to
        zero at an interior optimum however close to the bound it lies or however
        wide the bounds are.  A parameter is at a bound when that step points to the
        nearer bound and is longer than ``step``, or when θ equals the bound to 12
        digits (there g and h are rounding noise), within 1e-12 of the span of a
        bound between two (where ``to_z`` clips), or e^z has underflowed.
        (A test on |θ − bound| relative to the bounds' scale flagged every estimate
        inside CTSM-style bounds such as [1e-6, 1e6], and a variance of 4e-6 above 0.)
        """
        z = np.asarray(z, dtype=np.float64)
        g = np.asarray(gradient, dtype=np.float64)
        h = np.asarray(curvature, dtype=np.float64)
        bounded = self.kind != NONE
        towards = np.where((self.kind == BOTH) & (z > 0), 1.0, -1.0)  # the direction of z that nears the bound
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = np.where(h > 0, -g / h, 0.0)
        pushed = (h > 0) & (newton * towards > step)
        # Within rounding of the bound, g and h in z are rounding noise themselves.
        theta = self.to_theta(z, np)
        nearest = np.where(((self.kind == BOTH) & (z > 0)) | (self.kind == UPPER), self.upper, self.lower)
        equal = np.abs(theta - nearest) <= 1e-12 * np.maximum(np.abs(theta), np.abs(nearest)) + 1e-300
        underflow = ~(np.abs(self.derivative(z)) > 0)
        # Between two bounds, within 1e-12 of the span of one is as near as to_z places a value: the
        # optimiser's z has run off towards the bound, and its g and h there are rounding noise.
        edge = (self.kind == BOTH) & (np.abs(z) >= EDGE_Z)
        return bounded & (pushed | equal | underflow | edge)
