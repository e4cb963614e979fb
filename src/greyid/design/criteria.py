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
  Gauss' formula (6.35), J M⁻¹ Jᵀ with J = ∂f/∂θ, e.g. the model's UA;
* ``prior``: any of these of the posterior information M + Σ_prior⁻¹ (6.53).

[`average_criterion()`][greyid.design.criteria.average_criterion] and
[`minimax_criterion()`][greyid.design.criteria.minimax_criterion] take the criterion over
a prior distribution of θ (J₃, 6.36–6.38) or its worst case over a box (6.39).
"""

from __future__ import annotations

from itertools import product

import numpy as np
import pandas as pd

from ..errors import ModelError, UndefinedCriterionWarning, UndeterminedWarning, warn
from ..scaled import ScaledInformation

CRITERIA = ("D", "A", "C", "E", "L", "Ds")


def _matrix(info) -> tuple[np.ndarray, list[str]]:
    if isinstance(info, pd.DataFrame):
        return info.to_numpy(dtype=np.float64), list(info.index)
    M = np.asarray(info, dtype=np.float64)
    return M, [f"p{i}" for i in range(M.shape[0])]


def with_prior(info, prior) -> pd.DataFrame:
    """The posterior information M + Σ_prior⁻¹ (6.53) of a Gaussian prior on some of the parameters.

    Parameters
    ----------
    info : pandas.DataFrame
        An information matrix.
    prior : dict
        As for ``fit(criterion="map")``: ``{"mean": {...}, "sd": {...}, "corr": ...}``
        (the means do not enter); parameters without a prior get no prior information.

    Returns
    -------
    pandas.DataFrame
        The posterior information, over the same parameters.
    """
    from ..estimate.criteria import GaussianPrior

    M, names = _matrix(info)
    spec = prior if isinstance(prior, GaussianPrior) else GaussianPrior.from_spec(prior, names)
    unknown = [n for n in spec.names if n not in names]
    if unknown:
        raise ModelError(f"the prior names '{unknown[0]}', which is not in the information matrix")
    index = [names.index(n) for n in spec.names]
    out = M.copy()
    out[np.ix_(index, index)] += np.linalg.inv(spec.covariance)
    return pd.DataFrame(out, index=names, columns=names)


def _undetermined(scaled: ScaledInformation, what: str) -> float:
    """+inf, with a warning naming the direction the information does not determine."""
    warn(f"the information does not determine the direction {scaled.describe()} "
                  f"(scaled parameters): {what} is +inf", UndeterminedWarning)
    return float("inf")


def _schur_information(scaled: ScaledInformation, interest: list[str]) -> np.ndarray:
    """M_ss − M_sn M_nn⁻¹ M_ns in the user's units, computed on the unit-diagonal matrix."""
    names = scaled.names
    s = [names.index(n) for n in interest]
    rest = [i for i in range(len(names)) if i not in s]
    V, w = scaled.eigenvectors, scaled.eigenvalues
    Ms = (V * w) @ V.T
    block = Ms[np.ix_(s, s)]
    if rest:
        nuisance = ScaledInformation.of(Ms[np.ix_(rest, rest)])
        block = block - Ms[np.ix_(s, rest)] @ nuisance.covariance() @ Ms[np.ix_(rest, s)]
    return block / np.outer(scaled.scale[s], scaled.scale[s])


def criterion(info, name: str, params=None, interest=None, V=None, k: float = 1.0, derived=None,
              prior=None) -> float:
    """The value of a design criterion for an information matrix (smaller is better; 6.32–6.35).

    Ranks, inverses and determinants are taken on M scaled to unit diagonal, so
    that units alone never make M singular; a criterion of quantities that M does
    not determine is +inf, with an [`UndeterminedWarning`][greyid.errors.UndeterminedWarning]
    naming the direction.

    Parameters
    ----------
    info : pandas.DataFrame
        An information matrix.
    name : {"D", "A", "C", "E", "L", "Ds"}
        The criterion: −log det M; the mean variance; the mean variance relative to
        θ² (V = diag(1/θ)); the largest eigenvalue of M⁻¹ (of V M⁻¹ Vᵀ with ``V``);
        the ``k``-norm of V M⁻¹ Vᵀ's eigenvalues; −log det of the Schur
        complement of the parameters of ``interest``.
    params : mapping of str to float, optional
        θ, for ``"C"`` and for ``derived`` quantities.
    interest : sequence of str, optional
        The parameters of interest of ``"Ds"``.
    V : array_like, optional
        The weight matrix of ``"L"`` and ``"E"``.
    k : float
        The power of ``"L"``.
    derived : mapping of str to str, optional
        ``{name: expression}``: the criterion of these quantities' covariance
        J M⁻¹ Jᵀ instead (6.35, 7.47); for ``"C"``, V = diag(1/f(θ)).
    prior : dict, optional
        A Gaussian prior as for MAP fits: its precision is added first (the MAP criteria, 6.53).

    Returns
    -------
    float
        The criterion's value; +inf where M does not determine what it measures,
        NaN for ``"C"`` where a parameter is 0 (with an
        [`UndefinedCriterionWarning`][greyid.errors.UndefinedCriterionWarning]).

    Raises
    ------
    ModelError
        An unknown criterion, or one that lacks its argument (``interest``, ``params``, ``k``).
    """
    if name not in CRITERIA:
        raise ModelError(f"unknown criterion {name!r}; use one of {list(CRITERIA)}")
    if prior is not None:  # the MAP forms (6.53, J₂ and J₄ of 6.65)
        info = with_prior(info if isinstance(info, pd.DataFrame) else pd.DataFrame(info), prior)
    M, names = _matrix(info)
    scaled = ScaledInformation.of(M, names)
    if name == "Ds":
        if not interest:
            raise ModelError("criterion 'Ds' needs interest=[parameter names]")
        missing = [n for n in interest if n not in names]
        if missing:
            raise ModelError(f"'{missing[0]}' is not in the information matrix")
        s = [names.index(n) for n in interest]
        rows = np.eye(len(names))[s]
        if np.any(scaled.undetermined(rows)):
            return _undetermined(scaled, f"criterion Ds of {', '.join(interest)}")
        block = ScaledInformation.of(_schur_information(scaled, list(interest)), list(interest))
        return -block.logdet() if not block.singular else _undetermined(block, "criterion Ds")
    if derived is None:
        if scaled.singular:
            return _undetermined(scaled, f"criterion {name}")
        if name == "D":
            return float(-scaled.logdet())
        cov = scaled.covariance()
    else:  # quantities M may determine although it is singular (e.g. UA without Ri and Ro apart)
        J, labels, params = _derived_jacobian(names, params, derived)
        if np.any(scaled.undetermined(J)):
            return _undetermined(scaled, f"criterion {name} of {', '.join(labels)}")
        cov = J @ scaled.covariance() @ J.T
        cov, names = 0.5 * (cov + cov.T), labels
        if name == "D":  # −log det of the derived quantities' information, log det J M⁻¹ Jᵀ
            inner = ScaledInformation.of(cov, labels)  # a covariance: its log det, if it is one
            return inner.logdet() if not inner.singular else _undetermined(inner, "criterion D")
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
        zero = [n for n, value in zip(names, theta) if value == 0.0]
        if zero:  # relative variances of a parameter whose value is 0 do not exist
            warn(f"criterion C (variances relative to θ², V = diag(1/θ)) is undefined: "
                          f"{', '.join(zero)} {'is' if len(zero) == 1 else 'are'} 0", UndefinedCriterionWarning)
            return float("nan")
        Vc = np.diag(1.0 / theta)
        return float(np.trace(Vc @ cov @ Vc) / p)
    W = np.eye(p) if V is None else np.asarray(V, dtype=np.float64)
    if not k > 0:
        raise ModelError(f"criterion 'L' needs a power k > 0, got {k!r}")
    eig = np.linalg.eigvalsh(0.5 * (W @ cov @ W.T + (W @ cov @ W.T).T))
    return float((np.sum(np.maximum(eig, 0.0) ** k) / p) ** (1.0 / k))


def _derived_jacobian(names, params, derived):
    """J = ∂f/∂θ of the quantities ``derived`` (6.35) by SymPy, their labels and values."""
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
    return np.array(rows), list(derived), values


def cramer_rao_bound(info, params=None, derived=None) -> pd.Series:
    """The Cramér–Rao bound: the least variance of an unbiased estimate (6.30, 6.35).

    M is inverted scaled to unit diagonal, so the bounds convert between unit
    systems by the units' factors.  An infinite bound marks a parameter or
    quantity along a direction the experiment does not determine (see
    [`local_identifiability()`][greyid.design.information.local_identifiability]);
    the others keep their finite bounds.

    Parameters
    ----------
    info : pandas.DataFrame
        An information matrix.
    params : mapping of str to float, optional
        The parameters' values, needed for ``derived`` quantities.
    derived : mapping of str to str, optional
        ``{name: expression in the parameters}``: their bounds J M⁻¹ Jᵀ by Gauss' formula.

    Returns
    -------
    pandas.Series
        The bound of each parameter (the diagonal of M⁻¹) and of each derived quantity.
    """
    M, names = _matrix(info)
    scaled = ScaledInformation.of(M, names)
    out = pd.Series(scaled.variances(), index=names, name="variance bound")
    if derived:
        J, labels, _ = _derived_jacobian(names, params, derived)
        out = pd.concat([out, pd.Series(scaled.variances(J), index=labels)]).rename("variance bound")
    if scaled.singular:
        warn(f"the information does not determine the direction {scaled.describe()} (scaled "
                      "parameters): the bounds along it are +inf", UndeterminedWarning)
    return out


def parameter_points(model, params, prior=None, minimax=None, draws: int = 20, seed: int = 0,
                     levels: int = 2) -> tuple[list[dict], np.ndarray]:
    """The parameter values θ_j a Bayesian or minimax design looks at, and their weights π_j.

    ``prior``: a Gaussian ``{"mean", "sd", "corr"}`` on some parameters (``draws``
    seeded draws, equal weights) or a DataFrame of points, one row each, with an
    optional ``weight`` column (a quadrature rule).  ``minimax``: a box
    ``{name: (low, high)}`` gridded with ``levels`` values per parameter (the
    corners for 2).  Parameters not named take their values in ``params``.
    """
    names = list(model.structure.parameter_names)
    base = dict(params)
    if prior is not None and minimax is not None:
        raise ModelError("give prior= (a Bayesian design) or minimax= (a worst-case design), not both")
    given = prior if isinstance(prior, pd.DataFrame) else minimax if isinstance(minimax, pd.DataFrame) else None
    if given is not None:
        what = "prior's" if given is prior else "minimax"
        columns = [c for c in given.columns if c != "weight"]
        unknown = [c for c in columns if c not in names]
        if unknown:
            raise ModelError(f"the {what} points name '{unknown[0]}', which is not a parameter of model "
                             f"'{model.name}'")
        if len(given) == 0:
            raise ModelError(f"the {what} points are empty")
        weights = (given["weight"].to_numpy(dtype=np.float64) if "weight" in given and given is prior
                   else np.full(len(given), 1.0 / len(given)))
        if np.any(~(weights >= 0)) or not np.isclose(weights.sum(), 1.0):
            raise ModelError("the prior's 'weight' column must be non-negative and sum to 1")
        points = [dict(base, **{c: float(row[c]) for c in columns}) for _, row in given.iterrows()]
        return points, weights
    if prior is not None:
        from ..estimate.criteria import GaussianPrior

        spec = GaussianPrior.from_spec(prior, names)
        if draws < 1:
            raise ModelError(f"draws must be at least 1, got {draws!r}")
        sample = np.random.default_rng(seed).multivariate_normal(spec.mean, spec.covariance, size=draws)
        return [dict(base, **dict(zip(spec.names, row))) for row in sample], np.full(draws, 1.0 / draws)
    if minimax is not None:
        unknown = [n for n in minimax if n not in names]
        if unknown:
            raise ModelError(f"the box names '{unknown[0]}', which is not a parameter of model '{model.name}'")
        if levels < 2:
            raise ModelError(f"levels must be at least 2, got {levels!r}")
        for name, bounds in minimax.items():
            low, high = (float(b) for b in bounds)
            if not low <= high:
                raise ModelError(f"the box of '{name}' must be (low, high) with low ≤ high, got {bounds!r}")
        grids = [np.linspace(float(lo), float(hi), levels) for lo, hi in minimax.values()]
        points = [dict(base, **dict(zip(minimax, corner))) for corner in product(*grids)]
        return points, np.full(len(points), 1.0 / len(points))
    return [base], np.ones(1)


def average_criterion(model, plan, name: str, prior, draws: int = 20, seed: int = 0, map_prior: bool = False,
                      params=None, **options) -> dict:
    """The criterion averaged over a prior of θ: the Bayesian criterion J₃ (6.36–6.38).

    Parameters
    ----------
    model : Model
        The model.
    plan : pandas.DataFrame
        The planned experiment's times and inputs.
    name : str
        The criterion (as [`criterion()`][greyid.design.criteria.criterion]).
    prior : dict or pandas.DataFrame
        A Gaussian prior ``{"mean": ..., "sd": ..., "corr": ...}`` on some
        parameters (``draws`` seeded draws), or a DataFrame of points (a quadrature
        rule, with an optional ``weight`` column).
    draws : int
        Draws from a Gaussian prior.
    seed : int
        Their random seed.
    map_prior : bool
        Each draw's information includes the prior's precision (J₄).
    params : mapping of str to float, optional
        The values of the parameters without a prior (default: their initial values).
    **options
        For [`criterion()`][greyid.design.criteria.criterion] (``interest``,
        ``derived``, ...) and [`fisher_information()`][greyid.design.information.fisher_information]
        (``time``, ``hold``, ``free``, ``method``, ...).

    Returns
    -------
    dict
        ``{"value", "standard_error", "values"}``: the average, its Monte Carlo
        standard error and the value at each point.
    """
    from ..estimate.criteria import GaussianPrior
    from .information import fisher_information

    criterion_keys = ("interest", "V", "k", "derived")
    crit = {k: options.pop(k) for k in criterion_keys if k in options}
    base = dict(model.initial_values() if params is None else params)
    spec = GaussianPrior.from_spec(prior, list(model.structure.parameter_names)) if map_prior else None
    points, weights = parameter_points(model, base, prior=prior, draws=draws, seed=seed)
    values = np.asarray([criterion(fisher_information(model, point, plan, **options), name, params=point,
                                   prior=spec, **crit) for point in points])
    drawn = not isinstance(prior, pd.DataFrame)  # seeded draws have a Monte Carlo error, quadrature none
    error = float(values.std(ddof=1) / np.sqrt(len(values))) if drawn and len(values) > 1 else 0.0
    return {"value": float(weights @ values), "standard_error": error, "values": values}


def minimax_criterion(model, plan, name: str, box, levels: int = 2, params=None, **options) -> dict:
    """The worst value of the criterion over a box of parameter values (6.39).

    Parameters
    ----------
    model : Model
        The model.
    plan : pandas.DataFrame
        The planned experiment's times and inputs.
    name : str
        The criterion.
    box : mapping of str to tuple
        ``{parameter: (low, high)}``.
    levels : int
        Grid values per parameter (2: the corners).
    params : mapping of str to float, optional
        The values of the parameters outside the box (default: their initial values).
    **options
        As for [`average_criterion()`][greyid.design.criteria.average_criterion].

    Returns
    -------
    dict
        ``{"value", "at"}``: the worst value and the point where it is.
    """
    from .information import fisher_information

    criterion_keys = ("interest", "V", "k", "derived", "prior")
    crit = {k: options.pop(k) for k in criterion_keys if k in options}
    base = dict(model.initial_values() if params is None else params)
    worst, at = -np.inf, None
    for point in parameter_points(model, base, minimax=box, levels=levels)[0]:
        value = criterion(fisher_information(model, point, plan, **options), name, params=point, **crit)
        if value > worst:
            worst, at = value, point
    return {"value": float(worst), "at": {n: at[n] for n in box}}
