"""One driver for every filter family: the scan over a series' rows.

Row k first predicts from t_{k-1} to t_k (row 0 "predicts" over an interval of
length 0, so the filter starts from its state at t₀ and updates it with the
observation there), then updates with the observed elements of y_k.  The same
scan gives the log-likelihood (3.18), the filtered and predicted states for
results and the smoother, and — from the same steps — k-step predictions.  A
family's steps come from its module ([`FAMILIES`][greyid.filters.driver.FAMILIES]); where a family hands
over a steady-state model (a regular series of a time-invariant linear model),
the driver switches to the steady-state form once the filter has settled
([`steady`][greyid.filters.steady]).
"""

from __future__ import annotations

import numbers
from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

from ..runtime.jit import jit
from ..errors import ModelError
from ..model.structure import Structure
from ..model.distributions import check_method
from . import diffuse, ensemble, extended, kalman, laplace, particle, second_order, unscented
from . import steady as steady_form
from .protocol import (EKF, EKF2, ENKF, GAUSSIAN2, IEKF, KALMAN, LAPLACE, PARTICLE, STOCHASTIC, TRUNCATED2, UKF,
                       Family, FilterInputs, FilterOptions, FilterSteps)
from .updates import DensityTerms, GaussianState, StepTerms, to_matrix

#: The module that prepares each method's steps: ``prepare(structure, options)(theta, data) -> FilterSteps``.
FAMILIES: dict[str, Family] = {
    KALMAN: kalman.prepare,
    EKF: extended.prepare,
    IEKF: extended.prepare,
    EKF2: second_order.prepare,
    TRUNCATED2: second_order.prepare,
    GAUSSIAN2: second_order.prepare,
    UKF: unscented.prepare,
    PARTICLE: particle.prepare,
    ENKF: ensemble.prepare,
}
#: Methods that give the log-likelihood of a series as a whole (a marginal), not row by row:
#: ``prepare(structure, options)(theta, data) -> (log-likelihood, what the method found)``.
MARGINALS = {LAPLACE: laplace.prepare}


def filter_steps(structure: Structure, options: FilterOptions) -> Callable[..., FilterSteps]:
    """``steps(theta, data) -> FilterSteps`` of the options' method (see [`protocol`][greyid.filters.protocol]).

    Raises
    ------
    ModelError
        A Gaussian filter asked for outputs whose distribution is not normal.
    """
    check_method(structure.distributions, structure.output_names, options.method)
    check_diffuse(structure, options.method)
    if options.method in MARGINALS:
        raise ModelError(f"the {options.method} method gives a likelihood, not a filter's predictions and updates; "
                         "use a filter (method='ekf', 'ukf', 'particle', ...) for filtered states and predictions")
    return FAMILIES[options.method](structure, options)


def check_diffuse(structure: Structure, method: str) -> None:
    """Refuse a diffuse initial state to every method but the exact Kalman filter and the Laplace method."""
    diffuse = structure.initial_covariance.diffuse
    if diffuse and method not in (KALMAN, LAPLACE):
        names = [structure.state_names[i] for i in diffuse]
        raise ModelError(f"the diffuse initial states {names} are started exactly by the Kalman filter "
                         f"(method='kalman') and the Laplace method (a flat prior), not by method='{method}'; "
                         "give them a mean and a covariance to use it")


def marginal_terms(structure: Structure, options: FilterOptions):
    """``run(theta, data) -> DensityTerms`` of a marginal method: the series' log-likelihood in row 0's
    term (nothing in the others'), each row's count of observed outputs."""
    check_method(structure.distributions, structure.output_names, options.method)
    check_diffuse(structure, options.method)
    marginal = MARGINALS[options.method](structure, options)

    def run(theta, data: FilterInputs):
        value, _ = marginal(theta, data)
        loglik = jnp.zeros(data.t.shape[0]).at[0].set(value)
        return DensityTerms(loglik, jnp.sum(data.mask, axis=-1))

    return run


def state_moments(state, form: str):
    """The mean and covariance matrix of a filter's state: a Gaussian state's own (its covariance in the
    carried ``form``), or the moments a family's state computes (the particles')."""
    if isinstance(state, GaussianState):
        return state.mean, to_matrix(state.covariance, form)
    return state.moments()


class StepOutput(NamedTuple):
    """What a Gaussian filter keeps of each row for results and the smoother."""

    predicted_mean: jnp.ndarray
    predicted_cov: jnp.ndarray
    filtered_mean: jnp.ndarray
    filtered_cov: jnp.ndarray
    output_prediction: jnp.ndarray
    innovation: jnp.ndarray
    innovation_cov: jnp.ndarray
    transition: jnp.ndarray
    guarded: jnp.ndarray  # 1 where a moment update's covariance was guarded (see predictors.moment_update)
    pit: jnp.ndarray  # each output's probability integral transform (the particle filter's; 0.5 for the others)


def make_filter(structure: Structure, options: FilterOptions, keep_outputs: bool | str):
    """A jitted ``run(theta, data) -> (StepTerms, StepOutput | None)``.

    The per-step terms give the Gaussian log-likelihood (``terms.loglik.sum()``)
    and the robust criteria alike.  ``keep_outputs="innovations"`` keeps only
    the innovations and their covariances, ``(ε_k, R_k)``: what the scoring
    matrix needs, without the states' per-step storage.
    """
    form = options.form
    if options.method in MARGINALS:
        if keep_outputs:
            filter_steps(structure, options)  # the error that says what to use instead
        terms = marginal_terms(structure, options)
        return jit(lambda theta, data: (terms(theta, data), None))
    build = filter_steps(structure, options)

    def collect(predicted: GaussianState, transition, upd, y_pred):
        out = None
        if keep_outputs == "innovations":
            out = (upd.innovation, upd.innovation_covariance)
        elif keep_outputs:
            out = StepOutput(*state_moments(predicted, form), *state_moments(upd.state, form), y_pred,
                             upd.innovation, upd.innovation_covariance, transition,
                             jnp.broadcast_to(jnp.asarray(upd.guarded, jnp.float64), upd.innovation.shape[:-1]),
                             jnp.full(upd.innovation.shape, 0.5) if getattr(upd, "pit", None) is None else upd.pit)
        return upd.terms, out

    def run(theta, data: FilterInputs):
        return scan_rows(build(theta, data), data.t.shape[0], collect)

    return jit(run)


def make_summed_filter(structure: Structure, options: FilterOptions, per_step: Callable,
                       forward_only: bool = False):
    """``run(theta, data) -> Σ_k per_step(StepTerms_k)``, summed in the scan's carry.

    Nothing is stored per step, so the memory of the value and of its forward
    derivatives does not grow with the length of the series.  ``forward_only``: the
    sum is never differentiated in reverse mode (see [`scan_rows()`][greyid.filters.driver.scan_rows]).
    """
    if options.method in MARGINALS:
        terms = marginal_terms(structure, options)
        return lambda theta, data: jnp.sum(per_step(terms(theta, data)))
    build = filter_steps(structure, options)

    def run(theta, data: FilterInputs):
        return scan_rows(build(theta, data), data.t.shape[0], None, accumulate=per_step, forward_only=forward_only)

    return run


def make_replicated_filter(structure: Structure, options: FilterOptions, replicates: int):
    """A jitted ``run(theta, data) -> (replicates,)`` log-likelihoods of a particle (or ensemble Kalman)
    filter run with independent random numbers (keys split from the seed's), vectorised: the spread of the
    estimate."""
    if options.method not in STOCHASTIC:
        raise ModelError(f"replicates are runs of a particle filter with other random numbers; '{options.method}' "
                         "has no random numbers")
    build = filter_steps(structure, options)

    def run(theta, data: FilterInputs):
        keys = jax.random.split(jax.random.PRNGKey(options.seed), replicates)

        def one(key):
            return scan_rows(build(theta, data, key=key), data.t.shape[0], None,
                             accumulate=lambda terms: terms.loglik)

        return jax.vmap(one)(keys)

    return jit(run)


def scan_rows(parts: FilterSteps, n_rows: int, collect: Callable | None, accumulate: Callable | None = None,
              forward_only: bool = False):
    """Predict and update over all rows; ``collect(predicted, transition, update, y_pred)`` picks what
    each step returns.

    With ``accumulate`` the scan instead sums ``accumulate(StepTerms_k)`` in its
    carry and returns the sum: nothing is kept per step.  Long regular series
    of a linear model switch to the steady-state form where the filter reaches
    it ([`steady`][greyid.filters.steady]), shorter ones too where the options ask for it; a sum
    only ever differentiated in forward mode (``forward_only``) tests more than
    once where to switch ([`loop_until_settled()`][greyid.filters.driver.loop_until_settled]).
    """

    if parts.diffuse is not None:
        return scan_diffuse(parts, n_rows, collect, accumulate, forward_only)

    def step(carry, row):
        state, total = carry
        predicted, transition = parts.predict(state, row)
        upd, y_pred = parts.update(predicted, row)
        if accumulate is not None:
            return (upd.state, total + accumulate(upd.terms)), None
        return (upd.state, total), collect(predicted, transition, upd, y_pred)

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


def scan_diffuse(parts: FilterSteps, n_rows: int, collect: Callable | None, accumulate: Callable | None,
                 forward_only: bool):
    """[`scan_rows()`][greyid.filters.driver.scan_rows] of a filter with a diffuse start: the diffuse period's rows
    with both parts of the covariance ([`diffuse`][greyid.filters.diffuse]), then the other rows as any filter's.

    What the diffuse rows report: the covariances +∞ where P∞ is not zero, and the outputs whose prediction has
    an infinite variance without an innovation (NaN; in the scoring's ``(ε, R)`` 0 and 1, adding nothing).
    """
    head = parts.diffuse.rows

    def collect_diffuse(predicted, transition, upd, y_pred, infinite, infinite_after, loaded, scale):
        out = collect(predicted, transition, upd, y_pred)
        both = loaded[:, None] | loaded[None, :]
        eye = jnp.eye(loaded.shape[0], dtype=bool)

        def reported(kept):
            if isinstance(kept, StepOutput):
                return kept._replace(
                    predicted_cov=kept.predicted_cov + diffuse.infinite_part(infinite, scale),
                    filtered_cov=kept.filtered_cov + diffuse.infinite_part(infinite_after, scale),
                    innovation=jnp.where(loaded, jnp.nan, kept.innovation),
                    innovation_cov=jnp.where(both, jnp.where(eye, jnp.inf, 0.0), kept.innovation_cov))
            if isinstance(kept, AheadStart):
                return kept._replace(unknown=jnp.any(diffuse.infinite_part(infinite_after, scale) > 0))
            if type(kept) is tuple and len(kept) == 2:  # the scoring's (ε, R)
                return jnp.where(loaded, 0.0, kept[0]), jnp.where(both, eye.astype(kept[1].dtype), kept[1])
            return kept

        return tuple(reported(k) for k in out) if type(out) is tuple else reported(out)

    first = jax.tree_util.tree_map(lambda a: a[:head], parts.rows)
    state, total, collected = diffuse.scan_head(parts.diffuse, parts.initial, parts.predict, first,
                                                None if accumulate is not None else collect_diffuse, accumulate)
    if head == n_rows:
        return total if accumulate is not None else collected
    steady = parts.steady if n_rows - head >= steady_form.SHORT_ROWS else None
    rest = parts._replace(initial=state, rows=jax.tree_util.tree_map(lambda a: a[head:], parts.rows),
                          steady=steady, diffuse=None)
    later = scan_rows(rest, n_rows - head, collect, accumulate, forward_only)
    if accumulate is not None:
        return total + later
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), collected, later)


def collected_steady(collect: Callable, outputs):
    """``collect`` of each row of the steady-state form's ``(x_pred, cov_pred, Φ, update, y_pred)``."""
    return jax.vmap(lambda x, cov, transition, upd, y_pred: collect(GaussianState(x, cov), transition, upd, y_pred)
                    )(*outputs)


def scan_settling(parts: FilterSteps, n_rows: int, step_by_step: Callable, collect, accumulate):
    """[`scan_rows()`][greyid.filters.driver.scan_rows] for a shorter series: its first HEAD rows step by step,
    then the rest at once in the steady state where the filter has settled there, otherwise step by step
    too ([`steady`][greyid.filters.steady])."""
    model, head = parts.steady, steady_form.HEAD
    first = jax.tree_util.tree_map(lambda a: a[:head], parts.rows)
    rest = jax.tree_util.tree_map(lambda a: a[head:], parts.rows)
    state, total, collected = step_by_step(parts.initial, first, head)
    steady, settled = steady_form.settled_state(model, state.covariance, n_rows - head, filtered=accumulate is None)
    padding = steady_form.padding_rows(rest)

    # One decision: a second chance further on (a cond within the cond) cost as much as
    # the rows it would save.
    def in_steady_state(_):
        if accumulate is not None:  # the criterion alone: the means and their terms, no per-row covariances
            terms = steady_form.steady_means(model, steady, state.mean, rest, padding)[-1]
            return jnp.sum(jax.vmap(accumulate)(terms)), None
        outputs, _ = steady_form.steady_rows(model, steady, state.mean, rest, padding)
        return jnp.zeros(()), collected_steady(collect, outputs)

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
    as [`scan_settling()`][greyid.filters.driver.scan_settling] does once, whether the filter has settled and all
    later rows are regular and observed, and stops where they are.  So a filter that settles late (the
    thesis' test cell, after 76 rows) switches then instead of stepping through every row, with one loop
    body and one steady form in the program.  The rest — from the row where the loop stopped, a
    window of n_rows − TEST_EVERY rows padded at the end — goes through
    [`summed_rest()`][greyid.filters.steady.summed_rest], whose own derivative rule takes the rest's gradient
    in reverse mode.
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
                               lambda cov: jnp.asarray(False), state.covariance)
        return block + 1, state, total, settled

    start = (jnp.asarray(0), parts.initial, jnp.zeros((), dtype=jnp.float64), jnp.asarray(False))
    block, state, total, settled = jax.lax.while_loop(going, one_block, start)

    def in_steady_state(_):
        # The rest as a window of fixed length from the row the loop stopped at: the rows past the
        # series' end are padding (no interval, nothing observed).
        padded = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.zeros((window, *a.shape[1:]), a.dtype)]), parts.rows)
        rest = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, block * every, window), padded)
        return steady_form.summed_rest(accumulate, model, state.mean, state.covariance, rest)

    return total + jax.lax.cond(settled, in_steady_state, lambda _: jnp.zeros(()), None)


def scan_chunks(parts: FilterSteps, n_rows: int, step_by_step: Callable, collect, accumulate):
    """[`scan_rows()`][greyid.filters.driver.scan_rows] a chunk of rows at a time, each step by step or in the
    steady state."""
    model, size = parts.steady, steady_form.CHUNK
    steady = steady_form.steady_state(model)

    def chunk(carry, rows):
        state, total, settled = carry
        # The rows padding the series to its length bucket fit either form: a chunk
        # holding the series' last rows stays in the steady state.
        padding = steady_form.padding_rows(rows)
        regular = settled & jnp.all(steady_form.usable_rows(model, rows))

        def in_steady_state(_):
            outputs, end = steady_form.steady_rows(model, steady, state.mean, rows, padding)
            if accumulate is not None:
                return (end, total + jnp.sum(jax.vmap(accumulate)(outputs[3].terms)), jnp.asarray(True)), None
            return (end, total, jnp.asarray(True)), collected_steady(collect, outputs)

        def ordinary(_):
            end, chunk_total, collected = step_by_step(state, rows, rows.t.shape[0])
            settled = steady_form.at_steady_state(end.covariance, model.form, steady)
            return (end, total + chunk_total, settled), collected

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


class AheadStart(NamedTuple):
    """A filtered state k-step predictions start from, and whether it still has a diffuse part."""

    state: object
    unknown: jnp.ndarray


class AheadOutput(NamedTuple):
    """k-step predictions ŷ_{k|k-h}, their covariances and criterion terms."""

    output_prediction: jnp.ndarray
    output_cov: jnp.ndarray
    state_prediction: jnp.ndarray
    state_cov: jnp.ndarray
    terms: StepTerms


def checked_horizon(steps) -> int:
    """The prediction horizon, checked: a positive whole number of samples."""
    if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 1:
        raise ModelError(f"the prediction horizon must be a positive integer, got {steps!r}")
    return int(steps)


def make_ahead(structure: Structure, options: FilterOptions, horizon: int | None):
    """A jitted ``run(theta, data) -> AheadOutput`` of ``horizon``-step predictions.

    Row k is predicted from the filtered state at row k − horizon, or from the
    state at t₀ for the first rows (section 7.2's k-step criterion).  With
    ``horizon=None`` the horizon is an argument, ``run(theta, data, horizon)``: one
    program predicts at every horizon, but its loop over the horizon's intervals
    has no reverse-mode derivative (the k-step criterion fixes the horizon).
    """
    if horizon is not None:
        horizon = checked_horizon(horizon)
    form = options.form
    build = filter_steps(structure, options)

    def run(theta, data: FilterInputs, steps=horizon):
        parts = build(theta, data)
        rows = jnp.arange(data.t.shape[0])
        filtered = scan_rows(parts, data.t.shape[0],
                             lambda predicted, transition, upd, y_pred: AheadStart(upd.state, jnp.asarray(False)))
        # From a state with a diffuse part (the prior, rows of the diffuse period), predictions are unknown.
        prior_unknown = parts.diffuse is not None

        def row_at(k):
            return jax.tree_util.tree_map(lambda a: a[k], parts.rows)

        def ahead(k):
            start = k - steps
            from_prior = start < 0
            state = jax.tree_util.tree_map(
                lambda first, each: jnp.where(from_prior, first, each[jnp.maximum(start, 0)]), parts.initial,
                filtered.state)
            unknown = jnp.where(from_prior, prior_unknown, filtered.unknown[jnp.maximum(start, 0)])
            first = jnp.maximum(start + 1, 1)

            def advance(j, state):
                row = first + j
                moved, _ = parts.predict(state, row_at(jnp.minimum(row, k)))
                active = row <= k
                return jax.tree_util.tree_map(lambda new, old: jnp.where(active, new, old), moved, state)

            state = jax.lax.fori_loop(0, steps, advance, state)
            upd, y_pred = parts.update(state, row_at(k))
            # The prediction's covariance is wanted for every output, observed or not.
            full, _ = parts.update(state, row_at(k), jnp.ones_like(data.mask[k]))
            x, P = state_moments(state, form)
            if parts.diffuse is None:
                return y_pred, full.innovation_covariance, x, P, upd.terms
            # Unknown: infinite variances, no term of the criterion.
            terms = jax.tree_util.tree_map(lambda a: jnp.where(unknown, jnp.zeros_like(a), a), upd.terms)
            return (y_pred, jnp.where(unknown, jnp.inf, full.innovation_covariance), x,
                    jnp.where(unknown, jnp.inf, P), terms)

        y, R, x, P, terms = jax.vmap(ahead)(rows)
        return AheadOutput(y, R, x, P, terms)

    return jit(run)
