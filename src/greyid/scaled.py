"""Information matrices decided in scaled coordinates, so that no answer depends on units.

A change of a parameter's unit, θ_i → c_i θ_i, turns an information matrix M
into D M D with D = diag(1/c_i): a house's capacities in J/K and resistances in
K/W give M a condition number of 1e20 from the units alone.  Every rank
decision, inverse and log-determinant is therefore taken on the matrix scaled
to unit diagonal,

    M_s = S M S,   S = diag(1/√M_ii),

whose eigenvalues do not change with the units (M_s is the information of
θ_i/S_ii, a unit-free coordinate).  An eigenvalue of M_s below
[`RANK_TOLERANCE`][greyid.scaled.RANK_TOLERANCE] times the largest is a direction the information does
not determine; results go back to the user's units through S:
M⁻¹ = S M_s⁻¹ S and log det M = log det M_s − 2 Σ log S_ii.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Eigenvalues of the unit-diagonal information below this fraction of the largest are zero
#: (a standard error √(1/λ) more than 10⁵ times what the parameter's own information says).
RANK_TOLERANCE = 1e-10
#: A loading above this (of the largest) names a parameter in an undetermined direction.
LOADING = 0.05


def diagonal_scale(M: np.ndarray) -> np.ndarray:
    """S_ii = 1/√|M_ii| (1 where M_ii is 0: such a parameter is undetermined anyway)."""
    diagonal = np.abs(np.diag(M))
    return np.where(diagonal > 0, 1.0 / np.sqrt(np.where(diagonal > 0, diagonal, 1.0)), 1.0)


def loadings(vector: np.ndarray, names) -> dict:
    """A direction as {name: loading}, largest loading +1, those under [`LOADING`][greyid.scaled.LOADING] left out."""
    vector = vector / vector[np.argmax(np.abs(vector))]
    return {names[i]: float(vector[i]) for i in np.argsort(-np.abs(vector)) if abs(vector[i]) > LOADING}


@dataclass(frozen=True)
class ScaledInformation:
    """An information matrix as its scaling S and the eigen-decomposition of S M S."""

    names: list
    scale: np.ndarray  # S_ii = 1/√M_ii (1 where M_ii is 0: such a parameter is undetermined anyway)
    eigenvalues: np.ndarray  # of S M S, ascending
    eigenvectors: np.ndarray  # columns
    tolerance: float

    @classmethod
    def of(cls, matrix, names=None, tolerance: float = RANK_TOLERANCE) -> "ScaledInformation":
        M = np.asarray(matrix, dtype=np.float64)
        M = 0.5 * (M + M.T)
        names = list(names) if names is not None else [f"p{i}" for i in range(M.shape[0])]
        if not np.all(np.isfinite(M)):
            raise ValueError("the information matrix holds non-finite values")
        scale = diagonal_scale(M)
        w, V = np.linalg.eigh(scale[:, None] * M * scale[None, :])
        return cls(names, scale, w, V, float(tolerance))

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def null_mask(self) -> np.ndarray:
        """The eigenvalues that count as zero (negative ones too: not an information)."""
        top = max(float(self.eigenvalues.max(initial=0.0)), 1e-300)
        return self.eigenvalues <= self.tolerance * top

    @property
    def rank(self) -> int:
        return int(self.size - np.count_nonzero(self.null_mask))

    @property
    def singular(self) -> bool:
        return bool(np.any(self.null_mask))

    @property
    def condition(self) -> float:
        """Condition number of the scaled matrix (inf where singular)."""
        if self.singular:
            return float("inf")
        return float(self.eigenvalues.max() / self.eigenvalues.min())

    def null_directions(self) -> np.ndarray:
        """The undetermined directions, columns in scaled coordinates (unit-free loadings)."""
        return self.eigenvectors[:, self.null_mask]

    def directions(self) -> list[dict]:
        """Each undetermined direction as {parameter: loading}, largest loading 1, small ones left out."""
        return [loadings(self.eigenvectors[:, j], self.names) for j in np.flatnonzero(self.null_mask)]

    def describe(self) -> str:
        """The undetermined directions in words, e.g. "+1.000·Cw −0.933·Ro"."""
        return "; ".join(", ".join(f"{v:+.3f}·{n}" for n, v in d.items()) for d in self.directions())

    def undetermined(self, rows) -> np.ndarray:
        """Which linear functionals cᵀθ (rows of ``rows``, user units) the information does not
        determine: those with a part along an undetermined direction."""
        C = np.atleast_2d(np.asarray(rows, dtype=np.float64)) * self.scale[None, :]
        if not self.singular:
            return np.zeros(C.shape[0], dtype=bool)
        along = np.abs(C @ self.null_directions()).max(axis=1)
        return along > 1e-6 * np.maximum(np.linalg.norm(C, axis=1), 1e-300)

    def logdet(self) -> float:
        """log det M (−inf where singular)."""
        if self.singular:
            return float("-inf")
        return float(np.sum(np.log(self.eigenvalues)) - 2.0 * np.sum(np.log(self.scale)))

    def covariance(self) -> np.ndarray:
        """M⁻¹ = S M_s⁻¹ S on the determined subspace (a pseudo-inverse where singular; see
        `undetermined()` for which entries are then meaningless)."""
        keep = ~self.null_mask
        V = self.eigenvectors[:, keep]
        inner = (V / self.eigenvalues[keep]) @ V.T
        cov = self.scale[:, None] * inner * self.scale[None, :]
        return 0.5 * (cov + cov.T)

    def variances(self, rows=None) -> np.ndarray:
        """The variance bound of each functional cᵀθ (default: each parameter), inf where undetermined."""
        C = np.eye(self.size) if rows is None else np.atleast_2d(np.asarray(rows, dtype=np.float64))
        values = np.einsum("ij,jk,ik->i", C, self.covariance(), C)
        return np.where(self.undetermined(C), np.inf, values)


def scaled_inverse(M, pseudo: bool = False) -> np.ndarray:
    """M⁻¹ taken as S (S M S)⁻¹ S with S = diag(1/√|M_ii|): the same in any units; with ``pseudo``
    the pseudo-inverse of the scaled matrix (relative cutoff [`RANK_TOLERANCE`][greyid.scaled.RANK_TOLERANCE]), for a
    singular M."""
    M = np.asarray(M, dtype=np.float64)
    scale = diagonal_scale(M)
    inner = scale[:, None] * M * scale[None, :]
    inverse = np.linalg.pinv(inner, rcond=RANK_TOLERANCE, hermitian=True) if pseudo else np.linalg.inv(inner)
    return scale[:, None] * inverse * scale[None, :]


__all__ = ["ScaledInformation", "RANK_TOLERANCE", "scaled_inverse"]
