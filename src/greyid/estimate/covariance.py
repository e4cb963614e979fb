"""Covariance of the estimates: from the Hessian, the scores, or both (section 3.3.2).

* ``"hessian"``: H⁻¹, with H the Hessian of the negative log-posterior at the
  optimum.  Right when the criterion is the model's log-likelihood (or log
  posterior) and the model holds: the default for ML and MAP.
* ``"opg"``: J⁻¹, with J = Σ_k s_k s_kᵀ the outer product of the per-step
  scores s_k (Berndt, Hall, Hall & Hausman).
* ``"sandwich"``: H⁻¹ J H⁻¹ (Huber; Godambe), right for any M-estimator — the
  k-step criterion of section 7.2 and the robust criteria (3.57–3.58), whose
  H⁻¹ is not a covariance because they are not likelihoods — and robust to a
  misspecified likelihood.  The default for k-step and robust fits.

A k-step criterion's terms at steps less than k apart share innovations, so
their scores are correlated and J sums their cross products up to lag k − 1
(Hansen & Hodrick, 1980); should that sum not be positive semi-definite,
Newey–West's Bartlett weights are used instead, which always give a positive
semi-definite J.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import ModelError
from ..scaled import scaled_inverse

COV_TYPES = ("hessian", "opg", "sandwich")


def default_cov_type(robust, horizon: int) -> str:
    """The sandwich for criteria that are not log-likelihoods, the Hessian otherwise."""
    return "sandwich" if robust or horizon > 1 else "hessian"


def check_cov_type(cov_type) -> str:
    if cov_type not in COV_TYPES:
        raise ModelError(f"cov_type must be one of {list(COV_TYPES)}, got {cov_type!r}")
    return cov_type


def _lagged_sum(scores: np.ndarray, lags: int, weights) -> np.ndarray:
    J = scores.T @ scores
    for j in range(1, lags + 1):
        cross = scores[j:].T @ scores[:-j]
        J = J + weights(j) * (cross + cross.T)
    return J


class ScoreCovariance(NamedTuple):
    """J and, per parameter, the effective number of steps its scores rest on."""

    matrix: np.ndarray
    effective_steps: np.ndarray


#: Below this effective number of steps a score-based standard error is flagged.
FEW_STEPS = 10


def score_covariance(scores: list[np.ndarray], horizon: int = 1) -> ScoreCovariance:
    """J = Σ over data sets of Σ_{|j|<horizon} Σ_k s_k s_{k+j}ᵀ (each ``scores`` array: steps × parameters).

    The effective number of steps of parameter i, (Σ_k s_ki²)² / Σ_k s_ki⁴, says
    how many observations its J_ii averages over: an initial state's scores sit
    on the first few steps, and a variance estimated from a handful of squares is
    itself unreliable.
    """
    lags = max(int(horizon) - 1, 0)
    J = sum(_lagged_sum(s, lags, lambda j: 1.0) for s in scores)
    if lags and np.min(np.linalg.eigvalsh(0.5 * (J + J.T))) < -1e-10 * max(np.abs(J).max(), 1e-300):
        J = sum(_lagged_sum(s, lags, lambda j: 1.0 - j / (lags + 1.0)) for s in scores)
    squares = np.concatenate([s**2 for s in scores])
    with np.errstate(divide="ignore", invalid="ignore"):
        effective = np.sum(squares, axis=0) ** 2 / np.sum(squares**2, axis=0)
    return ScoreCovariance(0.5 * (J + J.T), np.nan_to_num(effective))


def parameter_covariance(H: np.ndarray, J: np.ndarray | None, cov_type: str, singular: bool) -> np.ndarray:
    """The covariance of the estimates from H (and J); pseudo-inverses where H is ``singular``.

    Inverses are taken scaled to unit diagonal ([`greyid.scaled.scaled_inverse()`][greyid.scaled.scaled_inverse]):
    capacities
    in J/K beside resistances in K/W give H a condition number of 1e20 from the units alone.
    """
    if cov_type == "hessian":
        cov = scaled_inverse(H, singular)
    elif cov_type == "opg":
        cov = scaled_inverse(J, True)
    else:
        H_inv = scaled_inverse(H, singular)
        cov = H_inv @ J @ H_inv
    return 0.5 * (cov + cov.T)
