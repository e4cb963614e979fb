"""Long regular series through the exact Kalman filter: the steady state in vectorised blocks.

For a time-invariant linear model sampled at a constant interval the filter's
covariance recursion (4.35, 4.29) does not depend on the data and converges to
the solution P∞ of the discrete algebraic Riccati equation.  From there on the
gain K, the innovation covariance R and the filtered covariance are constant, and
the mean follows a linear recursion x_k = F x_{k−1} + v_k with F = (I − KC)Φ,
which is computed a block of rows at a time by one matrix product instead of a
sequential step per row (Anderson and Moore, "Optimal Filtering", ch. 4).

The rows are cut into chunks of CHUNK rows.  A chunk runs through the ordinary
filter steps until, at a chunk's end, the filtered covariance equals the steady
state's to TOLERANCE; the following chunks that are fully observed at the
regular interval then take the steady-state form.  A chunk with a missing value
or another interval runs the ordinary steps again (and checks again at its end).
The answers equal the ordinary filter's up to that tolerance; the derivatives are
those of the same computation, P∞'s through the doubling iterations.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax
import jax.numpy as jnp

from . import small
from .discretize import Discretization
from .updates import StepTerms, Update, from_matrix, symmetrize, to_matrix

#: Rows of a series from which the filter takes the steady-state form where it can.
MIN_ROWS = 20_000
#: Rows per chunk: the unit in which the filter switches between the two forms.
CHUNK = 512
#: Rows per block of the vectorised mean recursion (one matrix product each).
BLOCK = 32
#: The filtered covariance is at the steady state when every element is within
#: TOLERANCE·√(P∞_ii P∞_jj) of P∞'s.
TOLERANCE = 1e-12
#: Doubling iterations for P∞: the Riccati recursion's 2^DOUBLINGS-th iterate.
DOUBLINGS = 48


class SteadyModel(NamedTuple):
    """The time-invariant pieces of a linear model at its regular sampling interval."""

    disc: Discretization  # Φ, Γ, Υ, Λ of the regular interval
    regular_index: jnp.ndarray  # that interval's index into FilterInputs.unique_dt
    C: jnp.ndarray  # ∂h/∂x
    noise: jnp.ndarray  # S, the outputs' noise covariance (full matrix)
    affine_drift: Callable  # (u, t) -> f(0, u, t)
    affine_output: Callable  # (u, t) -> h(0, u, t)
    foh: jnp.ndarray
    form: str  # how the filter carries its covariance


class SteadyState(NamedTuple):
    """P∞ and what the steady-state filter derives from it."""

    predicted: jnp.ndarray  # P∞ = P_{k|k−1}
    filtered: jnp.ndarray  # P_{k|k}
    gain: jnp.ndarray  # K = P∞Cᵀ R⁻¹
    innovation_cov: jnp.ndarray  # R = C P∞ Cᵀ + S
    chol_R: jnp.ndarray
    whitening: jnp.ndarray  # L⁻¹ with R = LLᵀ: one product per chunk instead of a triangular solve per row
    recursion: "Recursion"  # of the filtered mean, F = (I − KC)Φ


def riccati_solution(transition, noise, C, S):
    """P∞ = ΦPΦᵀ − ΦPCᵀ(CPCᵀ + S)⁻¹CPΦᵀ + Λ by the structure-preserving doubling algorithm.

    The control-form iteration of Chu, Fan and Lin (2005) on the dual problem
    (A = Φᵀ, G = CᵀS⁻¹C, H = Λ): Hₖ is the covariance after 2ᵏ steps of the
    recursion from P = Λ, so it converges quadratically once the filter's
    closed loop is stable.  Where there is no steady state (a mode that is
    neither stable nor observed) the result is meaningless or NaN: the carried
    covariance never equals it, so no chunk switches (:func:`at_steady_state`).
    """
    n = transition.shape[0]
    eye = jnp.eye(n)

    def double(_, AGH):
        A, G, H = AGH
        W = eye + G @ H
        WA, WG = jnp.linalg.solve(W, A), jnp.linalg.solve(W, G)
        return A @ WA, symmetrize(G + A @ WG @ A.T), symmetrize(H + A.T @ H @ WA)

    G = C.T @ jnp.linalg.solve(S, C)
    _, _, P = jax.lax.fori_loop(0, DOUBLINGS, double, (transition.T, symmetrize(G), noise))
    return P


def steady_state(model: SteadyModel) -> SteadyState:
    """P∞ and the constant gain, innovation covariance (4.28–4.29) and filtered covariance of the steady state."""
    P = riccati_solution(model.disc.transition, model.disc.noise_covariance, model.C, model.noise)
    PCt = P @ model.C.T
    R = symmetrize(model.C @ PCt + model.noise)
    chol_R = jnp.linalg.cholesky(R)
    gain = jax.scipy.linalg.cho_solve((chol_R, True), PCt.T).T
    IKC = jnp.eye(P.shape[0]) - gain @ model.C
    filtered = symmetrize(IKC @ P @ IKC.T + gain @ model.noise @ gain.T)  # Joseph form
    whitening = jax.scipy.linalg.solve_triangular(chol_R, jnp.eye(R.shape[0]), lower=True)
    return SteadyState(P, filtered, gain, R, chol_R, whitening, recursion(IKC @ model.disc.transition))


def at_steady_state(cov, form: str, steady: SteadyState):
    """Whether the carried filtered covariance equals P∞'s filtered one (see TOLERANCE)."""
    scale = jnp.sqrt(jnp.diag(steady.filtered))
    difference = jnp.abs(to_matrix(cov, form) - steady.filtered) / jnp.outer(scale, scale)
    return jnp.max(difference) <= TOLERANCE  # False where anything is NaN


class Recursion(NamedTuple):
    """The powers of F that :func:`linear_recursion` applies, computed once per steady state."""

    powers: jnp.ndarray  # F⁰ … F^BLOCK
    toeplitz: jnp.ndarray  # (BLOCK, BLOCK, n, n): F^(l−i) where l ≥ i, else 0
    block_powers: jnp.ndarray  # (F^BLOCK)⁰ … (F^BLOCK)^⌈CHUNK/BLOCK⌉: from block to block


def _powers(F, count):
    return jax.lax.scan(lambda M, _: (F @ M, M), jnp.eye(F.shape[0]), None, length=count + 1)[1]


def recursion(F) -> Recursion:
    """:class:`Recursion` of x_r = F x_{r−1} + v_r."""
    L = BLOCK
    powers = _powers(F, L)
    lag = jnp.arange(L)[:, None] - jnp.arange(L)[None, :]
    return Recursion(powers, jnp.where((lag >= 0)[:, :, None, None], powers[jnp.maximum(lag, 0)], 0.0),
                     _powers(powers[L], -(-CHUNK // L)))


@jax.custom_jvp
def linear_recursion(F: Recursion, v, start):
    """x_r = F x_{r−1} + v_r for r = 0 … len(v) − 1, x_{−1} = start, in blocks of BLOCK rows.

    Within a block the response to its own v is one product with the block's
    lower block-Toeplitz matrix of powers of F; the blocks' ends are carried
    into the following blocks the same way, with powers of F^BLOCK (a scan over
    the blocks where there are more than a chunk's).  A last partial block is
    padded with v = 0 (rows beyond the end, dropped).
    """
    rows, n = v.shape
    L = BLOCK
    if rows % L:
        padded = jnp.concatenate([v, jnp.zeros((L - rows % L, n), v.dtype)])
        return linear_recursion(F, padded, start)[:rows]
    count = rows // L
    local = jnp.einsum("liac,bic->bla", F.toeplitz, v.reshape(count, L, n))
    if count < F.block_powers.shape[0]:
        # x at the end of block b − 1 = Σ_{j<b} (F^L)^(b−1−j) (own end of block j) + (F^L)^b start
        lag = jnp.arange(count)[:, None] - jnp.arange(count)[None, :]
        between = jnp.where((lag >= 1)[:, :, None, None], F.block_powers[jnp.maximum(lag - 1, 0)], 0.0)
        previous_ends = (jnp.einsum("bjac,jc->ba", between, local[:, -1])
                         + jnp.einsum("bac,c->ba", F.block_powers[:count], start))
    else:
        def carry(end, block_end):
            return F.powers[L] @ end + block_end, end

        _, previous_ends = jax.lax.scan(carry, start, local[:, -1])
    x = local + jnp.einsum("lac,bc->bla", F.powers[1:], previous_ends)
    return x.reshape(rows, n)


@linear_recursion.defjvp
def _linear_recursion_jvp(primals, tangents):
    """The tangent of x_r = F x_{r−1} + v_r is the same recursion, x'_r = F x'_{r−1} + (F' x_{r−1} + v'_r):
    derivatives of any order reuse F's powers instead of differentiating the products with them."""
    F, v, start = primals
    dF, dv, dstart = tangents
    x = linear_recursion(F, v, start)
    before = jnp.concatenate([start[None], x[:-1]])
    return x, linear_recursion(F, applied(before, dF.powers[1]) + dv, dstart)


def applied(rows, M):
    """``rows @ Mᵀ`` for a matrix M of a few columns, as a fused multiply-sum: a matrix-multiply
    call with two columns is several times slower here, and more so with the derivatives' tangents."""
    if M.shape[1] > small.SMALL:
        return rows @ M.T
    return jnp.sum(rows[..., None, :] * M, axis=-1)


def padding_rows(rows):
    """The rows that pad a series to its length bucket (no interval, nothing observed), see ``filters.api``."""
    return (rows.dt == 0) & jnp.all(rows.mask == 0, axis=-1)


def steady_rows(model: SteadyModel, steady: SteadyState, x_start, rows, padding):
    """The filter over a chunk of rows in the steady state, all at once.

    Returns per-row ``(x_pred, cov_pred, transition, Update, y_pred)`` — what a
    step of the ordinary filter gives — and the carried ``(x, cov)`` at the end.
    Rows marked ``padding`` (only after the series' last row) count nothing in
    the criterion; the means carried through them are never used.
    """
    disc, C = model.disc, model.C
    n_rows = rows.t.shape[0]
    b_prev = jax.vmap(model.affine_drift)(rows.u_prev, rows.t_prev)
    b_cur = jax.vmap(model.affine_drift)(rows.u_cur, rows.t)
    inputs = applied(b_prev, disc.input_gain) + model.foh * applied(b_cur - b_prev, disc.ramp_gain)  # Γb + Υ(b' − b)
    offsets = jax.vmap(model.affine_output)(rows.u_cur, rows.t)  # h(0, u, t)
    IKC = jnp.eye(C.shape[1]) - steady.gain @ C
    # x_{k|k} = (I − KC)(Φ x_{k−1|k−1} + input terms) + K(y_k − h(0, u_k, t_k))
    v = applied(inputs, IKC) + applied(rows.y - offsets, steady.gain)
    filtered = linear_recursion(steady.recursion, v, x_start)
    before = jnp.concatenate([x_start[None], filtered[:-1]])
    predicted = applied(before, disc.transition) + inputs
    y_pred = applied(predicted, C) + offsets
    innovation = rows.y - y_pred
    whitened = applied(innovation, steady.whitening)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diag(steady.chol_R)))

    def each(a):
        return jnp.broadcast_to(a, (n_rows, *jnp.shape(a)))

    cov_pred, cov_filt = from_matrix(steady.predicted, model.form), from_matrix(steady.filtered, model.form)
    counted = jnp.where(padding, 0.0, 1.0)
    terms = StepTerms(whitened * counted[:, None], counted * logdet, counted * C.shape[0])
    update = Update(filtered, each(cov_filt), innovation, each(steady.innovation_cov), terms,
                    jnp.zeros(innovation.shape[:-1]))
    return (predicted, each(cov_pred), each(disc.transition), update, y_pred), (filtered[-1], cov_filt)
