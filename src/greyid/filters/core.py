"""One implementation of each continuous–discrete filter, as a ``lax.scan``.

The scan runs over the rows of a data set.  Row k first predicts from t_{k-1}
to t_k (row 0 "predicts" over an interval of length 0, so the filter starts
from x(t₀) ~ N(x0, P0) and updates it with the observation at t₀), then
updates with the observed elements of y_k.  The same function gives the
log-likelihood (3.18), the filtered and predicted states for results, and the
quantities the smoother needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

from .. import _jax  # noqa: F401  (64-bit JAX before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..compiler import jit
from ..errors import ModelError
from ..model.structure import LTI, Structure
from . import small
from .delays import Pieces, delays_at, interval_pieces, regular_offsets, with_delayed_inputs
from .discretize import discretize, discretize_each, stationary_covariance, time_varying_step
from . import steady as steady_form
from .predictors import (
    Interval,
    extended_predict,
    linear_predict,
    linearized_observation,
    second_order_term,
    second_order_update,
    sigma_weights,
    unscented_predict,
    unscented_update,
)
from .updates import FORMS, StepTerms, correlated_update, from_matrix, linear_update, propagate, to_matrix

KALMAN, EKF, IEKF, UKF, EKF2 = "kalman", "ekf", "iekf", "ukf", "ekf2"
#: The modified truncated and Gaussian second-order filters (section 4.2.2).
TRUNCATED2, GAUSSIAN2 = "truncated2", "gaussian2"
SECOND_ORDER = (TRUNCATED2, GAUSSIAN2)
METHODS = (KALMAN, EKF, IEKF, UKF, EKF2, TRUNCATED2, GAUSSIAN2)


@dataclass(frozen=True)
class FilterOptions:
    """Static settings of a filter; each distinct value compiles once."""

    method: str
    form: str = "sqrt"
    substeps: int = 1
    iterations: int = 5
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0
    #: Shorter regular series (steady.SHORT_ROWS rows or more) of a time-invariant linear model
    #: filtered exactly switch to the steady state too, after their first rows where the filter
    #: has settled ([`steady`][greyid.filters.steady]); long ones (steady.MIN_ROWS or more) always do.  Its programs
    #: hold both forms: a fit's first call compiles them 2–3 times as long, and its later
    #: evaluations run in half the time (docs/performance.md).  The public likelihood turns it on
    #: for its single evaluations ([`greyid.estimate.likelihood`][greyid.estimate.likelihood]); programs vectorised over
    #: series or parameter vectors (fleets, populations, a fit's starts) would run both forms for
    #: every member and do not take it.
    steady_state: bool = False

    def __post_init__(self):
        if self.method not in METHODS:
            raise ModelError(f"unknown filter method '{self.method}'; use one of {list(METHODS)}")
        if self.form not in FORMS:
            raise ModelError(f"unknown covariance form '{self.form}'; use 'sqrt' or 'plain'")
        if not isinstance(self.substeps, int) or self.substeps < 1:
            raise ModelError(f"substeps must be a positive integer, got {self.substeps!r}")
        if not isinstance(self.iterations, int) or self.iterations < 1:
            raise ModelError(f"iterations must be a positive integer, got {self.iterations!r}")
        if not isinstance(self.steady_state, (bool, np.bool_)):
            raise ModelError(f"steady_state must be True or False, got {self.steady_state!r}")


class FilterInputs(NamedTuple):
    """Arrays of one (padded) series; row k describes the interval ending at t_k."""

    t: jnp.ndarray  # (N,)
    t_prev: jnp.ndarray  # (N,)
    dt: jnp.ndarray  # (N,), 0 at row 0 and on padding
    u_prev: jnp.ndarray  # (N, nu)
    u_cur: jnp.ndarray  # (N, nu)
    y: jnp.ndarray  # (N, ny), 0 where unobserved
    mask: jnp.ndarray  # (N, ny), 1.0 observed / 0.0 not
    dt_index: jnp.ndarray  # (N,) into unique_dt
    unique_dt: jnp.ndarray  # (M,)
    first_interval: jnp.ndarray  # t_1 − t_0
    foh: jnp.ndarray  # 0.0 (zoh) or 1.0 (foh)
    delay_slots: jnp.ndarray  # (W,) zeros: W cuts per delay fit in one interval; (0,): regular sampling


class StepOutput(NamedTuple):
    predicted_mean: jnp.ndarray
    predicted_cov: jnp.ndarray
    filtered_mean: jnp.ndarray
    filtered_cov: jnp.ndarray
    output_prediction: jnp.ndarray
    innovation: jnp.ndarray
    innovation_cov: jnp.ndarray
    transition: jnp.ndarray
    guarded: jnp.ndarray  # 1 where a moment update's covariance was guarded (see predictors.moment_update)


def initial_state(structure: Structure, theta, data: FilterInputs, first_noise=None):
    """x0 and P0 (matrix, CTSM's scaled process noise, or stationary covariance).

    ``first_noise`` is Λ of the first interval when the caller has it already.
    """
    x0 = structure.initial_mean(theta)
    spec = structure.initial_covariance
    if spec.kind == "matrix":
        return x0, spec.matrix(theta)
    if spec.kind == "process" and first_noise is not None:
        return x0, spec.scale * first_noise
    u0, t0 = data.u_cur[0], data.t[0]
    if structure.linear_drift is not None:
        A = structure.linear_drift(theta)[0]
    else:
        A = jax.jacfwd(structure.drift, argnums=0)(x0, u0, t0, theta)
    G = structure.diffusion(x0, u0, t0, theta)
    if spec.kind == "process":
        return x0, spec.scale * discretize(A, G @ G.T, data.first_interval).noise_covariance
    return x0, stationary_covariance(A, G @ G.T)


class Row(NamedTuple):
    """What one step needs of its row; the filter scans over these (leading axis N)."""

    t: jnp.ndarray
    t_prev: jnp.ndarray
    dt: jnp.ndarray
    u_prev: jnp.ndarray
    u_cur: jnp.ndarray
    y: jnp.ndarray
    mask: jnp.ndarray
    dt_index: jnp.ndarray
    pieces: Pieces | None = None  # with delayed inputs: the interval's pieces (see .delays)


class FilterSteps(NamedTuple):
    """The pieces of a filter for one parameter vector and data set."""

    initial: tuple  # (x0, covariance in the carried form)
    rows: Row  # per-row inputs, leading axis N
    predict: Callable  # (x, cov, row) -> (x_{k|k-1}, cov_{k|k-1}, Φ_k)
    update: Callable  # (x_pred, cov_pred, row, mask=None) -> (Update, ŷ_{k|k-1})
    steady: steady_form.SteadyModel | None = None  # regular series of a linear model, see .steady


def carried_from_start(theta, *initial):
    """The scan's initial carries plus 0·θ summed: the same values, with a derivative in θ (zero).

    Differentiating a scan, JAX first assumes that a carry whose initial value
    does not depend on θ (a given P₀) keeps a zero derivative, finds that the
    carry's derivative after a step is not zero and transforms the step again —
    at each order of differentiation and of vectorisation, so a Hessian's tracing
    did twice the work (Armadillo Hessian program, tracing and lowering: 0.74–0.84
    → 0.65 s).  The added term is exactly zero (non-finite elements of θ are left
    out of it), and so are its derivatives: nothing else changes.
    """
    tie = jnp.sum(jnp.where(jnp.isfinite(theta), 0.0 * theta, 0.0))
    return tuple(a + tie for a in initial)


def takes_steady_state(structure: Structure, options: FilterOptions) -> bool:
    """Whether this model's filter can switch to the steady state (given enough regular rows): exact
    Kalman filtering of a time-invariant linear model without delays, with a constant observation."""
    return (options.method == KALMAN and structure.kind == LTI and not structure.delays
            and structure.constant_observation)


def filter_steps(structure: Structure, options: FilterOptions):
    """``steps(theta, data) -> FilterSteps``: one implementation of each filter.

    The scan of [`make_filter()`][greyid.filters.core.make_filter] and the k-step predictions of
    [`make_ahead()`][greyid.filters.core.make_ahead] are both built from these predict and update closures.
    A long regular series of a linear model takes the steady-state form where
    the filter reaches it ([`steady`][greyid.filters.steady]).
    """
    f, G, h, S = structure.drift, structure.diffusion, structure.observation, structure.observation_variance
    S_full = structure.observation_covariance  # None unless the outputs' noise is correlated
    form, method = options.form, options.method
    if method == KALMAN and not structure.is_linear:
        raise ModelError(
            f"the exact Kalman filter needs a linear model, but this model is {structure.kind}; "
            "use method='ekf', 'iekf' or 'ukf'"
        )
    n = structure.n_states
    weights = sigma_weights(n, options.alpha, options.beta, options.kappa) if method == UKF else None
    jac_f = jax.jacfwd(f, argnums=0)
    zeros = np.zeros(n)  # a constant of the traced code; NumPy, so nothing compiles here

    def linear_discretization(theta, data, A):
        """Discretizations of a time-invariant linear model, one per distinct sampling interval."""
        g = G(zeros, data.u_cur[0], data.t[0], theta)
        return discretize_each(A, g @ g.T, data.unique_dt)

    def predict_interval(x, cov, interval: Interval, theta, linear_matrices):
        """One interval (or piece of one) with its inputs held or ramped: mean, covariance and Φ."""
        if method == KALMAN and structure.kind == LTI:
            disc = discretize(*linear_matrices, interval.dt)
            b_prev = f(zeros, interval.u_prev, interval.t_prev, theta)
            b_cur = f(zeros, interval.u_cur, interval.t_prev + interval.dt, theta)
            x_pred, cov_pred = linear_predict(x, cov, disc, b_prev, b_cur, interval.foh, form)
            return x_pred, cov_pred, disc.transition
        if method == KALMAN:
            step = time_varying(theta, interval)
            x_pred = small.mm(step.transition, x) + step.offset
            return x_pred, propagate(cov, step.transition, step.noise_covariance, form), step.transition
        if method == UKF:
            return unscented_predict(x, cov, interval, theta, f, G, options.substeps, form, weights)
        return extended_predict(x, cov, interval, theta, f, G, options.substeps, form,
                                bias_correction=method in (EKF2, *SECOND_ORDER),
                                noise_correction=method in SECOND_ORDER)

    def time_varying(theta, interval: Interval):
        """The interval's Φ, offset and Λ of a time-varying linear model (sub-stepped)."""
        def matrices(u, t):
            g = G(zeros, u, t, theta)
            return jac_f(zeros, u, t, theta), small.mm(g, g.T)

        return time_varying_step(matrices, lambda u, t: f(zeros, u, t, theta), interval.t_prev, interval.dt,
                                 interval.u_prev, interval.u_cur, interval.foh, options.substeps)

    def steps(theta, data: FilterInputs) -> FilterSteps:
        first_noise = None
        delays = delays_at(structure, theta, data.t, data.u_cur, data.foh) if structure.delays else None
        data = with_delayed_inputs(structure, theta, data)
        exact_linear = method == KALMAN and structure.kind == LTI
        regular = data.delay_slots.shape[0] == 0
        pieces = piece_gains = linear_matrices = None
        if exact_linear and structure.linear_drift is not None:
            A, B, c = structure.linear_drift(theta)

            def affine(u, t):  # f(0, u, t) = B u + c: a few products, f itself never traced per step
                return small.mm(B, u) + c

            def affine_at(u, t, theta):  # the same with θ given (the steady state, steady.py)
                _, B, c = structure.linear_drift(theta)
                return small.mm(B, u) + c
        elif exact_linear:
            A = jac_f(zeros, data.u_cur[0], data.t[0], theta)

            def affine_at(u, t, theta):
                return f(zeros, u, t, theta)

            def affine(u, t):
                return affine_at(u, t, theta)
        if delays is not None:
            step = jnp.max(data.unique_dt)
            offsets = regular_offsets(delays.taus, step) if regular else None
            pieces = interval_pieces(delays, data, structure.n_inputs, offsets)
            if exact_linear:  # A and G Gᵀ; irregular sampling discretizes each piece as it comes
                g = G(zeros, data.u_cur[0], data.t[0], theta)
                linear_matrices = (A, g @ g.T)
                if regular:  # the same D + 1 pieces in every interval: discretized once
                    lengths = jnp.diff(jnp.concatenate([jnp.zeros(1), offsets, step[None]]))
                    piece_gains = discretize_each(*linear_matrices, lengths)
        rows = Row(data.t, data.t_prev, data.dt, data.u_prev, data.u_cur, data.y, data.mask, data.dt_index, pieces)
        if exact_linear and (delays is None or regular):
            cache = linear_discretization(theta, data, A)
            first_noise = cache.noise_covariance[data.dt_index[1]]  # the first interval's Λ
        x0, P0 = initial_state(structure, theta, data, first_noise)
        steady_pieces = None
        n_rows = data.t.shape[0]
        if (takes_steady_state(structure, options)
                and (n_rows >= steady_form.MIN_ROWS
                     or (options.steady_state and n_rows >= steady_form.SHORT_ROWS))):
            steady_pieces = steady_model(theta, data, cache, affine_at)

        def predict(x, cov, row: Row):
            if piece_gains is not None:
                return predict_regular_pieces(x, cov, row)
            if delays is not None:
                return predict_pieces(x, cov, row)
            if exact_linear:
                disc = jax.tree_util.tree_map(lambda a: a[row.dt_index], cache)
                # The affine terms b = f(0, u, t) at both ends, in the step: stored per row
                # they (and their derivatives) would grow with the series.
                b_prev, b_cur = affine(row.u_prev, row.t_prev), affine(row.u_cur, row.t)
                x_pred, cov_pred = linear_predict(x, cov, disc, b_prev, b_cur, data.foh, form)
                return x_pred, cov_pred, disc.transition
            return predict_interval(x, cov, Interval(row.t_prev, row.dt, row.u_prev, row.u_cur, data.foh),
                                    theta, linear_matrices)

        def predict_pieces(x, cov, row: Row):
            """The interval cut where a delayed input switches, each piece predicted in turn."""
            def piece(carry, p):
                x, cov, phi = carry
                x, cov, transition = predict_interval(x, cov, Interval(p.start, p.length, p.u_start, p.u_end,
                                                                       data.foh), theta, linear_matrices)
                return (x, cov, small.mm(transition, phi)), None

            (x, cov, phi), _ = jax.lax.scan(piece, (x, cov, jnp.eye(n)), row.pieces)
            return x, cov, phi

        def predict_regular_pieces(x, cov, row: Row):
            """(4.34) piece by piece for the mean; Φ and Λ of the whole interval for the covariance."""
            p = row.pieces
            x_new = x
            for i in range(p.length.shape[0]):  # D + 1 pieces, a static number
                b_start = f(zeros, p.u_start[i], p.start[i], theta)
                b_end = f(zeros, p.u_end[i], p.start[i] + p.length[i], theta)
                x_new = (small.mm(piece_gains.transition[i], x_new) + small.mm(piece_gains.input_gain[i], b_start)
                         + data.foh * small.mm(piece_gains.ramp_gain[i], b_end - b_start))
            disc = jax.tree_util.tree_map(lambda a: a[row.dt_index], cache)
            # Row 0 and padding rows have no interval: nothing moves.
            x_new = jnp.where(row.dt > 0, x_new, x)
            return x_new, propagate(cov, disc.transition, disc.noise_covariance, form), disc.transition

        def update(x_pred, cov_pred, row: Row, mask=None):
            u, t, y = row.u_cur, row.t, row.y
            mask = row.mask if mask is None else mask
            if method in (UKF, *SECOND_ORDER):
                noise = S(x_pred, u, t, theta) if S_full is None else S_full(x_pred, u, t, theta)
                if method == UKF:
                    return unscented_update(x_pred, cov_pred, y, mask, u, t, theta, h, noise, form, weights)
                return second_order_update(x_pred, cov_pred, y, mask, u, t, theta, h, noise, form,
                                           gaussian=method == GAUSSIAN2)
            y_pred, C = linearized_observation(h, x_pred, u, t, theta)
            if method == EKF2:  # (4.60)
                y_pred = y_pred + second_order_term(h, x_pred, to_matrix(cov_pred, form), u, t, theta)
            if method != IEKF:
                return measurement_update(x_pred, cov_pred, y, mask, y_pred, C, x_pred, u, t), y_pred

            # Iterated update (4.43): relinearize h about the latest estimate η.
            def iterate(_, eta):
                h_eta, C_eta = linearized_observation(h, eta, u, t, theta)
                pseudo = h_eta + C_eta @ (x_pred - eta)
                return measurement_update(x_pred, cov_pred, y, mask, pseudo, C_eta, eta, u, t).mean

            eta = jax.lax.fori_loop(0, options.iterations - 1, iterate, x_pred)
            h_eta, C = linearized_observation(h, eta, u, t, theta)
            y_pred = h_eta + C @ (x_pred - eta)
            return measurement_update(x_pred, cov_pred, y, mask, y_pred, C, eta, u, t), y_pred

        def measurement_update(x_pred, cov_pred, y, mask, y_pred, C, at, u, t):
            """(4.27–4.29) with the noise of the outputs at ``at``: independent or correlated."""
            if S_full is None:
                return linear_update(x_pred, cov_pred, y, mask, y_pred, C, S(at, u, t, theta), form)
            return correlated_update(x_pred, cov_pred, y, mask, y_pred, C, S_full(at, u, t, theta), form)

        return FilterSteps(carried_from_start(theta, x0, from_matrix(P0, form)), rows, predict, update,
                           steady_pieces)

    def output_at(u, t, theta):
        return h(zeros, u, t, theta)

    def steady_model(theta, data, cache, affine_at):
        """The model's time-invariant pieces at its most frequent sampling interval."""
        u0, t0 = data.u_cur[0], data.t[0]
        regular = jnp.argmax(jnp.bincount(data.dt_index, length=data.unique_dt.shape[0]))
        C = jax.jacfwd(h, argnums=0)(zeros, u0, t0, theta)
        noise = jnp.diag(S(zeros, u0, t0, theta)) if S_full is None else S_full(zeros, u0, t0, theta)
        return steady_form.SteadyModel(jax.tree_util.tree_map(lambda a: a[regular], cache), regular, C, noise,
                                       data.foh, form, theta, affine_at, output_at)

    return steps


def make_filter(structure: Structure, options: FilterOptions, keep_outputs: bool | str):
    """A jitted ``run(theta, data) -> (StepTerms, StepOutput | None)``.

    The per-step terms give the Gaussian log-likelihood (``terms.loglik.sum()``)
    and the robust criteria alike.  ``keep_outputs="innovations"`` keeps only
    the innovations and their covariances, ``(ε_k, R_k)``: what the scoring
    matrix needs, without the states' per-step storage.
    """
    form = options.form
    build = filter_steps(structure, options)

    def collect(x_pred, cov_pred, transition, upd, y_pred):
        out = None
        if keep_outputs == "innovations":
            out = (upd.innovation, upd.innovation_covariance)
        elif keep_outputs:
            out = StepOutput(x_pred, to_matrix(cov_pred, form), upd.mean, to_matrix(upd.covariance, form),
                             y_pred, upd.innovation, upd.innovation_covariance, transition,
                             jnp.broadcast_to(jnp.asarray(upd.guarded, jnp.float64), upd.innovation.shape[:-1]))
        return upd.terms, out

    def run(theta, data: FilterInputs):
        return scan_rows(build(theta, data), data.t.shape[0], collect)

    return jit(run)


def scan_rows(parts: FilterSteps, n_rows: int, collect: Callable | None, accumulate: Callable | None = None,
              forward_only: bool = False):
    """Predict and update over all rows; ``collect`` picks what each step returns.

    With ``accumulate`` the scan instead sums ``accumulate(StepTerms_k)`` in its
    carry and returns the sum: nothing is kept per step.  Long regular series
    of a linear model switch to the steady-state form where the filter reaches
    it ([`steady`][greyid.filters.steady]), shorter ones too where the options ask for it; a sum
    only ever differentiated in forward mode (``forward_only``) tests more than
    once where to switch ([`loop_until_settled()`][greyid.filters.core.loop_until_settled]).
    """

    def step(carry, row):
        state, total = carry
        x_pred, cov_pred, transition = parts.predict(*state, row)
        upd, y_pred = parts.update(x_pred, cov_pred, row)
        if accumulate is not None:
            return ((upd.mean, upd.covariance), total + accumulate(upd.terms)), None
        return ((upd.mean, upd.covariance), total), collect(x_pred, cov_pred, transition, upd, y_pred)

    def step_by_step(state, rows, length):
        (state, total), collected = jax.lax.scan(step, (state, jnp.zeros((), dtype=jnp.float64)), rows,
                                                 length=length)
        return state, total, collected

    if parts.steady is None:
        _, total, collected = step_by_step(parts.initial, parts.rows, n_rows)
        return collected if accumulate is None else total
    if (n_rows < steady_form.MIN_ROWS and accumulate is not None and forward_only
            and n_rows % steady_form.TEST_EVERY == 0):  # (as the length buckets of 128 rows and more are)
        return loop_until_settled(parts, n_rows, step, accumulate)
    if n_rows < steady_form.MIN_ROWS:
        return scan_settling(parts, n_rows, step_by_step, collect, accumulate)
    return scan_chunks(parts, n_rows, step_by_step, collect, accumulate)


def scan_settling(parts: FilterSteps, n_rows: int, step_by_step: Callable, collect, accumulate):
    """[`scan_rows()`][greyid.filters.core.scan_rows] for a shorter series: its first HEAD rows step by step, then the
    rest at once
    in the steady state where the filter has settled there, otherwise step by step too
    ([`steady`][greyid.filters.steady])."""
    model, head = parts.steady, steady_form.HEAD
    first = jax.tree_util.tree_map(lambda a: a[:head], parts.rows)
    rest = jax.tree_util.tree_map(lambda a: a[head:], parts.rows)
    state, total, collected = step_by_step(parts.initial, first, head)
    steady, settled = steady_form.settled_state(model, state[1], n_rows - head)
    padding = steady_form.padding_rows(rest)

    # One decision: a second chance further on (a cond within the cond) cost as much as
    # the rows it would save (Armadillo: tests after 16 and 32 rows, 0.235 ms; after 16, 0.187).
    def in_steady_state(_):
        outputs, _ = steady_form.steady_rows(model, steady, state[0], rest, padding)
        if accumulate is not None:
            return jnp.sum(jax.vmap(accumulate)(outputs[3].terms)), None
        return jnp.zeros(()), jax.vmap(collect)(*outputs)

    def ordinary(_):
        _, rest_total, rest_collected = step_by_step(state, rest, n_rows - head)
        return rest_total, rest_collected

    rest_total, rest_collected = jax.lax.cond(settled & jnp.all(steady_form.usable_rows(model, rest)), in_steady_state,
                                              ordinary, None)
    if accumulate is not None:
        return total + rest_total
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), collected, rest_collected)


def loop_until_settled(parts: FilterSteps, n_rows: int, step: Callable, accumulate: Callable):
    """The summed criterion of a shorter series, step by step until the filter has settled, then the
    rest at once in the steady state ([`steady`][greyid.filters.steady]).

    A loop whose length is decided as it runs (``lax.while_loop``, which forward-mode derivatives
    pass through and reverse mode does not), over blocks of TEST_EVERY rows: after each it tests,
    as [`scan_settling()`][greyid.filters.core.scan_settling] does once, whether the filter has settled and all later
    rows are
    regular and observed, and stops where they are.  So a filter that settles late (the thesis'
    test cell, after 76 rows) switches then instead of stepping through every row, with one loop
    body and one steady form in the program.  The rest — from the row where the loop stopped, a
    window of n_rows − TEST_EVERY rows padded at the end — goes through
    [`summed_rest()`][greyid.filters.steady.summed_rest], whose
    own derivative rule takes the rest's gradient in reverse mode.
    """
    model, every = parts.steady, steady_form.TEST_EVERY
    count, window = n_rows // every, n_rows - every
    # usable_from[k]: rows k … n_rows − 1 can all take the steady state.
    usable_from = jnp.flip(jnp.cumprod(jnp.flip(steady_form.usable_rows(model, parts.rows)).astype(jnp.int32))) > 0
    blocks = jax.tree_util.tree_map(lambda a: a.reshape(count, every, *a.shape[1:]), parts.rows)

    def going(carry):
        block, _, _, settled = carry
        return (block < count) & ~settled

    def one_block(carry):
        block, state, total, _ = carry
        (state, total), _ = jax.lax.scan(step, (state, total), jax.tree_util.tree_map(lambda a: a[block], blocks))
        k = (block + 1) * every  # rows done
        settled = jax.lax.cond(k < n_rows, lambda cov: steady_form.newton_test(model, cov)[2] & usable_from[k],
                               lambda cov: jnp.asarray(False), state[1])
        return block + 1, state, total, settled

    start = (jnp.asarray(0), parts.initial, jnp.zeros((), dtype=jnp.float64), jnp.asarray(False))
    block, state, total, settled = jax.lax.while_loop(going, one_block, start)

    def in_steady_state(_):
        # The rest as a window of fixed length from the row the loop stopped at: the rows past the
        # series' end are padding (no interval, nothing observed).
        padded = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.zeros((window, *a.shape[1:]), a.dtype)]), parts.rows)
        rest = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, block * every, window), padded)
        return steady_form.summed_rest(accumulate, model, state[0], state[1], rest)

    return total + jax.lax.cond(settled, in_steady_state, lambda _: jnp.zeros(()), None)


def scan_chunks(parts: FilterSteps, n_rows: int, step_by_step: Callable, collect, accumulate):
    """[`scan_rows()`][greyid.filters.core.scan_rows] a chunk of rows at a time, each step by step or in the steady
    state."""
    model, size = parts.steady, steady_form.CHUNK
    steady = steady_form.steady_state(model)

    def chunk(carry, rows):
        state, total, settled = carry
        # The rows padding the series to its length bucket fit either form: a chunk
        # holding the series' last rows stays in the steady state.
        padding = steady_form.padding_rows(rows)
        regular = settled & jnp.all(steady_form.usable_rows(model, rows))

        def in_steady_state(_):
            outputs, end = steady_form.steady_rows(model, steady, state[0], rows, padding)
            if accumulate is not None:
                return (end, total + jnp.sum(jax.vmap(accumulate)(outputs[3].terms)), jnp.asarray(True)), None
            return (end, total, jnp.asarray(True)), jax.vmap(collect)(*outputs)

        def ordinary(_):
            end, chunk_total, collected = step_by_step(state, rows, rows.t.shape[0])
            return (end, total + chunk_total, steady_form.at_steady_state(end[1], model.form, steady)), collected

        return jax.lax.cond(regular, in_steady_state, ordinary, None)

    count = n_rows // size
    head = jax.tree_util.tree_map(lambda a: a[:count * size].reshape(count, size, *a.shape[1:]), parts.rows)
    start = (parts.initial, jnp.zeros((), dtype=jnp.float64), jnp.asarray(False))
    (state, total, settled), collected = jax.lax.scan(chunk, start, head)
    collected = jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), collected)
    if n_rows > count * size:  # the last rows, a shorter chunk
        (_, total, _), last = chunk((state, total, settled),
                                    jax.tree_util.tree_map(lambda a: a[count * size:], parts.rows))
        collected = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), collected, last)
    return total if accumulate is not None else collected


def make_summed_filter(structure: Structure, options: FilterOptions, per_step: Callable,
                       forward_only: bool = False):
    """``run(theta, data) -> Σ_k per_step(StepTerms_k)``, summed in the scan's carry.

    Nothing is stored per step, so the memory of the value and of its forward
    derivatives does not grow with the length of the series.  ``forward_only``: the
    sum is never differentiated in reverse mode (see [`scan_rows()`][greyid.filters.core.scan_rows]).
    """
    build = filter_steps(structure, options)

    def run(theta, data: FilterInputs):
        return scan_rows(build(theta, data), data.t.shape[0], None, accumulate=per_step, forward_only=forward_only)

    return run


class AheadOutput(NamedTuple):
    """k-step predictions ŷ_{k|k-h}, their covariances and criterion terms."""

    output_prediction: jnp.ndarray
    output_cov: jnp.ndarray
    state_prediction: jnp.ndarray
    state_cov: jnp.ndarray
    terms: "StepTerms"


def make_ahead(structure: Structure, options: FilterOptions, horizon: int):
    """A jitted ``run(theta, data) -> AheadOutput`` of ``horizon``-step predictions.

    Row k is predicted from the filtered state at row k − horizon, or from the
    prior at t₀ for the first rows (section 7.2's k-step criterion).
    """
    if not isinstance(horizon, int) or horizon < 1:
        raise ModelError(f"the prediction horizon must be a positive integer, got {horizon!r}")
    form = options.form
    build = filter_steps(structure, options)

    def run(theta, data: FilterInputs):
        parts = build(theta, data)
        rows = jnp.arange(data.t.shape[0])
        means, covs = scan_rows(parts, data.t.shape[0], lambda *a: (a[3].mean, a[3].covariance))

        def row_at(k):
            return jax.tree_util.tree_map(lambda a: a[k], parts.rows)

        def ahead(k):
            start = k - horizon
            from_prior = start < 0
            x = jnp.where(from_prior, parts.initial[0], means[jnp.maximum(start, 0)])
            cov = jnp.where(from_prior, parts.initial[1], covs[jnp.maximum(start, 0)])
            first = jnp.maximum(start + 1, 1)

            def advance(j, state):
                row = first + j
                x_new, cov_new, _ = parts.predict(state[0], state[1], row_at(jnp.minimum(row, k)))
                active = row <= k
                return jnp.where(active, x_new, state[0]), jnp.where(active, cov_new, state[1])

            x, cov = jax.lax.fori_loop(0, horizon, advance, (x, cov))
            upd, y_pred = parts.update(x, cov, row_at(k))
            # The prediction's covariance is wanted for every output, observed or not.
            full, _ = parts.update(x, cov, row_at(k), jnp.ones_like(data.mask[k]))
            return y_pred, full.innovation_covariance, x, to_matrix(cov, form), upd.terms

        y, R, x, P, terms = jax.vmap(ahead)(rows)
        return AheadOutput(y, R, x, P, terms)

    return jit(run)
