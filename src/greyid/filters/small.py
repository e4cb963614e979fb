"""Cholesky factorisation and triangular solves unrolled for small matrices.

Filters work with state dimensions of a handful.  Written out element by
element, these factorisations become a few fused arithmetic kernels instead of
LAPACK calls inside every step of a scan, which on CPUs is several times faster,
above all in reverse-mode differentiation.  Larger matrices use jax.numpy.linalg.
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular as _solve_triangular

#: Largest dimension handled by the unrolled routines.
SMALL = 6


#: Largest dimension whose Cholesky factorisation is unrolled (and guarded, see below).
CHOLESKY_UNROLLED = 12
#: A pivot within this fraction of its diagonal element is rounding: the column is zero.
PIVOT_ROUNDING = 1e-12
#: A pivot below −(this fraction) of its diagonal element means the matrix is indefinite.
PIVOT_INDEFINITE = 1e-8


def cholesky(A: jnp.ndarray) -> jnp.ndarray:
    """Lower factor L with L Lᵀ = A for a symmetric positive *semi*-definite A.

    Covariances in a filter are often singular: a state without noise, a known
    initial state, an interval of 1e-5 s.  A pivot that is zero up to rounding
    (|d| ≤ PIVOT_ROUNDING·A_jj) gives a zero column, as in a semi-definite
    Cholesky factorisation, instead of 0/0; a clearly negative pivot (the matrix
    is indefinite, which no covariance is) gives NaN, so the error shows.
    Matrices larger than CHOLESKY_UNROLLED use LAPACK, which needs A definite.
    """
    n = A.shape[0]
    if n > CHOLESKY_UNROLLED:
        return jnp.linalg.cholesky(A)
    zero = jnp.zeros((), A.dtype)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), zero)
        scale = jnp.abs(A[j, j])
        positive = d > PIVOT_ROUNDING * scale
        root = jnp.sqrt(jnp.where(positive, d, 1.0))
        indefinite = d < -PIVOT_INDEFINITE * scale - 1e-300
        L[j][j] = jnp.where(positive, root, jnp.where(indefinite, jnp.nan, zero))
        for i in range(j + 1, n):
            off = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), zero)
            L[i][j] = jnp.where(positive, off / root, zero)
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def solve_lower(L: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """x with L x = b for lower-triangular L; b is a vector or a matrix of columns."""
    n = L.shape[0]
    if n > SMALL:
        return _solve_triangular(L, b, lower=True)
    x = []
    for i in range(n):
        acc = b[i] - sum((L[i, k] * x[k] for k in range(i)), jnp.zeros_like(b[i]))
        x.append(acc / L[i, i])
    return jnp.stack(x)


def solve_upper_transposed(L: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """x with Lᵀ x = b for lower-triangular L."""
    n = L.shape[0]
    if n > SMALL:
        return _solve_triangular(L.T, b, lower=False)
    x = [None] * n
    for i in reversed(range(n)):
        acc = b[i] - sum((L[k, i] * x[k] for k in range(i + 1, n)), jnp.zeros_like(b[i]))
        x[i] = acc / L[i, i]
    return jnp.stack(x)


def cho_solve(L: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """x with L Lᵀ x = b."""
    return solve_upper_transposed(L, solve_lower(L, b))



def mm(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """A @ B for small operands as a fused multiply-sum (no matrix-multiply call)."""
    if max(A.shape + B.shape) > 4 * SMALL:
        return A @ B
    if A.ndim == 1:
        return jnp.sum(A[:, None] * B, axis=0) if B.ndim == 2 else jnp.sum(A * B)
    if B.ndim == 1:
        return jnp.sum(A * B[None, :], axis=1)
    return jnp.sum(A[:, :, None] * B[None, :, :], axis=1)
