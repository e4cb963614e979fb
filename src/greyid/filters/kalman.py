"""The exact Kalman filter of linear models (section 4.1).

A time-invariant model's discretization (4.34)–(4.39) is computed once per
distinct sampling interval and looked up per row; a regular series with delayed
inputs has the same pieces in every interval, discretized once too.  A
time-varying model is discretized per interval in sub-steps.  A regular series
of a time-invariant model without delays hands the driver its pieces for the
steady-state form ([`steady`][greyid.filters.steady]).
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..model.structure import LTI, Structure
from . import small
from . import steady as steady_form
from .discretize import discretize, discretize_each, time_varying_step
from .diffuse import prepare_start
from .gaussian import carried_from_start, interval_steps, linearized_update, predict_in_pieces, start
from .predictors import Interval, linear_predict
from .protocol import KALMAN, FilterInputs, FilterOptions, FilterSteps, Row, series_rows
from .updates import GaussianState, propagate


def takes_steady_state(structure: Structure, options: FilterOptions) -> bool:
    """Whether this model's filter can switch to the steady state (given enough regular rows): exact
    Kalman filtering of a time-invariant linear model without delays, with a constant observation."""
    return (options.method == KALMAN and structure.kind == LTI and not structure.delays
            and structure.constant_observation)


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data) -> FilterSteps`` of the exact Kalman filter of a linear model."""
    assert options.method == KALMAN, options.method
    if not structure.is_linear:
        raise ModelError(
            f"the exact Kalman filter needs a linear model, but this model is {structure.kind}; "
            "use method='ekf', 'iekf' or 'ukf'"
        )
    if structure.kind == LTI:
        return time_invariant(structure, options)
    return time_varying(structure, options)


def _update(structure: Structure, options: FilterOptions):
    def update(state, row, mask, theta):
        return linearized_update(structure, theta, options.form, state, row, mask)

    return update


def time_varying(structure: Structure, options: FilterOptions):
    """A time-varying linear model: Φ, offset and Λ of each interval in sub-steps."""
    f, G = structure.drift, structure.diffusion
    jac_f = jax.jacfwd(f, argnums=0)
    zeros = np.zeros(structure.n_states)  # a constant of the traced code; NumPy, so nothing compiles here

    def predict_interval(x, cov, interval: Interval, theta):
        def matrices(u, t):
            g = G(zeros, u, t, theta)
            return jac_f(zeros, u, t, theta), small.mm(g, g.T)

        step = time_varying_step(matrices, lambda u, t: f(zeros, u, t, theta), interval.t_prev, interval.dt,
                                 interval.u_prev, interval.u_cur, interval.foh, options.substeps)
        x_pred = small.mm(step.transition, x) + step.offset
        return x_pred, propagate(cov, step.transition, step.noise_covariance, options.form), step.transition

    return interval_steps(structure, options, predict_interval, _update(structure, options))


def time_invariant(structure: Structure, options: FilterOptions):
    """A time-invariant linear model: one discretization per distinct interval (or delay piece)."""
    f, G, h = structure.drift, structure.diffusion, structure.observation
    form, n = options.form, structure.n_states
    jac_f = jax.jacfwd(f, argnums=0)
    zeros = np.zeros(n)  # a constant of the traced code; NumPy, so nothing compiles here
    update = _update(structure, options)

    def output_at(u, t, theta):
        return h(zeros, u, t, theta)

    def steady_model(theta, data, cache, affine_at):
        """The model's time-invariant pieces at its most frequent sampling interval."""
        u0, t0 = data.u_cur[0], data.t[0]
        regular = jnp.argmax(jnp.bincount(data.dt_index, length=data.unique_dt.shape[0]))
        C = jax.jacfwd(h, argnums=0)(zeros, u0, t0, theta)
        full = structure.observation_covariance
        noise = jnp.diag(structure.observation_variance(zeros, u0, t0, theta)) if full is None else full(
            zeros, u0, t0, theta)
        return steady_form.SteadyModel(jax.tree_util.tree_map(lambda a: a[regular], cache), regular, C, noise,
                                       data.foh, form, theta, affine_at, output_at)

    def steps(theta, data: FilterInputs) -> FilterSteps:
        series = series_rows(structure, theta, data)
        data, delays = series.data, series.delays
        regular = data.delay_slots.shape[0] == 0
        if structure.linear_drift is not None:
            A, B, c = structure.linear_drift(theta)

            def affine(u, t):  # f(0, u, t) = B u + c: a few products, f itself never traced per step
                return small.mm(B, u) + c

            def affine_at(u, t, theta):  # the same with θ given (the steady state, steady.py)
                _, B, c = structure.linear_drift(theta)
                return small.mm(B, u) + c
        else:
            A = jac_f(zeros, data.u_cur[0], data.t[0], theta)

            def affine_at(u, t, theta):
                return f(zeros, u, t, theta)

            def affine(u, t):
                return affine_at(u, t, theta)

        g = G(zeros, data.u_cur[0], data.t[0], theta)
        linear_matrices = (A, g @ g.T)  # A and G Gᵀ
        piece_gains = cache = first_noise = None
        if delays is not None:  # irregular sampling discretizes each piece as it comes
            if regular:  # the same D + 1 pieces in every interval: discretized once
                step = jnp.max(data.unique_dt)
                lengths = jnp.diff(jnp.concatenate([jnp.zeros(1), series.offsets, step[None]]))
                piece_gains = discretize_each(*linear_matrices, lengths)
        if delays is None or regular:  # one discretization per distinct sampling interval
            cache = discretize_each(*linear_matrices, data.unique_dt)
            first_noise = cache.noise_covariance[data.dt_index[1]]  # the first interval's Λ
        initial = start(structure, theta, data, form, first_noise)
        diffuse = prepare_start(structure, theta, data, form, carried_from_start)
        steady = None
        if (takes_steady_state(structure, options)
                and steady_form.switches(data.t.shape[0], options.steady_state)):
            steady = steady_model(theta, data, cache, affine_at)

        def predict_interval(x, cov, interval: Interval):
            disc = discretize(*linear_matrices, interval.dt)
            b_prev = f(zeros, interval.u_prev, interval.t_prev, theta)
            b_cur = f(zeros, interval.u_cur, interval.t_prev + interval.dt, theta)
            x_pred, cov_pred = linear_predict(x, cov, disc, b_prev, b_cur, interval.foh, form)
            return x_pred, cov_pred, disc.transition

        def predict_regular_pieces(state: GaussianState, row: Row):
            """(4.34) piece by piece for the mean; Φ and Λ of the whole interval for the covariance."""
            p = row.pieces
            x, cov = state
            x_new = x
            for i in range(p.length.shape[0]):  # D + 1 pieces, a static number
                b_start = f(zeros, p.u_start[i], p.start[i], theta)
                b_end = f(zeros, p.u_end[i], p.start[i] + p.length[i], theta)
                x_new = (small.mm(piece_gains.transition[i], x_new) + small.mm(piece_gains.input_gain[i], b_start)
                         + data.foh * small.mm(piece_gains.ramp_gain[i], b_end - b_start))
            disc = jax.tree_util.tree_map(lambda a: a[row.dt_index], cache)
            # Row 0 and padding rows have no interval: nothing moves.
            x_new = jnp.where(row.dt > 0, x_new, x)
            return GaussianState(x_new, propagate(cov, disc.transition, disc.noise_covariance, form)), disc.transition

        def predict(state: GaussianState, row: Row):
            if piece_gains is not None:
                return predict_regular_pieces(state, row)
            if delays is not None:
                return predict_in_pieces(predict_interval, state, row, data.foh, n)
            disc = jax.tree_util.tree_map(lambda a: a[row.dt_index], cache)
            # The affine terms b = f(0, u, t) at both ends, in the step: stored per row
            # they (and their derivatives) would grow with the series.
            b_prev, b_cur = affine(row.u_prev, row.t_prev), affine(row.u_cur, row.t)
            x_pred, cov_pred = linear_predict(*state, disc, b_prev, b_cur, data.foh, form)
            return GaussianState(x_pred, cov_pred), disc.transition

        def update_with(state: GaussianState, row: Row, mask=None):
            return update(state, row, row.mask if mask is None else mask, theta)

        return FilterSteps(initial, series.rows, predict, update_with, steady, diffuse)

    return steps
