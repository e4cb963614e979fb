"""Optimality criteria of an information matrix M (6.32)–(6.35), each to be minimised.

* ``"D"``: −log det M (6.33, κ = −1);
* ``"A"``: tr(M⁻¹)/p and ``"C"``: tr(V M⁻¹ V)/p with V = diag(1/θ) (6.32, k = 1):
  the mean variance, and the mean of 1/t² (scale-free);
* ``"E"``: λ_max(M⁻¹) (6.34), or λ_max(V M⁻¹ Vᵀ) with a scaling V;
* ``"L"``: [tr((V M⁻¹ Vᵀ)^k)/p]^{1/k} for a user matrix V and power k (Kiefer's
  family (6.32); k = 1 gives A and C, k → ∞ E);
* ``"Ds"``: −log det of the information on the parameters of ``interest`` with
  the others as nuisance, M_ss − M_sn M_nn⁻¹ M_ns;
* ``derived``: any of these applied to the covariance of derived quantities by
  Gauss' formula (6.35), J M⁻¹ Jᵀ with J = ∂f/∂θ, e.g. the model's UA.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import ModelError

CRITERIA = ("D", "A", "C", "E", "L", "Ds")


def _matrix(info) -> tuple[np.ndarray, list[str]]:
    if isinstance(info, pd.DataFrame):
        return info.to_numpy(dtype=np.float64), list(info.index)
    M = np.asarray(info, dtype=np.float64)
    return M, [f"p{i}" for i in range(M.shape[0])]


def criterion(info, name: str, params=None, interest=None, V=None, k: float = 1.0, derived=None) -> float:
    """The value of criterion ``name`` for the information ``info`` (smaller is better).

    ``params`` (a mapping) gives θ for ``"C"``; ``interest`` names the parameters
    of ``"Ds"``; ``V`` and ``k`` define ``"L"`` (``V`` also scales ``"E"``).  ``derived`` — a mapping of
    names to expressions, with ``params`` — replaces M⁻¹ by the covariance of
    those quantities (6.35, 7.47) for ``"D"`` (log det J M⁻¹ Jᵀ), ``"A"``, ``"C"``
    (V = diag(1/f(θ))), ``"E"`` and ``"L"``.  A singular M gives +inf (6.32).
    """
    if name not in CRITERIA:
        raise ModelError(f"unknown criterion {name!r}; use one of {list(CRITERIA)}")
    M, names = _matrix(info)
    M = 0.5 * (M + M.T)
    if name == "Ds":
        if not interest:
            raise ModelError("criterion 'Ds' needs interest=[parameter names]")
        missing = [n for n in interest if n not in names]
        if missing:
            raise ModelError(f"'{missing[0]}' is not in the information matrix")
        s = [names.index(n) for n in interest]
        rest = [i for i in range(len(names)) if i not in s]
        block = M[np.ix_(s, s)]
        if rest:
            block = block - M[np.ix_(s, rest)] @ np.linalg.pinv(M[np.ix_(rest, rest)]) @ M[np.ix_(rest, s)]
        sign, logdet = np.linalg.slogdet(block)
        return float(-logdet) if sign > 0 else float("inf")
    sign, logdet = np.linalg.slogdet(M)
    if sign <= 0 or not np.isfinite(logdet):
        return float("inf")
    if name == "D" and derived is None:
        return float(-logdet)
    cov = np.linalg.inv(M)
    if derived is not None:
        cov, names, params = _derived_covariance(cov, names, params, derived, with_values=True)
        if name == "D":  # −log det of the derived quantities' information, log det J M⁻¹ Jᵀ
            sign, logdet = np.linalg.slogdet(0.5 * (cov + cov.T))
            return float(logdet) if sign > 0 else float("inf")
    p = cov.shape[0]
    if name == "A":
        return float(np.trace(cov) / p)
    if name == "E":
        if V is not None:  # of a scaled covariance, V M⁻¹ Vᵀ (e.g. relative: V = diag(1/θ))
            W = np.asarray(V, dtype=np.float64)
            cov = W @ cov @ W.T
        return float(np.linalg.eigvalsh(0.5 * (cov + cov.T)).max())
    if name == "C":
        if params is None:
            raise ModelError("criterion 'C' needs params (V = diag(1/θ))")
        theta = np.array([float(params[n]) for n in names])
        Vc = np.diag(1.0 / theta)
        return float(np.trace(Vc @ cov @ Vc) / p)
    W = np.eye(p) if V is None else np.asarray(V, dtype=np.float64)
    if not k > 0:
        raise ModelError(f"criterion 'L' needs a power k > 0, got {k!r}")
    eig = np.linalg.eigvalsh(0.5 * (W @ cov @ W.T + (W @ cov @ W.T).T))
    return float((np.sum(np.maximum(eig, 0.0) ** k) / p) ** (1.0 / k))


def _derived_covariance(cov, names, params, derived, with_values: bool = False):
    """J M⁻¹ Jᵀ for the quantities ``derived`` (6.35), J by SymPy differentiation; with
    ``with_values``, also the quantities' names and values (for ``"C"``)."""
    import sympy as sp

    from ..model.equations import parse_expression

    if params is None:
        raise ModelError("derived quantities need params (the point at which to differentiate)")
    symbols = [parse_expression(n, "parameter") for n in names]
    at = {s: float(params[n]) for s, n in zip(symbols, names)}
    rows, values = [], {}
    for label, text in derived.items():
        expr = parse_expression(text, f"derived quantity '{label}'")
        extra = {s.name for s in expr.free_symbols} - set(names)
        if extra:
            raise ModelError(f"derived quantity '{label}' uses '{sorted(extra)[0]}', which is not in the matrix")
        rows.append([float(sp.diff(expr, s).subs(at)) for s in symbols])
        values[label] = float(expr.subs(at))
    J = np.array(rows)
    if with_values:
        return J @ cov @ J.T, list(derived), values
    return J @ cov @ J.T


def cramer_rao_bound(info, params=None, derived=None) -> pd.Series:
    """The Cramér–Rao bound: the least variance of an unbiased estimate of each parameter (the
    diagonal of M⁻¹, 6.30) and of each ``derived`` quantity (J M⁻¹ Jᵀ by Gauss' formula, 6.35).

    An infinite bound marks a parameter the experiment does not determine
    (a singular M, see :func:`~.information.local_identifiability`).
    """
    M, names = _matrix(info)
    w = np.linalg.eigvalsh(0.5 * (M + M.T))
    if w.min() <= 1e-12 * max(w.max(), 1e-300):
        values = np.full(len(names), np.inf)
        out = pd.Series(values, index=names, name="variance bound")
        if derived:
            out = pd.concat([out, pd.Series(np.inf, index=list(derived), name="variance bound")])
        return out
    cov = np.linalg.inv(M)
    out = pd.Series(np.diag(cov), index=names, name="variance bound")
    if derived:
        extra = pd.Series(np.diag(_derived_covariance(cov, names, params, derived)), index=list(derived),
                          name="variance bound")
        out = pd.concat([out, extra]).rename("variance bound")
    return out
