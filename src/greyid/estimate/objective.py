"""The function an estimator minimises: −(criterion + log prior) in unbounded z.

It is compiled once per model structure and setting (filter, criterion,
which parameters are free and how they are bounded) and takes everything else —
fixed values, bounds, prior moments and the data — as arguments, so a new data
set of similar length or new starting values reuse the compiled code.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import jit, kept_key
from ..filters import small
from ..filters.api import compiled_filter, shared_lengths
from ..filters.driver import make_ahead, make_summed_filter
from ..filters.protocol import GAUSSIAN_METHODS, KALMAN, LAPLACE, STOCHASTIC, FilterOptions
from .criteria import GaussianPrior, log_criterion, scale_consistency, step_criterion
from .transforms import Transform


#: Largest number of free parameters whose Hessian is taken forward over forward.
FORWARD_HESSIAN_MAX = 10
#: Rows (over all data sets) above which the Hessian is taken forward over forward
#: whatever the filter: reverse mode keeps every step's intermediates, several times the memory
#: and the time of forward mode on a 10⁵-sample logistic EKF fit (``benchmarks/length.py``).
LONG_SERIES = 20_000


@dataclass(frozen=True)
class Problem:
    """What stays fixed during one estimation."""

    options: FilterOptions
    robust: tuple | None
    horizon: int
    free: tuple[int, ...]  # positions of the free parameters in θ
    transform: Transform
    prior: GaussianPrior | None
    prior_index: tuple[int, ...]  # positions in θ of the prior's parameters
    long_series: bool = False  # more rows than LONG_SERIES: derivatives in forward mode only

    def key(self):
        prior = None if self.prior is None else self.prior.names
        return ("objective", self.options, self.robust, self.horizon, self.free,
                tuple(self.transform.kind.tolist()), prior, self.long_series)

    def arguments(self, base_theta):
        """The non-static arguments of the compiled functions."""
        if self.prior is None:
            mean, chol = np.zeros(0), np.zeros((0, 0))
        else:
            mean, chol = self.prior.mean, np.linalg.cholesky(self.prior.covariance)
        arrays = (base_theta, self.transform.lower, self.transform.upper, mean, chol)
        return tuple(jax.device_put([np.asarray(a, dtype=np.float64) for a in arrays]))

    def theta(self, z, base_theta, transform: Transform | None = None, xp=np):
        """θ at z: the free parameters from z, the fixed ones from ``base_theta``.

        In NumPy (``xp=np``, nothing to compile) or in the compiled objective
        (``xp=jax.numpy``, with the bounds passed as arguments in ``transform``).
        θ is assembled element by element: a scatter into ``base_theta`` would
        become a loop per derivative order in the compiled Hessian program.
        """
        return self.assemble((transform or self.transform).to_theta(z, xp), base_theta, xp)

    def assemble(self, free_theta, base_theta, xp=np):
        """θ with the free parameters' values ``free_theta`` and the fixed ones from ``base_theta``."""
        position = {index: j for j, index in enumerate(self.free)}
        return xp.stack([free_theta[position[i]] if i in position else base_theta[i]
                         for i in range(len(base_theta))])


def forward_value_and_grad(fun):
    """``(value, gradient)`` of a scalar ``fun(x, *args)`` by forward-mode differentiation.

    With the handful of parameters of a physical model, pushing one tangent per
    parameter through the filter is about twice as fast as reverse mode on long
    series and stores nothing per step (test cell, ``benchmarks/fit.py``).
    """
    def with_value(x, *args):
        v = fun(x, *args)
        return v, v

    def value_and_grad(x, *args):
        g, v = jax.jacfwd(with_value, has_aux=True)(x, *args)
        return v, g

    return value_and_grad


def log_prior(theta, index, mean, chol):
    """log N(θ[index]; mean, chol cholᵀ), the Gaussian prior of a MAP criterion (3.46)."""
    x = jnp.stack([theta[i] for i in index]) - mean
    z = jax.scipy.linalg.solve_triangular(chol, x, lower=True)
    return -0.5 * (z @ z + 2 * jnp.sum(jnp.log(jnp.diag(chol))) + len(index) * jnp.log(2 * jnp.pi))


def summed_over_datasets(criterion: Callable, theta, datasets):
    """Σ_d criterion(θ, d) over the data sets (3.18 sums over independent experiments).

    Data sets of the same shapes (the same length bucket) are evaluated together by
    one vectorised filter (``jax.vmap``) rather than a copy of it per data set: a fit
    to many data sets compiles one filter per shape, not one per data set.
    """
    groups: dict = {}
    for data in datasets:
        leaves, tree = jax.tree_util.tree_flatten(data)
        groups.setdefault((tree, tuple((np.shape(leaf), jnp.result_type(leaf)) for leaf in leaves)), []).append(data)
    total = 0.0
    for group in groups.values():
        if len(group) == 1:
            total = total + criterion(theta, group[0])
            continue
        stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *group)
        total = total + jnp.sum(jax.vmap(criterion, in_axes=(None, 0))(theta, stacked))
    return total


def evaluates_together(problem: Problem) -> bool:
    """Whether the criterion runs the data sets of one shape through one vectorised filter
    ([`summed_over_datasets()`][greyid.estimate.objective.summed_over_datasets]): not with the steady state,
    whose switch decides by ``lax.cond`` per data set (vectorised, both branches would run)."""
    return not (problem.long_series or problem.options.steady_state)


def evaluated_datasets(problem: Problem, prepared: list) -> list:
    """The data sets ``[(series, filter inputs), ...]`` as the criterion evaluates them: where a Gaussian
    filter runs them together ([`evaluates_together()`][greyid.estimate.objective.evaluates_together]),
    series of different lengths padded to shared shapes
    ([`shared_lengths()`][greyid.filters.api.shared_lengths]: one filter program for them all).  The particle
    and ensemble filters draw their random numbers by the padded shape and the Laplace method's grid grows
    with it: their data sets keep their own."""
    if evaluates_together(problem) and problem.options.method in GAUSSIAN_METHODS:
        return shared_lengths(prepared)
    return list(prepared)


def criterion_functions(structure, problem: Problem, forward_only: bool = False):
    """``(terms, negative)``: θ, data ↦ the filter's per-step terms, and θ ↦ the negative log-criterion
    (3.18, or the robust or k-step criterion) summed over the data sets, minus the log-prior (MAP).

    ``forward_only``: ``negative`` is differentiated in forward mode only, which lets a shorter
    series with the steady state switch where its filter settles ([`scan_rows()`][greyid.filters.driver.scan_rows]).
    """
    kappa = scale_consistency(problem.robust)
    if problem.horizon == 1:
        run = compiled_filter(structure, problem.options, keep_outputs=False)

        def terms(theta, data):
            return run(theta, data)[0]
    else:
        ahead = make_ahead(structure, problem.options, problem.horizon)

        def terms(theta, data):
            return ahead(theta, data).terms

    if problem.horizon == 1 and (problem.long_series or problem.options.steady_state):
        # Summed in the scan: nothing kept per step, so memory independent of the length (long
        # series), and no per-step stores in the rows run step by step (the public likelihood).
        criterion = make_summed_filter(
            structure, problem.options, lambda step_terms: step_criterion(step_terms, problem.robust, kappa),
            forward_only)
    else:
        def criterion(theta, data):
            return log_criterion(terms(theta, data), problem.robust)

    together = evaluates_together(problem)

    def negative(theta, prior_mean, prior_chol, datasets):
        total = summed_over_datasets(criterion, theta, datasets) if together else \
            sum(criterion(theta, d) for d in datasets)
        if problem.prior is not None:
            total = total + log_prior(theta, problem.prior_index, prior_mean, prior_chol)
        return -total

    return terms, negative


class Programs(NamedTuple):
    """The compiled functions of one estimation problem (see [`build()`][greyid.estimate.objective.build])."""

    derivatives: Callable  # (z, rows, *args) -> (f, g, rows·H)
    value: Callable  # (z, *args) -> f
    step_scores: Callable  # (z, base, lower, upper, data) -> ∂(term k)/∂z
    value_and_grad: Callable  # (z, *args) -> (f, g)
    scoring: Callable | None  # (z, rows, *args) -> pieces of (f, g, F); Gaussian ML/MAP only
    derivatives_sharing: Callable  # derivatives, sharing value_and_grad's trace (see build)


def build(structure, problem: Problem) -> Programs:
    """The [`Programs`][greyid.estimate.objective.Programs] of this problem.

    ``derivatives(z, ...) -> (value, gradient, Hessian)`` is one compiled
    program.  For the exact Kalman filter with up to FORWARD_HESSIAN_MAX free
    parameters it differentiates forward over forward, which compiles in half
    the time and runs about as fast; otherwise forward over reverse, whose cost
    grows with the number of parameters rather than its square and which is
    ten times faster through the EKF's sub-step Jacobians (Lotka–Volterra, A.66).
    """
    kappa = scale_consistency(problem.robust)
    forward = forward_hessian(problem.options.method, len(problem.free)) or problem.long_series
    terms, negative_at_theta = criterion_functions(structure, problem)
    kinds = problem.transform.kind

    def in_z(negative_at_theta):
        def negative(z, base, lower, upper, prior_mean, prior_chol, datasets):
            theta = problem.theta(z, base, Transform(kinds, lower, upper), jnp)
            return negative_at_theta(theta, prior_mean, prior_chol, datasets)

        return negative

    negative = in_z(negative_at_theta)
    for_hessian = negative
    if forward and problem.options.steady_state:
        # Forward over forward, a shorter series switches where its filter settles (tested every few
        # rows) rather than only after its first rows: its rows step by step are the costliest.
        for_hessian = in_z(criterion_functions(structure, problem, forward_only=True)[1])

    def contributions(z, base, lower, upper, data):
        theta = problem.theta(z, base, Transform(kinds, lower, upper), jnp)
        return step_criterion(terms(theta, data), problem.robust, kappa)

    def kept(name):
        return kept_key(structure, (name, problem.key(), problem.prior_index, forward))

    scoring = None
    if takes_scoring(problem):
        scoring = jit(expected_information(structure, problem, kinds), key=kept("scoring"))
    value_and_grad = jit(forward_value_and_grad(negative), key=kept("value_and_grad"))
    derivatives = jit(hessian_rows(for_hessian, forward), key=kept("derivatives"))
    sharing = derivatives
    if forward and for_hessian is negative:
        # The same Hessian pushing the value-and-gradient program's own jitted function along each
        # row: JAX traces that function once for both programs, so a fit that compiles both (a
        # quasi-Newton start) does not trace it twice; alone, the nesting costs a little tracing.
        sharing = jit(hessian_rows(for_hessian, forward, value_and_grad.jitted), key=kept("derivatives_sharing"))
    # Per-step scores (rows: steps, columns: ∂/∂z), forward mode: nothing stored per step.
    return Programs(derivatives, jit(negative, key=kept("value")),
                    jit(jax.jacfwd(contributions), key=kept("step_scores")), value_and_grad, scoring, sharing)


def observed_innovations(innovation, innovation_cov, mask):
    """(ε_k, R_k) with unobserved elements set to ε = 0 and an identity block: no information."""
    both = mask[:, :, None] * mask[:, None, :]
    return innovation * mask, jnp.where(both > 0, innovation_cov, jnp.eye(mask.shape[1]))


def whitened_sensitivities(R, d_eps, d_R):
    """M with rows i = (L⁻¹∂_iε_k, √½ L⁻¹∂_iR_k L⁻ᵀ) over all steps k (R_k = L_kL_kᵀ), so that
    MMᵀ = Σ_k ∂εᵀR⁻¹∂ε + ½ tr(R⁻¹∂_iR R⁻¹∂_jR), the Gaussian innovations' information (4.32–4.33).

    ``d_eps`` (directions, N, m) and ``d_R`` (directions, N, m, m) are the sensitivities.
    L⁻¹ comes from the filters' unrolled small-matrix routines, one row at a time:
    batched LAPACK calls over 10⁵ rows of 1 × 1 matrices take several times as long.
    """
    eye = np.eye(R.shape[-1])
    L_inv = jax.vmap(lambda R_k: small.solve_lower(small.cholesky(R_k), eye))(R)
    W = jnp.einsum("kab,ikb->ika", L_inv, d_eps)
    B = jnp.einsum("kab,ikbc,kdc->ikad", L_inv, d_R, L_inv)
    return jnp.concatenate([W.reshape(W.shape[0], -1), np.sqrt(0.5) * B.reshape(B.shape[0], -1)], axis=1)


def expected_information(structure, problem: Problem, kinds):
    """``(z, rows, *args) -> (f, rows·g, M_rows, prior)``, the pieces of Fisher's scoring matrix.

    F = MMᵀ + the prior's exact Hessian ([`combine_scoring()`][greyid.estimate.objective.combine_scoring]), with M the
    whitened sensitivities of the innovations to z
    ([`whitened_sensitivities()`][greyid.estimate.objective.whitened_sensitivities]):
    the expected information of the Gaussian innovations (3.33, 4.32–4.33), taken
    in z; ``prior`` holds the prior term's value, gradient and Hessian.  F is
    positive semi-definite everywhere and, with one tangent per parameter pushed
    forward through the filter, costs about one forward gradient, against a
    Hessian's one per parameter pair; near the optimum it approximates the
    Hessian up to terms that vanish with the innovations' mean.
    """
    run = compiled_filter(structure, problem.options, keep_outputs="innovations")

    def theta_of(z, base, lower, upper):
        return problem.theta(z, base, Transform(kinds, lower, upper), jnp)

    def innovations(z, base, lower, upper, datasets):
        theta = theta_of(z, base, lower, upper)
        value, parts = 0.0, []
        for data in datasets:
            terms, (innovation, innovation_cov) = run(theta, data)
            value = value + log_criterion(terms, None)
            parts.append(observed_innovations(innovation, innovation_cov, data.mask))
        return -value, parts

    def prior_term(z, base, lower, upper, prior_mean, prior_chol):
        if problem.prior is None:
            return jnp.zeros(())
        return -log_prior(theta_of(z, base, lower, upper), problem.prior_index, prior_mean, prior_chol)

    def scoring(z, rows, base, lower, upper, prior_mean, prior_chol, datasets):
        def along(u):
            return jax.jvp(lambda x: innovations(x, base, lower, upper, datasets), (z,), (u,))

        (value, parts), (slopes, tangents) = jax.vmap(along, out_axes=(None, 0))(rows)
        whitened = [whitened_sensitivities(R, d_eps, d_R) for (_, R), (d_eps, d_R) in zip(parts, tangents)]
        args = (base, lower, upper, prior_mean, prior_chol)
        prior_value, prior_gradient = jax.value_and_grad(prior_term)(z, *args)
        prior = (prior_value, prior_gradient, jax.hessian(prior_term)(z, *args))
        return value, slopes, jnp.concatenate(whitened, axis=1), prior

    return scoring


def takes_scoring(problem: Problem) -> bool:
    """Whether Fisher scoring applies: the one-step Gaussian likelihood (ML or MAP) of a deterministic
    filter's innovations (not a robust or k-step criterion, not the particle or ensemble filters' random
    numbers, not the Laplace method's marginal)."""
    return problem.horizon == 1 and problem.robust is None and problem.options.method not in (*STOCHASTIC, LAPLACE)


def forward_hessian(method: str, n_parameters: int) -> bool:
    """Whether to take the Hessian forward over forward (see [`build()`][greyid.estimate.objective.build])."""
    # The Laplace method's mode has a forward rule of its own (its implicit derivative).
    return (method == KALMAN and n_parameters <= FORWARD_HESSIAN_MAX) or method == LAPLACE


def hessian_rows(fun, forward: bool, value_and_grad: Callable | None = None):
    """``(x, rows, *args) -> (f, g, rows · H)`` for a scalar ``fun(x, *args)``.

    The gradient — forward or reverse mode, or ``value_and_grad`` of ``fun`` where
    given — is pushed forward along each row, so a block of rows of the Hessian
    comes with the value and the gradient.
    """
    if value_and_grad is None:
        value_and_grad = forward_value_and_grad(fun) if forward else jax.value_and_grad(fun)

    def evaluate(x, rows, *args):
        def gradient(x):
            v, g = value_and_grad(x, *args)
            return g, v

        def row(u):
            g, Hu, v = jax.jvp(gradient, (x,), (u,), has_aux=True)
            return v, g, Hu

        v, g, H_rows = jax.vmap(row)(rows)
        return v[0], g[0], H_rows

    return evaluate


def worker_count() -> int:
    """CPUs this process may use, for the Hessian's rows (``GREYID_THREADS`` overrides)."""
    setting = os.environ.get("GREYID_THREADS")
    if setting:
        return max(1, int(setting))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def combine_hessian(parts, n):
    """(f, g, H) from the blocks of [`hessian_rows()`][greyid.estimate.objective.hessian_rows]."""
    return parts[0][0], parts[0][1], np.concatenate([np.asarray(p[2]) for p in parts])[:n]


def combine_scoring(parts, n):
    """(f, g, F) from the blocks of [`expected_information()`][greyid.estimate.objective.expected_information]: F = MMᵀ
    + the prior's Hessian."""
    prior_value, prior_gradient, prior_hessian = (np.asarray(a) for a in parts[0][3])
    slopes = np.concatenate([np.asarray(p[1]) for p in parts])[:n]
    M = np.concatenate([np.asarray(p[2]) for p in parts])[:n]
    return parts[0][0] + prior_value, slopes + prior_gradient, M @ M.T + prior_hessian


def direction_blocks(n: int, workers: int | None = None) -> list:
    """The n unit directions in equal blocks, one per worker thread (the last padded with zeros)."""
    workers = min(worker_count() if workers is None else workers, n, 8)
    size = -(-n // workers)
    count = -(-n // size)
    directions = np.vstack([np.eye(n), np.zeros((count * size - n, n))])
    return jax.device_put(np.split(directions, count))


class Derivatives:
    """Derivatives at z from a program run on blocks of directions at once, in parallel threads.

    XLA runs one program on one CPU core; the rows of a Hessian (or of the
    scoring matrix's sensitivities) are independent directional derivatives, so
    blocks of them run in parallel threads (JAX releases the GIL while a program
    runs) and ``combine(parts, n)`` joins them (default: ``(f, g, H)`` of
    [`hessian_rows()`][greyid.estimate.objective.hessian_rows]).  All blocks have the same size — the last one padded
    with zero directions — so one compiled program serves them.
    """

    def __init__(self, program, n: int, arguments: tuple, workers: int | None = None,
                 combine: Callable = combine_hessian):
        self.blocks = direction_blocks(n, workers)
        self.n, self.program, self.arguments, self.combine = n, program, arguments, combine
        self.pool = ThreadPoolExecutor(len(self.blocks)) if len(self.blocks) > 1 else None
        self.pinned = None
        self.pending = None  # a compilation ahead (compile_ahead)

    def _block(self, program, z, rows):
        return jax.block_until_ready(program(z, rows, *self.arguments))

    def compile_ahead(self, z) -> None:
        """Compile in a background thread, while the search runs on.

        A search that scores first (or starts quasi-Newton) needs the exact Hessian
        only at its hand-over; its program, the costliest to compile, is then ready
        or nearly so.  The first call waits for it rather than compile it a second time.
        """
        # Traced here (reusing what an earlier program traced: the value and gradient of a
        # quasi-Newton start), compiled in the thread.
        self.pending = self.program.compile_in_background(np.asarray(z, dtype=np.float64), self.blocks[0],
                                                          *self.arguments)

    def _pin(self, z):
        # Compiled once, before any thread starts, and kept for the search: the program's own
        # call would look it up again each time (its arguments' tree and types).
        if self.pinned is None:
            self.pinned = self.program.executable(z, self.blocks[0], *self.arguments)
        return self.pinned

    def __call__(self, z):
        pending, self.pending = self.pending, None
        if pending is not None:
            self.pinned = pending.result()
        z = np.asarray(z, dtype=np.float64)  # transferred by the call, without a compiled conversion
        run = self._pin(z)
        if self.pool is None:
            parts = [self._block(run, z, rows) for rows in self.blocks]
        else:
            parts = list(self.pool.map(lambda rows: self._block(run, z, rows), self.blocks))
        return self.combine(parts, self.n)

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()
        if self.pending is not None:  # a compilation ahead never waited for
            wait([self.pending])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def compiled(structure, problem: Problem) -> Programs:
    """The [`Programs`][greyid.estimate.objective.Programs] of [`build()`][greyid.estimate.objective.build], built once
    per problem."""
    key = problem.key()
    if key not in structure.cache:
        structure.cache[key] = build(structure, problem)
    return structure.cache[key]


def step_scores(structure, problem: Problem, z, arguments, datasets) -> list[np.ndarray]:
    """∂(criterion term of step k)/∂z for every step of every data set (padding rows are 0)."""
    scores = compiled(structure, problem).step_scores
    base, lower, upper = arguments[:3]
    return [np.asarray(scores(np.asarray(z, dtype=np.float64), base, lower, upper, d)) for d in datasets]
