"""Delayed inputs in the filters: ``delay(u, tau)`` is u at time t − tau (chapter 8).

A held input (zero-order hold) switches value at the sampling instants t_j, so
the delayed input switches at t_j + tau, inside the sampling intervals.  Each
interval [t_{k-1}, t_k] is cut at those instants into pieces on which every
input is constant (or, with a first-order hold, linear), and the pieces are
predicted one after the other exactly as whole intervals are.  The likelihood is
then exact for linear models and smooth in tau, and its derivatives in tau are
exact: they come from the pieces' lengths.  Before the series starts a delayed
input takes its first value.

The most switching instants one interval can hold is fixed by the sampling
times; it is carried by the shape of ``FilterInputs.delay_slots`` so that each
sampling pattern compiles once.  Regular sampling, the common case, has its
own shape (0,): every interval is then cut at the same offsets, so a linear
model discretizes its D + 1 pieces once per parameter vector instead of once
per interval.
"""

from __future__ import annotations

from typing import NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError, ModelError


def delay_slots(times: np.ndarray, regular: bool = False) -> int:
    """The most sampling instants an open window as long as the longest interval can hold.

    0 for ``regular`` sampling (one cut per delay per interval, at the same offset).
    """
    times = np.asarray(times, dtype=np.float64)
    if regular:
        return 0
    if len(times) < 2:
        return 1
    widest = float(np.max(np.diff(times)))
    # Just under the width, so that regular sampling's rounding does not count a neighbour twice.
    ends = np.searchsorted(times, times + widest * (1.0 - 1e-9), side="left")
    return max(1, int(np.max(ends - np.arange(len(times)))))


def delayed_values(times, column, at, foh):
    """``column`` (one input over ``times``) at the instants ``at``: held or interpolated (``foh``).

    Before ``times[0]`` the first value, after the last the last.
    """
    n = times.shape[0]
    # Held: the value from t_j on (right-continuous).  Interpolated: at a sampling instant itself (to
    # within rounding) the segment before it, so that the derivative in τ of u(s − τ) is the one a
    # growing τ sees; the value is the same either way.
    tiny = 1e-10 * (times[-1] - times[0]) + 1e-14 * jnp.maximum(jnp.abs(times[0]), jnp.abs(times[-1]))
    j = jnp.searchsorted(times, jnp.where(foh > 0, at - tiny, at), side="right") - 1
    j = jnp.clip(j, 0, n - 1)
    nxt = jnp.minimum(j + 1, n - 1)
    span = times[nxt] - times[j]
    # No clip of the weight inside the series: at a sampling instant it may round to just past 0 or 1,
    # and a clip would cut (or halve) its derivative there.
    weight = jnp.where(span > 0, (at - times[j]) / jnp.where(span > 0, span, 1.0), 0.0)
    weight = jnp.where(at < times[0], 0.0, weight)
    return column[j] + foh * weight * (column[nxt] - column[j])


class Delays(NamedTuple):
    """The delays of one parameter vector on one data set."""

    taus: jnp.ndarray  # (D,)
    columns: jnp.ndarray  # (N, D): the delayed inputs' own values at the sampling times
    times: jnp.ndarray  # (N,)
    foh: jnp.ndarray


def delays_at(structure, theta, times, inputs, foh) -> Delays:
    """τ of each ``delay(u, tau)`` at θ and the columns of ``inputs`` (over ``times``) they delay."""
    taus = jnp.stack([jnp.asarray(d.tau(theta), dtype=jnp.float64) for d in structure.delays])
    columns = jnp.asarray(inputs)[:, [d.input for d in structure.delays]]
    return Delays(taus, columns, jnp.asarray(times), foh)


def values_at(delays: Delays, at) -> jnp.ndarray:
    """The D delayed inputs at the instants ``at`` (shape (..., D))."""
    at = jnp.asarray(at)[..., None] - delays.taus
    return jax.vmap(lambda col, s: delayed_values(delays.times, col, s, delays.foh), in_axes=(1, -1),
                    out_axes=-1)(delays.columns, at)


def with_delayed_inputs(structure, theta, data, delays: Delays | None = None):
    """``data`` with the delayed inputs appended to ``u_prev`` and ``u_cur`` (at t_{k-1} − τ, t_k − τ).

    The model functions take these extended input vectors; a data set's own
    inputs come first, in the model's order.  ``delays``: [`delays_at()`][greyid.filters.delays.delays_at]
    of these data, where the caller has it already.
    """
    if not structure.delays:
        return data
    if delays is None:
        delays = delays_at(structure, theta, data.t, data.u_cur, data.foh)
    return data._replace(u_prev=jnp.concatenate([data.u_prev, values_at(delays, data.t_prev)], axis=1),
                         u_cur=jnp.concatenate([data.u_cur, values_at(delays, data.t)], axis=1))


class Pieces(NamedTuple):
    """The pieces of every sampling interval: leading axes (row, piece)."""

    start: jnp.ndarray
    length: jnp.ndarray
    u_start: jnp.ndarray  # extended inputs at the piece's start
    u_end: jnp.ndarray  # and at its end


def regular_offsets(taus, step):
    """Where the delayed switching instants fall inside each interval of a series sampled every ``step``."""
    return jnp.sort(taus - jnp.floor(taus / step) * step)


def interval_pieces(delays: Delays, data, n_inputs: int, offsets=None) -> Pieces:
    """Every interval [t_{k-1}, t_k] cut at the delayed switching instants t_j + τ inside it.

    ``data`` holds the extended inputs.  With ``offsets`` (regular sampling) the
    cuts are t_{k-1} + offsets; otherwise each delay has ``slots`` candidate
    cuts per interval, and those that fall outside sit at t_k, giving pieces of
    length 0 that change nothing.
    """
    n = delays.times.shape[0]
    slots = max(1, data.delay_slots.shape[0])
    t_prev, t = data.t_prev, data.t

    def cuts(tau):  # (N, slots)
        # A switch exactly at t_{k-1} (a delay of whole sampling intervals) is kept as a cut there:
        # its piece has length 0, and moves into the interval as τ grows (its derivative in τ).
        first = jnp.searchsorted(delays.times, t_prev - tau, side="left")
        j = first[:, None] + jnp.arange(slots)[None, :]
        at = delays.times[jnp.minimum(j, n - 1)] + tau
        return jnp.where((j < n) & (at >= t_prev[:, None]) & (at < t[:, None]), at, t[:, None])

    if offsets is None:
        inner = jnp.sort(jnp.concatenate([cuts(tau) for tau in delays.taus], axis=1), axis=1)
    else:
        # offsets lie in [0, step): a where, not a clip, so that a cut exactly at t_{k-1} (a delay of
        # whole sampling intervals) keeps its derivative ∂cut/∂τ = 1 (a clip would halve it there).
        at = t_prev[:, None] + offsets[None, :]
        inner = jnp.where(at <= t[:, None], at, t[:, None])
    bounds = jnp.concatenate([t_prev[:, None], inner, t[:, None]], axis=1)
    start, end = bounds[:, :-1], bounds[:, 1:]
    dt = (t - t_prev)[:, None]
    fraction = jnp.where(dt > 0, (start - t_prev[:, None]) / jnp.where(dt > 0, dt, 1.0), 0.0)
    fraction_end = jnp.where(dt > 0, (end - t_prev[:, None]) / jnp.where(dt > 0, dt, 1.0), 0.0)
    own_prev, own_cur = data.u_prev[:, None, :n_inputs], data.u_cur[:, None, :n_inputs]
    ramp = delays.foh * (own_cur - own_prev)
    # Constant on each piece (zero-order hold): the value at its midpoint; on a piece of length 0 the
    # value just before its end — the piece that grows with τ, whose derivative carries the value
    # before the switch (at the midpoint, a switching instant itself, it would read the value after).
    tiny = 1e-9 * jnp.maximum(dt, 1e-300)
    inside = jnp.where(end - start > tiny, 0.5 * (start + end), end - tiny)
    held = values_at(delays, inside)
    delayed_start = jnp.where(delays.foh > 0, values_at(delays, start), held)
    delayed_end = jnp.where(delays.foh > 0, values_at(delays, end), held)
    return Pieces(start, end - start,
                  jnp.concatenate([own_prev + ramp * fraction[..., None], delayed_start], axis=2),
                  jnp.concatenate([own_prev + ramp * fraction_end[..., None], delayed_end], axis=2))


def step_pieces(delays: Delays, data, start, length, u_start, u_end, n_inputs: int) -> Pieces:
    """Any grid's steps [start, start + length] cut where the delayed inputs switch, as
    [`interval_pieces()`][greyid.filters.delays.interval_pieces] cuts the sampling intervals (a step no longer
    than the series' widest interval holds no more switching instants than an interval does).  ``u_start`` and
    ``u_end`` are the extended inputs at the steps' ends; leading axis the steps."""
    steps = _Steps(start, start + length, u_start, u_end, data.delay_slots)
    return interval_pieces(delays, steps, n_inputs)


class _Steps(NamedTuple):
    t_prev: jnp.ndarray
    t: jnp.ndarray
    u_prev: jnp.ndarray
    u_cur: jnp.ndarray
    delay_slots: jnp.ndarray


def piece_drift(f, x, pieces: Pieces, foh):
    """Σ_p f(x, u_p, s_p) ℓ_p / Σ_p ℓ_p: the drift of an Euler step at x with the inputs of each of the step's
    pieces (u_p held, or at the piece's middle with a first-order hold), weighted by its length — smooth in
    the delays, which move the pieces' ends."""
    u = pieces.u_start + 0.5 * foh * (pieces.u_end - pieces.u_start)
    values = jax.vmap(lambda ui, si: f(x, ui, si))(u, pieces.start)
    total = jnp.sum(pieces.length)
    return jnp.sum(values * pieces.length[:, None], axis=0) / jnp.where(total > 0, total, 1.0)


def check_delays(structure, theta, times: np.ndarray) -> None:
    """Named errors for a negative delay or one longer than the series."""
    if not structure.delays:
        return
    span = float(times[-1] - times[0]) if len(times) else 0.0
    for d in structure.delays:
        tau = float(d.tau(jnp.asarray(theta)))
        if not np.isfinite(tau) or tau < 0:
            raise ModelError(f"the delay of '{d.name}' is {tau} at the given parameters; "
                             "a delay looks back in time, so it must be ≥ 0")
        if tau > span:
            raise DataError(f"the delay of '{d.name}' is {tau:g}, longer than the series ({span:g} from first "
                            "to last time): the delayed input would never leave its first value")
