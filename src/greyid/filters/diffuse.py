"""The exact diffuse initialisation of the Kalman filter (Koopman & Durbin 2000; Durbin & Koopman 2012, §5.2).

States declared diffuse start as x0 = a + δ with δ ~ N(0, κ I) and κ → ∞: the initial covariance
is P = κ P∞ + P*, P∞ = I on the diffuse states, P* the given covariance of the others (zero on the
diffuse ones).  Over the first rows the filter carries both parts and treats the outputs one at a
time (the univariate form).  For output i with row c and noise variance s,

    F∞ = c P∞ cᵀ,  F* = c P* cᵀ + s,  M∞ = P∞ cᵀ,  M* = P* cᵀ,

and where F∞ > 0 (the observation says something about a diffuse direction)

    x ← x + M∞ v / F∞,   P∞ ← P∞ − M∞ M∞ᵀ / F∞,   P* ← (I − K c) P* (I − K c)ᵀ + s K Kᵀ,  K = M∞ / F∞,

with the term −½(log 2π + log F∞) of the log-likelihood; otherwise the ordinary update with F*.
The prediction takes P∞ ← Φ P∞ Φᵀ (no noise) beside the ordinary P* ← Φ P* Φᵀ + Λ.  Once P∞ is
zero the filter is the ordinary one started from P*: the driver runs these steps over the first
rows of a series only (the diffuse period, [`head_rows()`][greyid.filters.diffuse.head_rows]), then its
ordinary scan (``filters.driver``), so after the diffuse period nothing is added.

The log-likelihood's convention is statsmodels' (``use_exact_diffuse``) and Durbin & Koopman's
(7.2.5): the diffuse observations keep the constant −½ log 2π, which KFAS leaves out.  P∞ = I in
the states' own units, so a change of a diffuse state's unit shifts the log-likelihood by a constant
(estimates do not change).  The P* part keeps the options' form (in the square-root form the
factor of the Joseph form above, a sum of positive semi-definite terms, refactorised).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..model.structure import Structure
from . import small
from .predictors import linearized_observation
from .protocol import FilterInputs, Row
from .updates import (SQRT, GaussianState, StepTerms, Update, mask_observation, observed_root, symmetrize,
                      whiten)

#: F∞ counts as positive above this fraction of |c|² times the largest diagonal element P∞ has had
#: (P∞ starts as the identity on the diffuse states): rounding leaves P∞ at about 1e-16 of that.
TOLERANCE = 1e-9


class DiffuseStart(NamedTuple):
    """A filter's diffuse start: the rows of the diffuse period, P∞ at t₀ and the update of one row."""

    rows: int  # static: the first rows the driver filters with both parts
    infinite: jnp.ndarray  # P∞ at t₀
    #: ``update(state, infinite, scale, row) -> (Update, ŷ, P∞ after, loaded)``: ``loaded`` flags the outputs
    #: whose prediction has an infinite variance (their innovations are not reported).
    update: Callable


def head_rows(mask: np.ndarray, n_rows: int, seen_by: tuple[tuple[int, ...], ...]) -> int:
    """The rows of the diffuse period: for each diffuse state, up to the row holding the d-th row where an
    output that sees it is observed (d the number of diffuse states); the last of these.

    That many observations determine the diffuse states in the generic case; a model whose outputs
    determine them later (at these parameter values) leaves P∞ non-zero at the end of these rows, which
    [`scan_head()`][greyid.filters.diffuse.scan_head] marks and the filter's checks name.  ``seen_by`` holds, per
    diffuse state, the outputs that depend on it (``()``: every output).

    Raises
    ------
    DataError
        A diffuse state's outputs are observed in fewer rows than there are diffuse states.
    """
    d = len(seen_by)
    mask = np.asarray(mask)[:n_rows]
    rows = 0
    for outputs in seen_by:
        observed = np.flatnonzero(mask[:, list(outputs)].any(axis=1) if outputs else mask.any(axis=1))
        if len(observed) < d:
            raise DataError(f"the data have {len(observed)} observed rows of the outputs that see the diffuse initial "
                            f"states, fewer than the model's {d} diffuse states: their initial values cannot be "
                            "determined; give them a mean and a covariance instead")
        rows = max(rows, int(observed[d - 1]) + 1)
    return rows


def diffuse_update(mean, cov, infinite, scale, y, mask, y_pred, C, S, form: str):
    """Koopman and Durbin's univariate update of (x, P*, P∞) with independent output noise S (a vector).

    Returns ``(Update, P∞ after)``; the Update's terms hold −½(log 2π + log F∞) for a diffuse
    observation (its whitened innovation 0), its innovation covariance C P* Cᵀ + S.
    """
    innovation, C, S = mask_observation(y, y_pred, C, S, mask)
    s, n = C.shape
    x, P, infinite_now = mean, cov, infinite
    whitened, logdet = [], jnp.zeros(())
    for i in range(s):
        c = C[i]
        m_inf = small.mm(infinite_now, c)
        f_inf = jnp.sum(c * m_inf)
        if form == SQRT:
            f = small.mm(P.T, c)
            m_star = small.mm(P, f)
            f_star = jnp.sum(f * f) + S[i]
        else:
            m_star = small.mm(P, c)
            f_star = jnp.sum(c * m_star) + S[i]
        e = innovation[i] - jnp.sum(c * (x - mean))
        is_diffuse = f_inf > TOLERANCE * jnp.sum(c * c) * scale
        f_inf = jnp.where(is_diffuse, f_inf, 1.0)  # a safe divisor where the branch is not taken
        gain = m_inf / f_inf
        # (I − K c) P* (I − K c)ᵀ + s K Kᵀ: the Joseph form, with the diffuse gain.
        joseph = jnp.eye(n) - jnp.outer(gain, c)
        if form == SQRT:
            factor = small.mm(joseph, P)
            P_diffuse = small.cholesky(symmetrize(small.mm(factor, factor.T) + S[i] * jnp.outer(gain, gain)))
            # Potter's update, as linear_update's.
            P_ordinary = P - jnp.outer(m_star, f) / (f_star + jnp.sqrt(f_star * S[i]))
        else:
            P_diffuse = symmetrize(small.mm(small.mm(joseph, P), joseph.T) + S[i] * jnp.outer(gain, gain))
            k = m_star / f_star
            plain = jnp.eye(n) - jnp.outer(k, c)
            P_ordinary = symmetrize(small.mm(small.mm(plain, P), plain.T) + S[i] * jnp.outer(k, k))
        x = jnp.where(is_diffuse, x + gain * e, x + m_star * (e / f_star))
        P = jnp.where(is_diffuse, P_diffuse, P_ordinary)
        infinite_now = jnp.where(is_diffuse, symmetrize(infinite_now - jnp.outer(m_inf, m_inf) / f_inf),
                                 infinite_now)
        whitened.append(jnp.where(is_diffuse, 0.0, e / jnp.sqrt(f_star)))
        logdet = logdet + jnp.log(jnp.where(is_diffuse, f_inf, f_star))
    full = cov @ cov.T if form == SQRT else cov
    R = symmetrize(C @ full @ C.T + jnp.diag(S))
    return Update(x, P, innovation, R, StepTerms(jnp.stack(whitened), logdet, jnp.sum(mask))), infinite_now


def loaded_outputs(C, infinite, mask, scale):
    """The observed outputs whose prediction has an infinite variance (c P∞ cᵀ > 0)."""
    C = C * mask[:, None]
    f_inf = jnp.einsum("ij,jk,ik->i", C, infinite, C)
    return (f_inf > TOLERANCE * jnp.sum(C * C, axis=1) * scale) & (mask > 0)


def prepare_start(structure: Structure, theta, data: FilterInputs, form: str, tie) -> DiffuseStart | None:
    """The diffuse start of a linear model's Kalman filter (None without diffuse states).

    ``tie`` is [`carried_from_start()`][greyid.filters.gaussian.carried_from_start] at θ.
    """
    diffuse = structure.initial_covariance.diffuse
    if not diffuse:
        return None
    n = structure.n_states
    index = np.asarray(diffuse)
    infinite = np.zeros((n, n))
    infinite[index, index] = 1.0
    (infinite,) = tie(theta, jnp.asarray(infinite))
    h, full = structure.observation, structure.observation_covariance

    def update(state: GaussianState, infinite, scale, row: Row):
        u, t = row.u_cur, row.t
        y_pred, C = linearized_observation(h, state.mean, u, t, theta)
        loaded = loaded_outputs(C, infinite, row.mask, scale)
        if full is None:
            S = structure.observation_variance(state.mean, u, t, theta)
            upd, infinite = diffuse_update(*state, infinite, scale, row.y, row.mask, y_pred, C, S, form)
            return upd, y_pred, infinite, loaded
        # Correlated noise: the observed outputs decorrelated by the Cholesky factor L of their noise
        # covariance (as updates.correlated_update), log det R gaining 2 log det L.
        m = row.mask
        L = observed_root(full(state.mean, u, t, theta), m)
        white, infinite = diffuse_update(*state, infinite, scale, whiten(L, m, row.y), m, whiten(L, m, y_pred),
                                         small.solve_lower(L, C * m[:, None]), jnp.ones_like(row.y), form)
        terms = white.terms._replace(logdet=white.terms.logdet + 2.0 * jnp.sum(jnp.log(jnp.diag(L))))
        R = symmetrize(small.mm(small.mm(L, white.innovation_covariance), L.T))
        upd = Update(white.mean, white.covariance, jnp.where(m > 0, row.y - y_pred, 0.0), R, terms)
        return upd, y_pred, infinite, loaded

    return DiffuseStart(data.diffuse_rows.shape[0], infinite, update)


def scan_head(start: DiffuseStart, initial, predict: Callable, rows: Row, collect: Callable | None,
              accumulate: Callable | None):
    """Filter the diffuse period's rows with both parts of the covariance.

    ``collect(predicted, transition, update, ŷ, P∞ predicted, P∞ filtered, loaded, scale)`` picks what each
    row returns, or ``accumulate(StepTerms)`` sums the criterion.  Returns ``(state, total, collected)``: the
    state after the last row, NaN where P∞ is not zero there (the outputs did not determine every diffuse
    state in these rows).
    """
    def step(carry, row):
        state, infinite, scale, total = carry
        predicted, transition = predict(state, row)
        infinite = symmetrize(small.mm(small.mm(transition, infinite), transition.T))
        scale = jax.lax.stop_gradient(jnp.maximum(scale, jnp.max(jnp.diag(infinite))))
        upd, y_pred, infinite_after, loaded = start.update(predicted, infinite, scale, row)
        if accumulate is not None:
            return (upd.state, infinite_after, scale, total + accumulate(upd.terms)), None
        out = collect(predicted, transition, upd, y_pred, infinite, infinite_after, loaded, scale)
        return (upd.state, infinite_after, scale, total), out

    begin = (initial, start.infinite, jnp.ones(()), jnp.zeros(()))
    (state, infinite, scale, total), collected = jax.lax.scan(step, begin, rows, length=start.rows)
    ended = jnp.max(jnp.abs(infinite)) <= TOLERANCE * scale
    state = jax.tree_util.tree_map(lambda a: jnp.where(ended, a, jnp.nan), state)
    return state, jnp.where(ended, total, jnp.nan), collected


def infinite_part(infinite, scale):
    """+∞ where P∞ is not zero, 0 elsewhere: what the reported covariances add during the diffuse period."""
    return jnp.where(jnp.abs(infinite) > TOLERANCE * scale, jnp.inf, 0.0)
