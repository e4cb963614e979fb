"""What the Gaussian families share: the initial state, the update of a linearized observation, and the
prediction over an interval cut where delayed inputs switch.

Each Gaussian family ([`kalman`][greyid.filters.kalman], [`extended`][greyid.filters.extended],
[`second_order`][greyid.filters.second_order], [`unscented`][greyid.filters.unscented]) carries a
[`GaussianState`][greyid.filters.updates.GaussianState]: the mean and the covariance in the
options' form (the covariance itself or its Cholesky factor).
"""

from __future__ import annotations

from typing import Callable

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..model.structure import Structure
from . import small
from .diffuse import prepare_start
from .discretize import discretize, stationary_covariance
from .predictors import Interval, linearized_observation, second_order_term
from .protocol import FilterInputs, FilterOptions, FilterSteps, Row, series_rows
from .updates import GaussianState, Update, correlated_update, from_matrix, linear_update, to_matrix

#: ``predict_interval(x, cov, interval) -> (x, cov, Φ)``: one interval (or piece of one) with its inputs
#: held or ramped.
IntervalPredictor = Callable[[jnp.ndarray, jnp.ndarray, Interval], tuple]


def initial_state(structure: Structure, theta, data: FilterInputs, first_noise=None):
    """x0 and P0 (matrix, CTSM's scaled process noise, or stationary covariance).

    ``first_noise`` is Λ of the first interval when the caller has it already.  Diffuse
    states' rows and columns of P0 are zero: their infinite part is the filter's P∞
    ([`diffuse`][greyid.filters.diffuse]).
    """
    x0, P0 = initial_moments(structure, theta, data, first_noise)
    diffuse = structure.initial_covariance.diffuse
    if not diffuse:
        return x0, P0
    index = np.asarray(diffuse)
    return x0, P0.at[index, :].set(0.0).at[:, index].set(0.0)


def initial_moments(structure: Structure, theta, data: FilterInputs, first_noise=None):
    """x0 and P0 as the initial covariance's kind gives them, diffuse states included
    ([`initial_state()`][greyid.filters.gaussian.initial_state] sets theirs to zero)."""
    x0 = structure.initial_mean(theta)
    spec = structure.initial_covariance
    if spec.kind == "matrix":
        return x0, spec.matrix(theta)
    if spec.kind == "process" and first_noise is not None:
        return x0, with_latent_block(spec, theta, spec.scale * first_noise)
    u0, t0 = data.u_cur[0], data.t[0]
    if structure.linear_drift is not None:
        A = structure.linear_drift(theta)[0]
    else:
        A = jax.jacfwd(structure.drift, argnums=0)(x0, u0, t0, theta)
    G = structure.diffusion(x0, u0, t0, theta)
    if spec.kind == "process":
        return x0, with_latent_block(spec, theta, spec.scale * discretize(A, G @ G.T, data.first_interval)
                                     .noise_covariance)
    if spec.latent is None and not spec.diffuse:
        return x0, stationary_covariance(A, G @ G.T)
    # The model's own states' stationary covariance without the forces' coupling (a periodic force's
    # oscillators have none to solve for) and without the diffuse states (a random walk has none), as
    # statsmodels' mixed initialisation solves each block on its own; the forces' own P∞ beside it.
    k = structure.n_states if spec.latent is None else spec.latent_start
    keep = np.array([i for i in range(k) if i not in spec.diffuse], dtype=int)
    own = stationary_covariance(A[np.ix_(keep, keep)], (G @ G.T)[np.ix_(keep, keep)]) if len(keep) else None
    P0 = jnp.zeros_like(A) if own is None else jnp.zeros_like(A).at[np.ix_(keep, keep)].set(own)
    return x0, with_latent_block(spec, theta, P0)


def with_latent_block(spec, theta, P0):
    """P0 with the latent forces' states (from ``spec.latent_start``) in their stationary law N(0, P∞),
    independent of the model's own states at t₀."""
    if spec.latent is None:
        return P0
    k = spec.latent_start
    return P0.at[k:, :].set(0.0).at[:, k:].set(0.0).at[k:, k:].set(spec.latent(theta))


def carried_from_start(theta, *initial):
    """The scan's initial carries plus 0·θ summed: the same values, with a derivative in θ (zero).

    Differentiating a scan, JAX first assumes that a carry whose initial value
    does not depend on θ (a given P₀) keeps a zero derivative, finds that the
    carry's derivative after a step is not zero and transforms the step again —
    at each order of differentiation and of vectorisation, so a Hessian's tracing
    would do twice the work.  The added term is exactly zero (non-finite elements
    of θ are left out of it), and so are its derivatives: nothing else changes.
    """
    tie = jnp.sum(jnp.where(jnp.isfinite(theta), 0.0 * theta, 0.0))
    return tuple(a + tie for a in initial)


def start(structure: Structure, theta, data: FilterInputs, form: str, first_noise=None) -> GaussianState:
    """The filter's state at t₀, before the update with the first row's observation."""
    x0, P0 = initial_state(structure, theta, data, first_noise)
    return GaussianState(*carried_from_start(theta, x0, from_matrix(P0, form)))


def predict_in_pieces(predict_interval: IntervalPredictor, state: GaussianState, row: Row, foh,
                      n_states: int) -> tuple[GaussianState, jnp.ndarray]:
    """The interval cut where a delayed input switches, each piece predicted in turn; Φ of the whole."""
    def piece(carry, p):
        x, cov, phi = carry
        x, cov, transition = predict_interval(x, cov, Interval(p.start, p.length, p.u_start, p.u_end, foh))
        return (x, cov, small.mm(transition, phi)), None

    (x, cov, phi), _ = jax.lax.scan(piece, (*state, jnp.eye(n_states)), row.pieces)
    return GaussianState(x, cov), phi


def predict_row(predict_interval: IntervalPredictor, state: GaussianState, row: Row, foh,
                n_states: int) -> tuple[GaussianState, jnp.ndarray]:
    """From t_{k-1} to t_k: the whole interval, or its pieces where delayed inputs switch inside it."""
    if row.pieces is not None:
        return predict_in_pieces(predict_interval, state, row, foh, n_states)
    x, cov, transition = predict_interval(*state, Interval(row.t_prev, row.dt, row.u_prev, row.u_cur, foh))
    return GaussianState(x, cov), transition


def measurement_update(structure: Structure, theta, form: str, state: GaussianState, y, mask, y_pred, C, at, u,
                       t) -> Update:
    """(4.27–4.29) with the noise of the outputs at ``at``: independent or correlated."""
    full = structure.observation_covariance
    if full is None:
        return linear_update(*state, y, mask, y_pred, C, structure.observation_variance(at, u, t, theta), form)
    return correlated_update(*state, y, mask, y_pred, C, full(at, u, t, theta), form)


def linearized_update(structure: Structure, theta, form: str, state: GaussianState, row: Row, mask,
                      bias: bool = False, iterations: int = 1) -> tuple[Update, jnp.ndarray]:
    """The update of h linearized about the prediction (4.27–4.29); with ``bias`` the second-order
    term of (4.60); with ``iterations`` > 1 relinearized about the latest estimate (4.43)."""
    h = structure.observation
    u, t, y = row.u_cur, row.t, row.y
    x_pred = state.mean
    y_pred, C = linearized_observation(h, x_pred, u, t, theta)
    if bias:  # (4.60)
        y_pred = y_pred + second_order_term(h, x_pred, to_matrix(state.covariance, form), u, t, theta)
    if iterations == 1:
        return measurement_update(structure, theta, form, state, y, mask, y_pred, C, x_pred, u, t), y_pred

    def iterate(_, eta):
        h_eta, C_eta = linearized_observation(h, eta, u, t, theta)
        pseudo = h_eta + C_eta @ (x_pred - eta)
        return measurement_update(structure, theta, form, state, y, mask, pseudo, C_eta, eta, u, t).mean

    eta = jax.lax.fori_loop(0, iterations - 1, iterate, x_pred)
    h_eta, C = linearized_observation(h, eta, u, t, theta)
    y_pred = h_eta + C @ (x_pred - eta)
    return measurement_update(structure, theta, form, state, y, mask, y_pred, C, eta, u, t), y_pred


def observation_noise(structure: Structure, theta, x, u, t):
    """The outputs' noise at x: the variances (a vector) or, where correlated, the covariance matrix."""
    if structure.observation_covariance is None:
        return structure.observation_variance(x, u, t, theta)
    return structure.observation_covariance(x, u, t, theta)


def interval_steps(structure: Structure, options: FilterOptions, predict_interval: Callable,
                   update: Callable) -> Callable:
    """``steps(theta, data)`` of a family given by its prediction over an interval and its update.

    ``predict_interval(x, cov, interval, theta)`` and ``update(state, row, mask, theta)``; the rows,
    the delays' pieces and the initial state are the same for every such family.
    """
    def steps(theta, data: FilterInputs) -> FilterSteps:
        series = series_rows(structure, theta, data)
        foh = series.data.foh

        def predict(state: GaussianState, row: Row):
            return predict_row(lambda x, cov, interval: predict_interval(x, cov, interval, theta), state, row, foh,
                               structure.n_states)

        def update_with(state: GaussianState, row: Row, mask=None):
            return update(state, row, row.mask if mask is None else mask, theta)

        diffuse = prepare_start(structure, theta, series.data, options.form, carried_from_start)
        return FilterSteps(start(structure, theta, series.data, options.form), series.rows, predict, update_with,
                           diffuse=diffuse)

    return steps
