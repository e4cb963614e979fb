"""Long regular series through the exact Kalman filter: the steady state in vectorised blocks.

For a time-invariant linear model sampled at a constant interval the filter's
covariance recursion (4.35, 4.29) does not depend on the data and converges to
the solution P∞ of the discrete algebraic Riccati equation.  From there on the
gain K, the innovation covariance R and the filtered covariance are constant, and
the mean follows a linear recursion x_k = F x_{k−1} + v_k with F = (I − KC)Φ,
which is computed a block of rows at a time by one matrix product instead of a
sequential step per row (Anderson and Moore, "Optimal Filtering", ch. 4).

A long series (MIN_ROWS rows or more) is cut into chunks of CHUNK rows.  A
chunk runs through the ordinary filter steps until, at a chunk's end, the
filtered covariance equals the steady state's to TOLERANCE; the following chunks
that are fully observed at the regular interval then take the steady-state form.
A chunk with a missing value or another interval runs the ordinary steps again
(and checks again at its end).  P∞ comes from the doubling algorithm.

A shorter series (SHORT_ROWS rows or more) runs its first HEAD rows step by
step, and if the filter's covariance there has settled ([`settled_state()`][greyid.filters.steady.settled_state],
to SETTLED_TOLERANCE) and every later row is fully observed at the regular
interval, those rows take the steady-state form all at once; otherwise they run
step by step too.  The Armadillo filter's covariance is within 1e-10 of P∞
after 16 rows at the optimum and about 30 at the fit's starting values (the
tests' random linear model: 24), and a sequential step costs about a tenth of
the whole vectorised rest.

The answers equal the ordinary filter's up to the tolerances; the derivatives
are P∞'s: through the doubling iterations (long series), by the implicit
function theorem (shorter ones, [`steady_prediction()`][greyid.filters.steady.steady_prediction]).
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from . import small
from .discretize import Discretization
from .updates import GaussianState, StepTerms, Update, from_matrix, symmetrize, to_matrix

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
#: Rows (the series' padded length) from which a shorter series may take the steady state.
SHORT_ROWS = 128
#: Rows of a shorter series' rest up to which [`short_recursion()`][greyid.filters.steady.short_recursion] takes it
#: (longer ones:
#: [`linear_recursion()`][greyid.filters.steady.linear_recursion]).
SHORT_REST = 1024
#: Rows of a shorter series that run step by step before it tests whether its filter has settled.
HEAD = 32
#: A fit's Hessian program (forward mode) tests whether a shorter series' filter has settled after
#: every TEST_EVERY rows, until it has (core.loop_until_settled).
TEST_EVERY = 16
#: A shorter series switches when the filter's predicted covariance is within this relative
#: distance of P∞ (as TOLERANCE).  The rows after the switch then differ from the ordinary
#: filter's by about this much each, times the few rows the filter would still take to settle:
#: 1e-10 keeps the log-likelihood within 1e-9 (absolute) of the ordinary filter's.
SETTLED_TOLERANCE = 1e-10
#: Doubling iterations of the Lyapunov sum in [`settled_state()`][greyid.filters.steady.settled_state]
#: (2^SMITH_DOUBLINGS terms).
SMITH_DOUBLINGS = 8


def switches(n_rows: int, asked: bool) -> bool:
    """Whether a series of ``n_rows`` (padded) rows takes the steady-state form where it can: long
    ones always, shorter ones where the filter's options ask for it."""
    return n_rows >= MIN_ROWS or (asked and n_rows >= SHORT_ROWS)


class SteadyModel(NamedTuple):
    """The time-invariant pieces of a linear model at its regular sampling interval."""

    disc: Discretization  # Φ, Γ, Υ, Λ of the regular interval
    regular_index: jnp.ndarray | None  # that interval's index into FilterInputs.unique_dt
    C: jnp.ndarray  # ∂h/∂x
    noise: jnp.ndarray  # S, the outputs' noise covariance (full matrix)
    foh: jnp.ndarray
    form: str  # how the filter carries its covariance
    theta: jnp.ndarray
    affine_drift_at: Callable  # (u, t, θ) -> f(0, u, t)
    affine_output_at: Callable  # (u, t, θ) -> h(0, u, t)

    @property
    def affine_drift(self) -> Callable:
        """(u, t) -> f(0, u, t) at this θ."""
        return lambda u, t: self.affine_drift_at(u, t, self.theta)

    @property
    def affine_output(self) -> Callable:
        """(u, t) -> h(0, u, t) at this θ."""
        return lambda u, t: self.affine_output_at(u, t, self.theta)


class SteadyState(NamedTuple):
    """P∞ and what the steady-state filter derives from it."""

    predicted: jnp.ndarray  # P∞ = P_{k|k−1}
    filtered: jnp.ndarray  # P_{k|k}
    gain: jnp.ndarray  # K = P∞Cᵀ R⁻¹
    innovation_cov: jnp.ndarray  # R = C P∞ Cᵀ + S
    chol_R: jnp.ndarray
    whitening: jnp.ndarray  # L⁻¹ with R = LLᵀ: one product per chunk instead of a triangular solve per row
    closed_loop: jnp.ndarray  # F = (I − KC)Φ, of the filtered mean's recursion x_k = F x_{k−1} + v_k
    recursion: "Recursion | None"  # F's powers for linear_recursion(); None: short_recursion()


def riccati_solution(transition, noise, C, S):
    """P∞ = ΦPΦᵀ − ΦPCᵀ(CPCᵀ + S)⁻¹CPΦᵀ + Λ by the structure-preserving doubling algorithm.

    The control-form iteration of Chu, Fan and Lin (2005) on the dual problem
    (A = Φᵀ, G = CᵀS⁻¹C, H = Λ): Hₖ is the covariance after 2ᵏ steps of the
    recursion from P = Λ, so it converges quadratically once the filter's
    closed loop is stable.  Where there is no steady state (a mode that is
    neither stable nor observed) the result is meaningless or NaN: the carried
    covariance never equals it, so no chunk switches ([`at_steady_state()`][greyid.filters.steady.at_steady_state]).
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


def steady_state(model: SteadyModel, predicted=None, rows: int | None = None, filtered: bool = True) -> SteadyState:
    """P∞ and the constant gain, innovation covariance (4.28–4.29) and filtered covariance of the steady state.

    ``predicted`` is P∞ where the caller has it (a shorter series); otherwise it
    comes from [`riccati_solution()`][greyid.filters.steady.riccati_solution].  F's powers for
    [`linear_recursion()`][greyid.filters.steady.linear_recursion]
    are computed for ``rows`` (of the rest) beyond SHORT_REST.  Without ``filtered`` the filtered
    covariance is None (a sum of the rest's criterion needs none).
    """
    P = predicted
    if P is None:
        P = riccati_solution(model.disc.transition, model.disc.noise_covariance, model.C, model.noise)
    # The small-matrix routines: a few fused kernels instead of LAPACK calls and their derivatives.
    mm = small.mm
    PCt = mm(P, model.C.T)
    R = symmetrize(mm(model.C, PCt) + model.noise)
    chol_R = small.cholesky(R)
    gain = small.cho_solve(chol_R, PCt.T).T
    IKC = jnp.eye(P.shape[0]) - mm(gain, model.C)
    if filtered:
        filtered = symmetrize(mm(mm(IKC, P), IKC.T) + mm(mm(gain, model.noise), gain.T))  # Joseph form
    else:
        filtered = None
    whitening = small.solve_lower(chol_R, jnp.eye(R.shape[0]))
    F = mm(IKC, model.disc.transition)
    powers = recursion(F) if rows is None or rows > SHORT_REST else None
    return SteadyState(P, filtered, gain, R, chol_R, whitening, F, powers)


def at_steady_state(cov, form: str, steady: SteadyState, tolerance: float = TOLERANCE):
    """Whether the carried filtered covariance equals P∞'s filtered one (see TOLERANCE)."""
    scale = jnp.sqrt(jnp.diag(steady.filtered))
    difference = jnp.abs(to_matrix(cov, form) - steady.filtered) / jnp.outer(scale, scale)
    return jnp.max(difference) <= tolerance  # False where anything is NaN


def settled_state(model: SteadyModel, cov, rows: int, filtered: bool = True, written: bool = False):
    """``(SteadyState, settled)`` from the filtered covariance a shorter series carries out of its first rows
    (``rows`` more to come; ``filtered`` as for [`steady_state()`][greyid.filters.steady.steady_state], ``written``
    as for [`steady_prediction()`][greyid.filters.steady.steady_prediction]).

    ``settled`` says whether the filter's next prediction P = ΦP_{k|k}Φᵀ + Λ is
    P∞ to SETTLED_TOLERANCE, tested against one Newton step (Hewer's iteration)
    from P: with P's gain K held, the covariance in the long run solves the Lyapunov
    equation X = F X Fᵀ + Q with F = Φ(I − KC) and Q = ΦKSKᵀΦᵀ + Λ, summed by
    doubling (Smith's method).  The step converges quadratically, so X is P∞ to
    rounding wherever P is close, and never equals P where the sum does not
    converge (an unstable F, a closed loop too slow for 2^SMITH_DOUBLINGS steps:
    spectral radius above about 0.93).  The steady state is X, with P∞'s own
    derivatives ([`steady_prediction()`][greyid.filters.steady.steady_prediction]): those the first rows gave P still
    hold the initial state's, which P∞ has none of.
    """
    P, X, settled = newton_test(model, cov)
    # Where it has not settled the steady state is not used: P keeps everything finite.
    X = jnp.where(settled, X, P)
    disc = model.disc
    P_infinity = steady_prediction(X, disc.transition, disc.noise_covariance, model.C, model.noise, written)
    return steady_state(model, P_infinity, rows, filtered), settled


def newton_test(model: SteadyModel, cov):
    """``(P, X, settled)``: the next prediction P from the filtered covariance ``cov``, one Newton step X
    from it, and whether the two agree (see [`settled_state()`][greyid.filters.steady.settled_state]); values only, no
    derivatives."""
    disc = model.disc
    P = symmetrize(small.mm(small.mm(disc.transition, to_matrix(cov, model.form)), disc.transition.T)
                   + disc.noise_covariance)
    T, noise, C, S, P = jax.lax.stop_gradient((disc.transition, disc.noise_covariance, model.C, model.noise, P))
    gain, F = closed_loop(P, T, C, S)
    TK = small.mm(T, gain)
    X = symmetrize(small.mm(small.mm(TK, S), TK.T) + noise)
    X, F = smith_sum(X, F)
    scale = jnp.sqrt(jnp.diag(X))
    difference = jnp.max(jnp.abs(P - X) / jnp.outer(scale, scale))
    # False where anything is not finite (a growing F overflows).
    return P, X, (jnp.max(jnp.abs(F)) <= 1e-8) & (difference <= SETTLED_TOLERANCE)


def closed_loop(P, transition, C, S):
    """The gain K = PCᵀ(CPCᵀ + S)⁻¹ of a predicted covariance P (4.28) and the closed loop F = Φ(I − KC)."""
    PCt = small.mm(P, C.T)
    gain = small.cho_solve(small.cholesky(symmetrize(small.mm(C, PCt) + S)), PCt.T).T
    return gain, small.mm(transition, jnp.eye(P.shape[0]) - small.mm(gain, C))


def smith_sum(X, F, symmetric: bool = True):
    """``(Σ_{k<2^d} F^k X (F^k)ᵀ, F^(2^d))`` with d = SMITH_DOUBLINGS, by doubling (Smith's method): the
    solution of the Stein equation Y = F Y Fᵀ + X where F's powers have vanished.

    Each doubling adds F Y Fᵀ to the sum and squares F.  A loop rather than unrolled products: the
    programs that differentiate the steady state twice then trace one doubling instead of eight
    (as [`discretize()`][greyid.filters.discretize.discretize] does with its Taylor terms).
    ``symmetric``: symmetrize the sum after each doubling (a covariance; a tangent is symmetrized
    by the caller once).
    """
    def double(_, sum_and_power):
        Y, power = sum_and_power
        Y = Y + small.mm(small.mm(power, Y), power.T)
        return (symmetrize(Y) if symmetric else Y), small.mm(power, power)

    return jax.lax.fori_loop(0, SMITH_DOUBLINGS, double, (X, F))


def riccati_step(P, transition, noise, C, S):
    """The filter's next predicted covariance ΦPΦᵀ − ΦPCᵀ(CPCᵀ + S)⁻¹CPΦᵀ + Λ (4.29, 4.35)."""
    TPCt = small.mm(small.mm(transition, P), C.T)
    R = symmetrize(small.mm(small.mm(C, P), C.T) + S)
    return symmetrize(small.mm(small.mm(transition, P), transition.T)
                      - small.mm(TPCt, small.cho_solve(small.cholesky(R), TPCt.T)) + noise)


def riccati_step_tangent(P, transition, C, S, d_transition, d_noise, dC, dS):
    """The derivative of [`riccati_step()`][greyid.filters.steady.riccati_step] in Φ, Λ, C and S with P held,
    written out, and the closed loop F = Φ(I − KC) at P: ``(∂R, F)``.

    With the gain K = PCᵀ(CPCᵀ + S)⁻¹, the predictor's gain ΦK and the filtered covariance
    P_f = (I − KC)P,

        ∂R = dΦ P_f Φᵀ + Φ P_f dΦᵀ − ΦK dC P Fᵀ − F P dCᵀ (ΦK)ᵀ + ΦK dS (ΦK)ᵀ + dΛ:

    a handful of products where differentiating the step carries the tangents through the
    factorisation of CPCᵀ + S.
    """
    gain, F = closed_loop(P, transition, C, S)
    predictor_gain = small.mm(transition, gain)
    filtered = P - small.mm(gain, small.mm(C, P))
    through_transition = small.mm(small.mm(d_transition, filtered), transition.T)
    through_output = small.mm(small.mm(predictor_gain, dC), small.mm(P, F.T))
    tangent = (through_transition + through_transition.T - through_output - through_output.T
               + small.mm(small.mm(predictor_gain, dS), predictor_gain.T) + d_noise)
    return tangent, F


@functools.partial(jax.custom_jvp, nondiff_argnums=(5,))
def steady_prediction(X, transition, noise, C, S, written: bool = False):
    """P∞ = X (given, found by [`settled_state()`][greyid.filters.steady.settled_state]), with the derivatives of the
    Riccati equation's fixed point.

    P∞ = R(P∞; Φ, Λ, C, S) gives, by the implicit function theorem,
    dP∞ = F dP∞ Fᵀ + ∂R (the step's derivative with P∞ held), F = Φ(I − KC) the
    closed loop at P∞, summed by SMITH_DOUBLINGS doublings with F, F², F⁴, …
    (Smith's method, as the test's sum).  The rule is written in this function's
    own output, so derivatives of higher order follow from it too, and it is
    linear in the tangents, so reverse mode transposes it.  ∂R is the step's
    derivative by JAX, or with ``written`` the one written out
    ([`riccati_step_tangent()`][greyid.filters.steady.riccati_step_tangent]): fewer operations to compile
    where the rule is differentiated again and transposed (a fit's Hessian), slower to run in a
    forward-mode gradient (the public likelihood's; docs/performance.md).
    """
    return X


@steady_prediction.defjvp
def _steady_prediction_jvp(written, primals, tangents):
    X, transition, noise, C, S = primals
    _, d_transition, d_noise, dC, dS = tangents
    P = steady_prediction(X, transition, noise, C, S, written)  # carries its own derivatives at the next order
    if written:
        dP, F = riccati_step_tangent(P, transition, C, S, d_transition, d_noise, dC, dS)
    else:
        _, dP = jax.jvp(lambda *a: riccati_step(P, *a), (transition, noise, C, S),
                        (d_transition, d_noise, dC, dS))
        _, F = closed_loop(P, transition, C, S)
    dP, _ = smith_sum(dP, F, symmetric=False)
    return P, symmetrize(dP)


class Recursion(NamedTuple):
    """The powers of F that [`linear_recursion()`][greyid.filters.steady.linear_recursion] applies, computed once per
    steady state."""

    powers: jnp.ndarray  # F⁰ … F^BLOCK
    toeplitz: jnp.ndarray  # (BLOCK, BLOCK, n, n): F^(l−i) where l ≥ i, else 0
    block_powers: jnp.ndarray  # (F^BLOCK)⁰ … (F^BLOCK)^⌈CHUNK/BLOCK⌉: from block to block


def _powers(F, count):
    return jax.lax.scan(lambda M, _: (F @ M, M), jnp.eye(F.shape[0]), None, length=count + 1)[1]


def recursion(F) -> Recursion:
    """[`Recursion`][greyid.filters.steady.Recursion] of x_r = F x_{r−1} + v_r."""
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


@jax.custom_jvp
def short_recursion(F, v, start):
    """x_r = F x_{r−1} + v_r for r = 0 … len(v) − 1, x_{−1} = start: the rest of a shorter series.

    The recursion is a block-bidiagonal linear system, solved by two triangular
    solves, each one call: within blocks of BLOCK rows, (I − S⊗F) X = V for all
    blocks at once (S shifts one row down; forward substitution is the recursion
    itself, the same products), and between blocks the blocks' ends,
    e_b = F^BLOCK e_{b−1} + (block b's own end), with F^BLOCK from
    (I − S⊗F) G = (F, 0, …, 0) (G = F, F², …, F^BLOCK).  A handful of kernels,
    where powers of F and products with them took dozens: on a few hundred rows
    these calls, not the arithmetic, are the cost.  Not for long series: the
    system between blocks grows with the square of their number.
    """
    rows, n = v.shape
    L = BLOCK
    count = -(-rows // L)
    if count * L > rows:  # a last partial block padded with v = 0 (rows beyond the end, dropped)
        v = jnp.concatenate([v, jnp.zeros((count * L - rows, n), v.dtype)])
    solve = functools.partial(jax.scipy.linalg.solve_triangular, lower=True, unit_diagonal=True)
    within = jnp.eye(L * n) - jnp.kron(jnp.eye(L, k=-1), F)
    local = solve(within, v.reshape(count, L * n).T)  # (L n, count): each block from x = 0
    # G is solved for apart from the data's blocks: mixed into one solve, G would carry the
    # derivatives' tangents, and reverse mode could not transpose G times them.
    G = solve(within, jnp.zeros((L * n, n), F.dtype).at[:n].set(F))
    F_block = G[-n:]
    ends = local[-n:].T.at[0].add(small.mm(F_block, start))  # (count, n)
    between = jnp.eye(count * n) - jnp.kron(jnp.eye(count, k=-1), F_block)
    carried = solve(between, ends.reshape(-1)).reshape(count, n)  # x at the end of each block
    starts = jnp.concatenate([start[None], carried[:-1]])
    x = local + G @ starts.T
    return x.T.reshape(count * L, n)[:rows]


@jax.custom_jvp
def doubling_recursion(F, v, start):
    """[`short_recursion()`][greyid.filters.steady.short_recursion] as a prefix sum by doubling (Hillis and Steele),
    for a fit's Hessian.

    With the start folded into the first row, level k adds to each row F^(2^k)
    times the row 2^k before it, so that after it each row holds Σ F^(r−j) v_j
    over its last 2^(k+1) rows: ⌈log₂ rows⌉ levels of a shifted product and a
    sum, and no LAPACK call.  The Hessian's rest ([`summed_rest()`][greyid.filters.steady.summed_rest]) takes its
    gradient in reverse mode, which transposes the triangular solves into LAPACK
    calls with dozens of right-hand sides; the BLAS library spreads those over
    its threads, and a thread held by other work stalls the fit: Armadillo fits
    with ``steady_state=True`` run several times faster by doubling.  The value
    and gradient (forward mode, a few right-hand sides) keep the solves, which
    are no slower there (``benchmarks/likelihood.py``).
    """
    rows = v.shape[0]
    x = v.at[0].add(small.mm(F, start))

    # A loop over the levels, each traced and differentiated once (as smith_sum's doublings): the rows
    # 2^k before each, zeros before the first, are a slice of the rows behind as many zeros.
    def level(k, x_and_power):
        x, power = x_and_power
        shifted = jax.lax.dynamic_slice_in_dim(jnp.concatenate([jnp.zeros_like(x), x]), rows - 2 ** k, rows)
        return x + applied(shifted, power), small.mm(power, power)

    return jax.lax.fori_loop(0, (rows - 1).bit_length(), level, (x, F))[0]


def _same_recursion(recursion):
    """The derivative rule of a mean recursion: as
    [`_linear_recursion_jvp()`][greyid.filters.steady._linear_recursion_jvp], the tangent is the
    same recursion, x'_r = F x'_{r−1} + (F' x_{r−1} + v'_r)."""
    def rule(primals, tangents):
        F, v, start = primals
        dF, dv, dstart = tangents
        x = recursion(F, v, start)
        before = jnp.concatenate([start[None], x[:-1]])
        return x, recursion(F, applied(before, dF) + dv, dstart)

    return rule


short_recursion.defjvp(_same_recursion(short_recursion))
doubling_recursion.defjvp(_same_recursion(doubling_recursion))


def applied(rows, M):
    """``rows @ Mᵀ`` for a matrix M of a few columns, as a fused multiply-sum: a matrix-multiply
    call with two columns is several times slower here, and more so with the derivatives' tangents."""
    if M.shape[1] > small.SMALL:
        return rows @ M.T
    return jnp.sum(rows[..., None, :] * M, axis=-1)


def padding_rows(rows):
    """The rows that pad a series to its length bucket (no interval, nothing observed), see ``filters.api``."""
    return (rows.dt == 0) & jnp.all(rows.mask == 0, axis=-1)


def usable_rows(model: SteadyModel, rows):
    """The rows the steady-state form can take: at the regular interval with every output observed, or
    padding."""
    return ((rows.dt_index == model.regular_index) & jnp.all(rows.mask > 0, axis=-1)) | padding_rows(rows)


def steady_means(model: SteadyModel, steady: SteadyState, x_start, rows, padding,
                 short: Callable = short_recursion):
    """The means of the filter over a chunk of rows in the steady state, all at once, and each row's
    terms of the criterion: ``(filtered, predicted, y_pred, innovation, StepTerms)`` per row (see
    [`steady_rows()`][greyid.filters.steady.steady_rows], which adds the constant covariances)."""
    disc, C = model.disc, model.C
    # The drift's affine part at both ends of every interval, in one call (one trace of the model's drift).
    b_prev, b_cur = jnp.split(jax.vmap(model.affine_drift)(jnp.concatenate([rows.u_prev, rows.u_cur]),
                                                           jnp.concatenate([rows.t_prev, rows.t])), 2)
    inputs = applied(b_prev, disc.input_gain) + model.foh * applied(b_cur - b_prev, disc.ramp_gain)  # Γb + Υ(b' − b)
    offsets = jax.vmap(model.affine_output)(rows.u_cur, rows.t)  # h(0, u, t)
    IKC = jnp.eye(C.shape[1]) - steady.gain @ C
    # x_{k|k} = (I − KC)(Φ x_{k−1|k−1} + input terms) + K(y_k − h(0, u_k, t_k))
    v = applied(inputs, IKC) + applied(rows.y - offsets, steady.gain)
    if steady.recursion is None:
        filtered = short(steady.closed_loop, v, x_start)
    else:
        filtered = linear_recursion(steady.recursion, v, x_start)
    before = jnp.concatenate([x_start[None], filtered[:-1]])
    predicted = applied(before, disc.transition) + inputs
    y_pred = applied(predicted, C) + offsets
    innovation = rows.y - y_pred
    whitened = applied(innovation, steady.whitening)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diag(steady.chol_R)))
    counted = jnp.where(padding, 0.0, 1.0)
    terms = StepTerms(whitened * counted[:, None], counted * logdet, counted * C.shape[0])
    return filtered, predicted, y_pred, innovation, terms


def steady_rows(model: SteadyModel, steady: SteadyState, x_start, rows, padding,
                short: Callable = short_recursion):
    """The filter over a chunk of rows in the steady state, all at once.

    Returns per-row ``(x_pred, cov_pred, transition, Update, y_pred)`` — what a
    step of the ordinary filter gives — and the carried ``(x, cov)`` at the end.
    Rows marked ``padding`` (only after the series' last row) count nothing in
    the criterion; the means carried through them are never used.  ``short``:
    the mean's recursion over a shorter series' rest ([`short_recursion()`][greyid.filters.steady.short_recursion] or
    [`doubling_recursion()`][greyid.filters.steady.doubling_recursion]).
    """
    filtered, predicted, y_pred, innovation, terms = steady_means(model, steady, x_start, rows, padding, short)
    n_rows = rows.t.shape[0]

    def each(a):
        return jnp.broadcast_to(a, (n_rows, *jnp.shape(a)))

    cov_pred, cov_filt = from_matrix(steady.predicted, model.form), from_matrix(steady.filtered, model.form)
    update = Update(filtered, each(cov_filt), innovation, each(steady.innovation_cov), terms,
                    jnp.zeros(innovation.shape[:-1]))
    return (predicted, each(cov_pred), each(model.disc.transition), update, y_pred), GaussianState(filtered[-1],
                                                                                                   cov_filt)


class RestRows(NamedTuple):
    """The rows [`steady_rows()`][greyid.filters.steady.steady_rows] reads (a shorter series' rest)."""

    t: jnp.ndarray
    t_prev: jnp.ndarray
    u_prev: jnp.ndarray
    u_cur: jnp.ndarray
    y: jnp.ndarray


def summed_rest(accumulate: Callable, model: SteadyModel, x_start, cov, rows):
    """Σ accumulate(StepTerms_r) over a shorter series' rest in the steady state, settled from the
    filtered covariance ``cov`` that the rows before carried out
    ([`settled_state()`][greyid.filters.steady.settled_state], [`steady_rows()`][greyid.filters.steady.steady_rows]).

    Its derivatives come from its own rule, which takes the gradient in reverse mode: a fit's Hessian
    (forward over forward) then differentiates the rest forward over reverse, carrying each row's
    seven tangents instead of the 49 of second order, which pays more the longer the series.
    Padding rows (no interval, nothing observed) count nothing.
    """
    static = (accumulate, model.form, model.affine_drift_at, model.affine_output_at)
    diff = (model.theta, model.disc, model.C, model.noise, model.foh, x_start, cov)
    counted = jnp.where(padding_rows(rows), 0.0, 1.0)
    data = (RestRows(rows.t, rows.t_prev, rows.u_prev, rows.u_cur, rows.y), counted)
    return _summed_rest(static, diff, data)


def _rest_sum(static, diff, data):
    accumulate, form, drift_at, output_at = static
    theta, disc, C, noise, foh, x_start, cov = diff
    rows, counted = data
    model = SteadyModel(disc, None, C, noise, foh, form, theta, drift_at, output_at)
    steady, _ = settled_state(model, cov, rows.t.shape[0], filtered=False, written=True)
    terms = steady_means(model, steady, x_start, rows, counted == 0, short=doubling_recursion)[-1]
    return jnp.sum(jax.vmap(accumulate)(terms))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _summed_rest(static, diff, data):
    return _rest_sum(static, diff, data)


def _summed_rest_jvp(static, primals, tangents):
    """The tangent ∇f · dθ with ∇f by reverse mode (the data have none)."""
    diff, data = primals
    d_diff, _ = tangents
    value, gradient = jax.value_and_grad(lambda d: _rest_sum(static, d, data))(diff)
    tangent = jnp.zeros_like(value)
    is_zero = lambda a: isinstance(a, SymbolicZero)  # noqa: E731
    for g, t in zip(jax.tree_util.tree_leaves(gradient), jax.tree_util.tree_leaves(d_diff, is_leaf=is_zero)):
        if not is_zero(t):
            tangent = tangent + jnp.vdot(g, t)
    return value, tangent


_summed_rest.defjvp(_summed_rest_jvp, symbolic_zeros=True)
