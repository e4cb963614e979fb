"""The Laplace method: the states on a time grid as random effects, integrated out (``method="laplace"``).

The states at the sample times, and at ``substeps`` − 1 points between each two,
X = (x_0, …, x_T), have the joint log-density

    J(X, θ) = log p(x_0) + Σ_j log N(x_{j+1}; m_j(x_j), V_j) + Σ_k log p(y_k | x_{k·s}),

with Gaussian transitions: Euler–Maruyama (m_j = x_j + f Δ, V_j = G Gᵀ Δ) or,
where the drift and diffusion are linear and time-invariant, the exact
discretization (4.36)–(4.39) over Δ; and any observation distribution
([`distributions`][greyid.model.distributions]).  The likelihood
p(Y | θ) = ∫ e^{J} dX is approximated by Laplace's method about the mode X̂(θ):

    log L(θ) ≈ J(X̂, θ) + (d/2) log 2π − ½ log det(−∂²J/∂X²(X̂, θ)),   d = n(T + 1).

The Hessian of J is block-tridiagonal (each term couples at most two neighbouring
states), so the mode is found by Newton steps solved with its block Cholesky
factor and the log-determinant read off the same factor: cost linear in T.  The
mode's derivative in θ is implicit, dX̂ = −H⁻¹ ∂²J/∂X∂θ dθ (a custom JVP), so
value, gradient and Hessian in θ are exact derivatives of the approximation.
For a linear Gaussian model the approximation is exact: it equals the Kalman
filter of the same discretization.

``scheme="euler"`` takes Euler–Maruyama transitions for any model (the grid's
sub-steps then converge to the exact likelihood); ``scheme="ctsmtmb"`` reproduces
ctsmTMB's ``method = "laplace"``: Euler–Maruyama transitions always, with
G Gᵀ + 10⁻⁸ I in place of G Gᵀ, and the inputs interpolated linearly between
samples.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import log_ndtr

from ..errors import ModelError
from ..model.distributions import COUNTS, NORMAL, cdf, observations_log_density
from ..model.structure import Structure
from . import small
from .delays import Pieces, piece_drift, step_pieces
from .discretize import discretize, discretize_each
from .gaussian import initial_state
from .protocol import FilterInputs, FilterOptions, series_rows
from .updates import observed_root, symmetrize, whiten

#: Newton steps at most, and the largest step (relative to the states' size) that ends the search.
NEWTON_STEPS = 50
NEWTON_TOLERANCE = 1e-10
#: The one-step residuals' searches (a mode per observation) stop at a full Newton step this short: the search's last
#: full step takes the mode to about its square, as close as NEWTON_TOLERANCE's loop takes it, one step sooner.
ONE_STEP_TOLERANCE = 1e-6
#: No devices named: the abstract mesh JAX traces a jitted function's body under (see ``mode`` in
#: [`build()`][greyid.filters.laplace.build]).
EMPTY_MESH = jax.sharding.AbstractMesh((), ())

#: ctsmTMB's jitter of G Gᵀ in its Laplace method.
CTSMTMB_JITTER = 1e-8
#: The shortest step along a Newton direction tried before the search stops, and the smallest curvature
#: a gradient step is scaled by.
MIN_STEP_LENGTH = 2.0**-20
MIN_CURVATURE = 1e-12
#: The stages of a Newton search's loop: damped steps, the last full step, done.
SEARCHING, LAST, DONE = (np.int32(stage) for stage in range(3))


class Grid(NamedTuple):
    """The fine grid's steps: from state j to j + 1 over ``length`` with inputs ``u_start``→``u_end``."""

    start: jnp.ndarray  # (T,)
    length: jnp.ndarray  # (T,)
    u_start: jnp.ndarray  # (T, nu)
    u_end: jnp.ndarray  # (T, nu)
    interval: jnp.ndarray  # (T,) the step's sampling interval among the data's distinct ones
    #: With delayed inputs, each step cut where they switch ([`step_pieces()`][greyid.filters.delays.step_pieces]).
    pieces: Pieces | None = None


class Terms(NamedTuple):
    """The joint log-density's pieces at one θ: the grid, the transition's, observations' and initial
    state's log-densities, the rows they read, x0 and the drift (where Newton starts)."""

    grid: Grid
    transition: Callable
    observed: Callable
    prior: Callable
    rows: tuple
    x0: jnp.ndarray
    drift: Callable
    #: The ``cdf`` terms of ``pieces`` (one row's) as a function of that row's states, and their index in X.
    tail: Callable | None = None
    tail_at: jnp.ndarray | None = None


def fine_grid(data: FilterInputs, substeps: int, linear_inputs: bool) -> Grid:
    """The grid's steps: ``substeps`` per sampling interval (rows 1 … N − 1; padding rows have length 0)."""
    fraction = jnp.arange(substeps) / substeps
    t_prev, dt = data.t_prev[1:], data.dt[1:]
    start = (t_prev[:, None] + dt[:, None] * fraction[None, :]).reshape(-1)
    length = jnp.repeat(dt / substeps, substeps)
    ramp = 1.0 if linear_inputs else data.foh
    du = (data.u_cur[1:] - data.u_prev[1:]) * ramp
    shape = (du.shape[0] * substeps, du.shape[-1])
    u_start = (data.u_prev[1:, None, :] + du[:, None, :] * fraction[None, :, None]).reshape(shape)
    u_end = (data.u_prev[1:, None, :] + du[:, None, :] * (fraction[None, :, None] + 1 / substeps)).reshape(shape)
    return Grid(start, length, u_start, u_end, jnp.repeat(data.dt_index[1:], substeps))


def block_cholesky(diagonal, lower):
    """The block Cholesky factor of a symmetric positive definite block-tridiagonal matrix with diagonal
    blocks ``diagonal`` (T+1, n, n) and blocks ``lower`` (T, n, n) below it: L_j and W_j = C_{j−1} L_{j−1}⁻ᵀ.

    The blocks are a few states wide: factorised and solved element by element
    ([`small`][greyid.filters.small]), which inside a scan is faster than LAPACK's calls (and
    its vectorised derivatives have hung XLA's CPU runtime on series of 8192 rows and more).
    """
    first = small.cholesky(diagonal[0])

    def step(previous, blocks):
        D, C = blocks
        W = small.solve_lower(previous, C.T).T
        L = small.cholesky(D - small.mm(W, W.T))
        return L, (L, W)

    _, (rest, couplings) = jax.lax.scan(step, first, (diagonal[1:], lower))
    return jnp.concatenate([first[None], rest]), couplings


def block_solve(factor, couplings, b):
    """x with A x = b, A = L Lᵀ from [`block_cholesky()`][greyid.filters.laplace.block_cholesky]; b (T+1, n)."""
    first = small.solve_lower(factor[0], b[0])

    def forward(previous, parts):
        L, W, bj = parts
        z = small.solve_lower(L, bj - small.mm(W, previous))
        return z, z

    _, rest = jax.lax.scan(forward, first, (factor[1:], couplings, b[1:]))
    z = jnp.concatenate([first[None], rest])
    last = small.solve_upper_transposed(factor[-1], z[-1])

    def backward(following, parts):
        L, W_next, zj = parts
        x = small.solve_upper_transposed(L, zj - small.mm(W_next.T, following))
        return x, x

    _, earlier = jax.lax.scan(backward, last, (factor[:-1], couplings, z[:-1]), reverse=True)
    return jnp.concatenate([earlier, last[None]])


def block_inverse_bands(factor, couplings):
    """The diagonal blocks of A⁻¹ (T+1, n, n) and the blocks right of them, Σ_{j,j+1} (T, n, n), from A's block
    Cholesky factor (L_j, W_j) (Takahashi's selected inversion).

    Lᵀ Σ = L⁻¹ is block lower triangular with diagonal blocks L_j⁻¹, so from the last block back,
    Σ_{j,j+1} = −L_j⁻ᵀ W_{j+1}ᵀ Σ_{j+1,j+1} and Σ_jj = L_j⁻ᵀ (L_j⁻¹ − W_{j+1}ᵀ Σ_{j+1,j}): the covariances
    of the Laplace approximation's marginals, in the same linear cost as the factorisation.
    """
    n = factor.shape[-1]
    eye = jnp.eye(n)

    def inverse_of(L):
        return small.solve_upper_transposed(L, small.solve_lower(L, eye))

    last = inverse_of(factor[-1])

    def backward(following, parts):
        L, W_next = parts
        cross = -small.solve_upper_transposed(L, small.mm(W_next.T, following))  # Σ_{j,j+1}
        inverse_L = small.solve_lower(L, eye)
        block = small.solve_upper_transposed(L, inverse_L - small.mm(W_next.T, cross.T))
        block = 0.5 * (block + block.T)
        return block, (block, cross)

    _, (earlier, crosses) = jax.lax.scan(backward, last, (factor[:-1], couplings), reverse=True)
    return jnp.concatenate([earlier, last[None]]), crosses


def block_inverse_diagonal(factor, couplings):
    """The diagonal blocks of A⁻¹ (see [`block_inverse_bands()`][greyid.filters.laplace.block_inverse_bands])."""
    return block_inverse_bands(factor, couplings)[0]


def block_matvec(diagonal, lower, x):
    """A x for the block-tridiagonal A (see [`block_cholesky()`][greyid.filters.laplace.block_cholesky])."""
    out = jnp.einsum("jab,jb->ja", diagonal, x)
    out = out.at[1:].add(jnp.einsum("jab,jb->ja", lower, x[:-1]))
    return out.at[:-1].add(jnp.einsum("jba,jb->ja", lower, x[1:]))


class Laplace(NamedTuple):
    """The Laplace method's functions of (θ, data): ``marginal`` (the value with exact derivatives in θ, and
    the mode), ``value(theta, data, cdf=None)`` (the value alone, optionally with CDF terms),
    ``smoothed(theta, data)`` (the mode at the sample times with its marginal covariances) and
    ``predictive(theta, data, k, i)`` (output i of row k standardized by its one-step Gaussian predictive) and
    ``one_step(theta, data)`` (every output so, in one pass forward, where the joint density is Gaussian)."""

    marginal: Callable
    value: Callable
    smoothed: Callable
    predictive: Callable
    one_step: Callable


def build(structure: Structure, options: FilterOptions) -> Laplace:
    """The [`Laplace`][greyid.filters.laplace.Laplace] functions of the method (see the module doc)."""
    if structure.delays and options.scheme == "ctsmtmb":
        raise ModelError("scheme='ctsmtmb' (ctsmTMB's transitions) does not take delay() inputs; use scheme='auto' "
                         "or 'euler'")
    n, s = structure.n_states, options.substeps
    families = structure.output_families
    f, G = structure.drift, structure.diffusion
    ctsmtmb = options.scheme == "ctsmtmb"
    exact = structure.linear_dynamics is not None and options.scheme == "auto"
    zeros = np.zeros(n)
    full = structure.observation_covariance

    def gaussian(root, residual):
        """log N(residual; 0, root rootᵀ)."""
        z = small.solve_lower(root, residual)
        return -0.5 * (z @ z) - jnp.sum(jnp.log(jnp.diag(root))) - 0.5 * n * jnp.log(2 * jnp.pi)

    def pieces(theta, data: FilterInputs, cdf=None) -> Terms:
        """The joint log-density's terms at θ, on the grid of ``data``: computed once per θ, outside the
        Newton loop that evaluates them many times.  ``cdf = (on, shift, upper)`` (N, outputs) adds, where
        ``on``, log P(Y ≤ y − shift | x) of each output, or log P(Y > y | x) where ``upper`` (the one-step
        transforms'); ``on`` marks outputs of one row at most (``Terms.tail``, taken at that row alone)."""
        series = series_rows(structure, theta, data)
        data = series.data
        grid = fine_grid(data, s, linear_inputs=ctsmtmb)
        if series.delays is not None:
            grid = grid._replace(pieces=step_pieces(series.delays, data, grid.start, grid.length, grid.u_start,
                                                    grid.u_end, structure.n_inputs))
        x0, P0 = initial_state(structure, theta, data)
        # Diffuse states ([`diffuse`][greyid.filters.diffuse]) have a flat prior: the others' Gaussian alone, less
        # ½ log 2π per diffuse state, so that the value is the exact diffuse likelihood in Koopman and Durbin's
        # convention (log ∫ p(y | δ) dδ − (d/2) log 2π, the limit of log p_κ(y) + (d/2) log κ).
        kept = np.array([i for i in range(n) if i not in structure.initial_covariance.diffuse], dtype=int)
        flat = 0.5 * (n - len(kept)) * np.log(2 * np.pi)
        prior_root = small.cholesky(0.5 * (P0 + P0.T)[np.ix_(kept, kept)]) if len(kept) else None
        if exact:  # one discretization per distinct step length, as the exact Kalman filter
            A, B, c = structure.linear_dynamics(theta)
            g = G(zeros, data.u_cur[0], data.t[0], theta)
            cache = discretize_each(A, g @ g.T, data.unique_dt / s)

            def pieces_mean(x, cut):
                def piece(x, p):
                    disc = discretize(A, g @ g.T, p.length)
                    b_start, b_end = B @ p.u_start + c, B @ p.u_end + c
                    return (disc.transition @ x + disc.input_gain @ b_start
                            + data.foh * disc.ramp_gain @ (b_end - b_start)), None

                return jax.lax.scan(piece, x, cut)[0]

        def transition(x, step):
            """log N(x_{j+1}; m_j(x_j), V_j); a step of length 0 (padding) is N(x_{j+1}; x_j, I)."""
            x_now, x_next = x[:n], x[n:]
            start, length, u_start, u_end, interval, cut = step
            still = length <= 0
            if exact:
                disc = jax.tree_util.tree_map(lambda a: a[interval], cache)
                if cut is None:
                    b_start, b_end = B @ u_start + c, B @ u_end + c
                    mean = (disc.transition @ x_now + disc.input_gain @ b_start
                            + data.foh * disc.ramp_gain @ (b_end - b_start))
                else:  # piece by piece where delayed inputs switch inside the step (the noise is the step's)
                    mean = pieces_mean(x_now, cut)
                V = disc.noise_covariance
            else:
                g = G(x_now, u_start, start, theta)
                velocity = (f(x_now, u_start, start, theta) if cut is None else
                            piece_drift(lambda x, u, t: f(x, u, t, theta), x_now, cut, data.foh))
                mean = x_now + velocity * length
                V = (g @ g.T + (CTSMTMB_JITTER * jnp.eye(n) if ctsmtmb else 0.0)) * length
            V = jnp.where(still, jnp.eye(n), 0.5 * (V + V.T))
            mean = jnp.where(still, x_now, mean)
            return gaussian(small.cholesky(V), x_next - mean)

        def law_of(x, row):
            """(y, the outputs' law) of ``row`` at x, both whitened where the noise is correlated, and L."""
            y, mask, u, t = row[:4]
            law = structure.observation_law(x, u, t, theta)
            if full is None:
                return y, law, None
            # Correlated noise: the observed outputs (and the one whose tail is taken) whitened by the
            # Cholesky factor L of their noise covariance, the density the whitened one's over det L.  A
            # whitened output's tail given the outputs before it is the output's own (L is triangular with
            # a positive diagonal), so the one-step transforms keep their meaning.
            seen = mask if cdf is None else jnp.maximum(mask, row[4])
            L = observed_root(full(zeros, u, t, theta), seen)
            return whiten(L, seen, y), (whiten(L, seen, law[0]), jnp.ones_like(law[1]), law[2]), L

        def observed(x, row):
            y, law, L = law_of(x, row)
            mask = row[1]
            value = observations_log_density(families, y, mask, *law)
            if full is not None:
                value = value - jnp.sum(jnp.where(mask > 0, jnp.log(jnp.diag(L)), 0.0))
            return value

        def tail(x, row):
            """The ``cdf`` terms of one row (its outputs where ``on``)."""
            y, law, _ = law_of(x, row)
            on, shift, upper = row[4:]
            value = 0.0
            for i, family in enumerate(families):
                # (y itself where off: a finite value whose derivatives are finite, which the where discards)
                at = jnp.where(on[i] > 0, y[i] - shift[i], y[i])
                term = log_tail(family, at, law[0][i], law[1][i], law[2][i], upper[i] > 0)
                value = value + jnp.where(on[i] > 0, term, 0.0)
            return value

        def drift(x, u, t):
            return f(x, u, t, theta)

        rows = (data.y, data.mask, data.u_cur, data.t) + (() if cdf is None else tuple(cdf))
        def prior(x):
            if prior_root is None:  # every state diffuse
                return -flat + 0.0 * jnp.sum(x)
            residual = (x - x0)[kept]
            z = small.solve_lower(prior_root, residual)
            return (-0.5 * (z @ z) - jnp.sum(jnp.log(jnp.diag(prior_root))) - 0.5 * len(kept) * jnp.log(2 * jnp.pi)
                    - flat)

        if cdf is None:
            return Terms(grid, transition, observed, prior, rows, x0, drift)
        # The cdf terms are one observation's (the one-step transforms'): taken at its row alone, not computed at
        # every row and discarded (a tail such as Poisson's incomplete gamma function is an iteration each).
        k = jnp.argmax(jnp.any(cdf[0] > 0, axis=1))
        row = tuple(a[k] for a in rows)
        return Terms(grid, transition, observed, prior, rows, x0, drift, lambda x: tail(x, row), k * s)

    def joint(terms: Terms, X):
        """J(X, θ) of the terms at θ: X (T + 1, n)."""
        pairs = jnp.concatenate([X[:-1], X[1:]], axis=1)
        value = (terms.prior(X[0]) + jnp.sum(jax.vmap(terms.transition)(pairs, terms.grid))
                 + jnp.sum(jax.vmap(terms.observed)(X[::s], terms.rows)))
        return value if terms.tail is None else value + terms.tail(X[terms.tail_at])

    def blocks(terms: Terms, X):
        """−∂²J/∂X²: its diagonal blocks (T + 1, n, n) and those below them (T, n, n)."""
        pairs = jnp.concatenate([X[:-1], X[1:]], axis=1)
        H_pairs = jax.vmap(jax.hessian(terms.transition))(pairs, terms.grid)  # (T, 2n, 2n)
        H_obs = jax.vmap(jax.hessian(terms.observed))(X[::s], terms.rows)  # (N, n, n)
        diagonal = jnp.zeros((X.shape[0], n, n))
        diagonal = diagonal.at[:-1].add(H_pairs[:, :n, :n]).at[1:].add(H_pairs[:, n:, n:])
        diagonal = diagonal.at[::s].add(H_obs).at[0].add(jax.hessian(terms.prior)(X[0]))
        if terms.tail is not None:
            diagonal = diagonal.at[terms.tail_at].add(jax.hessian(terms.tail)(X[terms.tail_at]))
        return -diagonal, -H_pairs[:, n:, :n]

    def start(terms: Terms):
        """The drift's path without noise from x0 (inputs as on the grid): where Newton starts."""
        def step(x, part):
            start, length, u_start, *_ = part
            x = x + terms.drift(x, u_start, start) * length
            return x, x

        _, path = jax.lax.scan(step, terms.x0, terms.grid)
        return jnp.concatenate([terms.x0[None], path])

    def newton(theta, data, cdf=None, tolerance=NEWTON_TOLERANCE):
        """The mode X̂: damped Newton steps until one is shorter than NEWTON_TOLERANCE (relative to X), or, with a
        larger ``tolerance``, until a full Newton step is shorter than that; then one more full step, as the
        loop's last pass (one copy of the step's work in the program)."""
        terms = pieces(theta, data, cdf)

        def improve(carry):
            X, value, count, stage = carry
            g = jax.grad(joint, argnums=1)(terms, X)
            diagonal, lower = blocks(terms, X)
            factor, couplings = block_cholesky(diagonal, lower)
            newton_direction = block_solve(factor, couplings, g)
            # Far from the mode of a density that is not log-concave (a diffusion that depends on the
            # state), −H may not be positive definite and its factor fails: a gradient step scaled by
            # the diagonal's size instead.
            scale = jnp.maximum(jnp.abs(jnp.diagonal(diagonal, axis1=1, axis2=2)), MIN_CURVATURE)
            newton_ok = jnp.all(jnp.isfinite(newton_direction))
            direction = jnp.where(newton_ok, newton_direction, g / scale)
            searching = stage == SEARCHING

            def shorter(search):
                length, _ = search
                return length / 2, joint(terms, X + (length / 2) * direction)

            def worse(search):
                length, trial = search
                return searching & ~(trial > value) & (length > MIN_STEP_LENGTH)

            # The longest of 1, 1/2, 1/4, ... that increases J (a damped Newton method).
            length, trial = jax.lax.while_loop(worse, shorter, (1.0, joint(terms, X + direction)))
            taken = trial > value
            step = jnp.where(taken, length, 0.0) * direction
            size = jnp.max(jnp.abs(step)) / (1.0 + jnp.max(jnp.abs(X)))
            full = taken & (length == 1.0) & newton_ok
            going = (count + 1 < NEWTON_STEPS) & (size > NEWTON_TOLERANCE) & ~(full & (size <= tolerance))
            # The last pass (stage LAST) takes the full Newton step whatever J does there: Newton's quadratic
            # convergence takes the mode to rounding (from a full step shorter than ``tolerance``, to about its
            # square), so that the value (whose log-determinant moves to first order with the mode) is smooth
            # in θ.
            last = X + newton_direction
            X = jnp.where(searching, X + step, jnp.where(jnp.all(jnp.isfinite(last)), last, X))
            return (X, jnp.where(taken, trial, value), count + 1,
                    jnp.where(searching, jnp.where(going, SEARCHING, LAST), DONE))

        X0 = start(terms)
        X, *_ = jax.lax.while_loop(lambda carry: carry[3] != DONE, improve, (X0, joint(terms, X0), 0, SEARCHING))
        return X

    # Each level of forward differentiation asks for the mode, and for the blocks and mixed derivative
    # of its rule below, again: as jitted functions the levels reuse their traces instead of tracing
    # them anew.
    newton_search = jax.jit(newton)
    hessian_blocks = jax.jit(lambda theta, data, X: blocks(pieces(theta, data), X))
    mixed_derivative = jax.jit(lambda theta, dtheta, data, X: jax.jvp(
        lambda th: jax.grad(joint, argnums=1)(pieces(th, data), X), (theta,), (dtheta,))[1])

    @jax.custom_jvp
    def mode(theta, data):
        # JAX keys a jitted function's trace on the abstract mesh in force too: none where it traces this
        # primal, the empty one inside the rule's calls.  Naming the empty one here lets the rule reuse the
        # search's trace instead of tracing the search a second time (about a sixth of a first fit's
        # tracing); a mesh of devices the caller set stays in force.
        mesh = jax.sharding.get_abstract_mesh()
        with jax.sharding.use_abstract_mesh(EMPTY_MESH if mesh.empty else mesh):
            return newton_search(jax.lax.stop_gradient(theta), data)

    @mode.defjvp
    def mode_jvp(primals, tangents):
        theta, data = primals
        dtheta, _ = tangents
        X = mode(theta, data)
        # ∂J/∂X (X̂(θ), θ) = 0:  H dX̂ = −∂²J/∂X∂θ dθ, with −H = A block-tridiagonal.
        mixed = mixed_derivative(theta, dtheta, data, X)
        diagonal, lower = hessian_blocks(theta, data, X)
        factor, couplings = block_cholesky(diagonal, lower)
        dX = jax.lax.custom_linear_solve(lambda v: block_matvec(diagonal, lower, v), mixed,
                                         lambda _, b: block_solve(factor, couplings, b), symmetric=True)
        return X, dX

    def laplace_value(J, X, factor):
        """J(X̂) + (d/2) log 2π − ½ log det(−H) at the mode X̂, from −H's block Cholesky factor there."""
        logdet = 2 * jnp.sum(jnp.log(jnp.diagonal(factor, axis1=1, axis2=2)))
        return J + 0.5 * X.size * jnp.log(2 * jnp.pi) - 0.5 * logdet

    def value_at(terms: Terms, X):
        """``laplace_value`` of the terms at the mode X̂."""
        return laplace_value(joint(terms, X), X, block_cholesky(*blocks(terms, X))[0])

    @jax.custom_jvp
    def marginal(theta, data: FilterInputs):
        """(log L(θ) by Laplace's method, the mode X̂ (T + 1, n))."""
        X = mode(theta, data)
        return value_at(pieces(theta, data), X), X

    @marginal.defjvp
    def marginal_jvp(primals, tangents):
        """d log L = ∂J/∂θ dθ − ½ tr(A⁻¹ dA), A = −∂²J/∂X² at the mode (∂J/∂X = 0 there: the envelope theorem),
        dA its blocks' derivative along (dθ, dX̂); the trace from A⁻¹'s diagonal and neighbouring blocks
        (``block_inverse_bands``) rather than through the derivative of A's block Cholesky factorisation."""
        theta, data = primals
        dtheta, _ = tangents
        X, dX = jax.jvp(lambda th: mode(th, data), (theta,), (dtheta,))
        J, dJ = jax.jvp(lambda th: joint(pieces(th, data), X), (theta,), (dtheta,))
        (diagonal, lower), (d_diagonal, d_lower) = jax.jvp(
            lambda th, x: blocks(pieces(th, data), x), (theta, X), (dtheta, dX))
        factor, couplings = block_cholesky(diagonal, lower)
        inner, crosses = block_inverse_bands(factor, couplings)
        # tr(A⁻¹ dA): the diagonal blocks, and each block below the diagonal twice (A is symmetric).
        d_logdet = jnp.sum(inner * d_diagonal) + 2 * jnp.sum(jnp.swapaxes(crosses, 1, 2) * d_lower)
        return (laplace_value(J, X, factor), X), (dJ - 0.5 * d_logdet, dX)

    def value(theta, data: FilterInputs, cdf=None):
        """The Laplace value alone (no derivatives in θ), with the ``cdf`` terms of ``pieces``; its mode to
        ONE_STEP_TOLERANCE (the one-step transforms evaluate it once per observation)."""
        return value_at(pieces(theta, data, cdf), newton(theta, data, cdf, ONE_STEP_TOLERANCE))

    def standardized(theta, row, i, x, spread):
        """Output i of ``row`` = (y, mask, u, t) standardized by its Gaussian predictive at the states' mean ``x``,
        (y − h_i(x)) / √(S_i + ∇h_i Σ ∇h_iᵀ), with ``spread(v)`` = Σ v for the states' covariance Σ; NaN where the
        variance is not a positive number.  With correlated noise, output i whitened given the outputs before it
        that the mask observes (``observed``)."""
        y, mask, u, t = row

        def centred(x):
            """(y_i − h_i(x), both whitened where the noise is correlated; S_i)."""
            mean, variance = structure.observation_law(x, u, t, theta)[:2]
            if full is None:
                return y[i] - mean[i], variance[i]
            seen = mask.at[i].set(1.0)
            L = observed_root(full(zeros, u, t, theta), seen)
            return whiten(L, seen, y)[i] - whiten(L, seen, mean)[i], 1.0

        # The slope is −∇h_i: its sign cancels in the variance.
        (residual, variance), slope = jax.value_and_grad(centred, has_aux=True)(x)
        total = variance + slope @ spread(slope)
        # No predictive where the states are not determined (a diffuse state before any observation of it):
        # NaN, as the exact diffuse filter has no innovation there.
        return jnp.where(jnp.isfinite(total) & (total > 0), residual / jnp.sqrt(total), jnp.nan)

    def predictive(theta, data: FilterInputs, k, i):
        """Output i of row k standardized by its one-step Gaussian predictive given the outputs that ``data``'s
        mask observes: (y − h_i(x̂)) / √(S_i + ∇h_i Σ_k ∇h_iᵀ), x̂ the states' mode given them at row k, Σ_k
        its marginal covariance there (the block of (−∂²J/∂X²)⁻¹), S_i the noise variance at the mode (NaN where
        that is not finite).  This is the mode and curvature of the joint density of the states and y_ki, exact
        for a linear Gaussian model.
        With correlated noise, output i whitened given the row's outputs before it (``observed``)."""
        terms = pieces(theta, data)
        X = newton(theta, data, tolerance=ONE_STEP_TOLERANCE)
        factor, couplings = block_cholesky(*blocks(terms, X))

        def spread(slope):
            return block_solve(factor, couplings, jnp.zeros_like(X).at[k * s].set(slope))[k * s]

        return standardized(theta, tuple(a[k] for a in terms.rows[:4]), i, X[k * s], spread)

    def one_step(theta, data: FilterInputs):
        """Every output standardized by its one-step Gaussian predictive, as ``predictive`` gives each, for a
        model whose joint log-density J is quadratic in the states (linear dynamics and observations, Gaussian
        outputs and initial state, none diffuse): one pass forward over the grid (N, outputs), 0 where unobserved.

        The states' density given the data before is carried as a mean m and a precision Λ (a Gaussian), with
        Λ's Cholesky factor.
        A grid step takes the joint of x_j ~ N(m, Λ⁻¹) and the transition's term T(x_j, x_{j+1}) to its mode and
        x_{j+1}'s marginal precision Q₂₂ − Q₂₁(Λ + Q₁₁)⁻¹Q₁₂ (Q = −∂²T); an observed output then adds its
        term's curvature to Λ and moves m by one Newton step.  Where J is quadratic each step is exact, so these
        are the predictive's mode and curvature given the same data (the information filter of the grid's
        discretization), in time and compilation linear in the series' length instead of quadratic."""
        terms = pieces(theta, data)
        n_rows, outputs = data.t.shape[0], jnp.arange(len(families))

        def slope_and_curvature(fun, x):
            """(∇fun, −∇²fun) at x, forward over reverse in one trace of ``fun``."""
            def slope(x):
                g = jax.grad(fun)(x)
                return g, g

            H, g = jax.jacfwd(slope, has_aux=True)(x)
            return g, -H

        def grid_step(belief, step):
            m, precision, root = belief
            guess = m + terms.drift(m, step.u_start, step.start) * step.length  # near the mode: small steps
            slope, Q = slope_and_curvature(lambda x: terms.transition(x, step), jnp.concatenate([m, guess]))
            # The joint's mode by its blocks: with A = Λ + Q₁₁ and the Schur complement S = Q₂₂ − Q₂₁A⁻¹Q₁₂
            # (x_{j+1}'s marginal precision), x_{j+1} moves by S⁻¹(g₂ − Q₂₁A⁻¹g₁): two factorisations of
            # n × n blocks instead of the joint's 2n × 2n one, and S's factor is carried to the next step.
            linked = small.cho_solve(small.cholesky(symmetrize(Q[:n, :n] + precision)), Q[:n, n:])  # A⁻¹Q₁₂
            marginal_precision = symmetrize(Q[n:, n:] - Q[n:, :n] @ linked)
            root = small.cholesky(marginal_precision)
            shift = small.cho_solve(root, slope[n:] - linked.T @ slope[:n])
            return (guess + shift, marginal_precision, root), None

        def row_step(belief, part):
            first, steps, row = part
            predicted, _ = jax.lax.scan(grid_step, belief, steps)
            belief = jax.tree_util.tree_map(lambda a, b: jnp.where(first, a, b), belief, predicted)
            y, mask, u, t = row

            def output(belief, i):
                m, precision, root = belief
                before, through = mask * (outputs < i), mask * (outputs <= i)
                residual = standardized(theta, (y, before, u, t), i, m, lambda v: small.cho_solve(root, v))
                # Output i's own term given the outputs before it: its density alone where the outputs' noise
                # is independent, the difference of two where it is correlated (whitened).
                def term(x):
                    if full is None:
                        return terms.observed(x, (y, mask * (outputs == i), u, t))
                    return terms.observed(x, (y, through, u, t)) - terms.observed(x, (y, before, u, t))

                slope, curvature = slope_and_curvature(term, m)
                precision = symmetrize(precision + curvature)
                root = small.cholesky(precision)
                return (m + small.cho_solve(root, slope), precision, root), jnp.where(mask[i] > 0, residual, 0.0)

            return jax.lax.scan(output, belief, outputs)

        prior_precision = symmetrize(-jax.hessian(terms.prior)(terms.x0))
        start = (terms.x0, prior_precision, small.cholesky(prior_precision))
        # The grid's steps into each row; row 0 has none (its own are a copy of row 1's, left unused).
        into = jax.tree_util.tree_map(lambda a: a.reshape(n_rows - 1, s, *a.shape[1:]), terms.grid)
        into = jax.tree_util.tree_map(lambda a: jnp.concatenate([a[:1], a]), into)
        rows = tuple(terms.rows[:4])
        return jax.lax.scan(row_step, start, (jnp.arange(n_rows) == 0, into, rows))[1]

    def smoothed(theta, data: FilterInputs):
        """The mode's states at the sample times (N, n) and their covariances (N, n, n): the diagonal blocks of
        (−∂²J/∂X²)⁻¹ at the mode, the Laplace approximation's marginals (for a linear Gaussian model the
        Rauch–Tung–Striebel smoother's)."""
        X = newton(theta, data)
        factor, couplings = block_cholesky(*blocks(pieces(theta, data), X))
        return X[::s], block_inverse_diagonal(factor, couplings)[::s]

    return Laplace(marginal, value, smoothed, predictive, one_step)


def prepare(structure: Structure, options: FilterOptions):
    """``marginal(theta, data) -> (log-likelihood, mode)`` of the Laplace method (see the module doc)."""
    return build(structure, options).marginal


def log_tail(family: str, y, m, variance, shape, upper):
    """log P(Y ≤ y | m, S, a), or log P(Y > y | m, S, a) where ``upper``; the normal's by log Φ, accurate far in
    either tail."""
    if family == NORMAL:
        z = (y - m) / jnp.sqrt(variance)
        return log_ndtr(jnp.where(upper, -z, z))
    below = cdf(family, y, m, variance, shape)
    return jnp.log(jnp.maximum(jnp.where(upper, 1 - below, below), 1e-300))


#: The "cdf" one-step transforms are computed for at most this many rows at a time (vectorised).
ONE_STEP_BATCH = 8


def row_batches(n_rows: int, most: int = ONE_STEP_BATCH) -> tuple[int, int]:
    """``(count, size)``: the fewest batches of at most ``most`` rows, all of one size, that cover ``n_rows``
    (``count * size - n_rows < count`` rows repeated)."""
    count = -(-n_rows // most)
    return count, -(-n_rows // count)


def each_observation(data: FilterInputs, n_out: int, evaluate, unobserved: float, most: int = ONE_STEP_BATCH,
                     parts: int = 1):
    """``evaluate(data_before, k, i)`` for every row k and output i, ``unobserved`` where y_ki is not observed: the
    data before y_ki are the rows before k and the outputs before i of row k (the mask), the rows after k left out
    (their intervals set to length 0, whose steps integrate to one exactly).  With ``parts`` > 1,
    ``evaluate(data_before, k, i, part)`` for each part (N, parts, outputs).

    The outputs run one after the other in a scan, so that the evaluation is traced and compiled once whatever
    their number; the rows one at a time (``most=1``) or vectorised in batches of at most ``most`` rows (their
    parts in the same batch, one vectorisation rather than one in another, which JAX traces a quarter to a half
    sooner), all of one size (the last row repeated), because ``lax.map`` vectorises rows left over by whole
    batches apart, a second copy of the evaluation for XLA to compile."""
    n_rows = data.t.shape[0]
    rows, outputs = jnp.arange(n_rows), jnp.arange(n_out)

    def at(pair):
        k, part = pair // parts, pair % parts
        truncated = data._replace(dt=jnp.where(rows > k, 0.0, data.dt))
        before = jnp.where((rows < k)[:, None], data.mask, 0.0)

        def output(_, i):
            mask = before.at[k].set(data.mask[k] * (outputs < i))
            value = evaluate(truncated._replace(mask=mask), k, i, *((part,) if parts > 1 else ()))
            return None, jnp.where(data.mask[k, i] > 0, value, unobserved)

        return jax.lax.scan(output, None, outputs)[1]

    n_pairs = n_rows * parts
    if most == 1:
        values = jax.lax.map(at, jnp.arange(n_pairs))
    else:
        count, size = row_batches(n_rows, most)
        pairs = jnp.arange(n_pairs) if count * size == n_rows else jnp.minimum(jnp.arange(count * size * parts),
                                                                              n_pairs - 1)
        values = jax.lax.map(at, pairs, batch_size=size * parts)[:n_pairs]
    return values if parts == 1 else values.reshape(n_rows, parts, n_out)


def linear_gaussian(structure: Structure) -> bool:
    """Linear dynamics and observations (``structure.is_linear``) and Gaussian outputs."""
    return structure.is_linear and all(family == NORMAL for family in structure.output_families)


def gaussian_joint(structure: Structure) -> bool:
    """Whether the Laplace method's joint density of the states and the data is Gaussian for any θ: a linear
    Gaussian model (``linear_gaussian``) whose initial state has no diffuse part."""
    return linear_gaussian(structure) and not structure.initial_covariance.diffuse


def exact_kalman(structure: Structure, scheme: str | None) -> bool:
    """Whether the Laplace method's value is the exact Kalman filter's likelihood for any θ: a linear Gaussian
    model with time-invariant dynamics (exact transitions, ``scheme="auto"``); a diffuse initial state included
    (the Kalman filter's exact diffuse start)."""
    return linear_gaussian(structure) and structure.linear_dynamics is not None and scheme in (None, "auto")


def one_step_gaussian(structure: Structure, options: FilterOptions):
    """``residuals(theta, data) -> (N, outputs)``: each Gaussian observation standardized by its one-step-ahead
    predictive under the Laplace method, as ctsmTMB's one-step-ahead residuals (TMB's ``oneStepPredict``, method
    "oneStepGaussian", which ``estimate(laplace.residuals = TRUE)`` runs); 0 where y_ki is unobserved.

    For row k and output i, with D the data before it (rows before k, and outputs before i of row k), y_ki given
    D is taken Gaussian: its mean h_i(x̂_k) and variance S_i + ∇h_i Σ_k ∇h_iᵀ are the mode and curvature of the
    joint density of the states and y_ki given D (``Laplace.predictive``).  Exact for a linear Gaussian model,
    where they are the Kalman filter's innovation and its variance.  TMB finds the mode of its Laplace
    approximation of p(y_ki, D) in y_ki instead, whose log-determinant moves with y_ki where the observation
    or the transitions are nonlinear in the states: the two differ there by that term.  Cost: one Laplace mode
    per observation over the series up to it, so quadratic in the series' length; where the joint density is
    Gaussian (``gaussian_joint``) one pass forward instead (``Laplace.one_step``), linear in it.
    """
    laplace = build(structure, options)
    n_out = len(structure.output_families)
    if gaussian_joint(structure):
        return laplace.one_step

    def residuals(theta, data: FilterInputs):
        # One row at a time: vectorised over rows, the Newton searches (a loop whose rows all run until the
        # slowest has converged) compile longer and, from a few hundred rows on, run slower.
        return each_observation(data, n_out, lambda before, k, i: laplace.predictive(theta, before, k, i), 0.0,
                                most=1)

    return residuals


def one_step_transforms(structure: Structure, options: FilterOptions):
    """``transforms(theta, data, uniforms) -> (N, outputs)``: each observation's one-step-ahead probability integral
    transform under the Laplace method by TMB's ``oneStepPredict`` method "cdf" (Thygesen et al. 2017), for any
    observation distribution.

    For row k and output i, with D the data before it (rows before k, and outputs before i of row k),
    the probabilities of y_ki's two tails given D,

        P(Y_ki ≤ y_ki, D) = ∫ F(y_ki | x_k) p(D, X) dX,   P(Y_ki > y_ki, D) = ∫ (1 − F(y_ki | x_k)) p(D, X) dX,

    are each approximated by Laplace's method (log F or log(1 − F) a term of the joint density), and the
    transform is the first over their sum, as TMB does: each tail's approximation keeps its relative
    accuracy where the transform is close to 0 or 1.  For counts the three parts P(Y < y), P(Y = y)
    and P(Y > y) are approximated so, and the transform randomized between them by ``uniforms``
    (Dunn & Smyth 1996); 0.5 where y_ki is unobserved.  Cost: two Laplace evaluations (three for
    counts) per observation over the series up to it, so quadratic in the series' length.
    """
    laplace = build(structure, options)
    families = structure.output_families
    n_out = len(families)

    def transforms(theta, data: FilterInputs, uniforms):
        zero = jnp.zeros(data.mask.shape)
        is_count = [family in COUNTS for family in families]
        counts, n_parts = jnp.array(is_count), 3 if any(is_count) else 2

        def part_value(before, k, i, part):
            # Y ≤ y (< y for counts), Y > y and, for counts, Y = y (the density observed): (mask, on, shift,
            # upper) of each; a model with counts among its outputs takes the third for every output, left out
            # of the others' transforms.
            on = zero.at[k, i].set(1.0)
            lower_tail, upper_tail = part == 0, part == 1
            mask = jnp.where(part == 2, before.mask.at[k, i].set(1.0), before.mask)
            cdf = (jnp.where(part < 2, on, zero), jnp.where(lower_tail & counts[i], on, zero),
                   jnp.where(upper_tail, on, zero))
            value = laplace.value(theta, before._replace(mask=mask), cdf)
            return jnp.where((part < 2) | counts[i], value, -jnp.inf)

        values = each_observation(data, n_out, part_value, -jnp.inf, parts=n_parts)  # (N, parts, outputs)
        p = jnp.exp(values - jnp.max(values, axis=1, keepdims=True))
        point = uniforms * p[:, 2] if n_parts == 3 else 0.0
        transform = (p[:, 0] + point) / jnp.sum(p, axis=1)
        return jnp.where(data.mask > 0, transform, 0.5)

    return transforms
