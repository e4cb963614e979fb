"""Tests of model structure (section 5.1) and cross-validation (5.4).

* likelihood ratio of nested fits (5.2–5.3);
* Wald test of restrictions R(θ) = 0 at the unrestricted fit (5.4–5.5);
* Lagrange-multiplier (score) test at the restricted fit (5.6), the same
  statistic on simulated data to test the filter's approximations (5.1.1),
  and on a second data set for cross-validation (5.4);
* AIC, BIC and FPE (5.7–5.9) in a table comparing fits.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable, Sequence

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from scipy import stats

from ..errors import ModelError
from ..estimate.calls import simulate_at
from ..estimate.information import loglik_derivatives
from ..estimate.results import parameter_expression
from ..estimate.settings import filter_settings
from ..model.equations import parse_expression
from ..model.structure import lambdify_parameters
from .series import TestResult


def _require_ml(fit, test: str) -> None:
    s = fit.settings
    if s["criterion"] != "ml" or s.get("robust") or s.get("horizon", 1) != 1:
        raise ModelError(f"the {test} needs maximum-likelihood fits (criterion 'ml', Gaussian, one-step); "
                         f"the fit of '{fit.model.name}' used another criterion")


def lr_test(small, big, df: int | None = None) -> TestResult:
    """The likelihood-ratio test of nested fits on the same data (5.3): LR = −2 log(L̂₀/L̂₁) ~ χ²(r).

    Parameters
    ----------
    small : FitResult
        The restricted model's fit.
    big : FitResult
        The larger model's fit.
    df : int, optional
        r (default: the difference in free parameters).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    _require_ml(small, "likelihood-ratio test")
    _require_ml(big, "likelihood-ratio test")
    if small.n_obs != big.n_obs:
        raise ModelError(f"the fits have {small.n_obs} and {big.n_obs} observations; "
                         "a likelihood-ratio test needs both fitted to the same data")
    r = big.n_params - small.n_params if df is None else int(df)
    if r < 1:
        raise ModelError(f"the larger model must have more free parameters ({big.n_params} vs {small.n_params}); "
                         "pass the restricted fit first, or give df")
    stat = 2.0 * (big.loglik - small.loglik)
    if stat < -1e-6 * max(1.0, abs(big.loglik)):
        raise ModelError(f"the larger model's log-likelihood ({big.loglik:.6g}) is below the smaller model's "
                         f"({small.loglik:.6g}): the models are not nested or the larger fit did not reach "
                         "its optimum (try starts > 1)")
    stat = max(stat, 0.0)
    return TestResult("likelihood_ratio", float(stat), float(r), float(stats.chi2.sf(stat, r)))


def _restriction_text(r: str) -> str:
    if not isinstance(r, str):
        raise ModelError(f"a restriction must be a string such as 'Ri - Ro' or 'a = 2*b', got {r!r}")
    if "=" in r:
        lhs, rhs = r.split("=", 1)
        return f"({lhs}) - ({rhs})"
    return r


def wald_test(fit, restrictions: str | Sequence[str]) -> TestResult:
    """The Wald test of restrictions R(θ) = 0 (5.5): W = R(θ̂)ᵀ[F Σ̂ Fᵀ]⁻¹R(θ̂) ~ χ²(k).

    Parameters
    ----------
    fit : FitResult
        The fit; Σ̂ its covariance, F the Jacobian of R.
    restrictions : str or sequence of str
        Expressions in the parameters' names, ``"Ri - Ro"`` or ``"Ri = Ro"``.

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    if isinstance(restrictions, str):
        restrictions = [restrictions]
    names = list(fit.params.index)
    syms = [parse_expression(n, "parameter") for n in names]
    exprs = []
    for r in restrictions:
        exprs.append(parameter_expression(_restriction_text(r), names, f"restriction '{r}'"))
    if not exprs:
        raise ModelError("give at least one restriction")
    fn = lambdify_parameters(exprs, syms, (len(exprs),))
    theta = jnp.asarray(fit.params["estimate"].to_numpy(dtype=np.float64))
    value = np.asarray(fn(theta))
    jac = np.asarray(jax.jacfwd(fn)(theta))
    free = list(fit.cov.index)
    F = jac[:, [names.index(n) for n in free]]
    for i, r in enumerate(restrictions):
        if not np.any(F[i] != 0):
            raise ModelError(f"restriction '{r}' does not involve any estimated parameter")
    cov = fit.cov.to_numpy()
    used = np.any(F != 0, axis=0)
    if not np.all(np.isfinite(cov[np.ix_(used, used)])):
        bad = [n for n, u in zip(free, used) if u and not np.all(np.isfinite(cov[free.index(n)][used]))]
        raise ModelError(f"the fit has no covariance for '{bad[0]}' (at a bound or not determined); "
                         "the Wald test cannot use it")
    V = F[:, used] @ cov[np.ix_(used, used)] @ F[:, used].T
    try:
        w = float(value @ np.linalg.solve(V, value))
    except np.linalg.LinAlgError:
        raise ModelError("the restrictions are linearly dependent at the estimates (F Σ Fᵀ is singular)") from None
    k = len(exprs)
    return TestResult("wald", w, float(k), float(stats.chi2.sf(w, k)))


def _score_statistic(d) -> float:
    """SᵀM⁻¹S, scaled so parameters of very different magnitudes do not spoil the solve."""
    scale = np.sqrt(np.abs(np.diag(d.information)))
    scale = np.where(scale > 0, scale, 1.0)
    M = d.information / np.outer(scale, scale)
    S = d.score / scale
    w = np.linalg.eigvalsh(M)
    if w.min() <= 1e-12 * max(w.max(), 1e-300):
        names = ", ".join(d.names)
        hint = " (try information='fisher')" if d.kind != "fisher" else ""
        raise ModelError(f"the information matrix of ({names}) is not positive definite at these parameters{hint}")
    return float(S @ np.linalg.solve(M, S))


def _settings(fit, model, method):
    out = filter_settings(fit.settings)
    if method is not None:
        out["method"] = method
    elif model is not fit.model and not (model.structure.is_linear or out["method"] != "kalman"):
        out["method"] = None  # the default filter of the larger model
    return out


def _free_names(model) -> list[str]:
    declared = model.parameters
    return [n for n in model.parameter_names if not (n in declared and declared[n].fixed)]


def lm_test(fit, model, at: dict | None = None, data=None, df: int | None = None, information: str = "fisher",
            method: str | None = None) -> TestResult:
    """The Lagrange multiplier (score) test at a restricted fit (5.6): LM = SᵀM⁻¹S, with no fit of the larger model.

    Parameters
    ----------
    fit : FitResult
        The ML fit of the restricted model.
    model : Model
        The larger model; S and M are its score and information at the fit's estimates.
    at : mapping of str to float, optional
        The values of the larger model's parameters that the fit lacks (the restriction).
    data : pandas.DataFrame, optional
        Other data (default: the fit's).
    df : int, optional
        r (default: the difference in free parameters).
    information : {"fisher", "hessian", "opg"}
        M: the expected information of the innovations, the observed information,
        or the outer product of scores.
    method : str, optional
        The filter (default: the fit's).

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    _require_ml(fit, "Lagrange-multiplier test")
    big_names = list(model.parameter_names)
    values = {k: v for k, v in fit.values.items() if k in big_names}
    values.update(at or {})
    missing = [n for n in _free_names(model) if n not in values]
    if missing:
        raise ModelError(f"the restricted fit gives no value for '{missing[0]}' of model '{model.name}'; "
                         f"pass it in at={{'{missing[0]}': ...}}")
    free = _free_names(model)
    r = len(free) - fit.n_params if df is None else int(df)
    if r < 1:
        raise ModelError(f"model '{model.name}' has {len(free)} free parameters, no more than the fit's "
                         f"{fit.n_params}; give df explicitly")
    d = loglik_derivatives(model, values, fit._data(data), free, information, **_settings(fit, model, method))
    lm = _score_statistic(d)
    return TestResult("lagrange_multiplier", lm, float(r), float(stats.chi2.sf(lm, r)))


def cross_validation_test(fit, data, information: str = "fisher", estimation_error: bool = True) -> TestResult:
    """The LM test at a fit's estimates on a new data set: do the same parameters fit there too? (5.4)

    The score S₁ of the new data at θ̂ has variance M₁ from the new data's noise plus
    M₁Σ̂M₁ from θ̂'s own estimation error, so by default LM = S₁ᵀ(M₁ + M₁Σ̂M₁)⁻¹S₁ ~
    χ²(dim θ).

    Parameters
    ----------
    fit : FitResult
        The fit.
    data : pandas.DataFrame
        The new data set.
    information : {"fisher", "hessian", "opg"}
        M₁.
    estimation_error : bool
        False: the thesis' S₁ᵀM₁⁻¹S₁, which treats θ̂ as exact and rejects too often
        unless the new data set is much longer.

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    _require_ml(fit, "cross-validation test")
    free = list(fit.cov.index)
    d = loglik_derivatives(fit.model, fit.values, data, free, information, **filter_settings(fit.settings))
    if estimation_error:
        cov = fit.cov.to_numpy()
        if not np.all(np.isfinite(cov)):
            raise ModelError("the fit has parameters without covariance (at a bound or not determined); "
                             "use estimation_error=False")
        M = d.information
        d = replace(d, information=M + M @ cov @ M)
    lm = _score_statistic(d)
    k = len(free)
    return TestResult("cross_validation", lm, float(k), float(stats.chi2.sf(lm, k)))


def simulated_datasets(fit, n_sim: int = 1, seed: int = 0, method: str | None = None, substeps: int = 20):
    """Data sets simulated from a fitted model with the measured inputs, times and gaps.

    Parameters
    ----------
    fit : FitResult
        The fit.
    n_sim : int
        The number of data sets.
    seed : int
        Their random seed.
    method : str, optional
        The simulation scheme.
    substeps : int
        Integration steps per sampling interval.

    Returns
    -------
    list of pandas.DataFrame
        The data sets.
    """
    settings = fit.settings
    method = method or ("exact" if fit.model.structure.is_linear else "milstein")
    outputs = list(fit.model.output_names)
    out = []
    for i, frame in enumerate(fit.data if fit.data is not None else []):
        sim = simulate_at(fit.model, fit.values, frame, n_paths=n_sim, seed=seed + 1000 * i, method=method,
                          substeps=substeps, hold=settings["hold"], time=settings["time"],
                          time_unit=settings.get("time_unit"))
        for p in range(n_sim):
            sim_frame = sim.frame(p)
            observed = frame[outputs].notna().to_numpy()
            sim_frame[outputs] = sim_frame[outputs].where(observed)
            out.append(sim_frame)
    if not out:
        raise ModelError("this fit carries no data (it was loaded from a file); simulation needs its inputs")
    return out


def approximation_test(fit, n_sim: int = 1, seed: int = 0, method: str | None = None, substeps: int = 20,
                       information: str = "fisher") -> TestResult:
    """The LM test on data simulated from the fitted model: is the filter's approximation good enough? (5.1.1)

    Under an adequate filter LM ~ χ²(dim θ).

    Parameters
    ----------
    fit : FitResult
        The fit.
    n_sim : int
        Independent simulated data sets, pooled.
    seed : int
        Their random seed.
    method : str, optional
        The simulation scheme (default: the exact discretisation for linear models,
        Milstein steps otherwise).
    substeps : int
        Integration steps per sampling interval.
    information : {"fisher", "hessian", "opg"}
        M.

    Returns
    -------
    TestResult
        ``test``, ``statistic``, ``df`` and ``p_value``; ``reject(level)``.
    """
    _require_ml(fit, "approximation test")
    sims = simulated_datasets(fit, n_sim, seed, method, substeps)
    settings = filter_settings(fit.settings)
    settings.pop("time_unit", None)  # simulated times are numbers
    free = list(fit.cov.index)
    d = loglik_derivatives(fit.model, fit.values, sims, free, information, **settings)
    lm = _score_statistic(d)
    k = len(free)
    return TestResult("filter_approximation", lm, float(k), float(stats.chi2.sf(lm, k)))


def _innovations(fit) -> np.ndarray:
    res = fit.filter()
    frames = res if isinstance(res, list) else [res]
    return np.concatenate([r.innovations.to_numpy() for r in frames])


def fpe(fit) -> float:
    """The final prediction error (5.9): det Σ̂ (N + k)/(N − k), Σ̂ the innovations' mean square.

    Rows with every output observed are used; for one output this is ((N + k)/(N − k)) σ̂².

    Parameters
    ----------
    fit : FitResult
        The fit.

    Returns
    -------
    float
        The FPE.
    """
    eps = _innovations(fit)
    eps = eps[~np.isnan(eps).any(axis=1)]
    n, k = len(eps), fit.n_params
    if n <= k:
        raise ModelError(f"FPE needs more fully observed rows ({n}) than parameters ({k})")
    sigma = eps.T @ eps / n
    return float(np.linalg.det(sigma) * (n + k) / (n - k))


def compare_fits(fits: Iterable, names: Sequence[str] | None = None) -> pd.DataFrame:
    """The log-likelihood, AIC, BIC and FPE (5.7–5.9) of several fits, with differences to the best.

    Parameters
    ----------
    fits : iterable of FitResult
        The fits, of the same data.
    names : sequence of str, optional
        Their labels (default: the models' names).

    Returns
    -------
    pandas.DataFrame
        One row per fit.
    """
    fits = list(fits)
    if not fits:
        raise ModelError("give at least one fit to compare")
    labels = list(names) if names is not None else [f.model.name for f in fits]
    if len(labels) != len(fits):
        raise ModelError(f"{len(labels)} names for {len(fits)} fits")
    seen = {}
    for i, label in enumerate(labels):
        seen[label] = seen.get(label, 0) + 1
        if seen[label] > 1:
            labels[i] = f"{label} #{seen[label]}"
    n_obs = {f.n_obs for f in fits}
    if len(n_obs) > 1:
        raise ModelError(f"the fits use different numbers of observations {sorted(n_obs)}; "
                         "information criteria compare fits to the same data")
    table = pd.DataFrame({
        "n_params": [f.n_params for f in fits],
        "n_obs": [f.n_obs for f in fits],
        "loglik": [f.loglik for f in fits],
        "aic": [f.aic for f in fits],
        "bic": [f.bic for f in fits],
        "fpe": [fpe(f) for f in fits],
    }, index=pd.Index(labels, name="model"))
    table["delta_aic"] = table["aic"] - table["aic"].min()
    table["delta_bic"] = table["bic"] - table["bic"].min()
    return table

